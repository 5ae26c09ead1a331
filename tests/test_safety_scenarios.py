"""Whole jobs meeting faults: each ends with the arm stopped, the reason recorded and the frames kept;
operator stops from the service call, the STOP file and the CLI; the guard as the only way to the arm;
the paper's barrier planes respected by a scan."""

from __future__ import annotations

import csv
import gc
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest
from typer.testing import CliRunner

from cell.cli.main import app
from cell.config import load_config
from cell.config.load import parse_config
from cell.jobs.control import JobControl, StopEffect
from cell.jobs.progress import JobProgress
from cell.jobs.runner import ScanRequest, run_scan
from cell.jobs.session import retrace_starts
from cell.planning.base import Planner, ScanSession
from cell.safety.guard import TwistRefused
from drivers.arm.base import ArmMode, JointTrajectory, MotionToken
from drivers.arm.sim import SimArm
from drivers.errors import OPERATOR_STOP, SAFETY_STOP, DriverError, SafetyStop
from drivers.transforms import look_at

from .conftest import FRANKA, UR5E, ended_without_a_frame, register_planner


class OrbitPlanner(Planner):
    """Streams a slow orbit of the sensor (sideways velocity plus the yaw that keeps it looking at the
    station) with continuous capture, like the servo planners do."""

    name: ClassVar[str] = "test-orbit"

    def run(self, session: ScanSession) -> str:
        session.set_continuous_capture(True)
        for _ in range(400):
            session.command_sensor_twist(np.array([0.04, 0.0, 0.0, 0.0, -0.15, 0.0]))
            session.wait(0.05)
        session.hold()
        session.wait(1.0)
        return "orbit done"


class PushPlanner(Planner):
    """Streams a base-frame velocity into the corner of the maximum-reach plane and the floor."""

    name: ClassVar[str] = "test-push"

    def run(self, session: ScanSession) -> str:
        session.set_continuous_capture(True)
        for _ in range(160):
            R = session.sensor_pose()[:3, :3]
            session.command_sensor_twist(np.concatenate([R.T @ np.array([0.2, 0.05, -0.12]), np.zeros(3)]))
            session.wait(0.05)
        return "push done"


class RetracePlanner(Planner):
    """Looks at the object from 25 cm, streams the sensor sideways for a while and then straight at the
    object until the guard refuses (the object's ROI ahead), then retraces the last two seconds of the
    arm's path, round the corner; ``refused_at`` keeps the job time [s] and sensor position [m] of the
    refusal."""

    name: ClassVar[str] = "test-retrace"
    refused_at: ClassVar[list[tuple[float, np.ndarray]]] = []

    def run(self, session: ScanSession) -> str:
        station = session.config.station
        centre = np.array([*station.xy_m, station.table_z_m + 0.05])
        assert session.move_to_sensor_pose(look_at(centre + np.array([0.0, -0.15, 0.2]), centre))
        session.set_continuous_capture(True)
        session.wait(1.0)
        session.command_sensor_twist(np.array([0.08, 0.0, 0.0, 0.0, 0.0, 0.0]))
        session.wait(0.8)
        try:
            for _ in range(200):
                session.command_sensor_twist(np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0]))
                session.wait(0.05)
        except TwistRefused:
            self.refused_at.append((session.now(), session.sensor_pose()[:3, 3].copy()))
            return "retraced" if session.retrace(2.0) else "not retraced"
        return "never refused"


class BypassPlanner(Planner):
    """Tries to move the arm around the guard, with everything it can find."""

    name: ClassVar[str] = "test-bypass"
    attempts: ClassVar[list[str]] = []

    def run(self, session: ScanSession) -> str:
        arm = next(o for o in gc.get_objects() if isinstance(o, SimArm) and o.is_connected)
        q = arm.state().q
        moves: list[tuple[str, Any]] = [
            ("twist with a forged token", lambda: arm.command_twist(np.ones(6) * 0.1, MotionToken())),
            ("trajectory with a forged token", lambda: arm.execute_trajectory(
                JointTrajectory(t=np.array([0.0, 1.0]), q=np.vstack([q, q + 0.5])), MotionToken())),
            ("claim the arm", arm.claim_motion),
        ]
        for what, move in moves:
            with pytest.raises(DriverError):
                move()
            BypassPlanner.attempts.append(what)
        session.wait(0.5)
        assert np.allclose(arm.state().q, q) and arm.state().mode is ArmMode.IDLE
        return "bypass refused"


