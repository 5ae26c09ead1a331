"""What the hardware arm backends (UR5e, Franka) share: input checks, twist ceilings and frame changes,
lazy imports of client libraries, and the per-controller modes that ``cell arm status`` prints.

Twists are (vx, vy, vz, wx, wy, wz) [m/s, rad/s] in the base frame. A twist of the flange origin and a
twist of a point rigidly attached to the flange (the TCP) share the angular part; the linear parts differ
by the lever: ``v_point = v_flange + w x (p_point - p_flange)``.
"""

from __future__ import annotations

import importlib
from abc import abstractmethod
from types import ModuleType

import numpy as np
from numpy.typing import NDArray

from drivers.arm.base import Arm, JointTrajectory
from drivers.errors import DriverError
from drivers.robots.model import RobotModel
from drivers.transforms import make_T, rotation_from_rotvec, rotvec

Array = NDArray[np.float64]

# a trajectory must start this close to where the arm is [rad]
TRAJECTORY_START_TOL_RAD = 1e-2


def require_module(module: str, pip_spec: str, device: str) -> ModuleType:
    """Import a client library, or fail with the pip command that installs it."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise DriverError(f"the client library is missing ({exc}); install it with: "
                          f"pip install '{pip_spec}'", device=device) from None


def checked_vector(values: object, n: int, what: str, device: str) -> Array:
    """``values`` as a float vector of length ``n``, all finite; ``ValueError`` otherwise, so that nothing
    malformed is sent (ur-rtde does not check lengths)."""
    v = np.asarray(values, dtype=float)
    if v.shape != (n,):
        raise ValueError(f"{device}: {what} must have {n} values, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{device}: {what} holds a non-finite value: {v}")
    return v


def clamp_twist(v: Array, max_linear: float, max_angular: float) -> Array:
    """Scale the linear and the angular part of a twist down (direction kept) to the ceilings."""
    out = v.copy()
    for sl, limit in ((slice(0, 3), max_linear), (slice(3, 6), max_angular)):
        speed = float(np.linalg.norm(out[sl]))
        if speed > limit:
            out[sl] *= limit / speed
    return out


def shift_twist(v: Array, lever_base: Array) -> Array:
    """The twist of a point ``lever_base`` [m] (base frame) away from the point whose twist ``v`` is."""
    out = v.copy()
    out[:3] = v[:3] + np.cross(v[3:], lever_base)
    return out


def ur_pose_to_T(pose: object) -> Array:
    """A UR pose (x, y, z [m], rx, ry, rz [rad, axis-angle]) as a 4x4 transform."""
    p = np.asarray(pose, dtype=float)
    return make_T(rotation_from_rotvec(p[3:]), p[:3])


def T_to_ur_pose(T: Array) -> Array:
    return np.concatenate([T[:3, 3], rotvec(T[:3, :3])])


def check_trajectory(trajectory: JointTrajectory, model: RobotModel, q_now: Array, device: str) -> None:
    """Refuse a trajectory for another arm, outside the joint limits, or not starting at ``q_now``."""
    n = model.n_joints
    if trajectory.q.shape[1] != n:
        raise ValueError(f"{device}: trajectory has {trajectory.q.shape[1]} joints, the arm has {n}")
    if np.any(trajectory.q < model.q_min) or np.any(trajectory.q > model.q_max):
        raise ValueError(f"{device}: trajectory leaves the {model.name} joint limits")
    dev = float(np.max(np.abs(trajectory.q[0] - q_now)))
    if dev > TRAJECTORY_START_TOL_RAD:
        raise ValueError(f"{device}: trajectory starts {dev:.4f} rad away from the current joints "
                         f"(tolerance {TRAJECTORY_START_TOL_RAD} rad)")


def interpolate(trajectory: JointTrajectory, t: float) -> Array:
    """Joint positions at time ``t`` [s] from the trajectory's start (held at the ends)."""
    tt = trajectory.t[0] + t
    return np.array([np.interp(tt, trajectory.t, trajectory.q[:, j]) for j in range(trajectory.q.shape[1])])


class HardwareArm(Arm):
    """An arm behind a real controller: it can say what the controller's own modes are."""

    @abstractmethod
    def controller_modes(self) -> dict[str, str]:
        """The controller's modes in words (e.g. ``{"safety mode": "PROTECTIVE_STOP"}``), for people."""
