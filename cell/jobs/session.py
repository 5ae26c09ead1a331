"""The scan session a planner drives: motion through the guard, captures, accumulation, the job clock.

In sim mode ``wait`` advances the simulated clock one control period at a time, which steps the simulated
arm; the sensor pose is written to ``trajectory.csv`` at every tick. The time budget is checked on every
tick: when it runs out ``TimeBudgetExhausted`` ends the planner's run.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cell.config.models import CellConfig
from cell.control.trajectory import joint_trajectory
from cell.jobs.recorder import JobRecorder
from cell.perception.cloud import CloudAccumulator
from cell.perception.metrics import CoverageTracker
from cell.perception.pipeline import PerceptionPipeline, PerceptionUpdate
from cell.planning.base import Array
from cell.safety.guard import MotionGuard
from drivers.arm.base import ArmMode
from drivers.clock import Clock
from drivers.depth.base import DepthSensor
from drivers.errors import KinematicsError
from drivers.robots.model import RobotModel
from drivers.transforms import inv_T

# A point-to-point move that has not finished this long after its planned duration is a fault.
MOVE_TIMEOUT_MARGIN_S = 2.0


class TimeBudgetExhausted(Exception):
    """The job's time budget ran out; the runner turns this into the termination reason."""


class JobSession:
    """Implements ``cell.planning.base.ScanSession`` for one job."""

    def __init__(self, config: CellConfig, *, clock: Clock, guard: MotionGuard, model: RobotModel,
                 sensor: DepthSensor, perception: PerceptionPipeline, recorder: JobRecorder,
                 max_time_s: float, coverage: CoverageTracker | None,
                 on_progress: Callable[[JobSession], None] | None = None) -> None:
        self.config = config
        self._clock = clock
        self._guard = guard
        self._model = model
        self._sensor = sensor
        self._recorder = recorder
        self._max_time = max_time_s
        self._dt = 1.0 / config.scan.control_rate_hz
        self._T_flange_sensor = config.mount.matrix()
        home = config.arm.home_joints_rad
        self._q_home = np.asarray(home, dtype=float) if home is not None else model.q_home
        self.perception = perception
        self._capture_period = 1.0 / config.perception.rate_hz
        self._next_capture: float | None = None
        self.coverage = coverage
        self.n_captures = 0
        self.n_unreachable = 0
        self.n_registration_rejected = 0
        self.path_length_m = 0.0
        self._last_position: Array | None = None
        self._on_progress = on_progress
        self._record_pose()

    def now(self) -> float:
        return self._clock.now()

    def log(self, message: str) -> None:
        self._recorder.log(self.now(), message)

    def sensor_pose(self) -> Array:
        return self._guard.state().T_base_flange @ self._T_flange_sensor

    def _record_pose(self) -> None:
        T = self.sensor_pose()
        p = T[:3, 3]
        if self._last_position is not None:
            self.path_length_m += float(np.linalg.norm(p - self._last_position))
        self._last_position = p
        self._recorder.pose(self.now(), T)

    @property
    def cloud(self) -> CloudAccumulator:
        return self.perception.cloud

    def latest_perception(self) -> PerceptionUpdate | None:
        return self.perception.latest

    def set_continuous_capture(self, on: bool) -> None:
        """Capture at ``perception.rate_hz`` of job time while the planner moves the arm (first capture
        at once), or stop doing so."""
        self._next_capture = self.now() if on else None

    def _tick(self) -> None:
        if self.now() >= self._max_time:
            raise TimeBudgetExhausted(f"time budget of {self._max_time:g} s used up")
        if self._next_capture is not None and self.now() >= self._next_capture - 1e-9:
            self._next_capture += self._capture_period
            self.capture()
        self._clock.sleep(self._dt)
        self._record_pose()

    def wait(self, dt: float) -> None:
        end = self.now() + dt
        while self.now() < end - 1e-9:
            self._tick()

    def move_to_sensor_pose(self, T_base_sensor: Array) -> bool:
        state = self._guard.state()
        q_goal = self._solve_ik(T_base_sensor @ inv_T(self._T_flange_sensor), state.q)
        if q_goal is None:
            self.n_unreachable += 1
            return False
        s = self.config.safety
        traj = joint_trajectory(self._model, state.q, q_goal, dt=self._dt,
                                velocity_scale=s.joint_velocity_scale,
                                acceleration_scale=s.joint_acceleration_scale, jerk_scale=s.joint_jerk_scale)
        self._guard.execute_trajectory(traj)
        deadline = self.now() + traj.duration + MOVE_TIMEOUT_MARGIN_S
        while self._guard.state().mode == ArmMode.TRAJECTORY:
            if self.now() > deadline:
                raise KinematicsError("the arm did not finish its move in time")
            self._tick()
        return True

    def _solve_ik(self, T_base_flange: Array, q_now: Array) -> Array | None:
        """Joints reaching ``T_base_flange``, seeded from the current joints, then from home.

        Seeding from the current joints keeps moves short; a redundant arm can however drift into a
        folded configuration from which the next views are out of reach, and the home seed recovers.
        """
        error: KinematicsError | None = None
        for seed in (q_now, self._q_home):
            try:
                return self._model.ik_pose(T_base_flange, seed)
            except KinematicsError as exc:
                error = exc
        self.log(f"view at {np.round(T_base_flange[:3, 3], 3).tolist()} (flange) unreachable: {error}")
        return None

    def capture(self) -> int:
        frame = self._sensor.capture()
        state = self._guard.state()
        T_fk = state.T_base_flange @ self._T_flange_sensor
        update = self.perception.process(frame, T_fk)
        reg = update.registration
        self._recorder.frame(frame, T_fk, state.T_base_flange,
                             {"T_base_sensor_registered": update.T_base_sensor})
        self.n_captures += 1
        if reg.rejected:
            self.n_registration_rejected += 1
        if self.coverage is not None:
            self.coverage.add(update.points_base)
        h = f"{update.h_roi:.4f}" if update.h_roi is not None else "-"
        self.log(f"capture {frame.seq}: {frame.points.shape[0]} points, {update.points_base.shape[0]} after "
                 f"filtering; registration {reg.reason} (fitness {reg.fitness:.3f}, correction "
                 f"{reg.correction_m * 1e3:.2f} mm / {reg.correction_deg:.3f} deg); H_ROI {h}")
        if self._on_progress is not None:
            self._on_progress(self)
        return int(update.points_base.shape[0])
