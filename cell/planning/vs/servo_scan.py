"""The servo loop the three visual-servoing strategies share (visual-servoing paper section II, Fig. 2).

A scan moves to the start view (a sideways view at Z* from the station, paper III-B), switches on
continuous capture (perception at ``perception.rate_hz``), and then runs the dual-task law of eq. 1 at
``planners.vs.servo_rate_hz`` of job time: each iteration reads the sensor pose, expresses the low-pass
filtered object centroid in the camera frame (s of eq. 2), asks the strategy for the secondary task g once
the primary task has converged, streams the twist through the guard and lets 1 / rate pass.

Each new perception update (a new occupancy map) rebuilds the objective (eq. 9) on the new map, its rays
clipped to the box of every ROI of the scan so far (``PerceptionUpdate.extent``, the box H_ROI averages
over: a box that shrank with the segmentation would change f for reasons unrelated to what a view
reveals), and adds the update's H_ROI (eq. 12, which the job's pipeline computes in the objective's form,
``PerceptionPipeline``) to the history used by the entropy termination of Global and Hybrid.
A strategy ends the scan by returning a reason from ``secondary``'s companion ``finished``; the time
budget and safety stops end it from the session.

Limits the paper handled with barrier planes placed by hand are handled here for any placement: the
secondary direction g is projected so that it does not move a joint that is within
``joint_activation_rad`` of its position margin further towards it (``session.joint_limit_twists``,
mapped through the primary task's null-space projector of eq. 1), nor lower the smallest singular value
of the arm's Jacobian once it is below ``singular_value_activation`` (``session.singularity_twists``:
the arm at the edge of its reach), and the camera slides along the joint limit or the edge of the
reach as along a plane. When the guard refuses a streamed twist (a collision predicted ahead,
``TwistRefused``), the arm has been stopped; the scan backs off by retracing the arm's joint path of the
last ``backoff_s`` (``session.retrace``), then goes on with the refused secondary direction blocked within
``refusal_radius_m`` of where it was refused: the last direction the camera followed where g had fallen to
zero as the arm slowed (projected out near a joint limit; with no direction blocked, a Table I teapot
scan went back to the same refusal every 2 s, 67 times, to its time budget). A back-off the guard refuses
ends the scan.

``telemetry`` keeps one row per servo iteration (decimated in long jobs, ``cell.control.decimation``): the
series of the paper's Fig. 4 (||e||, f(r), ||g|| before clipping, H_ROI) with the job time and the
strategy's mode. ||g|| there is after the barrier projection and scaled by the share of the commanded motion
the arm realizes, so that it falls when the camera is held by a plane, a joint limit or the arm's reach (a
singularity), as at the drop of the paper's Fig. 4 at 38 s.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from cell.config.models import CellConfig
from cell.control.decimation import DecimatedSeries
from cell.control.servo import DualTaskServo, ServoOutput, null_space_projector
from cell.perception.filters import CentroidLowPass
from cell.perception.occupancy import binary_entropy
from cell.planning.base import Array, Planner, ScanSession
from cell.planning.vs.objective import EntropyObjective, PoseBatch, ray_grid
from cell.safety.barriers import project_onto_halfspaces
from cell.safety.guard import TwistRefused
from drivers.errors import NoObjectFound, PlanningError
from drivers.transforms import look_at


@dataclass(frozen=True)
class TelemetryRow:
    """One servo iteration: job time [s], ||e|| [m], f(r) [nats], ||g|| before clipping [1], H_ROI [nats] as
    the termination judges it (None before the first ROI), and the strategy's mode ("primary", "local",
    "global")."""

    t: float
    e_norm: float
    f: float
    g_norm: float
    h_roi: float | None
    mode: str


@dataclass(frozen=True)
class Secondary:
    """What a strategy returns for one iteration: g (6,) in the camera frame, after projection and
    clipping, its norm before clipping, f(r) at the current pose [nats], the mode it came from, and
    ``speed``: the multiple of the exploration speed (``ServoConfig``) at which the camera follows g (1
    but where VS-Local crosses views it has used up, ``cell.planning.vs.local``), and ``refused``: g is
    below ``g_max`` only because the camera avoids a direction the guard refused nearby (VS-Local's
    difference over delta would lead on without that; such an evaluation is no convergence,
    ``cell.planning.vs.local``)."""

    g: Array
    g_norm: float
    f: float
    mode: str
    speed: float = 1.0
    refused: bool = False


def objective_rays(config: CellConfig) -> Array:
    """The rays of eq. 9 for this cell: the configured grid (23 x 23 over 30 deg), over a multizone ToF
    sensor's own field of view where it has one (``planners.vs.objective.use_sensor_fov``)."""
    oc = config.planners.vs.objective
    sensor = config.sensor
    if oc.use_sensor_fov and sensor.type in ("sim-tof", "vl53l8cx"):
        return ray_grid(oc.rays_per_side, sensor.fov_deg)
    return ray_grid(oc.rays_per_side, oc.fov_deg)


