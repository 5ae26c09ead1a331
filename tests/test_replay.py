"""Replay: a recorded job's frames as a sensor and its poses as a read-only arm; a replayed job rebuilds its
original cloud exactly."""

from __future__ import annotations

import csv
import json
import shutil
from typing import ClassVar

import numpy as np
import pytest
from typer.testing import CliRunner

from cell.cli.main import app
from cell.cli.sensor import replay_perception
from cell.config import load_config
from cell.config.models import CellConfig
from cell.jobs.replay import replay_config
from cell.jobs.requests import REQUESTS_FILE
from cell.perception.cloud import read_ply
from cell.perception.metrics import METRICS_KEYS
from cell.planning.base import Planner, ScanSession
from cell.safety.guard import TwistRefused
from drivers.arm.replay import ReplayArm
from drivers.clock import SimClock
from drivers.depth.config import ReplayConfig
from drivers.depth.replay import JobRecording, PlaybackClock, ReplaySensor
from drivers.errors import DriverError
from drivers.factory import make_sensor
from drivers.robots import get_robot_model
from drivers.transforms import look_at, quat_xyzw

from .conftest import FRANKA, UR5E, raster_scan, register_planner


def _scan(tmp_path_factory, config, max_time_s: float):
    out = tmp_path_factory.mktemp("jobs") / "job"
    raster_scan(out, config, "cube", 1, max_time_s)
    return out


@pytest.fixture(scope="module")
def tof_job(tmp_path_factory):
    return _scan(tmp_path_factory, UR5E, 15)


@pytest.fixture(scope="module")
def rgbd_job(tmp_path_factory):
    return _scan(tmp_path_factory, FRANKA, 6)


@pytest.mark.parametrize("job, config", [("tof_job", UR5E), ("rgbd_job", FRANKA)])
def test_a_replayed_job_rebuilds_its_cloud_exactly(request, job, config):
    job_dir = request.getfixturevalue(job)
    cloud, n, unreadable = replay_perception(job_dir, load_config(config), seed=1)
    assert unreadable == []
    assert n == len(list((job_dir / "frames").glob("*.npz"))) >= 3
    recorded = read_ply(job_dir / "cloud.ply")
    assert recorded.shape[0] > 50
    assert cloud.tobytes() == recorded.tobytes()


def test_replay_command_writes_and_compares(tof_job):
    res = CliRunner().invoke(app, ["sensor", "replay", str(tof_job), "--config", str(UR5E)])
    assert res.exit_code == 0, res.output
    assert "identical to the recorded cloud.ply" in res.output
    assert read_ply(tof_job / "cloud_replay.ply").shape == read_ply(tof_job / "cloud.ply").shape


