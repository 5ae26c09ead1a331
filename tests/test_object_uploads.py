"""Uploaded meshes: the service keeps an outline of each (its size and its footprint's hull, beside the
mesh as ``<name>.json``), never the mesh, so a listing after a restart reads no mesh; an upload from
before outlines gets its outline once. An operator deletes an upload through the API (a real ``cell
serve``), never a shipped object nor one a queued or running job scans."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import trimesh

import cell.service.objects as objects_module
from cell.config import load_config
from cell.jobs.placement import check_on_table, footprint_bounds
from cell.service.arm_clearance import ArmClearance
from cell.service.objects import ObjectLibrary, ObjectOutline
from cell.service.search_views import SearchViews
from cell.service.store import JobRecord
from cell.service.submission import JobRequest, validate
from drivers.errors import JobError, ServiceError
from drivers.sim.objects import ObjectMesh, load_object
from tests.conftest import FRANKA
from tests.service_process import ServedCell, submit

CONFIG = load_config(FRANKA)


def _library(folder: Path) -> ObjectLibrary:
    """The object library of the cell ``CONFIG`` describes, its uploads in ``folder``."""
    return ObjectLibrary(folder, CONFIG, ArmClearance(CONFIG))


def _l_shape() -> trimesh.Trimesh:
    """An L of two boxes (12 x 4 cm and 4 x 10 cm, 5 cm tall): its footprint is not its bounding box."""
    bar = trimesh.creation.box(extents=(0.12, 0.04, 0.05))
    leg = trimesh.creation.box(extents=(0.04, 0.10, 0.05))
    leg.apply_translation((-0.04, 0.07, 0.0))
    return trimesh.util.concatenate([bar, leg])


@pytest.fixture
def counted_loads(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The paths the object library reads as meshes, from now on."""
    loads: list[str] = []

    def counting(name_or_path: str | Path, scale: float = 1.0) -> ObjectMesh:
        loads.append(str(name_or_path))
        return load_object(name_or_path, scale)

    monkeypatch.setattr(objects_module, "load_object", counting)
    return loads


def test_after_a_restart_the_list_and_a_jobs_placement_read_no_uploaded_mesh(
        tmp_path: Path, counted_loads: list[str]) -> None:
    """The service had loaded every upload to list it (and kept them all: 16 s and 800 MB for twelve
    16 MB STLs); its outline, written at the upload, now answers both, as the mesh would have."""
    source = tmp_path / "L part.stl"
    _l_shape().export(source)
    entry = _library(tmp_path / "objects").add(source.name, source.read_bytes())
    assert entry.name == "l_part" and entry.extents_m == pytest.approx((0.12, 0.14, 0.05))
    assert len(counted_loads) == 1  # the upload's own check
    kept = json.loads((tmp_path / "objects" / "l_part.json").read_text())
    assert kept["extents_m"] == pytest.approx([0.12, 0.14, 0.05])

    restarted = _library(tmp_path / "objects")
    listed = {e.name: e for e in restarted.entries()}
    assert listed["l_part"].source == "uploaded" and listed["l_part"].extents_m == entry.extents_m
    shape = restarted.shape("l_part")
    assert len(counted_loads) == 1  # no mesh read since the upload

    mesh = load_object(tmp_path / "objects" / "l_part.stl")
    np.testing.assert_allclose(shape.extents_m, mesh.extents_m, atol=1e-9)
    for yaw in np.linspace(-360.0, 360.0, 49):
        for a, b in zip(footprint_bounds(CONFIG, shape, (0.0, 0.0, yaw)),
                        footprint_bounds(CONFIG, mesh, (0.0, 0.0, yaw)), strict=True):
            np.testing.assert_allclose(a, b, atol=1e-9)
    # off the table: refused as the mesh is, naming the footprint
    far = (0.0, float(CONFIG.sim.table_size_m[1]), 0.0)
    with pytest.raises(JobError, match="off the table") as refused:
        check_on_table(CONFIG, shape, far)
    with pytest.raises(JobError) as by_mesh:
        check_on_table(CONFIG, mesh, far)
    assert str(refused.value) == str(by_mesh.value).replace(mesh.name, "l_part")


def test_an_uploads_placement_no_search_view_sees_is_refused_at_submission_from_its_kept_surface(
        tmp_path: Path, counted_loads: list[str]) -> None:
    """The job's worker alone refused it (a job that failed with 0 captures); the outline now keeps the
    points on the upload's surface that the check tests: the submission refuses it as it refuses the
    mesh, reading no mesh, and takes a placement the views see."""
    source = tmp_path / "L part.stl"
    _l_shape().export(source)
    library = _library(tmp_path / "objects")
    library.add(source.name, source.read_bytes())
    restarted = _library(tmp_path / "objects")
    views = SearchViews(CONFIG)

    arm = ArmClearance(CONFIG)

    def submit_at(pose: tuple[float, float, float]) -> None:
        validate(CONFIG, restarted, arm, views, JobRequest(object="l_part", object_pose=pose))

    with pytest.raises(ServiceError, match="where none of the 2 views vs-local looks") as refused:
        submit_at((0.5, 0.0, 0.0))
    assert refused.value.field == "object_pose"
    mesh = load_object(tmp_path / "objects" / "l_part.stl")
    with pytest.raises(JobError) as by_mesh:
        views.check(mesh, (0.5, 0.0, 0.0), "vs-local")
    assert str(refused.value) == str(by_mesh.value)
    submit_at((0.0, 0.0, 30.0))
    assert len(counted_loads) == 1  # the upload's own check


