"""Run one scan job end to end and leave its folder.

Set-up order: every input (planner name, seed, time budget, object, its size and placement, the folder)
is checked by :func:`prepare_scan` before the job's folder exists and before any driver connects, so bad
input fails before anything moves and leaves nothing behind. Once the folder exists it always ends with
a ``result.json``, whatever happens: a failure inside the loop stops the arm through the guard, writes
everything recorded so far with ``status`` ``failed`` (or ``stopped`` for a safety stop or Ctrl-C) and
``termination`` saying why, then re-raises; a failure while setting up or while writing the outputs
leaves a ``failed`` result with the error.

A job whose planner ended its run (its search for an object, or its whole path) with segmentation never
having found an object above the table in the frames it captured (an empty table; a part that did not
arrive) ends ``no_object``, not ``completed``: termination "no object found: ...". It is decided from what
the job saw, never from ground truth, so it holds on a real cell too. A limit that cut the planner's run
short before an object was found (the time budget, the end of a replayed recording) decides nothing
either way: such a job ends ``completed``, its termination saying that no object was found yet and that
the planner's search had not ended. One ToF frame of 64 zones cannot show a 10 cm cube to segmentation
(a cluster of at least ``min_cluster_points``), so a 1 s budget that stopped LR-NBV after its first frame
said "no object" of a cube standing there, and a packing line takes ``no_object`` for "no part".

Sim mode runs every device on the simulated clock (deterministic); a dry run (``mode: dry-run``) runs the
job on the wall clock with a hardware arm and a simulated sensor that sees the virtual object from where
the arm reports it is; ``mode: real`` runs a hardware arm and a hardware sensor on the wall clock, with
no ground truth (metrics are None). On the wall clock perception runs asynchronously from control
(``cell.jobs.live``). ``mode: replay`` re-runs a recorded job (``cell.jobs.replay``).

Every job with a session leaves the sensor's path (``path.png``, ``cell.planning.path_plot``; the views
captured from marked where the planner keeps its captures); a servo planner's job also its telemetry
(``servo.csv``, ``servo.png``; see ``cell.planning.vs.telemetry``), with the coverage over time in sim
(the cloud's, unregistered: ``cell.perception.metrics.CloudCoverage``).
"""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from cell.config.models import CellConfig
from cell.jobs.control import JobControl
from cell.jobs.inputs import CHOOSE_OUT, check_job_folder, check_pose, check_seed, check_time_budget
from cell.jobs.live import PoseHistory
from cell.jobs.live_cloud import LIVE_CLOUD_FILE, LiveCloudWriter
from cell.jobs.memory import release_freed_heap
from cell.jobs.placement import (
    check_in_view,
    check_placement,
    object_pose_in_base,
    view_points,
    where_views_look,
)
from cell.jobs.progress import JobProgress
from cell.jobs.rebuild import recorded_result
from cell.jobs.recorder import JobRecorder
from cell.jobs.replay import ReplaySession, check_recording
from cell.jobs.session import JobSession, ScanLimitReached, TimeBudgetExhausted
from cell.jobs.stop_file import STOP_FILE
from cell.packing.result import RecordsReconstruction, packing_section, section_box
from cell.perception.metrics import METRICS_KEYS, CloudCoverage, ground_truth_points, measure
from cell.perception.pipeline import PerceptionPipeline
from cell.planning.base import Array, Planner
from cell.planning.path_plot import PATH_NAME, plot_path
from cell.planning.registry import get_planner
from cell.planning.vs.servo_scan import ServoScanPlanner
from cell.planning.vs.telemetry import write_servo_outputs
from cell.safety.collision import CollisionWorld
from cell.safety.guard import MotionGuard
from drivers.arm.claim import ArmClaim
from drivers.arm.config import FrankaArmConfig, ReplayArmConfig, UR5eArmConfig
from drivers.arm.replay import ReplayArm
from drivers.arm.sim import SimArm
from drivers.clock import Clock, SimClock, WallClock
from drivers.depth.replay import ReplaySensor
from drivers.depth.sim_base import SimDepthSensor
from drivers.errors import OPERATOR_STOP, CellError, JobError, NoObjectFound, SafetyStop, stop_termination
from drivers.factory import SimWorld, make_arm, make_sensor, true_flange_pose
from drivers.robots import get_robot_model
from drivers.sim.board import TableTexture, board_on_table, board_texture
from drivers.sim.contact import SimContact
from drivers.sim.errors import SimErrors, draw_sim_errors
from drivers.sim.faults import SimFaultInjector
from drivers.sim.objects import EMPTY_TABLE, ObjectMesh, load_object
from drivers.sim.scene import SimScene