def voxel_entropy(config: CellConfig) -> Callable[[Array], Array]:
    """H per voxel probability for the objective (``planners.vs.objective.voxel_entropy``): eq. 8's binary
    entropy, or the residual H(p) - H(c) above the map's clamping bound c on p's side [nats], zero for a
    voxel the map is as sure of as it can be."""
    if config.planners.vs.objective.voxel_entropy == "shannon":
        return binary_entropy
    occ = config.perception.occupancy
    floor_free, floor_occupied = binary_entropy(np.array([occ.clamp_min, occ.clamp_max]))

    def residual(p: Array) -> Array:
        floor = np.where(p < 0.5, floor_free, floor_occupied)
        return np.maximum(binary_entropy(p) - floor, 0.0)

    return residual


def start_views(config: CellConfig) -> list[Array]:
    """T_base_sensor of the start view (``planners.vs.start``) at Z* from its target point, then of a
    view from straight above it, tried when the first shows no object (a sparse 8x8 frame from the side
    may hold too few object points to segment)."""
    st = config.planners.vs.start
    station = config.station
    target = np.array([station.xy_m[0], station.xy_m[1], station.table_z_m + st.target_height_m])
    el, az = np.deg2rad(st.elevation_deg), np.deg2rad(st.azimuth_deg)
    Z = config.scan.standoff_m
    eye = target + Z * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    # From above, image "up" points away from the robot base (+x), as the raster planner's zenith view.
    above = look_at(target + np.array([0.0, 0.0, Z]), target, up_hint=np.array([1.0, 0.0, 0.0]))
    return [look_at(eye, target), above]


def achieved_fraction(v_commanded: Array, v_allowed: Array) -> float:
    """The share in [0, 1] of the commanded translation that the arm realizes along the commanded
    direction: what the guard's limits let through (joint limits and margins, barrier planes, speed
    limits) and its differential IK achieves; 1 when nothing was commanded. Along the direction, not in
    norm: near a singularity damped least squares also turns the twist (a teapot scan's arm, unable to
    back the camera away, realized 38 % of the commanded speed in norm and 10 % along it)."""
    wanted = float(np.dot(v_commanded[:3], v_commanded[:3]))
    if wanted < 1e-18:
        return 1.0
    return min(1.0, max(0.0, float(np.dot(v_commanded[:3], v_allowed[:3])) / wanted))


def held_norm(sec: Secondary, v_commanded: Array, v_allowed: Array) -> float:
    """||g|| before clipping scaled by the share of the exploration speed the arm realizes along the
    commanded twist (``achieved_fraction`` times ``sec.speed``, at most 1): a camera held by a joint
    limit or the edge of the reach counts as converging, one that a speed limit slows from a faster
    crossing to the exploration speed does not."""
    return sec.g_norm * min(1.0, sec.speed * achieved_fraction(v_commanded, v_allowed))


def translated(T_base_cam: Array, offsets_cam: Array) -> PoseBatch:
    """Poses (n, 4, 4): ``T_base_cam`` moved by each camera-frame translation of ``offsets_cam`` (n, 3)
    [m], orientation unchanged (the virtual displacements r +- delta of eq. 5-6)."""
    out = np.repeat(T_base_cam[None], offsets_cam.shape[0], axis=0)
    out[:, :3, 3] += offsets_cam @ T_base_cam[:3, :3].T
    return out