def _upload_l_part(tmp_path: Path) -> Path:
    """Upload the L (:func:`_l_shape`) as ``l_part`` into ``tmp_path / "objects"``; its outline file."""
    source = tmp_path / "L part.stl"
    _l_shape().export(source)
    _library(tmp_path / "objects").add(source.name, source.read_bytes())
    return tmp_path / "objects" / "l_part.json"


def test_an_outline_file_from_before_surfaces_has_its_mesh_read_once_for_a_submission(
        tmp_path: Path, counted_loads: list[str]) -> None:
    outline_file = _upload_l_part(tmp_path)
    kept = json.loads(outline_file.read_text())
    del kept["surface_m"]  # as an outline file written before
    outline_file.write_text(json.dumps(kept))
    library = _library(outline_file.parent)
    assert "l_part" in {e.name for e in library.entries()} and len(counted_loads) == 1  # listed as it was
    for _ in range(2):
        with pytest.raises(ServiceError, match="where none of the 2 views"):
            validate(CONFIG, library, ArmClearance(CONFIG), SearchViews(CONFIG),
                     JobRequest(object="l_part", object_pose=(0.5, 0.0, 0.0)))
    assert len(counted_loads) == 2 and "surface_m" in json.loads(outline_file.read_text())


Points = list[list[float]]
"""A list of points as an outline file keeps them (``footprint_m``, ``surface_m``)."""


def _nan_at_first(points: Points) -> Points:
    return [[float("nan"), *points[0][1:]], *points[1:]]


@pytest.mark.parametrize(("field", "damage"), [
    ("surface_m", lambda points: []),
    ("surface_m", lambda points: points[:100]),
    ("surface_m", _nan_at_first),
    ("footprint_m", lambda points: []),
], ids=["surface emptied", "surface cut short", "surface not finite", "footprint emptied"])
def test_a_damaged_outline_file_has_its_mesh_read_again_and_a_placement_its_views_see_is_accepted(
        tmp_path: Path, counted_loads: list[str], field: str, damage: Callable[[Points], Points]) -> None:
    """An outline file damaged on disk (its surface emptied, cut short or not finite, its footprint
    emptied) is no outline: its mesh is read again and the file written whole, once; the placement checks
    never run on what was left (with no surface point, no view sees the object anywhere: a placement at
    the station was refused)."""
    outline_file = _upload_l_part(tmp_path)
    kept = json.loads(outline_file.read_text())
    whole = np.asarray(kept["surface_m"])
    kept[field] = damage(kept[field])
    outline_file.write_text(json.dumps(kept))
    library = _library(outline_file.parent)
    for _ in range(2):
        validate(CONFIG, library, ArmClearance(CONFIG), SearchViews(CONFIG),
                 JobRequest(object="l_part", object_pose=(0.0, 0.0, 0.0)))
    shape = library.shape("l_part", surface=True)
    assert isinstance(shape, ObjectOutline) and shape.surface is not None
    assert np.array_equal(np.round(shape.surface, 6), whole)
    assert shape.extents_m == pytest.approx((0.12, 0.14, 0.05))
    assert len(counted_loads) == 2  # the upload's check, then the damaged file's once
    assert np.array_equal(json.loads(outline_file.read_text())["surface_m"], whole)


