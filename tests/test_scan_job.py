"""A simulated scan end to end: job folder, determinism, eq. 13 against an independent computation,
failures that keep what was recorded."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from cell.cli.main import app
from cell.config import load_config
from cell.jobs.recorder import JobRecorder
from cell.jobs.runner import ScanRequest, run_scan
from cell.perception.cloud import read_ply
from cell.perception.metrics import METRICS_KEYS
from cell.perception.octomap_io import read_bt
from cell.planning.base import Planner, ScanSession
from cell.planning.vs.servo_scan import start_views
from drivers.depth.base import DepthFrame
from drivers.depth.projection import back_project
from drivers.depth.sim_rgbd import SimRGBD
from drivers.errors import DriverError

from .conftest import FRANKA, REPO, UR5E, ended_without_a_frame, raster_scan, register_planner


@pytest.fixture(scope="module")
def bunny_job(tmp_path_factory):
    out = tmp_path_factory.mktemp("jobs") / "bunny"
    return out, raster_scan(out, FRANKA, "bunny", 0, 8)


def test_vs_local_is_the_default_planner():
    assert load_config(FRANKA).scan.planner == "vs-local"  # `cell scan` and `make demo` without --planner


def test_job_folder_is_complete(bunny_job):
    out, output = bunny_job
    result = json.loads((out / "result.json").read_text())
    for key in ("planner", "object", "config", "seed", "status", "termination", "sim_time_s", "wall_time_s",
                "path_length_m", "n_captures", "object_pose", "metrics"):
        assert key in result
    assert result["status"] == "completed" and result["planner"] == "raster"
    assert result["mode"] == "sim"  # the clock of sim_time_s (cell jobs show labels it so)
    assert "time budget" in result["termination"] and result["limit_reached"] is True
    assert result["n_captures"] >= 3 and result["path_length_m"] > 0.1
    assert np.allclose(np.array(result["object_pose"])[:3, 3], [0.45, 0.0, 0.0])
    assert set(result["metrics"]) == set(METRICS_KEYS)
    with (out / "trajectory.csv").open() as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["t", "x", "y", "z", "qx", "qy", "qz", "qw"]
    assert len(rows) > 100
    frames = sorted((out / "frames").glob("*.npz"))
    assert len(frames) == result["n_captures"]
    f0 = np.load(frames[0])
    # the paper's scan time runs from the first frame, after the move from home to the first view
    assert result["scan_time_s"] == pytest.approx(result["sim_time_s"] - float(f0["timestamp"]), abs=1e-6)
    assert 0.0 < result["scan_time_s"] < result["sim_time_s"]
    traj = np.loadtxt(out / "trajectory.csv", delimiter=",", skiprows=1)  # the sensor's path
    after = traj[traj[:, 0] >= float(f0["timestamp"]) - 1e-9, 1:4]
    walked = float(np.linalg.norm(np.diff(after, axis=0), axis=1).sum())
    assert result["scan_path_length_m"] == pytest.approx(walked, abs=0.01)
    assert 0.0 < result["scan_path_length_m"] < result["path_length_m"]
    assert f0["depth"].shape == (480, 640) and f0["K"].shape == (3, 3) and f0["T_base_sensor"].shape == (4, 4)
    assert read_ply(out / "cloud.ply").shape[0] == result["n_cloud_points"] > 1000
    # the sensor's frame 0 was the survey from home, which is not one of the scan's
    assert frames[0].name == "000001.npz"
    log = (out / "log.txt").read_text()
    assert "survey from home" in log and "capture 1: " in log
    occupancy = read_bt(out / "map.bt")
    assert occupancy.occupied_centers().shape[0] > 100
    # The first frame has no target to register onto: a skip, not a rejection.
    assert result["perception"]["n_registration_rejected"] == 0
    n_constrained = result["perception"]["registration_n_constrained"]
    assert len(n_constrained) == result["n_captures"] and all(0 <= n <= 6 for n in n_constrained)
    roi = result["perception"]["roi"]
    assert roi is not None and result["perception"]["h_roi"] is not None
    np.testing.assert_allclose(np.subtract(roi["aabb_max_m"], roi["aabb_min_m"]), [0.156, 0.121, 0.154],
                               atol=0.015)
    assert f"job folder: {out}" in output
    # the sensor's path for every planner; the servo telemetry only for a servo planner's job
    assert (out / "path.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not (out / "servo.png").exists()
    assert f"cloud coverage (eq. 13): {result['metrics']['coverage_pct']:.1f} %" in output


class HRoiProbe(Planner):
    """Captures twice at the servo planners' start view and keeps H_ROI of the last map in both forms."""

    name = "test-h-roi-probe"
    h_roi: ClassVar[dict[str, float]] = {}

    def run(self, session: ScanSession) -> str:
        assert session.move_to_sensor_pose(start_views(self.config)[0])
        session.capture()
        session.capture()
        update = session.latest_perception()
        assert update is not None and update.extent is not None
        HRoiProbe.h_roi = {form: update.map.mean_entropy_in_box(*update.extent, observation_aware=aware)
                           for form, aware in (("paper", False), ("observation_aware", True))}
        return "probed"