INTERRUPTED = f"{OPERATOR_STOP}interrupted (Ctrl-C)"


def interrupt_reason(exc: KeyboardInterrupt) -> str:
    """The operator stop an interrupt is: Ctrl-C's, or the one its raiser named (``cell scan`` raises one
    naming SIGTERM or SIGHUP)."""
    return f"{OPERATOR_STOP}{exc.args[0]}" if exc.args else INTERRUPTED


@dataclass(frozen=True)
class ScanRequest:
    """What to scan and how. ``object_pose`` is (x [m], y [m], yaw [deg]) relative to the station;
    ``object_scale`` multiplies a mesh's coordinates into metres (0.001 for a mesh in millimetres);
    ``object`` ``"none"`` is an empty table. ``choose_folder`` is what a job folder that cannot be made
    asks of the user, in the caller's words (``cell scan``'s ``--out``, the service's data dir).
    ``part_id`` and ``submitted_by``: the part and the key that asked for a service's job, kept in its
    job.json (a store restored from an older backup imports them from there); None for ``cell scan``."""

    config: CellConfig
    config_path: str
    object: str
    object_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    planner: str | None = None
    seed: int = 0
    out: Path | None = None
    max_time_s: float | None = None
    object_scale: float = 1.0
    choose_folder: str = CHOOSE_OUT
    part_id: str | None = None
    submitted_by: str | None = None


@dataclass(frozen=True)
class PreparedScan:
    """A request checked and resolved by :func:`prepare_scan`, before its folder exists: the planner,
    the object's name, and its mesh and pose in the base frame when known (the ground truth), the time
    budget [s], the folder the job will create, and the cell's collision world, which checked the
    placement and which the job's guard checks with (``CollisionWorld.for_cell``)."""

    request: ScanRequest
    planner_name: str
    planner: Planner
    replay_dir: Path | None
    object_name: str
    mesh: ObjectMesh | None
    T_base_object: np.ndarray | None
    max_time_s: float
    folder: Path
    collision: CollisionWorld


@dataclass(frozen=True)
class ScanOutcome:
    folder: Path
    result: dict[str, Any]


class JobGenerators(NamedTuple):
    """The random generators of one job: the simulated devices' noise, perception's draws (RANSAC), the
    planner's and the simulated cell's calibration error (``sim.error``)."""

    world: np.random.Generator
    perception: np.random.Generator
    planner: np.random.Generator
    calibration_error: np.random.Generator


def job_generators(seed: int) -> JobGenerators:
    """One seed per job, split into independent streams, so that perception's and the planner's draws
    never change the noise the simulated devices see, nor each other's."""
    return JobGenerators(*(np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4)))


