"""SimScene: ray casting against the table and the placed object."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim.objects import load_object
from drivers.sim.scene import HIT_NONE, HIT_OBJECT, HIT_TABLE, SimScene
from drivers.transforms import T_from_xyz_rpy, make_T, transform_points

DOWN = np.array([[0.0, 0.0, -1.0]])


@pytest.fixture(scope="module")
def cube_scene() -> SimScene:
    return SimScene(load_object("cube"), make_T(np.eye(3), np.array([0.5, 0.2, 0.1])), table_z=0.1)


def test_ray_straight_down_hits_the_table(cube_scene: SimScene) -> None:
    hits = cube_scene.cast(np.array([[0.3, -0.2, 1.0]]), DOWN)
    assert hits.what[0] == HIT_TABLE
    assert hits.t[0] == pytest.approx(0.9, abs=1e-6)
    np.testing.assert_allclose(hits.normals[0], [0.0, 0.0, 1.0], atol=1e-6)
    assert hits.cos_incidence[0] == pytest.approx(1.0, abs=1e-6)


def test_ray_down_at_the_object_hits_its_top(cube_scene: SimScene) -> None:
    hits = cube_scene.cast(np.array([0.52, 0.21, 1.0]), DOWN)  # origin (3,) broadcast
    assert hits.what[0] == HIT_OBJECT
    assert hits.t[0] == pytest.approx(1.0 - 0.2, abs=1e-6)  # cube top at table_z + 0.1
    np.testing.assert_allclose(hits.normals[0], [0.0, 0.0, 1.0], atol=1e-6)


def test_horizontal_ray_hits_the_side_with_a_normal_facing_it(cube_scene: SimScene) -> None:
    hits = cube_scene.cast(np.array([[0.2, 0.2, 0.15]]), np.array([[1.0, 0.0, 0.0]]))
    assert hits.what[0] == HIT_OBJECT
    assert hits.t[0] == pytest.approx(0.25, abs=1e-6)
    np.testing.assert_allclose(hits.normals[0], [-1.0, 0.0, 0.0], atol=1e-6)


def test_misses(cube_scene: SimScene) -> None:
    origins = np.array([[0.5, 0.0, 1.0], [3.0, 0.0, 1.0]])
    dirs = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])  # up into the sky; down beside the table
    hits = cube_scene.cast(origins, dirs)
    assert np.all(hits.what == HIT_NONE)
    assert np.all(np.isinf(hits.t))
    assert np.all(hits.normals == 0.0)
    assert np.all(hits.cos_incidence == 0.0)


def test_table_seen_from_below_has_its_normal_facing_the_ray(cube_scene: SimScene) -> None:
    hits = cube_scene.cast(np.array([[0.3, 0.0, -1.0]]), np.array([[0.0, 0.0, 1.0]]))
    assert hits.what[0] == HIT_TABLE
    assert hits.normals[0, 2] == pytest.approx(-1.0)


def test_normals_face_the_rays_on_a_rotated_bunny() -> None:
    T = T_from_xyz_rpy([0.5, 0.0, 0.0], [0.0, 0.0, 0.7])
    scene = SimScene(load_object("bunny"), T)
    rng = np.random.default_rng(0)
    eye = np.array([0.2, -0.1, 0.35])
    targets = np.array([0.5, 0.0, 0.07]) + rng.uniform(-0.08, 0.08, size=(2000, 3))
    dirs = targets - eye
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hits = scene.cast(eye, dirs)
    hit = hits.what != HIT_NONE
    assert (hits.what == HIT_OBJECT).sum() > 500
    dots = np.einsum("ij,ij->i", hits.normals[hit], dirs[hit])
    assert np.all(dots <= 1e-9)
    np.testing.assert_allclose(np.linalg.norm(hits.normals[hit], axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(hits.cos_incidence[hit], -dots, atol=1e-6)
    # hit points on the object lie on the placed mesh's bounding box
    pts = hits.points(np.broadcast_to(eye, dirs.shape), dirs)[hits.what == HIT_OBJECT]
    lo, hi = scene.object_vertices_base.min(axis=0), scene.object_vertices_base.max(axis=0)
    assert np.all(pts >= lo - 1e-5) and np.all(pts <= hi + 1e-5)


def test_placed_mesh_is_exposed_for_ground_truth() -> None:
    obj = load_object("pyramid")
    T = T_from_xyz_rpy([0.4, 0.1, 0.0], [0.0, 0.0, 0.3])
    scene = SimScene(obj, T)
    np.testing.assert_allclose(scene.object_vertices_base, transform_points(T, obj.vertices))
    assert np.array_equal(scene.object_triangles, obj.triangles)
    np.testing.assert_allclose(scene.T_base_object, T)


def test_bad_pose_is_rejected() -> None:
    with pytest.raises(ValueError):
        SimScene(load_object("cube"), np.eye(3))