def test_the_reported_h_roi_is_the_one_the_servo_termination_judges(tmp_path, monkeypatch):
    """result.json and the log carry H_ROI in the objective's form (the observation-aware one on the
    RGB-D cell), which ``ServoScanPlanner.entropy_settled`` judges, not eq. 8's, and say which it is."""
    register_planner(monkeypatch, HRoiProbe)
    cfg = load_config(FRANKA)
    assert cfg.planners.vs.objective.entropy == "observation_aware"
    out = tmp_path / "job"
    result = run_scan(ScanRequest(config=cfg, config_path=str(FRANKA), object="cube", planner=HRoiProbe.name,
                                  out=out, max_time_s=10.0)).result
    aware, paper = HRoiProbe.h_roi["observation_aware"], HRoiProbe.h_roi["paper"]
    assert round(aware, 6) != round(paper, 6)
    assert result["perception"]["h_roi"] == round(aware, 6)
    assert result["perception"]["h_roi_entropy"] == "observation_aware"
    log = (out / "log.txt").read_text()
    # the scan's second frame (the sensor's frame 0 was the survey from home)
    assert next(line for line in log.splitlines() if "capture 2:" in line).endswith(f"H_ROI {aware:.4f}")
    # a planner of no servo termination (the probe) reports it in that form too, and the log says so
    assert ("H_ROI (eq. 12) reported in its observation_aware form (planners.vs.objective.entropy, whatever "
            "the planner)") in log


class Idle(Planner):
    """Ends at once."""

    name = "test-idle"

    def run(self, session: ScanSession) -> str:
        return "idle"


def test_a_scan_builds_one_collision_world(tmp_path, monkeypatch, built_worlds):
    """The placement's check clear of the arm and the job's guard use the same collision world."""
    register_planner(monkeypatch, Idle)
    result = run_scan(ScanRequest(config=load_config(FRANKA), config_path=str(FRANKA), object="cube",
                                  planner=Idle.name, out=tmp_path / "job", max_time_s=5.0)).result
    assert ended_without_a_frame(result, "idle")
    assert len(built_worlds) == 1


def test_a_depth_frame_is_kept_as_its_image_with_or_without_a_grey_one(tmp_path):
    recorder = JobRecorder(tmp_path / "job")
    depth = np.full((4, 6), 0.5, dtype=np.float32)
    K = np.array([[5.0, 0.0, 2.5], [0.0, 5.0, 1.5], [0.0, 0.0, 1.0]])
    grey = np.full((4, 6), 110, dtype=np.uint8)
    for seq, intensity in ((0, None), (1, grey)):
        frame = DepthFrame(seq=seq, timestamp=0.0, points=back_project(depth, K), depth=depth, intrinsics=K,
                           intensity=intensity)
        recorder.frame(frame, np.eye(4), np.eye(4), {})
    recorder.close()
    plain, with_grey = (np.load(tmp_path / "job" / "frames" / f"{seq:06d}.npz") for seq in (0, 1))
    # the points follow from the depth image: a camera's frame does not keep them twice
    assert {"depth", "K"} <= set(plain.files) and not {"points", "intensity"} & set(plain.files)
    assert "points" not in with_grey.files and np.array_equal(with_grey["intensity"], grey)


DEV_FULL = Path("/dev/full")


@pytest.mark.skipif(not DEV_FULL.exists(), reason="no /dev/full to stand for a full disk")
def test_rows_that_cannot_reach_the_disk_are_said_in_the_result_which_is_written_all_the_same(tmp_path):
    """``trajectory.csv`` on a full disk (here /dev/full): its buffered rows fail at the flush before
    ``result.json``, which had then never been written (the job's own end lost to a generic "failed")."""
    folder = tmp_path / "job"
    folder.mkdir()
    (folder / "trajectory.csv").symlink_to(DEV_FULL)
    recorder = JobRecorder(folder)
    for k in range(3):
        recorder.pose(0.01 * k, np.eye(4))
    recorder.log(0.0, "a line of the log")
    recorder.result({"status": "completed", "termination": "done"})
    recorder.close()
    result = json.loads((folder / "result.json").read_text())
    assert result["status"] == "completed" and result["termination"] == "done"
    assert result["files_incomplete"] == {"trajectory.csv": "No space left on device"}
    assert (folder / "log.txt").read_text() == "[    0.000] a line of the log\n"


