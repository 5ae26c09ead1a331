"""The motion guard: every motion command of a job passes here before it reaches the arm backend.

It checks and limits what it forwards:

- twists: finite, six values; the flange's linear and angular speed scaled down (direction kept) to the
  cell's ``tcp_max_linear_mps`` / ``tcp_max_angular_rps``, each clamp counted; refused when the flange or
  the sensor would leave the workspace box within ``lookahead_s``;
- joint trajectories: every sample inside the joint limits, joint speeds within the cell's share of the
  model's maxima, flange and sensor inside the workspace box at every sample; refused otherwise, naming
  the first offending sample.

A refusal stops the arm and raises ``SafetyStop``; the reason is recorded in the job's ``SafetyLog``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cell.config.models import SafetyConfig
from cell.safety.events import SafetyLog
from drivers.arm.base import Arm, ArmState, JointTrajectory
from drivers.clock import Clock
from drivers.errors import SafetyStop
from drivers.robots.model import RobotModel

Array = NDArray[np.float64]

LOOKAHEAD_S = 0.1
# Joint speeds of sampled trajectories are finite differences, a hair above the planned bound.
VELOCITY_TOLERANCE = 1.02


class MotionGuard:
    """Owns the arm's motion methods for a job. ``T_flange_sensor`` is the hand-eye transform."""

    def __init__(self, arm: Arm, model: RobotModel, safety: SafetyConfig, T_flange_sensor: Array,
                 clock: Clock, log: SafetyLog | None = None) -> None:
        self._arm = arm
        self._model = model
        self._safety = safety
        self._T_flange_sensor = T_flange_sensor
        self._clock = clock
        self._token = arm.claim_motion()
        self.log = log if log is not None else SafetyLog()
        self._ws_min = np.asarray(safety.workspace.min_m)
        self._ws_max = np.asarray(safety.workspace.max_m)

    def state(self) -> ArmState:
        return self._arm.state()

    def _outside(self, T_base_flange: Array) -> str | None:
        sensor = (T_base_flange @ self._T_flange_sensor)[:3, 3]
        for name, p in (("flange", T_base_flange[:3, 3]), ("sensor", sensor)):
            if np.any(p < self._ws_min) or np.any(p > self._ws_max):
                return f"{name} at {np.round(p, 3).tolist()} m would leave the workspace box"
        return None

    def _refuse(self, reason: str) -> SafetyStop:
        self.log.refuse(self._clock.now(), reason)
        self.stop(f"refused: {reason}")
        return SafetyStop(reason)

    def command_twist(self, v_base_flange: Array) -> Array:
        """Forward a flange twist (base frame, [m/s, rad/s]) after limiting it; returns what was sent."""
        v = np.asarray(v_base_flange, dtype=float)
        if v.shape != (6,) or not np.all(np.isfinite(v)):
            raise self._refuse(f"twist must be 6 finite values, got {np.array2string(v, precision=4)}")
        v = v.copy()
        for kind, sl, limit in (("tcp_linear_speed", slice(0, 3), self._safety.tcp_max_linear_mps),
                                ("tcp_angular_speed", slice(3, 6), self._safety.tcp_max_angular_rps)):
            speed = float(np.linalg.norm(v[sl]))
            if speed > limit:
                v *= limit / speed
                self.log.clamp(kind)
        T = self._arm.state().T_base_flange.copy()
        T[:3, 3] += v[:3] * LOOKAHEAD_S
        reason = self._outside(T)
        if reason:
            raise self._refuse(reason)
        self._arm.command_twist(v, self._token)
        return v

    def execute_trajectory(self, trajectory: JointTrajectory) -> None:
        """Check a joint trajectory sample by sample, then start it."""
        m = self._model
        q = trajectory.q
        if q.shape[1] != m.n_joints:
            raise self._refuse(f"trajectory has {q.shape[1]} joints, the {m.name} has {m.n_joints}")
        bad = np.nonzero(np.any((q < m.q_min) | (q > m.q_max), axis=1))[0]
        if bad.size:
            raise self._refuse(f"trajectory sample {bad[0]} leaves the joint limits")
        if q.shape[0] > 1:
            qd = np.diff(q, axis=0) / np.diff(trajectory.t)[:, None]
            qd_limit = m.qd_max * self._safety.joint_velocity_scale * VELOCITY_TOLERANCE
            fast = np.nonzero(np.any(np.abs(qd) > qd_limit, axis=1))[0]
            if fast.size:
                raise self._refuse(f"trajectory sample {fast[0]} exceeds the joint speed limit")
        for k in range(q.shape[0]):
            reason = self._outside(m.fk(q[k]))
            if reason:
                raise self._refuse(f"trajectory sample {k}: {reason}")
        self._arm.execute_trajectory(trajectory, self._token)

    def stop(self, reason: str) -> None:
        """Bring the arm to rest and record why."""
        self.log.stop(self._clock.now(), reason)
        self._arm.stop()