@pytest.fixture(autouse=True)
def _test_planners(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    register_planner(monkeypatch, OrbitPlanner)
    register_planner(monkeypatch, BypassPlanner)
    register_planner(monkeypatch, PushPlanner)
    register_planner(monkeypatch, RetracePlanner)
    yield


def _run(tmp_path: Path, config_path: Path, *, faults: list[dict[str, Any]] | None = None,
         planner: str = OrbitPlanner.name, max_time: float = 12.0,
         on_progress: Any = None, control: JobControl | None = None,
         ) -> tuple[dict[str, Any], Path, BaseException | None]:
    data = load_config(config_path).model_dump(mode="json")
    data["sim"]["faults"] = faults or []
    cfg = parse_config(data, file=str(config_path))
    out = tmp_path / "job"
    error: BaseException | None = None
    try:
        run_scan(ScanRequest(config=cfg, config_path=str(config_path), object="bunny", planner=planner,
                             out=out, max_time_s=max_time), on_progress=on_progress, control=control)
    except SafetyStop as exc:
        error = exc
    return json.loads((out / "result.json").read_text()), out, error


def _trajectory(out: Path) -> np.ndarray:
    """trajectory.csv's rows: job time [s], sensor position [m], orientation (quaternion xyzw)."""
    with (out / "trajectory.csv").open() as f:
        return np.array([[float(v) for v in r] for r in list(csv.reader(f))[1:]])


def _sensor_positions(out: Path) -> np.ndarray:
    return _trajectory(out)[:, 1:4]


def _assert_stopped_and_kept(result: dict[str, Any], out: Path, error: BaseException | None,
                             reason: str) -> None:
    assert isinstance(error, SafetyStop)
    assert result["status"] == "stopped"
    assert reason in result["termination"]
    assert any(reason in s["reason"] for s in result["safety"]["stops"])
    frames = sorted((out / "frames").glob("*.npz"))
    assert len(frames) >= 1 and len(frames) == result["n_captures"]
    assert (out / "cloud.ply").stat().st_size > 0 and (out / "map.bt").exists()
    assert reason in (out / "log.txt").read_text()


@pytest.mark.parametrize(("kind", "reason"), [
    ("protective stop", "arm fault: protective stop"),
    ("reflex", "arm fault: reflex"),
    ("emergency stop", "arm fault: emergency stop"),
    ("disconnect", "arm fault: disconnect"),
])
def test_arm_fault_stops_the_job_and_keeps_the_frames(tmp_path, kind, reason):
    result, out, error = _run(tmp_path, FRANKA, faults=[{"at_s": 2.5, "kind": kind}])
    _assert_stopped_and_kept(result, out, error, reason)
    assert result["sim_time_s"] == pytest.approx(2.5, abs=0.05)


def test_late_control_loop_stops_the_arm(tmp_path):
    fault = {"at_s": 1.0, "kind": "loop overrun", "duration_s": 1.0, "overrun_s": 0.01}
    result, out, error = _run(tmp_path, UR5E, faults=[fault])
    _assert_stopped_and_kept(result, out, error, "watchdog: control loop missed its deadline 3 times")
    # Three late ticks of 20 ms after the overrun began, then the stop.
    assert 1.0 < result["sim_time_s"] < 1.2


def test_stale_perception_stops_the_arm(tmp_path):
    result, out, error = _run(tmp_path, FRANKA, faults=[{"at_s": 1.5, "kind": "sensor stall",
                                                         "duration_s": 10.0}])
    _assert_stopped_and_kept(result, out, error, "watchdog: perception data are")
    # Frames at 0 s and 1 s, then none: the limit of 3 s is passed just after t = 4 s.
    assert result["n_captures"] == 2 and result["n_capture_failures"] >= 3
    assert 4.0 < result["sim_time_s"] < 4.1
    assert "capture failed" in (out / "log.txt").read_text()


def test_arm_comes_to_rest_after_a_fault(tmp_path):
    _, out, _ = _run(tmp_path, FRANKA, faults=[{"at_s": 2.5, "kind": "protective stop"}])
    positions = _sensor_positions(out)
    # Moving at about 4 cm/s before the fault; the job records the braking until the arm is at rest.
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    assert steps[200:240].min() > 3e-4
    assert len(positions) > 252 and steps[-1] < 1e-6


def test_operator_stop_from_the_service_call(tmp_path):
    control = JobControl()
    effects: list[StopEffect] = []

    def stop_at_second_frame(progress: JobProgress) -> None:
        if progress.n_captures == 2:
            effects.append(control.request_stop("operator pressed stop"))

    result, out, error = _run(tmp_path, FRANKA, on_progress=stop_at_second_frame, control=control)
    _assert_stopped_and_kept(result, out, error, "operator stop: operator pressed stop")
    assert result["n_captures"] == 2 and effects == [StopEffect.COMMANDED]
    # a stop after the job's motion ended has nothing left to stop, and says so
    assert control.request_stop("too late") is StopEffect.AFTER_MOTION


def test_a_stop_the_service_makes_by_itself_is_the_safety_layers_not_an_operators(tmp_path):
    """A stop nobody asked for (the service stopping a job whose worker stopped answering, or after its
    own failure) ends the job as the safety layer's stop, which a line reads as such (StopReason 4), where
    every stop through the guard had read ``operator stop``."""
    control = JobControl()

    def stop_at_second_frame(progress: JobProgress) -> None:
        if progress.n_captures == 2:
            control.request_stop("the job's worker sent nothing for 5 s: hung", operator=False)

    result, out, error = _run(tmp_path, FRANKA, on_progress=stop_at_second_frame, control=control)
    _assert_stopped_and_kept(result, out, error, "the job's worker sent nothing for 5 s: hung")
    assert result["termination"].startswith(SAFETY_STOP) and OPERATOR_STOP not in result["termination"]


def test_a_stop_asked_before_the_job_moves_is_applied_before_its_first_motion(tmp_path):
    control = JobControl()
    assert control.request_stop("stopped while queued") is StopEffect.BEFORE_MOTION
    result, out, error = _run(tmp_path, FRANKA, control=control)
    assert isinstance(error, SafetyStop) and result["status"] == "stopped"
    assert "operator stop: stopped while queued" in result["termination"]
    # the sensor never moved: the stop reached the guard before the planner's first command
    assert np.ptp(_sensor_positions(out), axis=0).max() < 1e-9 and result["path_length_m"] == 0.0


def test_operator_stop_from_the_cli(tmp_path):
    def cli_stop(progress: JobProgress) -> None:
        if progress.n_captures == 3:
            res = CliRunner().invoke(app, ["stop", str(tmp_path / "job"), "--reason", "lunch"])
            assert res.exit_code == 0, res.output

    result, out, error = _run(tmp_path, FRANKA, on_progress=cli_stop)
    _assert_stopped_and_kept(result, out, error, "operator stop: lunch (cell stop)")
    assert not (out / "STOP").exists()


def test_cli_stop_refuses_a_finished_job(tmp_path):
    result, out, _ = _run(tmp_path, FRANKA, max_time=1.0)
    assert result["status"] in ("completed", "no_object")  # it ended, whatever its first second saw
    res = CliRunner().invoke(app, ["stop", str(out)])
    assert res.exit_code != 0 and "not running" in res.output


def test_planner_cannot_reach_the_arm_around_the_guard(tmp_path):
    BypassPlanner.attempts.clear()
    result, _, error = _run(tmp_path, FRANKA, planner=BypassPlanner.name, max_time=5.0)
    assert error is None and ended_without_a_frame(result, "bypass refused"), result["termination"]
    assert len(BypassPlanner.attempts) == 3


def test_streamed_motion_slides_along_the_barrier_planes(tmp_path):
    result, out, error = _run(tmp_path, FRANKA, planner=PushPlanner.name, max_time=12.0)
    assert error is None and result["status"] == "completed"
    cfg = load_config(FRANKA)
    positions = _sensor_positions(out)
    for plane in cfg.safety.barrier_planes:
        n = np.asarray(plane.normal) / np.linalg.norm(plane.normal)
        d = (positions - np.asarray(plane.point)) @ n
        assert d.min() >= 0.0, plane.name
        assert d.min() < 0.02, f"{plane.name} never approached"
    # Pushed into both planes, the sensor ends in their corner and kept sliding sideways along them.
    clamps = result["safety"]["clamps"]
    assert clamps.get("barrier max reach x", 0) > 0 and clamps.get("barrier floor", 0) > 0
    assert positions[-1, 1] - positions[len(positions) // 2, 1] > 0.05
    assert result["safety"]["stops"] == [] and result["safety"]["refusals"] == []


def test_after_a_refused_twist_the_arm_retraces_its_path(tmp_path):
    """The arm stopped short of the object goes back the way it came, round the corner of its path, and
    ends where it was two seconds before the refusal: not along some reverse of the last command, nor
    along the straight joint line that cuts the corner."""
    RetracePlanner.refused_at.clear()
    result, out, error = _run(tmp_path, FRANKA, planner=RetracePlanner.name, max_time=20.0)
    assert error is None and result["termination"] == "retraced", result["termination"]
    assert result["refused_moves"] == {"collision": 1}
    refusals = [r["reason"] for r in result["safety"]["refusals"]]
    assert refusals == ["camera would touch object ROI within 0.15 s"]
    (t_refused, p_refused), = RetracePlanner.refused_at
    rows = _trajectory(out)
    came = rows[(rows[:, 0] >= t_refused - 2.0 - 1e-9) & (rows[:, 0] <= t_refused + 1e-9)]
    back = rows[rows[:, 0] > t_refused + 0.5]  # the stop has braked the arm by then
    np.testing.assert_allclose(back[-1, 1:4], came[0, 1:4], atol=1e-3)
    assert abs(float(np.dot(back[-1, 4:], came[0, 4:]))) > 1.0 - 1e-6  # same orientation
    off_path = np.linalg.norm(back[:, None, 1:4] - came[None, :, 1:4], axis=2).min(axis=1)
    assert off_path.max() < 1e-3  # every sample of the way back lies on the way it came
    chord = (p_refused - came[0, 1:4]) / np.linalg.norm(p_refused - came[0, 1:4])
    rel = came[:, 1:4] - came[0, 1:4]
    corner = np.linalg.norm(rel - np.outer(rel @ chord, chord), axis=1).max()
    assert corner > 0.02  # and that way has a corner a straight line back would cut


def test_a_refused_retrace_is_tried_half_and_a_quarter_as_far_back():
    times = [0.01 * k for k in range(300)]
    assert retrace_starts(times, 2.5, 1.0) == [(1.0, 150), (0.5, 200), (0.25, 225)]  # at 1.5, 2.0, 2.25 s
    assert retrace_starts(times[100:], 1.5, 1.0)[0] == (1.0, 0)  # the record starts later: its first


def test_raster_scan_respects_the_barrier_planes(tmp_path):
    result, out, _ = _run(tmp_path, FRANKA, planner="raster", max_time=20.0)
    assert result["status"] == "completed" and result["n_captures"] >= 5
    assert result["safety"]["stops"] == []
    cfg = load_config(FRANKA)
    positions = _sensor_positions(out)
    for plane in cfg.safety.barrier_planes:
        n = np.asarray(plane.normal) / np.linalg.norm(plane.normal)
        assert ((positions - np.asarray(plane.point)) @ n).min() >= cfg.safety.barrier_margin_m - 1e-9