class ServoScanPlanner(Planner):
    """The shared loop (module docstring); a strategy supplies ``secondary`` and ``finished``."""

    def __init__(self, config: CellConfig) -> None:
        super().__init__(config)
        vs = config.planners.vs
        self.vs = vs
        sc = vs.servo
        self.servo = DualTaskServo(standoff_m=config.scan.standoff_m, lambda_0=sc.lambda_0,
                                   lambda_inf=sc.lambda_inf, lambda_0_slope=sc.lambda_0_slope,
                                   lambda_g=sc.lambda_g, e_converged_m=sc.e_converged_m)
        self.rays_cam = objective_rays(config)
        self._voxel_entropy = voxel_entropy(config)
        # the objective's choice of voxel uncertainty (H_ROI's comes with the perception update)
        self._observation_aware = vs.objective.entropy == "observation_aware"
        self.objective: EntropyObjective | None = None
        self.centroid: Array | None = None
        self.h_roi: list[float] = []
        self.telemetry: DecimatedSeries[TelemetryRow] = DecimatedSeries()
        self._centroid_filter = CentroidLowPass(vs.centroid_tau_s)
        # Where the guard refused a streamed twist, the secondary direction refused there (base frame) and
        # the guard's reason.
        self._refused: list[tuple[Array, Array, str]] = []
        # The last secondary direction the camera followed (unit, base frame), None before the first.
        self._moving: Array | None = None
        self._seq: int | None = None
        # Index of the first H_ROI value the termination of eq. 12 judges; None: not judged yet.
        self._h_roi_from: int | None = None

    def figures(self) -> dict[str, float | int | str | None]:
        """The last servo iteration: ||e|| [m], f [nats], ||g||, the mode, and the iteration count."""
        if not self.telemetry:
            return {"servo_iterations": 0}
        row = self.telemetry.last
        return {"servo_iterations": self.telemetry.count, "e_norm_m": round(row.e_norm, 6),
                "f_nats": round(row.f, 6), "g_norm": round(row.g_norm, 6), "mode": row.mode}

    @abstractmethod
    def secondary(self, session: ScanSession, T_base_cam: Array, objective: EntropyObjective,
                  rows: Array) -> Secondary:
        """The secondary task g for the current pose (called once the primary task has converged);
        ``rows``: the arm's ``limit_rows`` there."""

    @abstractmethod
    def finished(self, session: ScanSession) -> str | None:
        """Why the scan is complete, or None to go on; called after every iteration."""

    def observe(self, secondary: Secondary, g_norm: float, position_m: Array) -> None:
        """After the twist went out: ``g_norm`` is ||g|| before clipping scaled by the share of the motion
        the arm realizes, ``position_m`` (3,) [m, base frame] where the camera was when g was computed (a
        strategy with a convergence rule on ||g|| counts it here)."""

    def open_entropy_window(self) -> None:
        """Start judging the H_ROI termination, on the values from the next perception update on (a
        goal strategy calls this when it reaches or gives up its first goal; later calls change
        nothing)."""
        if self._h_roi_from is None:
            self._h_roi_from = len(self.h_roi)

    def entropy_settled(self) -> str | None:
        """The H_ROI termination of section II-D: the standard deviation of the last ``h_roi_window``
        (10) values of eq. 12 is below ``h_roi_std`` (0.001), judged only on values recorded since
        ``open_entropy_window``. The paper samples a new goal on arrival and gives no rule for the way
        to the first one; judged in flight, a flat H_ROI on the way (the start view's surroundings are
        known, the goal's not yet seen) ended a dragon scan at 54 % before its first goal.

        H_ROI takes each voxel's entropy as the objective f (eq. 9) does (``ObjectiveConfig.entropy``): eq.
        8's H(p) with ``paper``; with ``observation_aware`` (the default, a departure from eq. 8 in eq. 12)
        H(p) weighted by the information one more observation of the voxel still gives
        (``OccupancyMap.mean_entropy_in_box``). Surface voxels that flicker between occupied and free under
        the simulated calibration error kept eq. 8's H_ROI oscillating between 0.535 and 0.56 nats with a
        15 s period, and a cube's VS-Global scan (RGB-D cell, seed 0) ran to its 180 s budget after reaching
        100 % coverage at 30 s, although f had stopped counting those voxels long before. The values are
        the perception updates' own (``PerceptionUpdate.h_roi``): a job builds its pipeline with the
        objective's form (``PerceptionPipeline``'s ``h_roi_entropy``), so that H_ROI is computed once per
        capture and what the job reports is what is judged here; an update in another form is refused
        (``_perceive``)."""
        n = self.vs.h_roi_window
        if self._h_roi_from is None or len(self.h_roi) - self._h_roi_from < n:
            return None
        std = float(np.std(self.h_roi[-n:]))
        if std < self.vs.h_roi_std:
            return (f"H_ROI settled: std {std:.5f} of the last {n} values < {self.vs.h_roi_std:g} "
                    f"(H_ROI {self.h_roi[-1]:.4f})")
        return None

    def _perceive(self, session: ScanSession) -> None:
        """Take in a new perception update: filtered centroid, objective on the new map, the update's H_ROI
        (eq. 12 in the objective's form, ``entropy_settled``; ``PlanningError`` if it is in another)."""
        update = session.latest_perception()
        if update is None or update.seq == self._seq:
            return
        if update.h_roi_entropy != self.vs.objective.entropy:
            raise PlanningError(f"the perception pipeline computes H_ROI in its {update.h_roi_entropy} form, "
                                f"the termination judges the {self.vs.objective.entropy} one "
                                "(planners.vs.objective.entropy): build the pipeline with "
                                "h_roi_entropy=planners.vs.objective.entropy")
        self._seq = update.seq
        if update.extent is None or update.centroid is None:
            return  # segmentation found no object in this map: keep servoing on the last one
        self.centroid = self._centroid_filter.update(update.centroid, update.timestamp)
        perception = self.config.perception
        grow = self.vs.objective.roi_margin_m
        lo, hi = update.extent
        # down to the table the object stands on, above the voxel layer its surface lies in
        # (ObjectiveConfig.roi_margin_m)
        floor = self.config.station.table_z_m + perception.occupancy.resolution_m
        lo = np.array([lo[0] - grow, lo[1] - grow, min(lo[2], floor)])
        # the update's own map: on the wall clock perception runs on another thread, and this is the copy
        # published with the update, which nothing writes
        self.objective = EntropyObjective(update.map, lo, hi + grow, perception.crop_box,
                                          self.rays_cam, self._voxel_entropy, self._observation_aware)
        if update.h_roi is not None:
            self.h_roi.append(update.h_roi)

    def _find_object(self, session: ScanSession, period: float) -> None:
        """Go to the start views in turn until perception segments an object, waiting at each up to
        ``first_object_timeout_s`` [s] of captures; continuous capture is on from the first view
        reached."""
        capturing = False
        for view in start_views(self.config):
            if not session.move_to_sensor_pose(view):
                continue
            if not capturing:
                session.set_continuous_capture(True)
                capturing = True
            deadline = session.now() + self.vs.first_object_timeout_s
            self._perceive(session)
            while self.centroid is None and session.now() < deadline:
                session.wait(period)
                self._perceive(session)
            if self.centroid is not None:
                return
        if not capturing:
            raise PlanningError("none of the start views is reachable (the log names them)")
        raise NoObjectFound(f"no object segmented from the start views within "
                            f"{self.vs.first_object_timeout_s:g} s each (unreachable views are in the log)")

    def _features(self, T_base_cam: Array) -> Array:
        """s of eq. 2: the filtered object centroid in the camera frame [m]."""
        assert self.centroid is not None
        return T_base_cam[:3, :3].T @ (self.centroid - T_base_cam[:3, 3])

    def limit_rows(self, session: ScanSession) -> Array:
        """Rows a (m, 6) of the arm's state now, by which a sensor twist v (sensor frame, [m/s, rad/s])
        drives it further into a limit at a . v: each joint within ``joint_activation_rad`` of its margin
        (``session.joint_limit_twists``), and the smallest singular value of its Jacobian once below
        ``singular_value_activation`` (``session.singularity_twists``). ``run`` builds them once per
        servo iteration, for the strategy's ``secondary`` and ``_within_limits``: both judge the state read
        then (on the wall clock the arm goes on under the last streamed twist meanwhile, for less than an
        iteration)."""
        return np.concatenate([session.joint_limit_twists(self.vs.joint_activation_rad),
                               session.singularity_twists(self.vs.singular_value_activation)])

    def _blocked_directions(self, rows: Array, T_base_cam: Array, s: Array, refusals: bool = True) -> Array:
        """Rows B (m, 2) such that a secondary direction g (camera x, y) keeps clear of the joint limits,
        of singular configurations and of refused motions when B g >= 0: for each of ``rows``
        (``limit_rows``) a . (P g) of eq. 1, P the primary task's null-space projector, must not be
        positive (a joint within ``joint_activation_rad`` of its margin must not move towards it, the
        arm's smallest singular value below ``singular_value_activation`` must not fall further), and with
        ``refusals`` each refused secondary direction d (base frame) within ``refusal_radius_m`` of where
        the guard refused it (g . d <= 0)."""
        B = [-(rows @ null_space_projector(s))[:, :2]] if rows.shape[0] else []
        if refusals:
            B += [-(T_base_cam[:3, :3].T @ d)[None, :2] for _, d, _ in self._refusals_at(T_base_cam)]
        return np.concatenate(B) if B else np.zeros((0, 2))

    def _refusals_at(self, T_base_cam: Array) -> list[tuple[Array, Array, str]]:
        """The refusals in force at the camera pose ``T_base_cam``: those within ``refusal_radius_m`` [m]
        of where the guard refused (where, refused direction (base frame), the guard's reason)."""
        here = T_base_cam[:3, 3]
        return [r for r in self._refused if float(np.linalg.norm(here - r[0])) < self.vs.refusal_radius_m]

    def follows(self, session: ScanSession, T_base_cam: Array, rows: Array,
                refusals: bool = True) -> Callable[[Array], Array]:
        """A map from a secondary direction (3,) in the camera frame to the part of it the camera can follow
        from ``T_base_cam``: without its components into the barrier planes and into the half-planes
        ``_blocked_directions`` gives (``rows``: joint limits, the edge of the reach, ``limit_rows``; and
        with ``refusals`` refused motions)."""
        B = self._blocked_directions(rows, T_base_cam, self._features(T_base_cam), refusals)
        activation = self.vs.barrier_activation_m

        def follow(v: Array) -> Array:
            out = session.feasible_sensor_velocity(v, activation)
            if B.shape[0] and np.any(out[:2]):
                out[:2], _ = project_onto_halfspaces(out[:2], B, np.zeros(B.shape[0]), np.ones(2))
            return out

        return follow

    def _within_limits(self, session: ScanSession, T_base_cam: Array, s: Array, sec: Secondary,
                       rows: Array) -> Secondary:
        """``sec`` with g projected into the set ``_blocked_directions`` allows (``rows``: ``limit_rows``),
        the camera sliding along a joint limit as along a barrier plane (paper Fig. 3): g before clipping
        is projected, and then clipped again to the norm g had, so that a strong gradient slides the
        camera along the limit at full speed, and ||g|| before clipping, the projected one, falls below 1
        when the camera is held there, as at a plane. Projection onto these half-planes through the origin
        scales with its argument: g before clipping is ``sec.g`` times ||g|| before clipping over
        ||``sec.g``||. A crossing faster than the exploration speed slows to it near the limits g moves
        towards (``_limits_ahead``)."""
        if sec.speed > 1.0 and self._limits_ahead(session, T_base_cam, s, sec):
            sec = replace(sec, speed=1.0)
        norm = float(np.linalg.norm(sec.g[:2]))
        B = self._blocked_directions(rows, T_base_cam, s) if norm > 0.0 else np.zeros((0, 2))
        if not B.shape[0]:
            return sec
        xy, _ = project_onto_halfspaces(sec.g[:2], B, np.zeros(B.shape[0]), np.ones(2))
        raw = xy * (sec.g_norm / norm)  # g before clipping, projected
        projected = float(np.linalg.norm(raw))
        g = sec.g.copy()
        g[:2] = raw * min(1.0, norm / projected) if projected > 0.0 else 0.0
        return replace(sec, g=g, g_norm=projected)

    def _limits_ahead(self, session: ScanSession, T_base_cam: Array, s: Array, sec: Secondary) -> bool:
        """Whether g moves the camera towards a joint's margin or a barrier plane within ``sec.speed`` times
        the distance at which the camera starts sliding along it (``joint_activation_rad``,
        ``barrier_activation_m``): those distances are the seconds of travel the arm needs at the
        exploration speed to turn g along the limit, and a faster crossing covers them that much sooner
        (a held-out vertical box's camera, crossing over the far side at 16 cm/s, brought joint 1 to its
        margin at 0.275 rad/s, and the guard stopped the scan)."""
        rows = session.joint_limit_twists(self.vs.joint_activation_rad * sec.speed)
        if rows.shape[0] and np.any((rows @ null_space_projector(s))[:, :2] @ sec.g[:2] > 0.0):
            return True
        slid = session.feasible_sensor_velocity(sec.g[:3].copy(), self.vs.barrier_activation_m * sec.speed)
        return not np.allclose(slid, sec.g[:3])

    def _back_off(self, session: ScanSession, refused: Secondary, refusal: TwistRefused) -> None:
        """After the guard refused the streamed twist (and stopped the arm): remember the refused secondary
        direction where it happened (the last one the camera followed, if g was zero then), then retrace
        the arm's last ``backoff_s`` [s] of joint path (``session.retrace``). Where it cannot, ``refusal``
        ends the scan."""
        T = session.sensor_pose()
        direction = T[:3, :3] @ refused.g[:3]
        if not np.any(direction) and self._moving is not None:
            # g had fallen to zero as the arm slowed (projected out near a joint limit), the arm still
            # moving the way g had led it
            direction = self._moving
        norm = float(np.linalg.norm(direction))
        if norm > 0.0:
            self._refused.append((T[:3, 3].copy(), direction / norm, refusal.refusal.message))
        session.log(f"retracing the arm's last {self.vs.backoff_s:g} s of path, then avoiding "
                    f"{np.round(direction / norm, 3).tolist() if norm > 0.0 else 'no direction'} (base "
                    f"frame) within {self.vs.refusal_radius_m:g} m of {np.round(T[:3, 3], 3).tolist()}")
        if not session.retrace(self.vs.backoff_s):
            raise refusal

    def _command(self, session: ScanSession, T_base_cam: Array, s: Array,
                 sec: Secondary) -> tuple[ServoOutput, float]:
        """Eq. 1 for the centroid ``s`` with g at ``sec.speed`` times the exploration speed, streamed to the
        arm from ``T_base_cam``: the servo's output and ||g|| as the arm could follow it (``held_norm``)."""
        if np.any(sec.g[:3]):
            self._moving = T_base_cam[:3, :3] @ sec.g[:3] / float(np.linalg.norm(sec.g[:3]))
        out = self.servo.step(s, sec.speed * sec.g)
        allowed = session.command_sensor_twist(out.v)
        return out, held_norm(sec, out.v, allowed)

    def search_views(self) -> list[Array]:
        """Its start views (:func:`start_views`), where it looks for the object before servoing."""
        return start_views(self.config)

    def run(self, session: ScanSession) -> str:
        period = 1.0 / self.vs.servo_rate_hz
        self._find_object(session, period)
        zero = np.zeros(6)
        while True:
            self._perceive(session)
            assert self.objective is not None
            T = session.sensor_pose()
            s = self._features(T)
            e = self.servo.error(s)
            if self.servo.secondary_active or self.servo.primary_converged(e):
                rows = self.limit_rows(session)
                sec = self.secondary(session, T, self.objective, rows)
                sec = self._within_limits(session, T, s, sec, rows)
            else:
                sec = Secondary(zero, 0.0, float(self.objective(T)), "primary")
            out, g_norm = self._command(session, T, s, sec)
            if sec.mode != "primary":
                self.observe(sec, g_norm, T[:3, 3])
            self.telemetry.append(TelemetryRow(
                t=session.now(), e_norm=float(np.linalg.norm(out.e)), f=sec.f, g_norm=g_norm,
                h_roi=self.h_roi[-1] if self.h_roi else None, mode=sec.mode))
            reason = self.finished(session)
            if reason is not None:
                session.hold()
                session.set_continuous_capture(False)
                return reason
            try:
                session.wait(period)
            except TwistRefused as refusal:
                self._back_off(session, sec, refusal)
