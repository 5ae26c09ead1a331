"""A read-only arm that follows a recorded job's poses (see :mod:`drivers.depth.replay`).

``state()`` reports the recorded flange pose at the clock's time: the last recorded pose at or before it
(zero-order hold; the recorder writes one every control tick, and the exact pose of every capture), the
first one before the recording starts and the last one after it ends. ``q`` is the joints the job recorded
at the last tick at or before the clock's time (``joints.csv``; NaN for a job recorded without them);
``qd`` and the flange twist are zero.

It cannot move: ``command_twist`` and ``execute_trajectory`` raise ``DriverError`` (after the motion
token check, so the safety guard stays the only way in). ``stop`` and ``recover`` do nothing: a recording
has nothing to stop and no fault to clear.
"""

from __future__ import annotations

import numpy as np

from drivers.arm.base import Arm, ArmMode, ArmState, JointTrajectory
from drivers.clock import Clock
from drivers.depth.replay import CSV_TIME_RESOLUTION_S, JobRecording
from drivers.errors import DriverError
from drivers.local_link import LocalLink
from drivers.robots.model import RobotModel

Array = np.ndarray


class ReplayArm(LocalLink, Arm):
    """The recorded poses of ``recording`` on ``clock`` as an arm of ``model`` (which only gives the
    number of joints)."""

    name = "replay"

    def __init__(self, recording: JobRecording, model: RobotModel, clock: Clock) -> None:
        self.recording = recording
        self._model = model
        self._clock = clock
        self._times, self._poses = recording.flange_track()
        joints = recording.joint_track()
        # joints of another arm's count are as good as none: decided once, not at every tick
        self._joints = joints if joints is not None and joints[1].shape[1] == model.n_joints else None
        self._unknown = np.full(model.n_joints, np.nan)

    @property
    def device(self) -> str:
        return f"arm replay of {self.recording.job_dir}"

    @property
    def n_joints(self) -> int:
        return self._model.n_joints

    @property
    def end_time(self) -> float:
        """The time of the last recorded pose [s, job clock]."""
        return float(self._times[-1])

    def pose_at(self, t: float) -> Array:
        """The recorded T_base_flange at time ``t`` [s] (a copy)."""
        # trajectory times carry 6 decimals: a time within half a microsecond counts as reached
        k = int(np.searchsorted(self._times, t + CSV_TIME_RESOLUTION_S / 2, side="right")) - 1
        return self._poses[max(k, 0)].copy()

    def joints_at(self, t: float) -> Array:
        """The recorded joints [rad] at time ``t`` [s] (zero-order hold, as :meth:`pose_at`); NaN when the
        job did not record them."""
        if self._joints is None:
            return self._unknown.copy()
        times, q = self._joints
        k = int(np.searchsorted(times, t + CSV_TIME_RESOLUTION_S / 2, side="right")) - 1
        return q[max(k, 0)].copy()

    def state(self) -> ArmState:
        self._require_connected("state", self.device)
        t = self._clock.now()
        n = self._model.n_joints
        return ArmState(timestamp=t, q=self.joints_at(t), qd=np.zeros(n), T_base_flange=self.pose_at(t),
                        v_base_flange=np.zeros(6), mode=ArmMode.IDLE)

    def _command_twist(self, v_base_flange: Array) -> None:
        raise DriverError("a replayed job's arm cannot move (it plays recorded poses)", device=self.device)

    def _execute_trajectory(self, trajectory: JointTrajectory) -> None:
        raise DriverError("a replayed job's arm cannot move (it plays recorded poses)", device=self.device)

    def stop(self) -> None:
        """Nothing to stop: the recorded poses play on regardless."""

    def recover(self) -> None:
        """Nothing to recover: a recording has no faults."""