def test_replay_arm_follows_the_recorded_poses(tof_job):
    rec = JobRecording(tof_job)
    clock = SimClock()
    arm = ReplayArm(rec, get_robot_model("ur5e"), clock)
    with pytest.raises(DriverError, match="disconnected"):
        arm.state()
    with arm:
        for k, frame in enumerate(rec.frames):
            clock.sleep(frame.timestamp - clock.now())
            state = arm.state()
            assert np.array_equal(state.T_base_flange, rec.load(k)[2])  # the capture's own pose, exactly
            assert state.q.shape == (6,) and np.all(np.isfinite(state.q)) and not np.any(state.v_base_flange)
        with (tof_job / "joints.csv").open() as f:  # the joints the live arm reported, exactly
            t, *q = (float(v) for v in list(csv.reader(f))[1:][100])
        assert arm.joints_at(t).tolist() == q
        with (tof_job / "trajectory.csv").open() as f:
            rows = list(csv.reader(f))[1:]
        t, *pose = (float(v) for v in rows[len(rows) // 3])
        T = arm.pose_at(t) @ rec.T_flange_sensor
        assert np.allclose(T[:3, 3], pose[:3], atol=1e-8)
        assert np.allclose(np.abs(quat_xyzw(T) @ np.asarray(pose[3:])), 1.0, atol=1e-8)
        assert np.array_equal(arm.pose_at(-1.0), arm.pose_at(0.0))  # before the recording: its first pose


def test_a_job_recorded_without_joints_replays_an_arm_without_them(tof_job, tmp_path):
    job = tmp_path / "old"
    shutil.copytree(tof_job, job)
    (job / "joints.csv").unlink()
    arm = ReplayArm(JobRecording(job), get_robot_model("ur5e"), SimClock())
    with arm:
        assert np.all(np.isnan(arm.state().q)) and arm.state().q.shape == (6,)


def test_replay_arm_cannot_move(tof_job):
    arm = ReplayArm(JobRecording(tof_job), get_robot_model("ur5e"), SimClock())
    with arm:
        with pytest.raises(DriverError, match="safety guard"):
            arm.command_twist(np.zeros(6), token=None)
        token = arm.claim_motion()
        with pytest.raises(DriverError, match="cannot move"):
            arm.command_twist(np.zeros(6), token)
        arm.stop()
        arm.recover()


def test_replay_sensor_plays_on_the_clock(tof_job):
    rec = JobRecording(tof_job)
    clock = SimClock()
    sensor = ReplaySensor(rec, clock, (0.02, 4.0))
    assert sensor.model.kind == "tof" and sensor.model.width == 8
    assert sensor.model.fov_x_deg == pytest.approx(45.0)
    with sensor:
        first = sensor.capture()  # waits (lets the clock run) until the first recorded frame
        assert clock.now() == pytest.approx(rec.frames[0].timestamp) and first.seq == rec.frames[0].seq
        k = len(rec.frames) - 2
        assert k >= 2
        clock.sleep(rec.frames[k].timestamp - clock.now())
        assert sensor.capture().seq == rec.frames[k].seq  # the newest due frame; the ones between: missed
        last = sensor.capture()
        assert sensor.remaining == 0
        assert last.seq == rec.frames[-1].seq and last.zones is not None and last.points.shape[1] == 3
        with pytest.raises(DriverError, match="replay ended"):
            sensor.capture()


def test_replay_of_a_depth_camera_gives_back_its_image_and_points(rgbd_job):
    rec = JobRecording(rgbd_job)
    frame, T_base_sensor, T_base_flange = rec.load(0)
    assert frame.depth.shape == (480, 640) and frame.intrinsics.shape == (3, 3)
    assert frame.points.shape[0] == np.count_nonzero(frame.depth)
    assert np.allclose(T_base_flange @ rec.T_flange_sensor, T_base_sensor)
    sensor = ReplaySensor(rec, SimClock(), (0.1, 1.5))
    assert sensor.model.kind == "rgbd" and sensor.model.width == 640


def test_not_a_job_folder(tmp_path):
    with pytest.raises(DriverError, match="no recorded frames"):
        JobRecording(tmp_path)
    with pytest.raises(DriverError, match="no recorded frames"):
        make_sensor(ReplayConfig(type="replay", job_dir=str(tmp_path)), None, lambda: np.eye(4))


def test_factory_replay_plays_in_real_time_from_the_first_frame(tof_job):
    sensor = make_sensor(ReplayConfig(type="replay", job_dir=str(tof_job)), None, lambda: np.eye(4))
    assert isinstance(sensor, ReplaySensor)
    clock = PlaybackClock(2.5)
    assert 2.5 <= clock.now() < 3.5


# -- a recorded job re-run through perception and the planners (mode: replay) ------------------------------
def _replay(job_dir, out, *args):
    res = CliRunner().invoke(app, ["scan", "--replay", str(job_dir), "--out", str(out), *args])
    assert res.exit_code == 0, res.output
    return json.loads((out / "result.json").read_text()), res.output


def test_a_replay_without_out_gets_a_folder_that_says_replay(tof_job, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, ["scan", "--replay", str(tof_job)])
    assert res.exit_code == 0, res.output
    (folder,) = (tmp_path / "jobs").iterdir()
    assert folder.name.endswith("-raster-s1-replay") and (folder / "result.json").exists()


def _requests(job_dir):
    with (job_dir / "planner_requests.csv").open() as f:
        return list(csv.DictReader(f))


def test_replay_through_the_recording_planner_rebuilds_the_job(tof_job, tmp_path):
    result, output = _replay(tof_job, tmp_path / "again")
    recorded = json.loads((tof_job / "result.json").read_text())
    assert result["planner"] == recorded["planner"] == "raster" and result["seed"] == 1
    # the job's own time budget, not the cell file's: the replay ends where the job did, and why
    assert result["status"] == "completed" and recorded["termination"] == "time budget of 15 s used up"
    assert result["termination"] == recorded["termination"] and result["limit_reached"] is True
    assert result["replay"]["job_dir"] == str(tof_job)
    assert (tmp_path / "again" / "cloud.ply").read_bytes() == (tof_job / "cloud.ply").read_bytes()
    assert result["metrics"] == recorded["metrics"]
    assert result["packing"]["dims_m"] == recorded["packing"]["dims_m"]
    moves = _requests(tmp_path / "again")
    # raster asked for the live job's views and got its answers (refused ones too); the live job's time
    # ran out on its way to the last
    live = _requests(tof_job)
    assert {r["kind"] for r in moves} == {"move"} and moves == live
    assert sum(r["answer"] == "reached" for r in live) == recorded["n_captures"] + 1
    assert result["replay"]["n_planner_requests"] == len(moves)
    assert result["replay"]["n_recorded_answers"] == len(live)
    assert "time budget of 15 s used up" in output
    # a longer budget than the job's plays the recording to its end: the live job's last move's capture
    # finds no frame
    longer, output = _replay(tof_job, tmp_path / "longer", "--max-time", "60")
    assert longer["termination"] == f"recording ended: all {recorded['n_captures']} recorded frames played"
    assert longer["limit_reached"] is True and "recording ended" in output
    assert (tmp_path / "longer" / "cloud.ply").read_bytes() == (tof_job / "cloud.ply").read_bytes()


def test_replay_through_another_planner_records_what_it_asks_for(tof_job, tmp_path):
    result, _ = _replay(tof_job, tmp_path / "vs", "--planner", "vs-local")
    recorded = json.loads((tof_job / "result.json").read_text())
    assert result["planner"] == "vs-local" and result["status"] == "completed"
    # whatever the planner asks, the recording plays: every recorded frame, with its recorded pose
    assert result["n_captures"] == recorded["n_captures"]
    replayed = JobRecording(tmp_path / "vs")
    original = JobRecording(tof_job)
    for k in range(len(original.frames)):
        assert np.array_equal(replayed.load(k)[2], original.load(k)[2])
    requests = _requests(tmp_path / "vs")
    twists = [r for r in requests if r["kind"] == "twist"]
    assert twists and all(r["x"] == "" and r["vx"] != "" for r in twists)
    assert np.all(np.isfinite([[float(r[k]) for k in ("vx", "vy", "vz", "wx", "wy", "wz")] for r in twists]))
    assert not any(r["kind"] == "move" and r["vx"] for r in requests)


def test_an_lr_nbv_job_replays_its_views_with_the_arms_answers(tmp_path):
    """LR-NBV chooses its next views from the arm's answers (a refused move ends a branch, an unreachable
    cached node is dropped), which the frames do not hold: the live job records its moves and reach checks
    with their answers, and the replay gives the same answers while its planner asks what the live one did.
    Replayed with its own planner, the job asks for the same views and rebuilds the same cloud."""
    live = tmp_path / "live"
    res = CliRunner().invoke(app, ["scan", "--config", str(UR5E), "--object", "gripper", "--planner",
                                   "lr-nbv", "--seed", "0", "--max-time", "10", "--out", str(live)])
    assert res.exit_code == 0, res.output
    asked = _requests(live)
    assert {r["answer"] for r in asked} == {"reached", "refused", "reachable", "unreachable"}
    result, _ = _replay(live, tmp_path / "again")
    assert _requests(tmp_path / "again")[:len(asked)] == asked
    assert result["replay"]["n_recorded_answers"] == len(asked)
    assert (tmp_path / "again" / "cloud.ply").read_bytes() == (live / "cloud.ply").read_bytes()
    # another seed grows other trees: the replay leaves the recorded requests, says so, and plays on
    other, _ = _replay(live, tmp_path / "other", "--seed", "1")
    assert other["replay"]["n_recorded_answers"] < len(asked) and other["status"] == "completed"
    assert "the planner asked for another " in (tmp_path / "other" / "log.txt").read_text()


def test_a_servo_scan_replays_through_its_secondary_task(tmp_path):
    """A VS-Local recording replayed through VS-Local: the recorded motion kept the object centred, so the
    secondary task starts, and its barrier rows (joint limits, the edge of the reach) ask a replayed arm,
    which reports no joints, for nothing."""
    args = ["scan", "--config", str(FRANKA), "--object", "cube", "--planner", "vs-local",
            "--out", str(tmp_path / "job"), "--max-time", "7"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    result, _ = _replay(tmp_path / "job", tmp_path / "again")
    assert result["status"] == "completed", result.get("termination")
    with (tmp_path / "again" / "servo.csv").open() as f:
        assert "local" in {row["mode"] for row in csv.DictReader(f)}


def test_replay_without_ground_truth_reports_no_metrics(tof_job, tmp_path):
    job = tmp_path / "real"
    shutil.copytree(tof_job, job)
    result = json.loads((job / "result.json").read_text())
    result.update(object=None, object_pose=None)  # as a job on a real cell records it
    (job / "result.json").write_text(json.dumps(result))
    replayed, output = _replay(job, tmp_path / "again", "--config", str(UR5E))
    assert replayed["metrics"] == dict.fromkeys(METRICS_KEYS)
    assert replayed["object_pose"] is None and replayed["packing"]["iou"] is None
    assert replayed["packing"]["dims_m"] is not None and "no ground truth" in output


def test_replay_mode_needs_replay_backends_of_one_job(tof_job, tmp_path):
    cfg = load_config(UR5E)
    replay = replay_config(cfg, tof_job)
    assert replay.mode == "replay" and replay.arm.type == "replay" and replay.sensor.type == "replay"
    data = replay.model_dump()
    with pytest.raises(ValueError, match=r"mode 'replay' needs arm\.type 'replay'"):
        CellConfig.model_validate({**data, "arm": cfg.model_dump()["arm"]})
    with pytest.raises(ValueError, match="must name the same recorded job"):
        CellConfig.model_validate({**data, "sensor": {**data["sensor"], "job_dir": str(tmp_path)}})
    with pytest.raises(ValueError, match="needs mode 'replay'"):
        CellConfig.model_validate({**data, "mode": "real"})
    res = CliRunner().invoke(app, ["scan", "--replay", str(tmp_path)])
    assert res.exit_code == 1 and "is not a job folder: no result.json and no recorded frames" in res.output


@pytest.mark.parametrize("option, value", [("--object", "bunny"), ("--object-pose", "0.01,0,0"),
                                           ("--object-scale", "1")])
def test_a_replay_refuses_another_object(tof_job, tmp_path, option, value):
    """The recording holds the scanned object: an object, pose or scale given with --replay was ignored."""
    out = tmp_path / "replayed"
    res = CliRunner().invoke(app, ["scan", "--replay", str(tof_job), option, value, "--out", str(out)])
    assert res.exit_code == 1, res.output
    assert res.stderr == (f"error: {option} cannot be given with --replay: a replay scans the recorded job's "
                          "object, where the recording has it\n")
    assert not out.exists()


class BackOffPlanner(Planner):
    """Streams the sensor straight at the object from 25 cm until the guard refuses (the object's ROI
    ahead), backs off along the arm's path and ends a second later; unrefused, it ends after 3 s. What it
    does, like a servo planner's back-off and refused directions, turns on the arm's refusal."""

    name: ClassVar[str] = "test-back-off"

    def run(self, session: ScanSession) -> str:
        station = session.config.station
        centre = np.array([*station.xy_m, station.table_z_m + 0.05])
        assert session.move_to_sensor_pose(look_at(centre + np.array([0.0, -0.15, 0.2]), centre))
        session.set_continuous_capture(True)
        try:
            for _ in range(60):
                session.command_sensor_twist(np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0]))
                session.wait(0.05)
        except TwistRefused:
            retraced = session.retrace(1.0)
            session.wait(1.0)
            return "backed off" if retraced else "not retraced"
        return "never refused"


@pytest.fixture(scope="module")
def refused_job(tmp_path_factory):
    """A Franka cube job whose streamed twist the guard refused (BackOffPlanner)."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        register_planner(monkeypatch, BackOffPlanner)
        out = tmp_path_factory.mktemp("jobs") / "refused"
        res = CliRunner().invoke(app, ["scan", "--config", str(FRANKA), "--object", "cube", "--planner",
                                       BackOffPlanner.name, "--out", str(out), "--max-time", "15"])
        assert res.exit_code == 0, res.output
        yield out


def test_a_job_whose_twist_was_refused_replays_byte_for_byte(refused_job, tmp_path, monkeypatch):
    """The live job records the refusal (its tick, the twist, the guard's reason) and its back-off; the
    replay's guard refuses the same twist at the same tick and the back-off plays as the live one ended,
    so the planner does what it did live and the cloud is rebuilt exactly. Unrefused, the planner would
    have streamed on and ended before the recording, with fewer frames."""
    register_planner(monkeypatch, BackOffPlanner)
    live = json.loads((refused_job / "result.json").read_text())
    assert live["termination"] == "backed off" and live["refused_moves"] == {"collision": 1}
    asked = _requests(refused_job)
    refused = [r for r in asked if r["answer"] == "refused"]
    assert [r["kind"] for r in refused] == ["twist"] and refused[0]["refusal"] == "collision"
    assert refused[0]["reason"] == "camera would touch object ROI within 0.15 s" and refused[0]["vz"] != ""
    assert [r["answer"] for r in asked if r["kind"] == "retrace"] == ["reached"]
    result, _ = _replay(refused_job, tmp_path / "again")
    assert (tmp_path / "again" / "cloud.ply").read_bytes() == (refused_job / "cloud.ply").read_bytes()
    for key in ("termination", "n_captures", "refused_moves", "metrics"):
        assert result[key] == live[key], key
    assert result["safety"]["refusals"] == live["safety"]["refusals"]
    assert result["replay"]["refusals_recorded"] is True
    replayed = [r for r in _requests(tmp_path / "again") if r["answer"]]
    assert replayed == [r for r in asked if r["answer"]]
    assert result["replay"]["n_recorded_answers"] == len(replayed)


def test_a_job_recorded_before_refusals_replays_and_says_it_may_diverge(refused_job, tmp_path, monkeypatch):
    register_planner(monkeypatch, BackOffPlanner)
    old = tmp_path / "old"
    shutil.copytree(refused_job, old)
    with (old / REQUESTS_FILE).open(newline="") as f:  # as it was written: moves and reach checks only
        rows = [r for r in csv.DictReader(f) if r["kind"] in ("move", "reach")]
    with (old / REQUESTS_FILE).open("w", newline="") as f:
        columns = [c for c in rows[0] if c not in ("refusal", "reason")]
        writer = csv.DictWriter(f, columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    (old / "joints.csv").unlink()
    result, _ = _replay(old, tmp_path / "again")
    assert result["status"] == "completed" and result["replay"]["refusals_recorded"] is False
    log = (tmp_path / "again" / "log.txt").read_text()
    assert "recorded before the arm's refusals" in log and "has no joints.csv" in log
    assert result["refused_moves"] == {}  # unrefused, the planner streamed on
