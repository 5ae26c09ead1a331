"""Time-optimal, jerk-limited point-to-point trajectories in joint space (ruckig, offline interface)."""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray
from ruckig import InputParameter, Result, Ruckig, Trajectory

from drivers.arm.base import JointTrajectory
from drivers.errors import PlanningError
from drivers.robots.model import RobotModel

Array = NDArray[np.float64]


def joint_trajectory(model: RobotModel, q_start: Array, q_goal: Array, *, dt: float,
                     velocity_scale: float, acceleration_scale: float, jerk_scale: float) -> JointTrajectory:
    """Rest-to-rest trajectory from ``q_start`` to ``q_goal`` [rad], sampled every ``dt`` [s].

    Each joint's velocity, acceleration and jerk are bounded by the model's maxima times the given
    scales (0, 1]; ruckig makes the move time-optimal under those bounds with all joints synchronised.
    The last sample is exactly ``q_goal``.
    """
    return waypoint_trajectory(model, [q_start, q_goal], dt=dt, velocity_scale=velocity_scale,
                               acceleration_scale=acceleration_scale, jerk_scale=jerk_scale)


def waypoint_trajectory(model: RobotModel, waypoints: Sequence[Array], *, dt: float, velocity_scale: float,
                        acceleration_scale: float, jerk_scale: float) -> JointTrajectory:
    """Rest-to-rest through each of ``waypoints`` (at least 2 joint vectors [rad]) in turn: the move of
    :func:`joint_trajectory` between every two consecutive ones, joined where the arm is at rest, sampled
    every ``dt`` [s]. The last sample is exactly the last waypoint."""
    scales = (velocity_scale, acceleration_scale, jerk_scale)
    n = model.n_joints
    ts, qs, qds = [np.zeros(1)], [np.asarray(waypoints[0], dtype=float).reshape(1, n)], [np.zeros((1, n))]
    for a, b in pairwise(waypoints):
        t, q, qd = _rest_to_rest(model, a, b, dt, scales)
        ts.append(t[1:] + ts[-1][-1])  # each leg's first sample is the previous one's last, at rest
        qs.append(q[1:])
        qds.append(qd[1:])
    return JointTrajectory(t=np.concatenate(ts), q=np.vstack(qs), qd=np.vstack(qds))


def _rest_to_rest(model: RobotModel, q_start: Array, q_goal: Array, dt: float,
                  scales: tuple[float, float, float]) -> tuple[Array, Array, Array]:
    """Times (K,) [s], joints (K, n) [rad] and joint speeds (K, n) [rad/s] of the move of
    :func:`joint_trajectory` from ``q_start`` to ``q_goal``; ``scales`` its velocity, acceleration and jerk
    scales."""
    n = model.n_joints
    inp = InputParameter(n)
    inp.current_position = np.asarray(q_start, dtype=float).tolist()
    inp.target_position = np.asarray(q_goal, dtype=float).tolist()
    inp.max_velocity = (model.qd_max * scales[0]).tolist()
    inp.max_acceleration = (model.qdd_max * scales[1]).tolist()
    inp.max_jerk = (model.qddd_max * scales[2]).tolist()
    traj = Trajectory(n)
    result = Ruckig(n).calculate(inp, traj)
    if result not in (Result.Working, Result.Finished):
        raise PlanningError(f"ruckig could not plan the joint move: {result}")
    q, qd, t = _sampled(traj, dt)
    q[-1] = q_goal
    return t, q, qd


def path_trajectory(model: RobotModel, path: Array, path_dt: float, *, dt: float, velocity_scale: float,
                    acceleration_scale: float, jerk_scale: float) -> JointTrajectory:
    """Rest-to-rest trajectory along a recorded joint path: ``path`` (K, n) [rad], its samples ``path_dt``
    [s] apart as the arm passed them (in either direction of time; linear between samples), sampled every
    ``dt`` [s].

    The path's own time u [s] follows ruckig's time-optimal one-axis profile from 0 to its end, rest to
    rest: du/dt at most 1 (never faster than the arm passed it, so the path's curvature asks no more of a
    joint than it did then) and at most each joint's scaled speed over its fastest rate along the path,
    d2u/dt2 and d3u/dt3 at most each joint's scaled acceleration and jerk over that rate (the profile's
    own share, q'(u) u'' and q'(u) u'''). The last sample is exactly the path's end.
    """
    q_path = np.asarray(path, dtype=float)
    if q_path.shape[0] < 2:
        return JointTrajectory(t=np.array([0.0]), q=q_path[:1].copy())
    fastest = np.maximum(np.max(np.abs(np.diff(q_path, axis=0)), axis=0) / path_dt, 1e-12)  # |dq/du|
    inp = InputParameter(1)
    inp.current_position = [0.0]
    inp.target_position = [path_dt * (q_path.shape[0] - 1)]
    inp.max_velocity = [min(1.0, float(np.min(model.qd_max * velocity_scale / fastest)))]
    inp.max_acceleration = [float(np.min(model.qdd_max * acceleration_scale / fastest))]
    inp.max_jerk = [float(np.min(model.qddd_max * jerk_scale / fastest))]
    traj = Trajectory(1)
    result = Ruckig(1).calculate(inp, traj)
    if result not in (Result.Working, Result.Finished):
        raise PlanningError(f"ruckig could not time the joint path: {result}")
    u, du, t = _sampled(traj, dt)
    k = np.clip(np.floor(u[:, 0] / path_dt).astype(int), 0, q_path.shape[0] - 2)
    w = u / path_dt - k[:, None]
    q = (1.0 - w) * q_path[k] + w * q_path[k + 1]
    qd = (q_path[k + 1] - q_path[k]) / path_dt * du
    q[-1] = q_path[-1]
    return JointTrajectory(t=t, q=q, qd=qd)


def _sampled(traj: Trajectory, dt: float) -> tuple[Array, Array, Array]:
    """A ruckig trajectory's positions and velocities (K, axes) at K times (K,) [s] from 0 to its end,
    at most ``dt`` apart."""
    steps = max(1, int(np.ceil(traj.duration / dt)))
    t = np.linspace(0.0, traj.duration, steps + 1) if traj.duration > 0 else np.array([0.0])
    samples = [traj.at_time(float(ti)) for ti in t]
    return np.array([s[0] for s in samples]), np.array([s[1] for s in samples]), t