def default_job_folder(object_name: str, planner: str, seed: int, replay: bool = False) -> Path:
    """``jobs/<stamp>-<object>-<planner>-s<seed>``, ending ``-replay`` for a replay of a recorded job."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("jobs") / f"{stamp}-{Path(object_name).stem}-{planner}-s{seed}{'-replay' if replay else ''}"


def _finite_or_none(values: dict[str, float]) -> dict[str, float | None]:
    return {k: (round(v, 6) if np.isfinite(v) else None) for k, v in values.items()}


def _scan_span(session: JobSession | None, end: float) -> tuple[float | None, float | None]:
    """The scan time [s] and trajectory length [m] of the visual-servoing paper (section III-C; its clocks
    start at the start view, Fig. 4 and 5): job time and sensor path from the first recorded frame to the
    end; None without a frame. The job's ``sim_time_s`` and ``path_length_m`` also count the move from
    home to the first view."""
    if session is None or session.first_frame_time is None:
        return None, None
    return (round(end - session.first_frame_time, 6),
            round(session.path_length_m - session.first_frame_path_m, 6))


def _perception_summary(session: JobSession | None) -> dict[str, Any]:
    """The ``perception`` section of result.json: registration counts, the well-constrained directions of
    each capture's registration (``RegistrationResult.n_constrained``), the last ROI, and H_ROI with its form
    (``h_roi_entropy``: the termination's, ``PerceptionPipeline``)."""
    latest = session.latest_perception() if session is not None else None
    roi = latest.roi if latest is not None else None
    return {
        "n_frames": session.n_captures if session else 0,
        "n_registration_rejected": session.n_registration_rejected if session else 0,
        "registration_n_constrained": session.registration_n_constrained if session else [],
        "h_roi": round(latest.h_roi, 6) if latest is not None and latest.h_roi is not None else None,
        "h_roi_entropy": session.perception.h_roi_entropy if session is not None else None,
        "roi": None if roi is None else {
            "aabb_min_m": np.round(roi.aabb_min, 6).tolist(),
            "aabb_max_m": np.round(roi.aabb_max, 6).tolist(),
            "obb_center_xy_m": np.round(roi.obb_center_xy, 6).tolist(),
            "obb_extent_xy_m": np.round(roi.obb_extent_xy, 6).tolist(),
            "obb_yaw_rad": round(float(roi.obb_yaw_rad), 6),
        },
    }


def _recorded_object(job_dir: Path) -> tuple[str, ObjectMesh | None, np.ndarray | None]:
    """The object a recorded job scanned, as its result names it (``result.json``, or the one rebuilt from
    ``job.json`` when that is missing or unreadable), with its mesh (at the scale
    the job used) and pose when it was a simulated job whose object is at hand (the ground truth for
    metrics); (name, None, None) otherwise."""
    recorded = recorded_result(job_dir).result
    name, pose = recorded.get("object"), recorded.get("object_pose")
    if not name or pose is None:
        return str(name or "unknown"), None, None
    try:
        return (str(name), load_object(str(name), float(recorded.get("object_scale", 1.0))),
                np.asarray(pose, dtype=float))
    except CellError:
        return str(name), None, None


def _scanned_object(req: ScanRequest, replay_dir: Path | None, planner_name: str, planner: Planner,
                    collision: CollisionWorld) -> tuple[str, ObjectMesh | None, np.ndarray | None]:
    """The object's name, and its mesh and pose in the base frame when they are known (the ground truth
    of sim and dry runs and of replays of them; a real cell scans an unknown object, an empty table has
    none). A placement is checked (``cell.jobs.placement``; clear of the arm in the cell's ``collision``
    world), also against ``planner``'s search views."""
    if replay_dir is not None:
        check_recording(replay_dir)
        return _recorded_object(replay_dir)
    if req.config.mode == "real":
        return req.object, None, None
    if req.object == EMPTY_TABLE:
        return EMPTY_TABLE, None, None
    mesh = load_object(req.object, req.object_scale)
    check_placement(req.config, mesh, req.object_pose, req.object_scale, world=collision)
    check_in_view(req.config, mesh, view_points(mesh), req.object_pose, planner.search_views(), planner_name)
    return req.object, mesh, object_pose_in_base(req.config, req.object_pose)


def prepare_scan(req: ScanRequest) -> PreparedScan:
    """Check every input of ``req`` and resolve it; raises ``CellError`` (one line) for bad input. Nothing
    is created and nothing connects."""
    cfg = req.config
    check_seed(req.seed)
    max_time = req.max_time_s if req.max_time_s is not None else cfg.scan.max_time_s
    check_time_budget(max_time)
    check_pose(req.object_pose)
    if cfg.sim.faults and cfg.mode != "sim":
        raise JobError("sim.faults needs the simulated arm and a simulated sensor (mode: sim)")
    if isinstance(cfg.arm, UR5eArmConfig | FrankaArmConfig):
        ArmClaim(cfg.arm.type, cfg.arm.host).check()
    planner_name = req.planner or cfg.scan.planner
    planner = get_planner(planner_name)(cfg)
    replay_dir = Path(cfg.arm.job_dir) if isinstance(cfg.arm, ReplayArmConfig) else None
    collision = CollisionWorld.for_cell(cfg)
    object_name, mesh, T_base_object = _scanned_object(req, replay_dir, planner_name, planner, collision)
    folder = req.out if req.out is not None else default_job_folder(object_name, planner_name, req.seed,
                                                                    replay=replay_dir is not None)
    check_job_folder(folder, req.choose_folder)
    return PreparedScan(req, planner_name, planner, replay_dir, object_name, mesh, T_base_object, max_time,
                        folder, collision)


def _run_planner(planner: Planner, session: JobSession) -> str:
    try:
        session.survey()
        return planner.run(session)
    finally:
        session.close()


def _outcome(config: CellConfig, session: JobSession, termination: str, planner_found_nothing: bool,
             cut_short: bool, budget_ran_out: bool) -> tuple[str, str]:
    """The status and termination of a job whose planner's run ended with ``termination`` (module
    docstring): a scan that captured no frame failed (:func:`_nothing_captured`), unless only its time
    budget ran out before its first view (``budget_ran_out``), with no view refused and no capture
    failed: a budget's matter, which its termination says. ``no_object`` needs the planner to have ended
    its run, by ``NoObjectFound`` (``planner_found_nothing``, its search ended) or by returning, with no
    object found in the frames it segmented; a run ``cut_short`` by a limit (``ScanLimitReached``)
    before an object was found ends ``completed``, undecided, with or without a frame."""
    n = session.n_captures
    if n == 0 and not (budget_ran_out and not (session.n_unreachable or session.n_capture_failures)):
        return "failed", _nothing_captured(session, termination)
    if session.object_found and not planner_found_nothing:
        return "completed", termination
    frames = f"{n} frame{'' if n == 1 else 's'}"
    # where it looked: an object elsewhere on the table is not "no object on the table"
    nothing = f"segmentation found nothing above the table near {where_views_look(config)} in {frames}"
    if cut_short:
        seen = "no frame captured" if n == 0 else nothing
        return "completed", (f"{termination} before an object was found or the planner's search for one had "
                             f"ended ({seen}): too soon to tell an empty table, so not no_object")
    return "no_object", f"no object found: {nothing} ({termination})"


def _nothing_captured(session: JobSession, planner_termination: str) -> str:
    """Why a scan that ended without a single frame failed: no view reachable (the cell file's mount,
    station, standoff or TCP is likely wrong: each view is a sensor pose, reached through them), every
    capture failing, or the planner's run ending before its first view for another reason."""
    if session.n_capture_failures:
        why = f"every capture failed ({session.n_capture_failures})"
    elif session.n_unreachable:
        why = (f"no view was reachable ({session.n_unreachable} unreachable): check the cell file's mount, "
               "station, scan.standoff_m and the arm's TCP (tcp_offset)")
    else:
        why = "the scan ended before its first view"
    return f"nothing captured: {why} ({planner_termination})"


def run_scan(req: ScanRequest, on_progress: Callable[[JobProgress], None] | None = None,
             control: JobControl | None = None) -> ScanOutcome:
    """Check ``req`` (:func:`prepare_scan`) and run it (:func:`run_prepared`); then give the memory the
    job freed back to the system (``cell.jobs.memory``), once its objects are gone."""
    try:
        return run_prepared(prepare_scan(req), on_progress, control)
    finally:
        release_freed_heap()


def run_prepared(job: PreparedScan, on_progress: Callable[[JobProgress], None] | None = None,
                 control: JobControl | None = None,
                 on_folder: Callable[[Path], None] | None = None) -> ScanOutcome:
    """Run a prepared scan; returns the job folder and the result written there.

    ``on_folder`` gets the job's folder as soon as it exists, before anything connects (``cell scan``
    names it then, for a ``cell stop`` from another terminal).

    ``on_progress`` gets a snapshot after each perception update, on the control thread (keep it short),
    and the job then also keeps its accumulated cloud in ``cloud_live.npy`` while it runs
    (``cell.jobs.live_cloud``); ``control`` lets another thread stop the job (``JobControl.request_stop``).
    A failure, a safety stop or Ctrl-C is raised once the folder is finished (``SafetyStop`` for the
    last two)."""
    req, cfg, planner, folder = job.request, job.request.config, job.planner, job.folder
    recorder = JobRecorder(folder)
    wall_start = time.monotonic()
    # With a hardware arm the job runs on the wall clock and perception runs asynchronously, its frames
    # paired with the poses the control loop records (poses); a dry run's simulated sensor renders the
    # virtual object from the newest of them. A replay plays recorded time on the simulated clock.
    wall = cfg.mode in ("dry-run", "real")
    clock: Clock = WallClock() if wall else SimClock()
    status, termination = "failed", "not started"
    limit_reached = False  # a limit of the job (ScanLimitReached) ended the planner's run, not the planner
    session: JobSession | None = None
    guard: MotionGuard | None = None
    live_cloud: LiveCloudWriter | None = None
    ground_truth: np.ndarray | None = None
    error: BaseException | None = None
    placed = f"replay of {job.replay_dir}" if job.replay_dir is not None else f"at {list(req.object_pose)}"
    scaled = "" if req.object_scale == 1.0 else f" scaled by {req.object_scale:g}"
    recorder.log(0.0, f"job: planner {job.planner_name}, object {job.object_name}{scaled} {placed}, seed "
                      f"{req.seed}, config {req.config_path}")
    try:
        if on_folder is not None:
            on_folder(folder)
        T_base_object = job.T_base_object
        # the cell's name: a service importing a folder its store does not know takes only its own
        asked_by = {k: v for k, v in (("part_id", req.part_id), ("submitted_by", req.submitted_by)) if v}
        recorder.job({**_identity(job), "cell": cfg.name, "object_placement": list(req.object_pose),
                      "max_time_s": job.max_time_s, **asked_by})
        world_rng, perception_rng, planner_rng, error_rng = job_generators(req.seed)
        poses = PoseHistory() if wall else None
        T_station = object_pose_in_base(cfg, (0.0, 0.0, 0.0))
        scene = sim_scene(cfg, job.mesh, T_base_object if T_base_object is not None else T_station) \
            if cfg.mode in ("sim", "dry-run") else None
        model = get_robot_model(cfg.arm.model)
        errors = (draw_sim_errors(cfg.sim.error, model, error_rng) if scene is not None and not cfg.sim.exact
                  else SimErrors.none())
        world = SimWorld(clock=clock, rng=world_rng, scene=scene, errors=errors)
        if scene is not None:
            recorder.log(0.0, f"sim: {errors.describe() if not cfg.sim.exact else 'exact (sim.exact)'}")
        # the simulated sensor renders from the mount it really has, the job believes ``mount``
        T_flange_sensor = cfg.true_mount_matrix(errors)
        arm = make_arm(cfg.arm, model, world)
        flange = poses.latest if poses is not None else true_flange_pose(arm)
        sensor = make_sensor(cfg.sensor, world, lambda: flange() @ T_flange_sensor)
        if job.mesh is not None and T_base_object is not None:
            ground_truth = ground_truth_points(job.mesh, T_base_object)
        if cfg.sim.faults:
            # a sim cell's devices (prepare_scan refused faults on any other)
            assert isinstance(clock, SimClock) and isinstance(arm, SimArm)
            assert isinstance(sensor, SimDepthSensor)
            SimFaultInjector(cfg.sim.faults, clock, arm, sensor)
        guard = MotionGuard.from_config(arm, model, cfg, clock, collision=job.collision)
        if scene is not None and isinstance(arm, SimArm) and isinstance(clock, SimClock):
            # the simulated arm hits the true object (and the table) as a real one would: it faults
            SimContact(clock, arm, scene, guard.collision.arm_bodies())

        # a watched job (``on_progress`` given) keeps a snapshot of its cloud for its watchers
        live_cloud = None if on_progress is None else LiveCloudWriter(
            folder / LIVE_CLOUD_FILE, log=lambda message: recorder.log(clock.now(), message))

        def report(s: JobSession) -> None:
            assert on_progress is not None and live_cloud is not None
            live_cloud.offer(s.cloud.points)
            on_progress(s.progress(planner.figures()))

        with arm, sensor:
            h_roi_entropy = cfg.planners.vs.objective.entropy
            perception = PerceptionPipeline(cfg.perception, table_z_m=cfg.station.table_z_m,
                                            range_max_m=sensor.model.range_max_m, rng=perception_rng,
                                            h_roi_entropy=h_roi_entropy,
                                            reach_m=job.collision.reach_m)
            recorder.log(clock.now(), f"H_ROI (eq. 12) reported in its {h_roi_entropy} form "
                                      "(planners.vs.objective.entropy, whatever the planner)")
            coverage = CloudCoverage(ground_truth) if ground_truth is not None else None
            common: dict[str, Any] = dict(
                clock=clock, guard=guard, model=model, perception=perception, recorder=recorder,
                max_time_s=job.max_time_s, coverage=coverage,
                on_progress=None if on_progress is None else report, stop_file=folder / STOP_FILE,
                rng=planner_rng)
            if isinstance(arm, ReplayArm) and isinstance(sensor, ReplaySensor):
                session = ReplaySession(cfg, arm=arm, sensor=sensor, **common)
            else:
                session = JobSession(cfg, sensor=sensor, poses=poses, **common)
            if control is not None:
                control.attach(session)
            # Whatever ends the planner's run, the arm is brought to rest and watched until it is, and
            # asynchronous capture stops before the sensor disconnects.
            planner_found_nothing = budget_ran_out = False
            try:
                termination = _run_planner(planner, session)
            except (ScanLimitReached, NoObjectFound) as exc:
                termination = str(exc)
                planner_found_nothing = isinstance(exc, NoObjectFound)
                limit_reached = isinstance(exc, ScanLimitReached)
                budget_ran_out = isinstance(exc, TimeBudgetExhausted)
            except SafetyStop:
                session.settle()
                raise
            except KeyboardInterrupt as exc:
                reason = interrupt_reason(exc)
                guard.stop(reason)
                session.settle()
                raise SafetyStop(reason) from None
            except Exception as exc:
                guard.stop(f"{type(exc).__name__}: {exc}")
                session.settle()
                raise
            guard.finish()
            session.settle()
            # a planner that ended for want of an object has the last word over what the map may hold
            status, termination = _outcome(cfg, session, termination, planner_found_nothing, limit_reached,
                                           budget_ran_out)
    except SafetyStop as exc:
        status, termination, error = "stopped", stop_termination(exc.reason), exc
    except KeyboardInterrupt as exc:
        reason = interrupt_reason(exc)
        status, termination, error = "stopped", stop_termination(reason), SafetyStop(reason)
    except CellError as exc:
        status, termination, error = "failed", f"{type(exc).__name__}: {exc}", exc
    except Exception as exc:
        status, termination, error = "failed", f"internal error: {type(exc).__name__}: {exc}", exc
        recorder.log(clock.now(), "".join(traceback.format_exception(exc)).rstrip())
    finally:
        if control is not None:
            control.detach()
        if guard is not None:
            guard.release()
        if live_cloud is not None:
            live_cloud.close()
        recorder.log(clock.now(), f"{status}: {termination}")
        try:
            result = _write_outputs(job, recorder, clock, wall_start, status, termination, limit_reached,
                                    session, guard, ground_truth)
        except Exception as exc:
            # the folder still ends with a result, which says what is missing and why
            status = "failed"
            termination = f"internal error while writing the job's outputs: {type(exc).__name__}: {exc}"
            recorder.log(clock.now(), termination)
            result = {**_identity(job), "status": status, "termination": termination}
            recorder.result(result)
            error = error or exc
        recorder.close()
    if error is not None:
        raise error
    return ScanOutcome(folder=folder, result=result)


def sim_scene(cfg: CellConfig, mesh: ObjectMesh | None, T_base_object: np.ndarray) -> SimScene:
    """The cell's simulated table (``sim``, ``station``, the calibration board of ``sim.board``) with
    ``mesh`` (None: the table only) on it at ``T_base_object`` (4x4, base frame [m])."""
    return SimScene(mesh, T_base_object, table_z=cfg.station.table_z_m,
                    table_center_xy=cfg.sim.table_center_xy_m, table_size_xy=cfg.sim.table_size_m,
                    texture=_sim_board(cfg))


def _sim_board(cfg: CellConfig) -> TableTexture | None:
    """The calibration board printed on the simulated table (``sim.board``), or None."""
    if cfg.sim.board is None or cfg.calibration.board is None:
        return None
    st = cfg.station
    return board_texture(cfg.calibration.board,
                         board_on_table(cfg.calibration.board, st.xy_m, st.table_z_m, cfg.sim.board.pose))


def _identity(job: PreparedScan) -> dict[str, Any]:
    """What result.json says of the job before its outcome: planner, object (its scale, and its pose in
    the base frame when known), cell file, the cell's mode (which says the clock of ``sim_time_s``:
    simulated in sim and replay, the wall clock in dry-run and real), seed."""
    req, T = job.request, job.T_base_object
    return {"planner": job.planner_name, "object": job.object_name, "object_scale": req.object_scale,
            "object_pose": None if T is None else np.round(T, 9).tolist(), "config": req.config_path,
            "mode": req.config.mode, "seed": req.seed}


def _write_outputs(job: PreparedScan, recorder: JobRecorder, clock: Clock, wall_start: float, status: str,
                   termination: str, limit_reached: bool, session: JobSession | None,
                   guard: MotionGuard | None, ground_truth: np.ndarray | None) -> dict[str, Any]:
    """Write the cloud, the map, the planner's telemetry or path, and result.json last; returns the
    result. ``limit_reached``: a limit of the job (its time budget, a replay's recording) ended the
    planner's run, not the planner's own termination rule."""
    cloud = session.cloud.points if session is not None else np.zeros((0, 3))
    recorder.cloud(cloud)
    if session is not None:
        recorder.occupancy_map(session.perception.map)
    metrics = (measure(ground_truth, cloud).as_dict() if ground_truth is not None
               else dict.fromkeys(METRICS_KEYS, float("nan")))
    scan_time, scan_path = _scan_span(session, clock.now())
    T_base_object = job.T_base_object
    result: dict[str, Any] = {
        **_identity(job),
        "status": status,
        "termination": termination,
        "limit_reached": limit_reached,
        "sim_time_s": round(clock.now(), 6),
        "scan_time_s": scan_time,
        "wall_time_s": round(time.monotonic() - wall_start, 3),
        "path_length_m": round(session.path_length_m, 6) if session else 0.0,
        "scan_path_length_m": scan_path,
        "n_captures": session.n_captures if session else 0,
        "n_capture_failures": session.n_capture_failures if session else 0,
        "n_unreachable_views": session.n_unreachable if session else 0,
        "refused_moves": dict(sorted(session.refused_moves.items())) if session else {},
        "n_cloud_points": int(cloud.shape[0]),
        "metrics": _finite_or_none(metrics),
        "perception": _perception_summary(session),
        "packing": packing_section(job.request.config, session, job.planner, job.mesh, T_base_object,
                                   ground_truth, no_object=status == "no_object"),
        "safety": guard.log.as_dict() if guard is not None else None,
        "control": None if session is None or guard is None else {
            **session.ticks.summary(), "first_motion_unix_s": guard.first_motion_unix_s},
    }
    if isinstance(session, ReplaySession):
        result["replay"] = {"job_dir": str(job.replay_dir), "n_planner_requests": session.n_planner_requests,
                            "n_recorded_answers": session.n_recorded_answers,
                            "refusals_recorded": session.refusals_recorded}
    _write_plots(job, session, result["packing"])
    # last: a client that finds result.json finds every other file of the job beside it, and the line
    # reports the end right after it
    recorder.result(result)
    return result


def _write_plots(job: PreparedScan, session: JobSession | None, packing: dict[str, Any]) -> None:
    """A servo planner's telemetry, else the sensor's path with the views captured from (when the planner
    keeps its captures) around the packing box's centre."""
    planner = job.planner
    if session is None:
        return
    positions = np.array(session.sensor_path.records())
    if isinstance(planner, ServoScanPlanner) and planner.telemetry:
        write_servo_outputs(job.folder, planner.telemetry.records(), session.perception.h_roi_entropy,
                            positions, planner.centroid,
                            session.coverage_history, session.first_frame_position)
    elif session.sensor_path:
        captures = ([s.T_base_sensor[:3, 3] for s in planner.reconstruction.sightings]
                    if isinstance(planner, RecordsReconstruction) else None)
        plot_path(job.folder / PATH_NAME, positions, _box_centre(packing),
                  None if captures is None else np.array(captures), session.first_frame_position)


def _box_centre(packing: dict[str, Any]) -> Array | None:
    """The centre [m, base frame] of a result's packing box (:func:`section_box`), None without one."""
    if packing.get("box") is None or packing.get("dims_m") is None:
        return None
    box = section_box(packing)
    return np.array([*box.center_xy, box.z_min + box.dims[2] / 2.0])
