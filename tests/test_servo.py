"""The dual-task servo law (visual-servoing paper eq. 1-3) and ViSP's adaptive gain."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cell.control.servo import DualTaskServo, adaptive_gain, interaction_matrix, null_space_projector
from drivers.transforms import look_at

PAPER = {"lambda_0": 2.0, "lambda_inf": 0.4, "lambda_0_slope": 30.0, "lambda_g": 0.33, "e_converged_m": 0.005}


def move_camera(T: np.ndarray, v: np.ndarray, dt: float) -> np.ndarray:
    """Apply a camera-frame twist (6,) for dt [s]: the pose at the end, base frame."""
    out = T.copy()
    out[:3, 3] = T[:3, 3] + T[:3, :3] @ v[:3] * dt
    out[:3, :3] = T[:3, :3] @ Rotation.from_rotvec(v[3:] * dt).as_matrix()
    return out


def centroid_in_camera(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    return T[:3, :3].T @ (P - T[:3, 3])


def test_interaction_matrix_predicts_the_feature_motion():
    rng = np.random.default_rng(0)
    P = np.array([0.4, 0.1, 0.05])
    T = look_at(np.array([0.2, -0.1, 0.3]), P + rng.normal(scale=0.03, size=3))
    s = centroid_in_camera(T, P)
    for _ in range(5):
        v = rng.normal(size=6)
        dt = 1e-6
        s_dot = (centroid_in_camera(move_camera(T, v, dt), P) - centroid_in_camera(move_camera(T, v, -dt), P))
        np.testing.assert_allclose(s_dot / (2 * dt), interaction_matrix(s) @ v, atol=1e-6)


def test_pseudo_inverse_and_null_space_projector():
    L = interaction_matrix(np.array([0.01, -0.02, 0.27]))
    L_pinv = np.linalg.pinv(L)
    null = np.eye(6) - L_pinv @ L
    np.testing.assert_allclose(L @ L_pinv, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(L @ null, 0.0, atol=1e-12)
    np.testing.assert_allclose(null @ null, null, atol=1e-12)
    assert np.linalg.matrix_rank(null) == 3
    np.testing.assert_allclose(null_space_projector(np.array([0.01, -0.02, 0.27])), null, atol=1e-12)


def test_adaptive_gain_is_vispy_exponential():
    assert adaptive_gain(0.0, 2.0, 0.4, 30.0) == pytest.approx(2.0)
    assert adaptive_gain(10.0, 2.0, 0.4, 30.0) == pytest.approx(0.4)
    h = 1e-7
    assert (adaptive_gain(h, 2.0, 0.4, 30.0) - 2.0) / h == pytest.approx(-30.0, rel=1e-5)
    assert adaptive_gain(0.05, 2.0, 0.4, 30.0) == pytest.approx(1.6 * np.exp(-30 * 0.05 / 1.6) + 0.4)


def simulate(servo: DualTaskServo, T: np.ndarray, P: np.ndarray, g: np.ndarray, steps: int, dt: float = 0.02):
    errors, poses, secondary = [], [], []
    for _ in range(steps):
        out = servo.step(centroid_in_camera(T, P), g)
        errors.append(np.linalg.norm(out.e))
        secondary.append(out.secondary)
        T = move_camera(T, out.v, dt)
        poses.append(T)
    return np.array(errors), poses, np.array(secondary)


def test_primary_task_converges_before_the_secondary_starts():
    P = np.array([0.45, 0.0, 0.06])
    T = look_at(P + np.array([-0.3, 0.05, 0.12]), P + np.array([0.03, -0.04, 0.0]))
    servo = DualTaskServo(standoff_m=0.25, **PAPER)
    g = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    errors, _, secondary = simulate(servo, T, P, g, steps=600)
    first = int(np.argmax(secondary))
    assert errors[0] > 0.05
    assert secondary[first] and not secondary[:first].any() and secondary[first:].all()
    assert errors[first] < 0.005 and errors[first - 1] >= 0.005
    # The error decays monotonically while the primary task acts alone.
    assert np.all(np.diff(errors[:first]) < 0)


def test_secondary_task_moves_on_the_sphere_keeping_the_object_centred():
    P = np.array([0.45, 0.0, 0.06])
    T = look_at(P + np.array([-0.25, 0.0, 0.0]), P)  # already converged: e = 0
    servo = DualTaskServo(standoff_m=0.25, **PAPER)
    errors, poses, secondary = simulate(servo, T, P, np.array([0.0, -1.0, 0.0, 0.0, 0.0, 0.0]), steps=300)
    assert secondary.all()
    # The projector keeps the orbit (v, w) = (0, Z, 0, 1, 0, 0) / sqrt(1 + Z^2) of g; its translation is
    # lambda_g Z^2 / (1 + Z^2) = 1.9 cm/s (the paper's 0.8 m in 42 s is of this order).
    path = sum(np.linalg.norm(b[:3, 3] - a[:3, 3]) for a, b in pairwise(poses))
    assert path / (299 * 0.02) == pytest.approx(0.33 * 0.25**2 / (1 + 0.25**2), rel=0.02)
    assert errors.max() < 0.01  # the null-space motion barely disturbs the primary task
    radii = [np.linalg.norm(p[:3, 3] - P) for p in poses]
    assert max(abs(r - 0.25) for r in radii) < 0.01
    assert poses[-1][2, 3] > T[2, 3] + 0.08  # camera -y is up here: it climbed towards the top


def test_secondary_task_is_ignored_until_the_primary_converges():
    servo = DualTaskServo(standoff_m=0.25, **PAPER)
    s = np.array([0.05, 0.0, 0.3])
    with_g = servo.step(s, np.ones(6))
    without = DualTaskServo(standoff_m=0.25, **PAPER).step(s, np.zeros(6))
    np.testing.assert_allclose(with_g.v, without.v)
    assert not with_g.secondary


def test_rejects_an_increasing_gain():
    with pytest.raises(ValueError, match="lambda_0"):
        DualTaskServo(standoff_m=0.25, **{**PAPER, "lambda_0": 0.3})
