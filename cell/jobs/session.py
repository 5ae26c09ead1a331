"""The scan session a planner drives: motion through the guard, captures, accumulation, the job clock.

Every control period is one tick: the time budget, an operator stop (``request_stop``, or a ``STOP``
file in the job folder written by ``cell stop``), a due continuous capture, then the guard's tick
(watchdog, arm faults, the next streamed command), then the clock moves on by one period (in sim mode this
steps the simulated arm) and the sensor pose is written to ``trajectory.csv``. When the time budget runs
out ``TimeBudgetExhausted`` (a ``ScanLimitReached``) ends the planner's run; a safety stop raises
``SafetyStop``.

While continuous capture is on (planners that move from perception), the watchdog judges the age of the
newest frame; a frame the sensor fails to deliver then is logged and counted, and the watchdog stops the
arm if no frame arrives for too long.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections import Counter, deque
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cell.config.models import CellConfig
from cell.control.decimation import DecimatedSeries
from cell.control.trajectory import path_trajectory, waypoint_trajectory
from cell.jobs.live import LivePerception, PoseHistory
from cell.jobs.progress import ControlTicks, JobProgress, quat_of, xyz_m
from cell.jobs.recorder import JobRecorder
from cell.jobs.requests import REACHABLE, REACHED, REFUSED, UNREACHABLE
from cell.packing.objects import current_object
from cell.perception.cloud import CloudAccumulator
from cell.perception.metrics import CloudCoverage
from cell.perception.pipeline import PerceptionPipeline, PerceptionUpdate
from cell.planning.base import Array
from cell.safety.events import Refusal
from cell.safety.guard import MotionGuard, TwistRefused
from drivers.arm.base import ArmState, JointTrajectory
from drivers.clock import Clock
from drivers.depth.base import DepthFrame, DepthSensor, SensorModel
from drivers.errors import DriverError, KinematicsError
from drivers.robots.model import RobotModel
from drivers.transforms import T_from_xyz_rpy, inv_T

# A point-to-point move that has not finished this long after its planned duration is a fault.
MOVE_TIMEOUT_MARGIN_S = 2.0
# After a stop the job records the arm until every joint is slower than this, for at most this long.
SETTLED_QD_RAD_S = 1e-4
SETTLE_TIMEOUT_S = 3.0
# On the wall clock, how long a capture waits for a frame newer than its request.
STALE_FRAME_TIMEOUT_S = 2.0
# Between consecutive poses of a path a few centimetres apart, a joint moving further than this [rad] is a
# change of configuration (an elbow or wrist flip), which a servo following the path cannot make.
MAX_PATH_JOINT_STEP_RAD = 0.5
# Two IK solutions whose joints all lie within this of each other [rad] are one (the solver stops within
# 1e-3 rad of the pose).
SAME_SOLUTION_RAD = 0.01
# How far back in job time [s] the joint path is kept for ``retrace``, and the shares of the asked duration
# it tries in turn.
JOINT_PATH_KEPT_S = 5.0
RETRACE_SHARES = (1.0, 0.5, 0.25)


def same_view_rolls(sensor: SensorModel) -> tuple[float, ...]:
    """Rolls [rad] of the sensor about its optical axis, other than none, after which it sees what it saw:
    its field of view and its grid of zones (or pixels), symmetric about the axis, map onto themselves. A
    quarter turn either way and a half turn for a square grid over a square field (the VL53L8CX's 8 x 8
    zones over 45 x 45 deg: a zone's central ray turns into another zone's), a half turn for a rectangle
    (a camera's image turns upside down; its principal point is taken to be the image centre). The flange
    pose differs by the roll, so a view whose joints lie past a joint's limit margin, or whose move the
    guard refuses, may be reached rolled; the capture records the pose it was taken from."""
    square = sensor.width == sensor.height and math.isclose(sensor.fov_x_deg, sensor.fov_y_deg)
    return (math.pi / 2.0, -math.pi / 2.0, math.pi) if square else (math.pi,)


def view_name(T_base_sensor: Array) -> str:
    """A view (sensor pose (4, 4), base frame) as the log names it: its position [m], rounded to 1 mm."""
    return f"view at {np.round(T_base_sensor[:3, 3], 3).tolist()} (sensor)"


def retrace_starts(times: Sequence[float], stopped_at_s: float, duration_s: float) -> list[tuple[float, int]]:
    """Where ``JobSession.retrace`` tries to go back to, in turn: for each share of ``RETRACE_SHARES``, the
    time back [s] and the index in ``times`` (job times [s] of the recorded joints, in order) of the last
    record at least that long before ``stopped_at_s`` [s], or of the first where the record starts later."""
    out = []
    for share in RETRACE_SHARES:
        back_to = stopped_at_s - share * duration_s
        out.append((share * duration_s, max(0, bisect_right(times, back_to + 1e-9) - 1)))
    return out


class ScanLimitReached(Exception):
    """The job reached a limit that ends the planner's run (not a fault); the runner turns the message
    into the termination reason."""


class TimeBudgetExhausted(ScanLimitReached):
    """The job's time budget ran out."""


class JobSession:
    """Implements ``cell.planning.base.ScanSession`` for one job."""

    def __init__(self, config: CellConfig, *, clock: Clock, guard: MotionGuard, model: RobotModel,
                 sensor: DepthSensor, perception: PerceptionPipeline, recorder: JobRecorder,
                 max_time_s: float, coverage: CloudCoverage | None, rng: np.random.Generator,
                 on_progress: Callable[[JobSession], None] | None = None,
                 stop_file: Path | None = None, poses: PoseHistory | None = None) -> None:
        self.config = config
        self.rng = rng
        self._clock = clock
        self._guard = guard
        self._model = model
        self._sensor = sensor
        self._recorder = recorder
        self._max_time = max_time_s
        self._dt = 1.0 / config.scan.control_rate_hz
        self._T_flange_sensor = config.mount.matrix()
        self._q_home = model.home(config.arm.home_joints_rad)
        self.perception = perception
        self._capture_period = 1.0 / config.perception.rate_hz
        self._next_capture: float | None = None
        self._perception_time: float | None = None
        self._stop_file = stop_file
        self.coverage = coverage
        self.n_captures = 0
        # job time [s] and sensor path [m] at the first recorded frame: where the paper's scan time and
        # trajectory length start (section III-C)
        self.first_frame_time: float | None = None
        self.first_frame_path_m = 0.0
        # the sensor origin [m], base frame, that the first recorded frame was taken from (FK): where the
        # scan starts on its path (``path.png``), the path itself starting at home
        self.first_frame_position: Array | None = None
        self.n_capture_failures = 0
        self.refused_moves: Counter[str] = Counter()
        self.n_unreachable = 0
        self.n_registration_rejected = 0
        # per capture, the directions of the ICP correction kept by the degeneracy-aware acceptance (6 when
        # ICP did not run; registration.RegistrationResult.n_constrained)
        self.registration_n_constrained: list[int] = []
        self.path_length_m = 0.0
        # The sensor origin [m], base frame, at every tick (decimated in long jobs); (job time [s],
        # coverage [%]: eq. 13 of the cloud as it stands, unregistered, ``CloudCoverage``) at every capture.
        self.sensor_path: DecimatedSeries[Array] = DecimatedSeries()
        self.coverage_history: list[tuple[float, float]] = []
        self._on_progress = on_progress
        self.ticks = ControlTicks(self._dt)
        self._T_base_sensor = np.eye(4)
        self._latest: PerceptionUpdate | None = None
        self._poses = poses
        self._live: LivePerception | None = None
        # (job time [s], joints [rad]) at every tick over the last JOINT_PATH_KEPT_S, for ``retrace``
        self._joint_path: deque[tuple[float, Array]] = deque(maxlen=int(JOINT_PATH_KEPT_S / self._dt) + 1)
        # the sensor twist last commanded (sensor frame [m/s, rad/s]), which a refusal refuses, and the
        # guard's refusal of the move or retrace under way: what planner_requests.csv records of them
        self._streamed: Array | None = None
        self._refusal: Refusal | None = None
        self._record_pose(self._guard.state())

    def now(self) -> float:
        return self._clock.now()

    def log(self, message: str) -> None:
        self._recorder.log(self.now(), message)

    def sensor_pose(self) -> Array:
        return self._guard.state().T_base_flange @ self._T_flange_sensor

    def sensor_model(self) -> SensorModel:
        return self._sensor.model

    def _record_pose(self, state: ArmState) -> None:
        T_base_flange = state.T_base_flange
        self._joint_path.append((self.now(), state.q))
        T = T_base_flange @ self._T_flange_sensor
        self._T_base_sensor = T
        p = T[:3, 3]
        if self.sensor_path:
            self.path_length_m += float(np.linalg.norm(p - self.sensor_path.last))
        self.sensor_path.append(p)
        self._recorder.pose(self.now(), T)
        self._recorder.joints(self.now(), state.q)
        if self._poses is not None:
            self._poses.add(self.now(), T_base_flange)

    @property
    def cloud(self) -> CloudAccumulator:
        return self.perception.cloud

    @property
    def object_found(self) -> bool:
        """Whether the job has seen an object above the table (what it saw, not ground truth): segmentation
        found one in a frame, or the occupancy map built from all its frames holds one. The map's object
        is the one LR-NBV scans and the packing box is measured on; a part about as high as the table cut
        (a 12 mm washer on the 8 x 8 ToF cell, its zones mixing it with the table) can stand out only
        from the evidence of several frames, and a job that scanned it and measured its box must not
        report that it found nothing."""
        return self.perception.extent.min_m is not None or current_object(self.perception).shape[0] > 0

    def latest_perception(self) -> PerceptionUpdate | None:
        return self._latest

    def set_continuous_capture(self, on: bool) -> None:
        """Capture while the planner moves the arm, or stop doing so. On the simulated clock: at
        ``perception.rate_hz`` of job time, first capture at once, in the planner's thread. On the wall
        clock (``poses`` given): the sensor's own rate, asynchronously (``cell.jobs.live``)."""
        self._next_capture = self.now() if on and self._poses is None else None
        self._perception_time = self.now() if on else None
        if self._poses is None or on == (self._live is not None):
            return
        if on:
            self._live = LivePerception(self._sensor, self.perception, self._poses, self._T_flange_sensor,
                                        record=self._record, log=self.log)
            self._live.start()
        else:
            self.close()

    def close(self) -> None:
        """Stop asynchronous capture if it runs (the end of a job, whatever ended it)."""
        live, self._live = self._live, None
        if live is not None:
            live.stop()
            self.n_capture_failures += live.n_capture_failures

    def request_stop(self, reason: str, *, operator: bool = True) -> None:
        """Stop the job (any thread): the arm stops now and the job ends at its next tick, ``stopped``; an
        operator stop unless not ``operator`` (``MotionGuard.request_stop``)."""
        self._guard.request_stop(reason, operator=operator)

    def _tick(self) -> None:
        fault = self._sensor.latched_fault()
        if fault is not None:  # a stop-and-go planner's move would run to its end, a second or more
            raise fault
        if self.now() >= self._max_time:
            raise TimeBudgetExhausted(f"time budget of {self._max_time:g} s used up")
        if self._stop_file is not None and self._stop_file.exists():
            reason = self._stop_file.read_text().strip() or "requested"
            self._stop_file.unlink()
            self.request_stop(f"{reason} (cell stop)")
        if self._next_capture is not None and self.now() >= self._next_capture - 1e-9:
            self._next_capture += self._capture_period
            self._capture_continuous()
        if self._live is not None:
            update = self._live.poll()
            if update is not None:
                self._apply(update)
        self._guard_tick()
        self._clock.sleep(self._dt)
        self.ticks.record(self.now())
        self._record_pose(self._guard.state())

    def _guard_tick(self) -> None:
        """The guard's part of a control tick (``MotionGuard.tick``): where it refuses a streamed twist."""
        self._guard.tick(self._perception_time)

    def progress(self, planner: dict[str, float | int | str | None]) -> JobProgress:
        """The job now, for ``run_scan``'s ``on_progress`` (control thread); ``planner`` holds the
        planner's own figures (``Planner.figures``)."""
        latest = self._latest
        extent = latest.extent if latest is not None else None
        stages = self.perception.stage_times.last
        return JobProgress(
            t_s=round(self.now(), 6), n_captures=self.n_captures,
            sensor_xyz_m=xyz_m(self._T_base_sensor[:3, 3]), sensor_quat_xyzw=quat_of(self._T_base_sensor),
            path_length_m=round(self.path_length_m, 6),
            h_roi=round(latest.h_roi, 6) if latest is not None and latest.h_roi is not None else None,
            h_roi_entropy=self.perception.h_roi_entropy,
            coverage_pct=round(self.coverage.coverage_pct, 3) if self.coverage is not None else None,
            roi_box_m=None if extent is None else (xyz_m(extent[0]), xyz_m(extent[1])),
            n_cloud_points=int(self.cloud.points.shape[0]),
            perception_cycle_s=round(sum(wall for wall, _ in stages.values()) * 1e-3, 6) if stages else None,
            planner=planner, ticks=self.ticks.histogram())

    def settle(self, timeout_s: float = SETTLE_TIMEOUT_S) -> bool:
        """After a stop: let time pass, recording the pose, until the arm reports rest (True) or
        ``timeout_s`` [s] passes or the arm no longer answers (False). Nothing is commanded."""
        end = self.now() + timeout_s
        ticked = False
        while True:
            try:
                state = self._guard.arm_state()
            except DriverError:
                return False
            if ticked:
                self._record_pose(state)
            if not np.any(np.abs(state.qd) > SETTLED_QD_RAD_S):
                return True
            if self.now() >= end:
                return False
            self._clock.sleep(self._dt)
            ticked = True

    def _capture_continuous(self) -> None:
        try:
            self.capture()
        except DriverError as exc:
            self.n_capture_failures += 1
            self.log(f"capture failed: {exc}")

    def wait(self, dt: float) -> None:
        """Let ``dt`` [s] pass. A streamed twist the guard refuses (``TwistRefused``: the arm has been
        stopped) is counted in ``refused_moves``, logged, recorded in ``planner_requests.csv`` (what a
        replay refuses it from) and raised to the planner, which may back off."""
        end = self.now() + dt
        while self.now() < end - 1e-9:
            try:
                self._tick()
            except TwistRefused as exc:
                self.refused_moves[exc.refusal.kind] += 1
                self.log(f"streamed twist refused, the arm stopped: {exc.refusal.message}")
                self._request(self.now(), "twist", v_sensor=self._streamed, answer=REFUSED,
                              refusal=exc.refusal)
                raise

    def move_to_sensor_pose(self, T_base_sensor: Array) -> bool:
        """The first of :meth:`_routes` to the pose that the guard accepts, followed, else the first to one
        of the pose's rolls that see the same (:func:`same_view_rolls`, tried only when joints reach the
        pose itself); False when there is none, the direct move's refusal recorded and counted (or the pose
        counted unreachable when no joints reach it). :meth:`sensor_view_reachable` gives its verdict on
        the goal beforehand, without the path. The request and its answer go to ``planner_requests.csv``
        (``cell.jobs.requests``: what a replay answers with)."""
        asked, self._refusal = self.now(), None
        reached = self._move_to_view(T_base_sensor)
        self._request(asked, "move", T_base_sensor, answer=REACHED if reached else REFUSED, t_done=self.now(),
                      refusal=None if reached else self._refusal)
        return reached

    def _request(self, t: float, kind: str, T_base_sensor: Array | None = None, v_sensor: Array | None = None,
                 answer: str = "", t_done: float | None = None, refusal: Refusal | None = None) -> None:
        """One row of ``planner_requests.csv``: a request asked at ``t`` [s], its answer and the guard's
        refusal."""
        self._recorder.planner_request(t, kind, T_base_sensor, v_sensor, answer, t_done, refusal)

    def _move_to_view(self, T_base_sensor: Array) -> bool:
        """:meth:`move_to_sensor_pose`'s move, unrecorded (a refusal is kept for the record)."""
        what = view_name(T_base_sensor)
        q_now, T_sensor_flange = self._guard.state().q, inv_T(self._T_flange_sensor)
        refusal: Refusal | None = None
        for roll in (0.0, *same_view_rolls(self._sensor.model)):
            if roll != 0.0 and refusal is None:
                break
            T_rolled = T_base_sensor @ T_from_xyz_rpy(np.zeros(3), (0.0, 0.0, roll))
            for waypoints in self._routes(T_rolled @ T_sensor_flange, q_now):
                traj = waypoint_trajectory(self._model, waypoints, dt=self._dt, **self._joint_scales())
                started, refused = self._guard.try_trajectory(traj)
                if refused is None:
                    self._until_done(started)
                    return True
                refusal = refusal or refused
        if refusal is None:
            self.n_unreachable += 1
        else:
            self._refused(refusal, what)
        return False

    def _routes(self, T_base_flange: Array, q_now: Array) -> Iterator[list[Array]]:
        """Joint waypoints from ``q_now`` to ``T_base_flange`` in the order they are tried: straight to the
        joints solved from the current ones, straight to those solved from home (a redundant arm's other
        branch, or a UR's other elbow or wrist), then to each through home. Home is the arm's known clear
        configuration: a view whose straight joint move sweeps the upper arm through the table or the
        object, or folds the wrist into the shoulder, is reached by way of it, as an operator jogging the
        arm would, and as the packing paper's arm, planned by a motion planner, reached its views. In the
        packing grid's 40 LR-NBV and NBV scans at seeds 5-9, the straight move alone gave up 124 views, with
        the other branch as well 108, and with home as well 92; LR-NBV's scans took 41.4, 43.2 and 47.6 s
        (coverage 61.6, 61.1 and 63.4 %), their boxes as accurate."""
        solutions: list[Array] = []
        for q_goal in self._ik_solutions(T_base_flange, q_now):
            solutions.append(q_goal)
            yield [q_now, q_goal]
        if not np.allclose(q_now, self._q_home):
            for q_goal in solutions:
                yield [q_now, self._q_home, q_goal]

    def retrace(self, duration_s: float) -> bool:
        """:meth:`_retrace`, its answer (and the guard's last refusal when it refused every try) recorded
        in ``planner_requests.csv``, as a move's is: what a replay answers with."""
        asked, self._refusal = self.now(), None
        retraced = self._retrace(duration_s)
        self._request(asked, "retrace", answer=REACHED if retraced else REFUSED, t_done=self.now(),
                      refusal=None if retraced else self._refusal)
        return retraced

    def _retrace(self, duration_s: float) -> bool:
        """After the guard stopped a streamed twist: tick until the arm is at rest, then move it (guarded,
        blocking in job time) back along the joint path it came, through every configuration it passed
        since ``duration_s`` [s] before this call (at most ``JOINT_PATH_KEPT_S``, or since the record
        starts), never faster than it came (``path_trajectory``). That undoes the motion the guard judged,
        whatever the planner commanded last (a Cartesian reverse of a command can carry the joints on
        towards the contact), and passes only where the guard let the arm pass (a straight joint line
        back cuts the corners of a path that slid along the floor's margin, into it and the table).
        Where the guard refuses it all the same, half as far back is tried, then a quarter
        (``RETRACE_SHARES``). Returns False, without moving, for an arm that reports no joints or when the
        guard refuses every one (recorded and counted); raises ``KinematicsError`` when the arm does not
        come to rest within ``SETTLE_TIMEOUT_S``."""
        stopped_at = self.now()
        deadline = stopped_at + SETTLE_TIMEOUT_S
        while np.any(np.abs(self._guard.state().qd) > SETTLED_QD_RAD_S):
            if self.now() > deadline:
                raise KinematicsError(f"the arm did not come to rest within {SETTLE_TIMEOUT_S:g} s of a stop")
            self._tick()
        if self._jointed_state() is None:
            return False
        times = [t for t, _ in self._joint_path]
        q_path = np.array([q for _, q in self._joint_path])
        moved = np.concatenate([[True], np.any(q_path[1:] != q_path[:-1], axis=1)])  # not the rests
        for back_s, start in retrace_starts(times, stopped_at, duration_s):
            path = q_path[start:][moved[start:]][::-1]
            traj = path_trajectory(self._model, path, self._dt, dt=self._dt, **self._joint_scales())
            if self._follow(traj, f"retrace of {back_s:g} s"):
                return True
        return False

    def _joint_scales(self) -> dict[str, float]:
        """The cell's shares of the joints' speed, acceleration and jerk limits for moves."""
        s = self.config.safety
        return {"velocity_scale": s.joint_velocity_scale, "acceleration_scale": s.joint_acceleration_scale,
                "jerk_scale": s.joint_jerk_scale}

    def _follow(self, traj: JointTrajectory, what: str) -> bool:
        """Follow a joint trajectory through the guard, ticking until it ends; False when the guard would
        refuse it (recorded and counted; ``what`` names the move in the log)."""
        started, refusal = self._guard.try_trajectory(traj)
        if refusal is not None:
            self._refused(refusal, what)
            return False
        self._until_done(started)
        return True

    def _until_done(self, started: JointTrajectory) -> None:
        """Tick until the joint trajectory the guard ``started`` ends."""
        deadline = self.now() + started.duration + MOVE_TIMEOUT_MARGIN_S
        while self._guard.following:
            if self.now() > deadline:
                raise KinematicsError("the arm did not finish its move in time")
            self._tick()

    def _refused(self, refusal: Refusal, what: str) -> None:
        """Record and count a move the guard would refuse; ``what`` names it in the log."""
        self._refusal = refusal
        self.refused_moves[refusal.kind] += 1
        self._guard.log.refuse(self.now(), f"move skipped: {refusal.message}")
        self.log(f"{what} skipped: {refusal.message}")

    def _sensor_twist_map(self, T_base_flange: Array) -> Array:
        """(6, 6) from a twist of the sensor frame expressed in the sensor frame to the flange twist in the
        base frame at ``T_base_flange``: w_b = R w_s, v_flange = R v_s - w_b x r, r the lever from the
        flange origin to the sensor origin (base frame)."""
        R = (T_base_flange @ self._T_flange_sensor)[:3, :3]
        r = R @ self._T_flange_sensor[:3, 3]
        r_cross = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
        out = np.zeros((6, 6))
        out[:3, :3] = out[3:, 3:] = R
        out[:3, 3:] = r_cross @ R
        return out

    def command_sensor_twist(self, v_sensor: Array) -> Array:
        """Stream a twist of the sensor frame, expressed in the sensor frame (v [m/s], w [rad/s]; the
        papers' camera twist), through the guard until the next command or ``hold``. Returns the twist the
        arm realizes of it now (within the limits, short of it near a singularity), in the sensor frame."""
        to_flange = self._sensor_twist_map(self._guard.state().T_base_flange)
        self._streamed = np.asarray(v_sensor, dtype=float)
        sent = self._guard.command_twist(to_flange @ self._streamed)
        # numpy's stub types solve() of float64 operands as NDArray[floating]; it returns float64
        return np.linalg.solve(to_flange, sent)  # type: ignore[return-value]

    def _jointed_state(self) -> ArmState | None:
        """The arm's state, or None when it reports no joints (the replayed arm of a job recorded without
        ``joints.csv``: its recorded motion plays whatever the planner asks, so no joint limit or reach
        holds it back; with it, the planner sees the joints the live one did)."""
        state = self._guard.state()
        return state if np.all(np.isfinite(state.q)) else None

    def joint_limit_twists(self, activation_rad: float) -> Array:
        """Rows a (m, 6), one per joint closer than ``activation_rad`` [rad] to its position margin: a
        sensor twist v (sensor frame, [m/s, rad/s]) moves that joint towards the margin at a . v [rad/s]
        (first order, the damped least-squares part of the arm's differential IK). No rows for an arm that
        reports no joints (:meth:`_jointed_state`)."""
        state = self._jointed_state()
        if state is None:
            return np.zeros((0, 6))
        q_lo, q_hi = self._guard.joint_bounds
        to_hi, to_lo = q_hi - state.q, state.q - q_lo
        near_hi, near_lo = to_hi < activation_rad, to_lo < activation_rad
        near = near_hi | near_lo
        if not np.any(near):
            return np.zeros((0, 6))
        rows = self._model.velocity_map(state.q).task @ self._sensor_twist_map(state.T_base_flange)
        sign = np.where(near_hi, 1.0, -1.0)
        return (sign[:, None] * rows)[near]

    def singularity_twists(self, activation: float) -> Array:
        """Rows a (0 or 1, 6): while the smallest singular value of the arm's Jacobian
        (``RobotModel.min_singular_value``) is below ``activation``, a sensor twist v (sensor frame,
        [m/s, rad/s]) lowers it at a . v per second (first order, the damped least-squares part of the
        arm's differential IK); none otherwise, and none for an arm that reports no joints
        (:meth:`_jointed_state`)."""
        state = self._jointed_state()
        if state is None or self._model.min_singular_value(state.q) >= activation:
            return np.zeros((0, 6))
        rate = self._model.min_singular_value_gradient(state.q) @ self._model.velocity_map(state.q).task
        return -(rate @ self._sensor_twist_map(state.T_base_flange))[None, :]

    def hold(self) -> None:
        """Ramp a streamed twist down to rest within the acceleration limits."""
        self._guard.hold()

    def feasible_sensor_velocity(self, v_sensor: Array, activation_m: float) -> Array:
        """Project a desired sensor velocity (3,) [m/s or unitless direction], sensor frame, into the set
        the barrier planes allow: the component into any plane closer than ``activation_m`` (beyond the
        margin) is removed, so the sensor slides along it (visual-servoing paper Fig. 3)."""
        T = self.sensor_pose()
        R = T[:3, :3]
        v = self._guard.barriers.project_velocity(T[:3, 3], R @ np.asarray(v_sensor, dtype=float),
                                                  activation_m)
        return R.T @ v

    def sensor_pose_allowed(self, T_base_sensor: Array) -> bool:
        """Whether the TCP and the sensor of a candidate sensor pose lie on the allowed side of every
        barrier plane and inside the workspace (margin included)."""
        return bool(self.sensor_poses_allowed(np.asarray(T_base_sensor)[None])[0])

    def sensor_poses_allowed(self, T_base_sensor: Array, from_here: bool = False) -> NDArray[np.bool_]:
        """``sensor_pose_allowed`` of each of the poses (K, 4, 4); ``from_here``: as far into a plane's
        margin as a motion from the arm's current pose may go (read once for the batch)."""
        floor = self._guard.motion_floor() if from_here else 0.0
        T_fs_inv = inv_T(self._T_flange_sensor)
        return np.array([self._guard.barrier_violation(T @ T_fs_inv, floor) is None for T in T_base_sensor],
                        dtype=bool)

    def sensor_path_reachable(self, T_base_sensor: Array, min_singular_value: float = 0.0) -> bool:
        """IK (within the guard's ``joint_bounds`` where it finds joints there) seeded from the current
        joints (from home where the arm reports none, as a replayed arm without recorded joints), then
        from each solution, reaches the poses (K, 4, 4) in turn, every solution one the arm may take
        (:meth:`_joints_allowed`) and no joint moving more than ``MAX_PATH_JOINT_STEP_RAD`` between
        consecutive poses."""
        q = self._q_reported()
        T_fs_inv = inv_T(self._T_flange_sensor)
        for k, T in enumerate(np.asarray(T_base_sensor, dtype=np.float64).reshape(-1, 4, 4)):
            try:
                q_next = self._model.ik_pose(T @ T_fs_inv, q, q_bounds=self._guard.joint_bounds)
            except KinematicsError:
                return False
            if (k > 0 and np.max(np.abs(q_next - q)) > MAX_PATH_JOINT_STEP_RAD) or \
                    not self._joints_allowed(q_next, min_singular_value):
                return False
            q = q_next
        return True

    def sensor_view_reachable(self, T_base_sensor: Array) -> bool:
        """Whether :meth:`move_to_sensor_pose` finds joints for the view (4, 4) that the arm may take
        (:meth:`_joints_allowed`): among the IK solutions it tries (:meth:`_ik_solutions`: seeded from the
        current joints, or home where the arm reports none, and from home) at the pose, or, where joints
        reach the pose, at one of its same-view rolls. The move checks its path as well. The check and its
        answer go to ``planner_requests.csv``, as a move's do."""
        reachable = self._view_reachable(T_base_sensor)
        self._request(self.now(), "reach", T_base_sensor, answer=REACHABLE if reachable else UNREACHABLE)
        return reachable

    def _view_reachable(self, T_base_sensor: Array) -> bool:
        """:meth:`sensor_view_reachable`'s verdict, unrecorded."""
        q_now, T_sensor_flange = self._q_reported(), inv_T(self._T_flange_sensor)
        for roll in (0.0, *same_view_rolls(self._sensor.model)):
            T_flange = T_base_sensor @ T_from_xyz_rpy(np.zeros(3), (0.0, 0.0, roll)) @ T_sensor_flange
            solutions = list(self._ik_solutions(T_flange, q_now, quiet=True))
            if any(self._joints_allowed(q) for q in solutions):
                return True
            if roll == 0.0 and not solutions:
                return False
        return False

    def _q_reported(self) -> Array:
        """The arm's joints, or home where it reports none (a replayed arm without recorded joints)."""
        q_now = self._guard.state().q
        return q_now if np.all(np.isfinite(q_now)) else self._q_home

    def _joints_allowed(self, q: Array, min_singular_value: float = 0.0) -> bool:
        """Whether the arm may take joints ``q``: each inside the guard's ``joint_bounds`` (limits less the
        margin), no collision (``CollisionWorld.check``) and the smallest singular value of the Jacobian
        at least ``min_singular_value`` (not computed for a bound of 0: every singular value meets it)."""
        q_lo, q_hi = self._guard.joint_bounds
        return bool(np.all((q >= q_lo) & (q <= q_hi))) and \
            (min_singular_value <= 0.0 or self._model.min_singular_value(q) >= min_singular_value) and \
            self._guard.collision.check(q) is None

    def _ik_solutions(self, T_base_flange: Array, q_now: Array, quiet: bool = False) -> Iterator[Array]:
        """Joints reaching ``T_base_flange`` (within the guard's ``joint_bounds`` where IK finds them there,
        ``RobotModel.ik_pose``), seeded from the current joints, then, where it differs, the solution
        seeded from home; none when neither converges (logged unless ``quiet``).

        Seeding from the current joints keeps moves short; a redundant arm can however drift into a
        folded configuration from which the next views are out of reach, and the home seed recovers.
        """
        found: list[Array] = []
        error: KinematicsError | None = None
        for seed in (q_now, self._q_home):
            try:
                q_goal = self._model.ik_pose(T_base_flange, seed, q_bounds=self._guard.joint_bounds)
            except KinematicsError as exc:
                error = exc
                continue
            if not any(np.allclose(q_goal, q, atol=SAME_SOLUTION_RAD) for q in found):
                found.append(q_goal)
                yield q_goal
        if not found and not quiet:
            self.log(f"view at {np.round(T_base_flange[:3, 3], 3).tolist()} (flange) unreachable: {error}")

    def survey(self) -> None:
        """Look before the first move: one frame from where the arm stands (home), taken in only for what
        stands on the table (``PerceptionPipeline.survey``), which the guard then keeps the arm from. The
        way to the first view is otherwise checked against the table and the configured obstacles alone,
        and a part put off the station may stand on it. The frame is not one of the scan's: it is neither
        recorded nor counted."""
        frame = self._fresh_frame()
        state = self._guard.state()
        cells = self.perception.survey(frame, state.T_base_flange @ self._T_flange_sensor)
        self._guard.set_seen(cells, q_free=state.q)
        self.log(f"survey from home: {len(cells)} cells of {cells.voxel_m * 100:g} cm seen above the table, "
                 "obstacles until the object is found among them")

    def capture(self) -> int:
        """One frame at the current pose through perception (:meth:`_fresh_frame`); while asynchronous
        capture runs, this waits for its next update instead."""
        if self._live is not None:
            return self._next_live_update()
        return self._ingest(self._fresh_frame(), self._guard.state().T_base_flange)

    def _fresh_frame(self) -> DepthFrame:
        """The sensor's frame, on the wall clock one stamped no earlier than this call: one queued by the
        device while the arm moved is skipped."""
        asked = self.now()
        frame = self._sensor.capture()
        deadline = asked + STALE_FRAME_TIMEOUT_S
        while self._poses is not None and frame.timestamp < asked:
            if self.now() > deadline:
                raise DriverError(f"no frame newer than the request at {asked:.3f} s within "
                                  f"{STALE_FRAME_TIMEOUT_S:g} s (newest at {frame.timestamp:.3f} s)",
                                  device=self._sensor.device)
            frame = self._sensor.capture()
        return frame

    def _next_live_update(self) -> int:
        assert self._live is not None
        end = self.now() + STALE_FRAME_TIMEOUT_S
        while self.now() < end:
            update = self._live.poll()
            if update is not None:
                self._apply(update)
                return int(update.points_base.shape[0])
            self._tick()
        raise DriverError(f"no perception update within {STALE_FRAME_TIMEOUT_S:g} s",
                          device=self._sensor.device)

    def _ingest(self, frame: DepthFrame, T_base_flange: Array) -> int:
        """Run a captured frame, taken with the flange at ``T_base_flange``, through perception, record it
        and take it in; returns the number of points kept."""
        update = self.perception.process(frame, T_base_flange @ self._T_flange_sensor)
        self._record(frame, T_base_flange, update)
        self._apply(update)
        return int(update.points_base.shape[0])

    def _apply(self, update: PerceptionUpdate) -> None:
        """Take in a perception update on the control thread: the ROI and what was seen outside it for
        collision checks, the age of perception for the watchdog, progress."""
        self._latest = update
        self._perception_time = update.timestamp if self._perception_time is not None else None
        if update.roi is not None:
            self._guard.set_roi(update.roi.aabb_min, update.roi.aabb_max)
        self._guard.set_seen(update.seen)
        if self._on_progress is not None:
            self._on_progress(self)

    def _record(self, frame: DepthFrame, T_base_flange: Array, update: PerceptionUpdate) -> None:
        """Write a processed frame to the job folder and count it (on the perception worker in
        asynchronous capture)."""
        reg = update.registration
        T_fk = T_base_flange @ self._T_flange_sensor
        self._recorder.frame(frame, T_fk, T_base_flange,
                             {"T_base_sensor_registered": update.T_base_sensor})
        self.n_captures += 1
        if self.first_frame_time is None:
            self.first_frame_time = frame.timestamp
            self.first_frame_path_m = self.path_length_m
            self.first_frame_position = T_fk[:3, 3].copy()
        if reg.rejected:
            self.n_registration_rejected += 1
        self.registration_n_constrained.append(reg.n_constrained)
        if self.coverage is not None:
            self.coverage_history.append((self.now(), self.coverage.update(self.cloud.points)))
        h = f"{update.h_roi:.4f}" if update.h_roi is not None else "-"
        self.log(f"capture {frame.seq}: {frame.points.shape[0]} points, {update.points_base.shape[0]} after "
                 f"filtering; {reg.describe()}; H_ROI {h}")