def test_an_outline_file_kept_from_before_loads_without_its_mesh(tmp_path: Path,
                                                                 counted_loads: list[str]) -> None:
    """The outline file's format (``extents_m`` and ``footprint_m``) is read as it was written; the
    outline's size is its footprint's and the stored height: x and y sizes that disagree with the
    footprint (a file edited by hand, or written by a bug) are not believed."""
    folder = tmp_path / "objects"
    folder.mkdir()
    mesh_file = folder / "wedge.stl"
    trimesh.creation.box(extents=(0.08, 0.05, 0.04)).export(mesh_file)
    stat = mesh_file.stat()
    (folder / "wedge.json").write_text(json.dumps({
        "mesh_file": {"bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns}, "extents_m": [0.3, 0.2, 0.04],
        "footprint_m": [[-0.04, -0.025], [0.04, -0.025], [0.04, 0.025], [-0.04, 0.025]]}, indent=1))
    library = _library(folder)
    assert {e.name: e.extents_m for e in library.entries()}["wedge"] == pytest.approx((0.08, 0.05, 0.04))
    assert library.shape("wedge").vertices[:, 2].max() == pytest.approx(0.04)
    assert counted_loads == []


def test_an_upload_from_before_outlines_is_read_once_and_again_only_when_its_file_changes(
        tmp_path: Path, counted_loads: list[str]) -> None:
    folder = tmp_path / "objects"
    folder.mkdir()
    old = folder / "crate.stl"
    trimesh.creation.box(extents=(0.06, 0.05, 0.04)).export(old)
    for _ in range(2):  # two services one after the other
        library = _library(folder)
        for _ in range(3):
            listed = {e.name: e.extents_m for e in library.entries()}
            assert listed["crate"] == pytest.approx((0.06, 0.05, 0.04))
    assert counted_loads == [str(old)]
    assert (folder / "crate.json").is_file()

    trimesh.creation.box(extents=(0.08, 0.05, 0.04)).export(old)  # another file copied in under the name
    assert {e.name: e.extents_m for e in library.entries()}["crate"] == pytest.approx((0.08, 0.05, 0.04))
    assert _library(folder).shape("crate").extents_m == pytest.approx((0.08, 0.05, 0.04))
    assert counted_loads == [str(old)] * 2


def test_an_upload_that_no_longer_reads_is_left_out_and_read_once(tmp_path: Path,
                                                                  counted_loads: list[str]) -> None:
    folder = tmp_path / "objects"
    folder.mkdir()
    (folder / "junk.ply").write_bytes(b"not a mesh")
    library = _library(folder)
    for _ in range(3):
        assert "junk" not in {e.name for e in library.entries()}
    with pytest.raises(ServiceError, match="no longer reads as a mesh"):
        library.shape("junk")
    assert len(counted_loads) == 1


def test_a_deletion_keeps_shipped_objects_and_those_of_queued_jobs(tmp_path: Path) -> None:
    library = _library(tmp_path / "objects")
    source = tmp_path / "crate.stl"
    trimesh.creation.box(extents=(0.06, 0.05, 0.04)).export(source)
    library.add(source.name, source.read_bytes())
    asked: list[str] = []

    def active() -> list[JobRecord]:
        asked.append("jobs")
        return []

    with pytest.raises(ServiceError, match="shipped with the cell") as shipped:
        library.remove("bunny", active)
    assert shipped.value.reason == "conflict"
    for name in ("nothing", "../crate", "CRATE"):
        with pytest.raises(ServiceError) as unknown:
            library.remove(name, active)
        assert unknown.value.reason == "not found"
    assert asked == []  # a name of no upload is refused without reading the store
    library.remove("crate", active)
    assert asked == ["jobs"]
    assert not list((tmp_path / "objects").iterdir())
    assert "crate" not in {e.name for e in library.entries()}


# ---------------------------------------------------------------------------------------------- the API


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServedCell]:
    with ServedCell(FRANKA, tmp_path_factory.mktemp("uploads") / "data", key_prefix="uploads") as cell:
        yield cell


def test_an_operator_deletes_an_upload_but_not_a_shipped_object_nor_one_a_queued_job_scans(
        served: ServedCell, tmp_path: Path) -> None:
    crate = tmp_path / "crate.ply"
    trimesh.creation.box(extents=(0.06, 0.05, 0.04)).export(crate)
    upload = {"file": (crate.name, crate.read_bytes())}
    with served.client("operator") as operator, served.client("viewer") as viewer:
        assert operator.post("/api/v1/objects", files=upload).status_code == 201

        assert viewer.delete("/api/v1/objects/crate").status_code == 403
        shipped = operator.delete("/api/v1/objects/bunny")
        assert shipped.status_code == 409 and "shipped with the cell" in shipped.json()["detail"]
        assert operator.delete("/api/v1/objects/nothing").status_code == 404

        # a STOP holds the queue: the job waits, queued, for its object
        assert operator.post("/api/v1/stop", json={"reason": "uploads test"}).status_code == 200
        try:
            job = submit(served, object="crate", max_time_s=1.0)
            busy = operator.delete("/api/v1/objects/crate")
            assert busy.status_code == 409, busy.text
            assert job["id"] in busy.json()["detail"] and "queued or running" in busy.json()["detail"]
            assert operator.delete(f"/api/v1/jobs/{job['id']}").json()["status"] == "cancelled"
        finally:
            operator.post("/api/v1/queue/resume")

        with served.client("admin") as admin:
            gone = admin.delete("/api/v1/objects/crate")
        assert gone.status_code == 204 and gone.content == b""
        assert "crate" not in {o["name"] for o in viewer.get("/api/v1/objects").json()}
        assert not list((served.data_dir / "objects").glob("crate.*"))
        # the name is free again
        assert operator.post("/api/v1/objects", files=upload).status_code == 201
