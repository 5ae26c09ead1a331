"""Uploaded meshes: the service keeps an outline of each (its size and its footprint's hull, beside the
mesh as ``<name>.json``), never the mesh, so a listing after a restart reads no mesh; an upload from
before outlines gets its outline once."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

import cell.service.objects as objects_module
from cell.config import load_config
from cell.jobs.placement import check_on_table, footprint_bounds
from cell.service.objects import ObjectLibrary
from drivers.errors import JobError, ServiceError
from drivers.sim.objects import ObjectMesh, load_object
from tests.conftest import FRANKA

CONFIG = load_config(FRANKA)


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
    entry = ObjectLibrary(tmp_path / "objects", CONFIG).add(source.name, source.read_bytes())
    assert entry.name == "l_part" and entry.extents_m == pytest.approx((0.12, 0.14, 0.05))
    assert len(counted_loads) == 1  # the upload's own check
    kept = json.loads((tmp_path / "objects" / "l_part.json").read_text())
    assert kept["extents_m"] == pytest.approx([0.12, 0.14, 0.05])

    restarted = ObjectLibrary(tmp_path / "objects", CONFIG)
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


def test_an_upload_from_before_outlines_is_read_once_and_again_only_when_its_file_changes(
        tmp_path: Path, counted_loads: list[str]) -> None:
    folder = tmp_path / "objects"
    folder.mkdir()
    old = folder / "crate.stl"
    trimesh.creation.box(extents=(0.06, 0.05, 0.04)).export(old)
    for _ in range(2):  # two services one after the other
        library = ObjectLibrary(folder, CONFIG)
        for _ in range(3):
            listed = {e.name: e.extents_m for e in library.entries()}
            assert listed["crate"] == pytest.approx((0.06, 0.05, 0.04))
    assert counted_loads == [str(old)]
    assert (folder / "crate.json").is_file()

    trimesh.creation.box(extents=(0.08, 0.05, 0.04)).export(old)  # another file copied in under the name
    assert {e.name: e.extents_m for e in library.entries()}["crate"] == pytest.approx((0.08, 0.05, 0.04))
    assert ObjectLibrary(folder, CONFIG).shape("crate").extents_m == pytest.approx((0.08, 0.05, 0.04))
    assert counted_loads == [str(old)] * 2


def test_an_upload_that_no_longer_reads_is_left_out_and_read_once(tmp_path: Path,
                                                                  counted_loads: list[str]) -> None:
    folder = tmp_path / "objects"
    folder.mkdir()
    (folder / "junk.ply").write_bytes(b"not a mesh")
    library = ObjectLibrary(folder, CONFIG)
    for _ in range(3):
        assert "junk" not in {e.name for e in library.entries()}
    with pytest.raises(ServiceError, match="no longer reads as a mesh"):
        library.shape("junk")
    assert len(counted_loads) == 1
