"""Object meshes: the shipped set, user files, errors and ground-truth surface sampling."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from drivers.errors import JobError
from drivers.sim.objects import (
    OBJECTS_DIR,
    ObjectMesh,
    face_normals,
    list_objects,
    load_object,
    sample_surface,
)

NAMES = ["banana", "baseball", "bunny", "cube", "dragon", "flange", "gripper", "horizontal_box",
         "mustard", "pyramid", "teapot", "vertical_box"]


def test_list_objects_names_all_twelve_sorted() -> None:
    infos = list_objects()
    assert [i.name for i in infos] == NAMES
    for info in infos:
        assert info.path.is_file()
        assert info.path.parent == OBJECTS_DIR
        assert info.extents_m.shape == (3,)
        assert np.all(info.extents_m > 0.02) and np.all(info.extents_m < 0.4)
        assert info.licence
    assert (OBJECTS_DIR / "CREDITS.md").is_file()


@pytest.mark.parametrize("name", NAMES)
def test_every_shipped_object_loads_in_the_object_frame(name: str) -> None:
    mesh = load_object(name)
    assert isinstance(mesh, ObjectMesh)
    assert mesh.name == name
    assert mesh.vertices.dtype == np.float64 and mesh.vertices.shape[1] == 3
    assert mesh.triangles.dtype == np.int32 and mesh.triangles.shape[1] == 3
    assert 0 < len(mesh.triangles) <= 20000
    assert mesh.triangles.min() >= 0 and mesh.triangles.max() < len(mesh.vertices)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    assert abs(lo[2]) < 1e-6
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2.0, 0.0, atol=1e-4)
    # outward winding: positive signed volume
    v = mesh.vertices[mesh.triangles]
    volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0
    assert volume > 0.0


def test_cube_extents() -> None:
    np.testing.assert_allclose(load_object("cube").extents_m, [0.1, 0.1, 0.1], atol=1e-6)


def test_unknown_name_raises_job_error_listing_names() -> None:
    with pytest.raises(JobError) as exc:
        load_object("bunnny")
    text = str(exc.value)
    assert "\n" not in text
    for name in NAMES:
        assert name in text


def test_missing_path_raises_job_error_listing_names(tmp_path: Path) -> None:
    with pytest.raises(JobError) as exc:
        load_object(str(tmp_path / "nothing.ply"))
    assert "bunny" in str(exc.value) and "vertical_box" in str(exc.value)


def test_unreadable_file_raises_job_error(tmp_path: Path) -> None:
    bad = tmp_path / "garbage.ply"
    bad.write_bytes(b"this is not a mesh\n")
    with pytest.raises(JobError) as exc:
        load_object(str(bad))
    assert "bunny" in str(exc.value)


def test_empty_mesh_raises_job_error(tmp_path: Path) -> None:
    empty = tmp_path / "empty.obj"
    empty.write_text("# no geometry\n")
    with pytest.raises(JobError):
        load_object(str(empty))


@pytest.mark.parametrize("suffix", [".ply", ".stl", ".obj"])
def test_user_file_is_recentred(tmp_path: Path, suffix: str) -> None:
    box = trimesh.creation.box(extents=[0.2, 0.1, 0.05])
    box.apply_translation([1.0, -2.0, 3.0])
    path = tmp_path / f"mybox{suffix}"
    box.export(path)
    mesh = load_object(path)
    assert mesh.name == "mybox"
    np.testing.assert_allclose(mesh.vertices.min(axis=0), [-0.1, -0.05, 0.0], atol=1e-6)
    np.testing.assert_allclose(mesh.vertices.max(axis=0), [0.1, 0.05, 0.05], atol=1e-6)


def test_sample_surface_leaves_out_the_bottom_face_of_the_cube() -> None:
    cube = load_object("cube")
    pts = sample_surface(cube, 20000, np.random.default_rng(1))
    assert pts.shape == (20000, 3)
    assert pts[:, 2].min() > 1e-9  # nothing on the bottom face (z = 0)
    # every sample lies on the cube's surface
    on_face = (np.isclose(np.abs(pts[:, 0]), 0.05, atol=1e-9) | np.isclose(np.abs(pts[:, 1]), 0.05, atol=1e-9)
               | np.isclose(pts[:, 2], 0.1, atol=1e-9))
    assert on_face.all()
    # the bottom is kept when nothing is excluded
    all_pts = sample_surface(cube, 6000, np.random.default_rng(1), exclude_down_deg=-1.0)
    assert np.mean(all_pts[:, 2] < 1e-9) == pytest.approx(1 / 6, abs=0.03)


def test_sample_surface_is_area_weighted() -> None:
    box = load_object("horizontal_box")  # 0.3 x 0.2 x 0.1: top 0.06 m^2, sides 0.10 m^2
    pts = sample_surface(box, 40000, np.random.default_rng(2))
    top = np.isclose(pts[:, 2], 0.1, atol=1e-9)
    assert top.mean() == pytest.approx(0.06 / 0.16, abs=0.015)
    x_sides = np.isclose(np.abs(pts[:, 0]), 0.15, atol=1e-9) & ~top
    assert x_sides.mean() == pytest.approx(0.04 / 0.16, abs=0.015)


def test_sample_surface_angle_threshold_on_the_pyramid() -> None:
    pyr = load_object("pyramid")
    normals, _ = face_normals(pyr.vertices, pyr.triangles)
    down_angle = np.degrees(np.arccos(np.clip(-normals[:, 2], -1, 1)))
    side = down_angle[down_angle > 1.0]
    assert side.min() > 90.0  # the sides face upwards: all kept at 45 deg
    pts = sample_surface(pyr, 5000, np.random.default_rng(3))
    assert pts[:, 2].min() >= 0.0
    # a threshold above every face's angle to -z (sides ~149 deg) leaves nothing: error
    with pytest.raises(ValueError):
        sample_surface(pyr, 10, np.random.default_rng(3), exclude_down_deg=179.0)


def test_sample_surface_is_deterministic() -> None:
    bunny = load_object("bunny")
    a = sample_surface(bunny, 1000, np.random.default_rng(7))
    b = sample_surface(bunny, 1000, np.random.default_rng(7))
    c = sample_surface(bunny, 1000, np.random.default_rng(8))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_an_stl_reads_with_one_vertex_per_corner(tmp_path: Path) -> None:
    """An STL repeats each corner in every facet (Open3D's reader kept them: 24 vertices for a box, and
    about a million for an upload of 16 MB); they are merged, the triangles kept."""
    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=[0.2, 0.1, 0.05]).export(path)
    mesh = load_object(path)
    assert len(mesh.vertices) == 8 and len(mesh.triangles) == 12
    np.testing.assert_allclose(mesh.extents_m, [0.2, 0.1, 0.05], atol=1e-9)
