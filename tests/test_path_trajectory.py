"""Retiming a recorded joint path rest to rest (``cell.control.trajectory.path_trajectory``)."""

from __future__ import annotations

import numpy as np
import pytest

from cell.control.trajectory import path_trajectory
from drivers.robots import get_robot_model

DT = 0.01


def _recorded_path(model, speed_scale: float) -> np.ndarray:
    """2 s of a joint path passed at ``speed_scale`` of the joints' speed limits, curving (a quarter turn
    in joints 1-2), sampled every DT, with the arm at rest for its last 20 samples."""
    t = np.arange(0.0, 2.0, DT)
    angle = 0.5 * np.pi * t / 2.0
    radius = speed_scale * float(np.min(model.qd_max[:2])) * 2.0 / (0.5 * np.pi)
    q = np.tile(model.q_home, (len(t), 1))
    q[:, 0] += radius * np.sin(angle)
    q[:, 1] += radius * (1.0 - np.cos(angle))
    return np.concatenate([q, np.tile(q[-1], (20, 1))])


@pytest.mark.parametrize("speed_scale", [0.05, 0.9])
def test_a_path_is_retraced_through_its_samples_from_rest_to_rest_within_the_limits(speed_scale):
    model = get_robot_model("panda")
    path = _recorded_path(model, speed_scale)[::-1]  # backwards, from where the arm came to rest
    traj = path_trajectory(model, path, DT, dt=DT, velocity_scale=0.5, acceleration_scale=0.5, jerk_scale=0.5)
    np.testing.assert_array_equal(traj.q[0], path[0])
    np.testing.assert_array_equal(traj.q[-1], path[-1])
    assert traj.qd is not None
    np.testing.assert_allclose(traj.qd[[0, -1]], 0.0, atol=1e-9)
    # on the path: each sample within a hair of one of the polyline's segments
    seg_a = path[:-1]
    d = path[1:] - seg_a
    length2 = np.maximum(np.einsum("kj,kj->k", d, d), 1e-30)
    for q in traj.q:
        w = np.clip(np.einsum("kj,kj->k", q - seg_a, d) / length2, 0.0, 1.0)
        assert np.min(np.linalg.norm(seg_a + w[:, None] * d - q, axis=1)) < 1e-9
    rates = np.abs(np.diff(traj.q, axis=0)) / np.diff(traj.t)[:, None]
    assert np.all(rates <= 0.5 * model.qd_max * 1.001)
    assert traj.t[-1] >= 2.0 * (1.0 - 1e-9)  # never faster than the path was passed (2 s of motion)
    assert traj.t[-1] < 2.0 / min(1.0, 0.5 / speed_scale) + 1.0  # nor much slower than it must be


def test_a_path_of_one_configuration_stays_there():
    model = get_robot_model("panda")
    traj = path_trajectory(model, model.q_home[None, :], DT, dt=DT, velocity_scale=0.5,
                           acceleration_scale=0.5, jerk_scale=0.5)
    np.testing.assert_array_equal(traj.q, model.q_home[None, :])
