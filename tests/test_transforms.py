"""Geometry helpers of ``drivers.transforms`` not covered through their users."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.transforms import smallest_rotation


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
