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


def test_a_folder_given_as_the_object_is_named_a_folder(tmp_path: Path) -> None:
    with pytest.raises(JobError, match="is a folder, not a mesh file") as exc:
        load_object(str(tmp_path))
    assert "not found" not in str(exc.value)


def _signed_volume(mesh: ObjectMesh) -> float:
    v = mesh.vertices[mesh.triangles]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


@pytest.mark.parametrize("suffix", [".stl", ".ply"])
def test_an_inverted_cube_loads_outward_and_its_top_is_ground_truth(tmp_path: Path, suffix: str) -> None:
    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    box.invert()
    path = tmp_path / f"flipped{suffix}"
    box.export(path)
    mesh = load_object(path)
    assert _signed_volume(mesh) == pytest.approx(1e-3, rel=1e-6)
    normals, _ = face_normals(mesh.vertices, mesh.triangles)
    centres = mesh.vertices[mesh.triangles].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", normals, centres - [0.0, 0.0, 0.05]) > 0.0)  # all outward
    pts = sample_surface(mesh, 5000, np.random.default_rng(0))
    assert pts[:, 2].min() > 1e-9  # the bottom is left out, not the top
    assert np.mean(np.isclose(pts[:, 2], 0.1)) == pytest.approx(0.2, abs=0.03)


def test_a_cube_of_mixed_winding_is_made_consistent(tmp_path: Path) -> None:
    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    faces = box.faces.copy()
    faces[::3] = faces[::3, ::-1]
    path = tmp_path / "mixed.ply"
    trimesh.Trimesh(box.vertices, faces, process=False).export(path)
    mesh = load_object(path)
    assert _signed_volume(mesh) == pytest.approx(1e-3, rel=1e-6)


def test_an_open_downward_sheet_faces_up(tmp_path: Path) -> None:
    sheet = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]], [[0, 2, 1], [0, 3, 2]],
                            process=False)
    path = tmp_path / "sheet.ply"
    sheet.export(path)
    mesh = load_object(path)
    normals, _ = face_normals(mesh.vertices, mesh.triangles)
    np.testing.assert_allclose(normals, [[0, 0, 1], [0, 0, 1]])


def test_a_moebius_strip_is_refused(tmp_path: Path) -> None:
    n = 12
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    ring = []
    for s in (-0.01, 0.01):
        ring.append(np.stack([(0.05 + s * np.cos(t / 2)) * np.cos(t), (0.05 + s * np.cos(t / 2)) * np.sin(t),
                              0.05 + s * np.sin(t / 2)], axis=1))
    vertices = np.vstack(ring)  # i: edge -1, n + i: edge +1; after a turn the edges swap
    faces = []
    for i in range(n):
        j = (i + 1) % n
        a, b, c, d = i, n + i, (j if j else n), (n + j if j else 0)
        faces += [[a, c, b], [b, c, d]]
    path = tmp_path / "moebius.ply"
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    with pytest.raises(JobError, match="cannot be oriented"):
        load_object(path)


@pytest.mark.parametrize("name", NAMES)
def test_the_shipped_meshes_are_already_outward(name: str) -> None:
    raw = trimesh.load(OBJECTS_DIR / f"{name}.ply", process=False)
    np.testing.assert_array_equal(load_object(name).triangles, raw.faces)


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
