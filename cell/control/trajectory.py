"""Time-optimal, jerk-limited point-to-point trajectories in joint space (ruckig, offline interface)."""

from __future__ import annotations

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
    n = model.n_joints
    inp = InputParameter(n)
    inp.current_position = np.asarray(q_start, dtype=float).tolist()
    inp.target_position = np.asarray(q_goal, dtype=float).tolist()
    inp.max_velocity = (model.qd_max * velocity_scale).tolist()
    inp.max_acceleration = (model.qdd_max * acceleration_scale).tolist()
    inp.max_jerk = (model.qddd_max * jerk_scale).tolist()
    traj = Trajectory(n)
    result = Ruckig(n).calculate(inp, traj)
    if result not in (Result.Working, Result.Finished):
        raise PlanningError(f"ruckig could not plan the joint move: {result}")
    steps = max(1, int(np.ceil(traj.duration / dt)))
    t = np.linspace(0.0, traj.duration, steps + 1) if traj.duration > 0 else np.array([0.0])
    samples = [traj.at_time(float(ti)) for ti in t]
    q = np.array([s[0] for s in samples])
    qd = np.array([s[1] for s in samples])
    q[-1] = q_goal
    return JointTrajectory(t=t, q=q, qd=qd)
