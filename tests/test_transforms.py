"""Geometry helpers of ``drivers.transforms`` not covered through their users."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.transforms import quat_xyzw, rotation_from_rotvec, rotvec, smallest_rotation


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


@pytest.mark.parametrize("seed", range(5))
def test_smallest_rotation_turns_one_vector_onto_the_other_about_their_normal(seed: int) -> None:
    rng = np.random.default_rng(seed)
    u, v = _unit(rng.normal(size=3)), _unit(rng.normal(size=3))
    R = smallest_rotation(u, v)
    np.testing.assert_allclose(R @ u, v, atol=1e-12)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # the angle of R is the angle between u and v (no extra turn), about their common normal
    angle = np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    assert angle == pytest.approx(np.arccos(u @ v), abs=1e-9)
    normal = _unit(np.cross(u, v))
    np.testing.assert_allclose(R @ normal, normal, atol=1e-12)


def test_smallest_rotation_of_equal_and_opposite_vectors() -> None:
    u = _unit(np.array([0.3, -0.2, 0.9]))
    np.testing.assert_allclose(smallest_rotation(u, u), np.eye(3), atol=1e-12)
    R = smallest_rotation(u, -u)
    np.testing.assert_allclose(R @ u, -u, atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def _rotvecs(seed: int) -> np.ndarray:
    """Axis-angle vectors (N, 3) [rad] at every scale the closed forms must handle: uniform rotations,
    angles from 1e-12 rad up to within 1e-9 rad of a half turn, and turns about each axis alone (where one
    diagonal entry is the largest)."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(60, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0.0, np.pi, 20), 10.0 ** rng.uniform(-12, -1, 20),
                             np.pi - 10.0 ** rng.uniform(-9, -1, 20)])
    single = np.vstack([np.eye(3) * a for a in (0.3, 2.0, np.pi - 1e-6)])
    return np.vstack([axes * angles[:, None], single])


@pytest.mark.parametrize("seed", range(3))
def test_the_closed_forms_agree_with_scipys_rotation(seed: int) -> None:
    for r in _rotvecs(seed):
        reference = Rotation.from_rotvec(r)
        R = rotation_from_rotvec(r)
        np.testing.assert_allclose(R, reference.as_matrix(), atol=1e-15)
        q = reference.as_quat()
        np.testing.assert_allclose(quat_xyzw(R), -q if q[3] < 0 else q, atol=1e-15)
        np.testing.assert_allclose(rotvec(R), r, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(rotvec(R), reference.as_rotvec(), rtol=1e-9, atol=1e-15)


def test_a_half_turn_and_no_turn() -> None:
    np.testing.assert_array_equal(rotvec(np.eye(3)), np.zeros(3))
    np.testing.assert_array_equal(rotation_from_rotvec([0.0, 0.0, 0.0]), np.eye(3))
    np.testing.assert_array_equal(quat_xyzw(np.eye(4)), [0.0, 0.0, 0.0, 1.0])
    for axis in np.eye(3):
        R = rotation_from_rotvec(np.pi * axis)
        r = rotvec(R)
        # either sign of the axis gives the same turn
        assert np.linalg.norm(r) == pytest.approx(np.pi, abs=1e-12)
        np.testing.assert_allclose(np.abs(r), np.pi * axis, atol=1e-12)
        np.testing.assert_allclose(rotation_from_rotvec(r), R, atol=1e-15)
