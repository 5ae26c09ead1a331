"""The motion guard: the one place where motion reaches an arm backend (safety issue, item 6).

The guard claims the arm's motion token when it is built (``drivers.arm.base``), so nothing else can move
the arm. It forwards two kinds of motion:

- **Streamed twists** (:meth:`MotionGuard.command_twist` sets the target, :meth:`MotionGuard.tick` sends
  one command per control period). Each tick, in this order: the flange's linear and angular speed are
  scaled down to the cell's limits (direction kept); the twist is projected into the set the barrier planes
  and the workspace box allow for the TCP and the sensor (it slides along active planes); it is scaled
  down (direction kept) so that no joint exceeds its share of its speed limit and no joint runs into its
  position margin, with the joint velocities the arm's differential IK gives (``RobotModel.velocity_map``:
  damped least squares plus, on a redundant arm, null-space joint-limit avoidance, which scales with the
  twist); ruckig smooths it to the TCP acceleration and jerk limits, and takes only as much of a step as
  every joint can follow within the robot's acceleration limit and half its jerk limit (a twist that would
  need more even when held is refused); the stop that would follow the
  smoothed twist (sent for one period, then ruckig's ramp to rest) must keep the TCP and the sensor out of
  every barrier margin and the joints inside their margins, or the next step of braking is sent instead
  (the projection and the joint margin above plan their braking with simpler bounds that the smoothing
  does not always keep, e.g. while it also ramps a turn: this check is what guarantees the stop); the
  twist sent keeps the TCP acceleration and jerk limits as differences over the control period of the
  twists sent (a speed cut or a share of a step after smoothing moved as little as needed to keep them),
  and one that is then still over a speed limit by more than ``SPEED_SLACK``, or whose stop would then
  enter a margin, is refused; the
  joint path to the configuration predicted ``collision.lookahead_s`` ahead at that twist, along which the
  next period and a stop after it run, is checked for collisions all along (robot, tool, table, object
  ROI, obstacles, self-collision). After a stop, a streamed twist starts once the arm's own stop has
  brought its joints to rest. A collision refuses the motion, and so does a joint
  that the arm reports moving towards its limit faster than its own stop could absorb within half the joint
  margin (a last resort where the IK's prediction falls short, near a singularity).
- **Joint trajectories** (:meth:`MotionGuard.execute_trajectory`, and :meth:`MotionGuard.try_trajectory`
  for a planner's moves, ruckig's time-optimal moves): every sample inside the joint limits and margins,
  slowed down uniformly in time when a joint or the TCP would be too fast, TCP and sensor on the allowed
  side of every plane, into its margin no deeper than a stop after a streamed twist may go
  (``BRAKING_MARGIN_SHARE``, or where the arm already is), and the whole path collision-free, between its
  samples too (``CollisionWorld.check_path``); refused otherwise.

Every tick also runs the watchdog (late control loop, stale perception), reads the arm's faults, and
honours an operator stop. A refusal or a fault stops the arm (zero velocity, decelerating within the arm's
limits), records the reason in the job's :class:`SafetyLog` and raises ``SafetyStop`` (``TwistRefused``
for a refused streamed twist, which a planner may answer by backing off); every clamp is counted there
too.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.config.models import CellConfig
from cell.perception.seen_obstacles import SeenCells
from cell.safety.barriers import BarrierPlane, Barriers, approach_speed, workspace_planes
from cell.safety.collision import Collision, CollisionWorld
from cell.safety.config import SafetyConfig
from cell.safety.events import Refusal, SafetyLog
from cell.safety.smoothing import TwistSmoother
from cell.safety.watchdog import Watchdog
from drivers.arm.base import Arm, ArmMode, ArmState, JointTrajectory
from drivers.clock import Clock
from drivers.errors import ARM_FAULT, CellError, RobotFault, SafetyStop, stop_cause
from drivers.robots.model import JointVelocityMap, RobotModel

Array = NDArray[np.float64]

# Sampled trajectories are checked with finite differences, a hair above the planned bound.
VELOCITY_TOLERANCE = 1.02
# A trajectory must start where the arm is, within this much in every joint [rad].
TRAJECTORY_START_TOL_RAD = 1e-3
GUARDED_POINTS = ("TCP", "sensor")
# Braking before a plane or a joint margin is planned at this share of the acceleration limit: a target
# that falls at the planned rate is tracked by the jerk-limited smoother with some lag, and the rest of the
# acceleration budget absorbs most of it (the braking check in ``tick`` catches the rest).
BRAKING_SHARE = 0.5
# The stop checked before each streamed twist may use this share of the barrier margin: the projection aims
# at the margin itself, and a twist sliding along it (whose realized motion grazes the plane by microns)
# must not be taken for one heading in; the rest of the margin is left for the arm's tracking error. A
# move's samples may go as deep: the straight joint line back along a path that slid along a margin (a
# retrace after a refusal) bends into it by the path's curvature.
BRAKING_MARGIN_SHARE = 0.5
# A streamed twist may exceed a speed limit, or its change over a period the acceleration or jerk limit, by
# this share (rounding: the smoother's own steps land on the limits).
RATE_TOLERANCE = 1e-6
# A streamed twist that the TCP jerk limit keeps from slowing down at once (a joint's speed grows as the arm
# turns near a singularity) may stay over a speed limit by this share while it slows down as fast as the
# limit lets it (counted as ``speed_while_slowing``); further over, the arm stops. Stopping at once would
# brake far harder than either limit allows.
SPEED_SLACK = 0.02


def _within_norm(x: Array, limit: float) -> Array:
    """``x`` scaled down (direction kept) to a norm of ``limit`` when it is over it by more than
    ``RATE_TOLERANCE`` (``x`` itself otherwise)."""
    norm = float(np.linalg.norm(x))
    return x * (limit / norm) if norm > limit * (1.0 + RATE_TOLERANCE) else x


class TwistRefused(SafetyStop):
    """The guard refused a streamed twist (a collision predicted ahead) and stopped the arm, as for any
    refusal; ``refusal`` says why. Uncaught it ends the job like any safety stop; a planner that streams
    twists may instead back off and go on (``cell.jobs.session`` reports it, counted as a refused move)."""

    def __init__(self, reason: str, refusal: Refusal) -> None:
        super().__init__(reason)
        self.refusal = refusal


@dataclass(frozen=True)
class GuardGeometry:
    """Where the guard's limits apply: ``T_flange_sensor`` (hand-eye), the table top height [m] and the
    control period [s]."""

    T_flange_sensor: Array
    table_z_m: float
    period_s: float


class MotionGuard:
    """Owns the motion of one arm for a job; see the module docstring for what each path checks."""

    def __init__(self, arm: Arm, model: RobotModel, safety: SafetyConfig, geometry: GuardGeometry,
                 clock: Clock, collision: CollisionWorld, log: SafetyLog | None = None) -> None:
        """``collision``: the collision world of ``model``, ``safety.collision`` and the table height of
        ``geometry`` (the cell's, ``CollisionWorld.for_cell``)."""
        self._arm = arm
        self._model = model
        self._safety = safety
        self._T_fs = geometry.T_flange_sensor
        self._period = geometry.period_s
        self._clock = clock
        self.log = log if log is not None else SafetyLog()
        planes = [BarrierPlane.make(p.name or f"plane {i}", p.point, p.normal)
                  for i, p in enumerate(safety.barrier_planes)]
        planes += workspace_planes(safety.workspace.min_m, safety.workspace.max_m)
        self.barriers = Barriers(planes, margin_m=safety.barrier_margin_m,
                                 acc=BRAKING_SHARE * safety.tcp_max_linear_acc_mps2,
                                 jerk=safety.tcp_max_linear_jerk_mps3,
                                 latency_s=geometry.period_s, time_constant_s=safety.collision.lookahead_s)
        self.collision = collision
        self.watchdog = Watchdog(safety.watchdog, geometry.period_s)
        self._smoother = TwistSmoother(
            geometry.period_s, (safety.tcp_max_linear_acc_mps2, safety.tcp_max_angular_acc_rps2),
            (safety.tcp_max_linear_jerk_mps3, safety.tcp_max_angular_jerk_rps3))
        self._qd_limit = model.qd_max * safety.joint_velocity_scale
        self._qdd_limit = model.qdd_max * safety.joint_acceleration_scale
        self._qddd_limit = model.qddd_max * safety.joint_jerk_scale
        # The most a streamed twist may change a joint's speed in one control period [rad/s]: within the
        # robot's acceleration limit, and at most half its jerk limit's worth, so that even a swing from
        # one extreme to the other in the next period keeps its jerk limit (``_joint_rate_share``).
        dt = geometry.period_s
        self._qd_step = np.minimum(model.qdd_max * dt, 0.5 * model.qddd_max * dt * dt)
        self._q_lo = model.q_min + safety.joint_position_margin_rad
        self._q_hi = model.q_max - safety.joint_position_margin_rad
        # A joint's measured motion must stop short of half its margin (``_joint_overrun``).
        self._q_lo_overrun = model.q_min + 0.5 * safety.joint_position_margin_rad
        self._q_hi_overrun = model.q_max - 0.5 * safety.joint_position_margin_rad
        self._target: Array | None = None
        # The last streamed twist sent and its change over the control period before it [per s]
        # (``_rate_limited``); zero at rest, where the smoother starts.
        self._sent: tuple[Array, Array] = (np.zeros(6), np.zeros(6))
        self._following = False
        # After a stop, streaming waits for the arm's own ramp to rest (``tick``).
        self._settling = False
        self._q_seen: Array | None = None  # the joints [rad] the last tick read
        self._stop_lock = threading.Lock()
        # (reason, whether someone asked for it) of a stop asked for from another thread
        self._stop_request: tuple[str, bool] | None = None
        self._token = arm.claim_motion()
        self.first_motion_unix_s: float | None = None
        """Wall-clock time [s since the epoch] of the first motion command sent to the arm (None before
        one): what a line's latency from its trigger to the arm is measured to."""

    @classmethod
    def from_config(cls, arm: Arm, model: RobotModel, config: CellConfig, clock: Clock,
                    log: SafetyLog | None = None, collision: CollisionWorld | None = None) -> MotionGuard:
        """The guard of a cell: its safety section, hand-eye mount, table height and control rate, and its
        collision world, ``collision`` when the job has it already (a job's, which checked its placement in
        it), else built here (``CollisionWorld.for_cell``)."""
        geometry = GuardGeometry(config.mount.matrix(), config.station.table_z_m,
                                 1.0 / config.scan.control_rate_hz)
        world = collision if collision is not None else CollisionWorld.for_cell(config)
        return cls(arm, model, config.safety, geometry, clock, world, log)

    # ------------------------------------------------------------------ state and stops

    def state(self) -> ArmState:
        """The arm's state; a fault it reports (or a lost connection) stops the job."""
        try:
            state = self._arm.state()
        except RobotFault as exc:
            raise self._halt(f"{ARM_FAULT}{exc.fault} ({exc})") from exc
        if state.faults:
            raise self._halt(f"{ARM_FAULT}{', '.join(state.faults)}")
        return state

    def arm_state(self) -> ArmState:
        """The arm's state as it reports it, faults included, without acting on them (e.g. to watch it come
        to rest after a stop). Raises ``DriverError`` when the arm does not answer."""
        return self._arm.state()

    @property
    def joint_bounds(self) -> tuple[Array, Array]:
        """The joint positions [rad] motion is kept within: each joint's limits less
        ``safety.joint_position_margin_rad`` (lower, upper)."""
        return self._q_lo, self._q_hi

    @property
    def following(self) -> bool:
        """True while a trajectory started through the guard is under way (as of the last tick)."""
        return self._following

    def stop(self, reason: str) -> None:
        """Bring the arm to rest and record why. Never raises: a failing stop is recorded as well."""
        self.log.stop(self._clock.now(), reason)
        self._target = None
        self._following = False
        self._smoother.reset()
        self._sent = (np.zeros(6), np.zeros(6))
        self._settling = True
        try:
            self._arm.stop()
        except CellError as exc:
            self.log.stop(self._clock.now(), f"the arm's stop failed too: {exc}")

    def finish(self) -> None:
        """End of a job's motion (not a safety event): stop streaming and bring the arm to rest."""
        self._target = None
        self._following = False
        self._smoother.reset()
        self._sent = (np.zeros(6), np.zeros(6))
        self._send(self._arm.stop, motion=False)

    def request_stop(self, reason: str, *, operator: bool = True) -> None:
        """Stop the job from any thread (the service, the CLI): the arm is told to stop at once and the
        job's next control tick ends it with ``SafetyStop``, ``operator stop: <reason>`` when someone asked
        for it (``operator``), else the safety layer's own (the service stopping a job whose worker stopped
        answering, or after its own failure)."""
        with self._stop_lock:
            self._stop_request = (reason, operator)
        # A failure here is not lost: the control tick repeats the stop and records its failure.
        with contextlib.suppress(CellError):
            self._arm.stop()

    def release(self) -> None:
        """Give the arm's motion token back at the end of a job."""
        self._arm.release_motion(self._token)

    def _halt(self, reason: str) -> SafetyStop:
        self.stop(reason)
        return SafetyStop(reason)

    def _refuse(self, reason: str) -> SafetyStop:
        self.log.refuse(self._clock.now(), reason)
        return self._halt(f"refused: {reason}")

    def refuse_twist(self, refusal: Refusal) -> TwistRefused:
        """Refuse the streamed twist for ``refusal``: the arm is stopped and the refusal recorded, as for
        any refusal; returns the exception to raise. :meth:`tick` refuses with it, and a replayed job
        (``cell.jobs.replay``) gives its planner the live job's refusals with it."""
        return TwistRefused(self._refuse(refusal.message).reason, refusal)

    # ------------------------------------------------------------------ geometry helpers

    def set_roi(self, aabb_min: Array | None, aabb_max: Array | None) -> None:
        """The object's ROI box (base frame [m]) for collision checks, as perception updates it. Its margin
        is shrunk where it would reach the arm where it stands (``CollisionWorld.set_roi``), counted as the
        clamp ``roi_margin_at_arm``."""
        # Without those joints the ROI keeps its full margin.
        q = self._q_free()
        if aabb_min is None or aabb_max is None:
            q = None
        if self.collision.set_roi(aabb_min, aabb_max, q_free=q) is not None:
            self.log.clamp("roi_margin_at_arm")

    def set_seen(self, cells: SeenCells | None, q_free: Array | None = None) -> None:
        """What the sensor has seen outside the object's ROI, as perception updates it: obstacles for
        collision checks but where the arm stands, at ``q_free`` [rad] (by default the joints the last tick
        read) (``CollisionWorld.set_seen``), counted as the clamp ``seen_at_arm``."""
        if self.collision.set_seen(cells, q_free=self._q_free() if q_free is None else q_free):
            self.log.clamp("seen_at_arm")

    def _q_free(self) -> Array | None:
        """The joints [rad] the arm stands at for the obstacles perception updates: those the last tick
        read (the arm is at rest after a capture), not a read of its own (a fault is the tick's to act on
        and name). None before the first tick, or from a replayed arm whose joints are not known."""
        q = self._q_seen
        return None if q is None or not np.all(np.isfinite(q)) else q

    def guarded_points(self, T_base_flange: Array) -> Array:
        """The TCP (flange origin) and the sensor origin (2, 3) [m] in the base frame."""
        return np.array([T_base_flange[:3, 3], (T_base_flange @ self._T_fs)[:3, 3]])

    def barrier_violation(self, T_base_flange: Array, floor: Array | float = 0.0) -> str | None:
        """Why a flange pose leaves the allowed side of a plane (margin included), or None; ``floor``: the
        clearance a guarded point may go down to (``motion_floor``: as far into the margin as a motion from
        the arm's current pose may go)."""
        return self.barriers.first_violation(self.guarded_points(T_base_flange), GUARDED_POINTS, floor)

    def motion_floor(self) -> Array:
        """The lowest clearance [m] (guarded points x planes) a motion from the arm's current pose may reach
        (``_margin_floor``)."""
        return self._margin_floor(self.state().T_base_flange)

    def _margin_floor(self, T_base_flange: Array) -> Array:
        """The lowest clearance [m] beyond the barrier margin (guarded points x planes) a motion from
        ``T_base_flange`` may reach: ``BRAKING_MARGIN_SHARE`` of the margin, and no deeper than a point
        already is."""
        return np.minimum(self.barriers.clearances(self.guarded_points(T_base_flange)),
                          -BRAKING_MARGIN_SHARE * self.barriers.margin_m)

    # ------------------------------------------------------------------ streamed twists

    def command_twist(self, v_base_flange: Array) -> Array:
        """Set the flange twist (base frame [m/s, rad/s]) that each control tick streams until the next
        command or ``hold``; returns the twist the arm realizes of it now: as the limits allow it (the
        tick re-applies them), through the arm's differential IK, whose damped least squares falls short
        of a twist along a direction the arm is near-singular in (an arm stretched to its reach moves
        a few percent of a twist outwards)."""
        v = np.asarray(v_base_flange, dtype=float)
        if v.shape != (6,) or not np.all(np.isfinite(v)):
            raise self._refuse(f"twist must be 6 finite values, got {np.array2string(v, precision=4)}")
        if self._following:
            raise self._refuse("a twist was commanded while a trajectory is being followed")
        self._target = v.copy()
        state = self.state()
        ik = self._model.velocity_map(state.q)
        return ik.realized(self._limit(v, state, ik, count=False))

    def hold(self) -> None:
        """Ramp the streamed twist down to zero (within the acceleration limits) and keep the arm still."""
        if self._target is not None:
            self._target = np.zeros(6)

    def _limit(self, v: Array, state: ArmState, ik: JointVelocityMap, *, count: bool) -> Array:
        """Speed limits, barrier projection and joint limits for a twist at ``state`` (module docstring);
        ``ik`` is the arm's differential IK at ``state.q`` (null-space joint-limit avoidance included;
        positively homogeneous, so scaling the twist scales every joint's velocity alike)."""
        s = self._safety
        v = v.copy()
        for kind, sl, limit in (("tcp_linear_speed", slice(0, 3), s.tcp_max_linear_mps),
                                ("tcp_angular_speed", slice(3, 6), s.tcp_max_angular_rps)):
            speed = float(np.linalg.norm(v[sl]))
            if speed > limit:
                v *= limit / speed
                if count:
                    self.log.clamp(kind)
        T = state.T_base_flange
        points = self.guarded_points(T)
        lever = float(np.linalg.norm(points[1] - points[0]))
        v, planes = self.barriers.project_twist(v, T[:3, 3], points,
                                                s.tcp_max_linear_mps + s.tcp_max_angular_rps * lever)
        if count:
            for name in planes:
                self.log.clamp(f"barrier {name}")
        qd = ik(v)
        ratio = float(np.max(np.abs(qd) / self._qd_limit))
        if ratio > 1.0:
            v /= ratio
            qd /= ratio
            if count:
                self.log.clamp("joint_velocity")
        # A joint may approach its margin only as fast as it can still stop before it.
        room = np.where(qd > 0.0, self._q_hi - state.q, state.q - self._q_lo)
        allowed = approach_speed(room, acc=BRAKING_SHARE * self._qdd_limit, jerk=self._qddd_limit,
                                 latency_s=self._period,
                                 time_constant_s=s.collision.lookahead_s)
        moving = np.abs(qd) > 1e-12
        if np.any(moving):
            scale = float(np.min(np.minimum(allowed[moving] / np.abs(qd[moving]), 1.0)))
            if scale < 1.0:
                v *= scale
                if count:
                    self.log.clamp("joint_position_margin")
        return v

    def tick(self, perception_time_s: float | None = None) -> None:
        """One control period: watchdog, faults, operator stop, then the next streamed command.

        ``perception_time_s``: capture time of the newest perception data when the motion depends on them
        (None otherwise). Raises ``SafetyStop`` after stopping the arm when anything is wrong.
        """
        now = self._clock.now()
        with self._stop_lock:
            request, self._stop_request = self._stop_request, None
        if request is not None:
            asked, operator = request
            raise self._halt(stop_cause(asked, operator))
        for reason in (self.watchdog.tick(now), self.watchdog.perception(now, perception_time_s)):
            if reason is not None:
                raise self._halt(f"watchdog: {reason}")
        state = self.state()
        self._q_seen = np.array(state.q, dtype=float)
        if self._following:
            self._following = state.mode is ArmMode.TRAJECTORY
            return
        if self._target is None:
            return
        if self._settling:
            # The smoother restarts from rest after a stop; a twist streamed while the arm's stop is still
            # braking its joints (a planner backing off at once) would be smoothed from a rest the joints
            # are not at, and no share of a step could bring them to it within their acceleration limit:
            # it starts once every joint is within one step of rest.
            if np.any(np.abs(state.qd) > self._qd_step):
                return
            self._settling = False
        overrun = self._joint_overrun(state)
        if overrun is not None:
            raise self.refuse_twist(Refusal("joint limit", overrun))
        ik = self._model.velocity_map(state.q)
        limited = self._limit(self._target, state, ik, count=True)
        snapshot = self._smoother.snapshot()
        v = self._smoother.step(limited)
        if np.any(np.abs(v - limited) > 1e-9):
            self.log.clamp("tcp_acceleration")
        # The smoother blends towards the target from a twist limited at an earlier configuration (which
        # may ask a joint for slightly more here), and when a new target arrives mid-ramp its axes are
        # only time-synchronised (the blend may bulge past a speed limit); scale such a twist down and
        # continue smoothing from there.
        s = self._safety
        qd = ik(v)
        ratio = max(float(np.max(np.abs(qd) / self._qd_limit)),
                    float(np.linalg.norm(v[:3])) / s.tcp_max_linear_mps,
                    float(np.linalg.norm(v[3:])) / s.tcp_max_angular_rps)
        if ratio > 1.0:
            v = self._smoother.scale(1.0 / ratio)
            qd /= ratio
            self.log.clamp("smoothed_twist")
        # Near a singularity a twist smoothed in Cartesian space can ask the joints for more acceleration than
        # the robot has; the arm then lags at its limit and its acceleration leaps past the jerk limit when
        # it catches up. Only as much of the smoother's step is taken as every joint can follow; when even
        # holding the previous twist needs more (the configuration alone turns the joints), the twist stops.
        share = self._joint_rate_share(state.qd, ik(np.asarray(snapshot[0])), qd)
        if share is None:
            reason = ("the joints would have to change speed faster than the robot allows to follow the "
                      "twist (near a singularity)")
            raise self.refuse_twist(Refusal("joint acceleration", reason))
        if share < 1.0:
            v = self._smoother.blend(snapshot, share)
            self.log.clamp("joint_acceleration")
        unsafe = self._braking_violation(state, ik)
        if unsafe is not None:
            # The step before this one was checked the same way, so braking from it is known to stay clear.
            self._smoother.restore(snapshot)
            v = self._smoother.step(np.zeros(6))
            self.log.clamp(unsafe)
        limited = self._rate_limited(v)
        if limited is not v:
            # Braking from the twist the rate limits leave must stay clear as well (it was checked from
            # the twist before them).
            v = limited
            unsafe = self._braking_violation(state, ik)
            if unsafe is not None:
                reason = f"{unsafe}: the stop cannot begin within the TCP jerk limit"
                raise self.refuse_twist(Refusal("speed", reason))
        too_fast = self._over_speed(v, ik(v), SPEED_SLACK)
        if too_fast is not None:
            raise self.refuse_twist(Refusal("speed", too_fast))
        if self._over_speed(v, ik(v), RATE_TOLERANCE) is not None:
            self.log.clamp("speed_while_slowing")
        hit = self._collision_ahead(state.q, ik(v))
        if hit is not None:
            reason = f"{hit} within {self._safety.collision.lookahead_s:g} s"
            raise self.refuse_twist(Refusal("collision", reason))
        self._send(lambda: self._arm.command_twist(v, self._token))
        self._sent = (v, (v - self._sent[0]) / self._period)

    def _rate_limited(self, v: Array) -> Array:
        """``v`` moved as little as needed for the streamed commands to keep the TCP acceleration and jerk
        limits, as finite differences over the control period of the twists sent (what the arm is
        commanded, and what a judge of the command stream sees): the change of acceleration from the last
        period's is cut to the jerk limit, then the acceleration to its limit (per linear and angular part,
        as norms; the second cut keeps the first, a projection onto a ball around zero that holds the last
        acceleration). The smoother's own steps pass unchanged; the speed cuts after it (``smoothed_twist``),
        a share of a step (``joint_acceleration``) and a braking step from an earlier state need not, and
        are counted as ``tcp_rate``. The smoother goes on from the twist sent."""
        s, dt = self._safety, self._period
        v_last, a_last = self._sent
        out = v.copy()
        changed = False
        for part, acc, jerk in ((slice(0, 3), s.tcp_max_linear_acc_mps2, s.tcp_max_linear_jerk_mps3),
                                (slice(3, 6), s.tcp_max_angular_acc_rps2, s.tcp_max_angular_jerk_rps3)):
            a = (v[part] - v_last[part]) / dt
            change = a - a_last[part]
            cut = _within_norm(change, jerk * dt)
            limited = _within_norm(a if cut is change else a_last[part] + cut, acc)
            if limited is not a:
                out[part] = v_last[part] + limited * dt
                changed = True
        if not changed:
            return v
        self.log.clamp("tcp_rate")
        self._smoother.restore((out.tolist(), ((out - v_last) / dt).tolist()))
        return out

    def _over_speed(self, v: Array, qd: Array, slack: float) -> str | None:
        """Why the twist ``v`` (joint velocities ``qd`` [rad/s] here) is over a speed limit by more than the
        share ``slack``, or None. The speed cuts before it aim below every limit; a twist still over one
        could not be slowed down within the TCP jerk limit (``_rate_limited``)."""
        s = self._safety
        for what, value, limit in (("the TCP's linear speed", float(np.linalg.norm(v[:3])),
                                    s.tcp_max_linear_mps),
                                   ("the TCP's angular speed", float(np.linalg.norm(v[3:])),
                                    s.tcp_max_angular_rps)):
            if value > limit * (1.0 + slack):
                return (f"{what} ({value:.4g}) would stay over its limit ({limit:g}): the twist cannot slow "
                        f"down within the TCP jerk limit")
        over = np.abs(qd) / self._qd_limit
        j = int(np.argmax(over))
        if over[j] > 1.0 + slack:
            return (f"joint {j + 1} at {qd[j]:+.4f} rad/s would stay over its share of its speed limit "
                    f"({self._qd_limit[j]:.4f} rad/s): the twist cannot slow down within the TCP jerk limit")
        return None

    def _collision_ahead(self, q: Array, qd: Array) -> Collision | None:
        """The contact the arm would make going on at joint velocities ``qd`` [rad/s] from ``q`` [rad] for
        ``collision.lookahead_s``, or None.

        The whole straight joint path to the predicted configuration is checked (``check_motion``), not only
        its end: where the arm turns, what it reaches next lies off the line that earlier predictions
        followed, so a corner of an obstacle can lie beside every predicted end and still on the arm's way
        (the soak's UR5e forearm went into one that way). One control period of motion and the arm's stop
        after it run along this line. An arm that already touches something (an ROI that grew over it)
        may still move where the predicted configuration is clear."""
        q_pred = np.clip(q + qd * self._safety.collision.lookahead_s, self._model.q_min, self._model.q_max)
        hit = self.collision.check_motion(q, q_pred)
        if hit is None:
            return None
        return hit[1] if hit[0] > 0 else self.collision.check(q_pred)

    def _joint_rate_share(self, qd_now: Array, qd_from: Array, qd_to: Array) -> float | None:
        """The largest share s in [0, 1] of the smoother's step, from the joint velocities of the twist it
        held (``qd_from``) to those of the twist it reached (``qd_to``), both at the arm's joints [rad/s],
        that no joint takes further than ``_qd_step`` from its speed ``qd_now``; None when no share does."""
        lo = qd_now - self._qd_step - qd_from
        hi = qd_now + self._qd_step - qd_from
        step = qd_to - qd_from
        moving = np.abs(step) > 1e-12
        if np.any(~moving & ((lo > 0.0) | (hi < 0.0))):
            return None
        ends = np.stack([lo[moving], hi[moving]]) / step[moving]
        first = max(0.0, float(np.max(np.min(ends, axis=0), initial=0.0)))
        last = min(1.0, float(np.min(np.max(ends, axis=0), initial=1.0)))
        return last if first <= last else None

    def _joint_overrun(self, state: ArmState) -> str | None:
        """Why the arm must stop now, or None: a joint that, at the speed the arm reports, would be carried
        past half its position margin by the arm's own stop begun one control period from now (all joints
        slowed together, the first to stop at the robot's deceleration limit, as a stop command does).

        The braking check in :meth:`tick` predicts joint motion with the differential IK at the current
        joints; near a singularity that map changes quickly along a stop and the prediction falls short.
        This check reads the joints' measured speeds instead, so it holds wherever the arm is."""
        speed = np.abs(state.qd)
        if not np.any(speed > 0.0):
            return None
        t_stop = float(np.max(speed / self._model.qdd_max))
        travel = speed * (self._period + 0.5 * t_stop)
        room = np.where(state.qd > 0.0, self._q_hi_overrun - state.q, state.q - self._q_lo_overrun)
        over = np.nonzero(travel > room)[0]
        if over.size == 0:
            return None
        j = int(over[0])
        return (f"joint {j + 1} at {state.qd[j]:+.3f} rad/s would be carried past half its limit margin "
                f"({travel[j] * 1e3:.1f} mrad to stop, {max(room[j], 0.0) * 1e3:.1f} mrad left)")

    def _braking_violation(self, state: ArmState, ik: JointVelocityMap) -> str | None:
        """What braking after the twist the smoother holds now would enter (``barrier braking`` or
        ``joint margin braking``, the clamp it is counted as), or None if it stays clear: the joints must
        stay inside their margins and the TCP and the sensor out of every barrier margin along the whole
        stop (:meth:`TwistSmoother.braking`; the stop may use ``BRAKING_MARGIN_SHARE`` of the barrier
        margin); a point or joint already inside a margin may not go deeper.
        The joints follow the differential IK at ``state.q``, and the flange moves as its Jacobian makes
        those joint motions move it (which differs from the twist asked for near a singularity); the
        sensor turns with the flange (by the rotation vector of that motion)."""
        times, twist = self._smoother.braking()
        qd = ik(twist)
        dq = np.concatenate([np.zeros((1, qd.shape[1])),
                             np.cumsum(0.5 * (qd[1:] + qd[:-1]) * np.diff(times)[:, None], axis=0)])
        q = state.q + dq
        if np.any(q < np.minimum(self._q_lo, state.q) - 1e-9) or np.any(q > np.maximum(self._q_hi, state.q)
                                                                         + 1e-9):
            return "joint margin braking"
        moved = dq @ ik.jacobian.T
        now = self.guarded_points(state.T_base_flange)
        lever = now[1] - now[0]
        turned = Rotation.from_rotvec(moved[:, 3:]).apply(lever)
        tcp = now[0] + moved[:, :3]
        path = np.stack([tcp, tcp + turned], axis=1)  # (k, 2, 3)
        floor = self._margin_floor(state.T_base_flange)
        clearance = self.barriers.clearances(path.reshape(-1, 3)).reshape(len(times), 2, -1)
        if np.any(clearance < floor[None] - 1e-9):
            return "barrier braking"
        return None

    def _send(self, command: Callable[[], None], *, motion: bool = True) -> None:
        if motion and self.first_motion_unix_s is None:
            self.first_motion_unix_s = time.time()
        try:
            command()
        except RobotFault as exc:
            raise self._halt(f"{ARM_FAULT}{exc.fault} ({exc})") from exc

    # ------------------------------------------------------------------ trajectories

    def check_trajectory(self, trajectory: JointTrajectory) -> tuple[JointTrajectory, Refusal | None]:
        """Check a joint trajectory without moving: returns it (slowed down in time if a joint or the TCP
        would be too fast) and why it would be refused, or None. Planners use the reason to discard a
        move and count it; :meth:`execute_trajectory` refuses it outright."""
        m = self._model
        q = trajectory.q
        if q.shape[1] != m.n_joints:
            return trajectory, Refusal("joints", f"trajectory has {q.shape[1]} joints, the {m.name} has "
                                                 f"{m.n_joints}")
        state = self.state()
        gap = float(np.max(np.abs(q[0] - state.q)))
        if gap > TRAJECTORY_START_TOL_RAD:
            return trajectory, Refusal("start", f"trajectory starts {gap:.4f} rad away from the arm's joints")
        outside = np.nonzero(np.any((q[1:] < self._q_lo) | (q[1:] > self._q_hi), axis=1))[0]
        if outside.size:
            return trajectory, Refusal("joint margin", f"trajectory sample {outside[0] + 1} enters the joint "
                                       f"limit margin ({self._safety.joint_position_margin_rad:g} rad)")
        F = np.array([m.fk(qk) for qk in q])
        trajectory = self._within_speed_limits(trajectory, F)
        floor = self._margin_floor(state.T_base_flange)
        for k, T in enumerate(F):
            reason = self.barriers.first_violation(self.guarded_points(T), GUARDED_POINTS, floor)
            if reason is not None:
                return trajectory, Refusal("barrier", f"trajectory sample {k}: {reason}")
        hit = self.collision.check_path(q, self._safety.collision.trajectory_step_rad)
        if hit is not None:
            return trajectory, Refusal("collision", f"trajectory sample {hit[0]}: {hit[1]}")
        return trajectory, None

    def execute_trajectory(self, trajectory: JointTrajectory) -> JointTrajectory:
        """Check a joint trajectory (:meth:`check_trajectory`) and start it; returns what was started. A
        trajectory that fails the check is refused: the arm stops and ``SafetyStop`` is raised."""
        checked, refusal = self._check_start(trajectory)
        if refusal is not None:
            raise self._refuse(refusal.message)
        self._start(trajectory, checked)
        return checked

    def try_trajectory(self, trajectory: JointTrajectory) -> tuple[JointTrajectory, Refusal | None]:
        """Check a joint trajectory (:meth:`check_trajectory`) and start it unless the check refuses it: a
        planner's move, to which a refusal is an answer (the arm is neither moved nor stopped), checked
        once. Returns what was started (or would have been) and the refusal, or None."""
        checked, refusal = self._check_start(trajectory)
        if refusal is None:
            self._start(trajectory, checked)
        return checked, refusal

    def _check_start(self, trajectory: JointTrajectory) -> tuple[JointTrajectory, Refusal | None]:
        if self._target is not None:
            raise self._refuse("a trajectory was commanded while a twist is being streamed")
        return self.check_trajectory(trajectory)

    def _start(self, trajectory: JointTrajectory, checked: JointTrajectory) -> None:
        """Start ``checked``, what :meth:`check_trajectory` made of ``trajectory`` and accepted."""
        if checked is not trajectory:
            self.log.clamp("trajectory_time_scaled")
        self._send(lambda: self._arm.execute_trajectory(checked, self._token))
        self._following = True

    def _within_speed_limits(self, trajectory: JointTrajectory, F: Array) -> JointTrajectory:
        """Stretch the trajectory's time uniformly (the path is kept) when a joint or the TCP would be
        faster than the limits; counted as a clamp. ``F``: the flange poses of the samples."""
        q, t = trajectory.q, trajectory.t
        if q.shape[0] < 2:
            return trajectory
        dt = np.diff(t)[:, None]
        ratio = float(np.max(np.abs(np.diff(q, axis=0)) / dt / (self._qd_limit * VELOCITY_TOLERANCE)))
        lin = np.linalg.norm(np.diff(F[:, :3, 3], axis=0), axis=1) / dt[:, 0]
        ratio = max(ratio, float(np.max(lin)) / (self._safety.tcp_max_linear_mps * VELOCITY_TOLERANCE))
        R_rel = np.einsum("kji,kjl->kil", F[:-1, :3, :3], F[1:, :3, :3])
        angle = np.arccos(np.clip((np.trace(R_rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
        ratio = max(ratio, float(np.max(angle / dt[:, 0])) / (self._safety.tcp_max_angular_rps
                                                                * VELOCITY_TOLERANCE))
        if ratio <= 1.0:
            return trajectory
        qd = None if trajectory.qd is None else trajectory.qd / ratio
        return JointTrajectory(t=t * ratio, q=q, qd=qd)