def test_same_seed_gives_identical_outputs(bunny_job, tmp_path):
    out, _ = bunny_job
    again = tmp_path / "again"
    raster_scan(again, FRANKA, "bunny", 0, 8)
    assert (out / "cloud.ply").read_bytes() == (again / "cloud.ply").read_bytes()
    a = json.loads((out / "result.json").read_text())
    b = json.loads((again / "result.json").read_text())
    for r in (a, b):  # the wall clock's figures are the only ones that differ from run to run
        r.pop("wall_time_s")
        r["control"].pop("first_motion_unix_s")
    assert a == b


def test_coverage_agrees_with_an_independent_eq13(bunny_job):
    """Eq. 13 recomputed with trimesh's sampler and its own face filter, on the job's cloud, with the ground
    truth where the sim placed it (the job's unregistered figures)."""
    out, _ = bunny_job
    result = json.loads((out / "result.json").read_text())
    mesh = trimesh.load(REPO / "drivers" / "sim" / "objects" / "bunny.ply")
    mesh.apply_transform(np.array(result["object_pose"]))
    down_angle = np.degrees(np.arccos(np.clip(-mesh.face_normals[:, 2], -1, 1)))
    visible = mesh.submesh([np.nonzero(down_angle > 45.0)[0]], append=True)
    gt, _ = trimesh.sample.sample_surface(visible, 10_000, seed=7)
    d, _ = cKDTree(read_ply(out / "cloud.ply")).query(gt)
    coverage = 100.0 * np.mean(d <= 0.0025)
    metrics = result["metrics"]
    assert abs(coverage - metrics["coverage_unregistered_pct"]) < 3.0
    chamfer_mm = metrics["chamfer_unregistered_mm"]
    assert abs(1e3 * d.mean() - chamfer_mm) < 0.15 * chamfer_mm


def test_tof_cell_scans(tmp_path):
    cfg = load_config(UR5E)
    outcome = run_scan(ScanRequest(config=cfg, config_path=str(UR5E), object="horizontal_box",
                                   out=tmp_path / "tof", max_time_s=10.0))
    r = outcome.result
    assert r["status"] == "completed" and r["n_captures"] >= 2
    assert r["n_cloud_points"] > 20
    f0 = np.load(sorted((tmp_path / "tof" / "frames").glob("*.npz"))[0])
    assert f0["zone_status"].shape == (64,) and f0["points"].shape[1] == 3
    # the ToF cell's registration is off: the log says so, with no ICP figures as if it had run
    log = (tmp_path / "tof" / "log.txt").read_text()
    assert "capture 1: 64 points, 64 after filtering; registration skipped (disabled in the cell file, " \
           "perception.registration.enabled: false): the FK pose is used; H_ROI" in log
    assert "directions constrained" not in log


def test_sensor_failure_stops_and_keeps_frames(tmp_path, monkeypatch):
    real_capture = SimRGBD.capture
    calls = {"n": 0}

    def failing_capture(self):
        calls["n"] += 1
        if calls["n"] == 4:  # the survey from home, two of the scan's frames, then the failure
            raise DriverError("frame timeout", device="depth sim-rgbd")
        return real_capture(self)

    monkeypatch.setattr(SimRGBD, "capture", failing_capture)
    cfg = load_config(FRANKA)
    with pytest.raises(DriverError, match="frame timeout"):
        run_scan(ScanRequest(config=cfg, config_path=str(FRANKA), object="cube", planner="raster",
                             out=tmp_path / "job"))
    result = json.loads((tmp_path / "job" / "result.json").read_text())
    assert result["status"] == "failed" and "frame timeout" in result["termination"]
    assert result["n_captures"] == 2
    assert len(list((tmp_path / "job" / "frames").glob("*.npz"))) == 2
    assert any("frame timeout" in s["reason"] for s in result["safety"]["stops"])
    assert (tmp_path / "job" / "cloud.ply").exists()


@pytest.mark.parametrize("args, message", [
    (["--object", "no-such-object"], "bunny"),
    (["--planner", "telepathy"], "raster"),
    (["--object-pose", "1,2"], "x,y,yaw"),
    (["--object-pose", "0,0,1e308"], "yaw must lie within +-360 deg"),
])
def test_cli_bad_input_exits_with_one_line_reason(tmp_path, args, message):
    res = CliRunner().invoke(app, ["scan", "--config", str(FRANKA), "--out", str(tmp_path / "j"), *args])
    assert res.exit_code != 0
    assert message in res.output
    assert not (tmp_path / "j" / "frames").exists()


def test_cli_reprocess_refuses_a_folder_that_is_not_a_job(tmp_path):
    res = CliRunner().invoke(app, ["reprocess", str(tmp_path)])
    assert res.exit_code == 1 and "not a job folder" in res.output


def test_cli_lists_planners_and_objects():
    runner = CliRunner()
    planners = runner.invoke(app, ["planners"])
    assert planners.exit_code == 0 and "raster" in planners.output
    objects = runner.invoke(app, ["objects"])
    names = [line.split()[0] for line in objects.output.strip().splitlines()]
    assert len(names) == 12 and "bunny" in names and "flange" in names
