"""Offline re-processing of a recorded job (visual-servoing paper section III-B): a short simulated
scan rebuilt at 1 mm with multiway registration and pose-graph optimization, its loop closures and the
pruning of pair edges."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from cell.cli.main import app
from cell.config import load_config
from cell.jobs.runner import ScanRequest, run_scan
from cell.perception.cloud import read_ply
from cell.perception.metrics import METRICS_KEYS
from cell.perception.registration import IcpResult, constrain_icp, estimate_normals, kept_directions
from cell.perception.reprocess import (
    MultiwayParams,
    _pairs,
    _point_to_plane_information,
    back_project,
    reprocess_job,
)
from drivers.errors import JobError

from .conftest import FRANKA

CROP = load_config(FRANKA).perception.crop_box
"""The crop box of the cell file the test jobs run with."""


@pytest.fixture(scope="module")
def cube_job(tmp_path_factory):
    out = tmp_path_factory.mktemp("reprocess") / "job"
    outcome = run_scan(ScanRequest(config=load_config(FRANKA), config_path=str(FRANKA), object="cube",
                                   max_time_s=8.0, out=out))
    assert outcome.result["n_captures"] >= 3
    return out, outcome.result


def test_reprocess_writes_hires_cloud_and_metrics(cube_job):
    job, online = cube_job
    out = reprocess_job(job, crop=CROP, crop_source=str(FRANKA))

    assert (job / "cloud_hires.ply").is_file() and (job / "result_hires.json").is_file()
    written = json.loads((job / "result_hires.json").read_text())
    assert written == out
    assert out["n_frames"] == online["n_captures"] and out["voxel_m"] == 0.001
    assert out["crop_box"]["source"] == str(FRANKA)
    cloud = read_ply(job / "cloud_hires.ply")
    assert cloud.shape[0] == out["n_cloud_points"] > online["n_cloud_points"]  # 1 mm vs 2.5 mm

    m, m_online = out["metrics"], online["metrics"]
    assert set(m) == set(METRICS_KEYS)
    timeline = out["timeline"]
    # the timeline follows the registered figures (the ground truth registered once, to the whole cloud)
    assert set(timeline) == {"t_s", "chamfer_mm", "hausdorff_mm", "coverage_pct"}
    assert all(len(v) == out["n_frames"] for v in timeline.values())
    assert timeline["t_s"][0] == 0.0 and np.all(np.diff(timeline["t_s"]) > 0.0)
    assert timeline["t_s"][-1] <= online["scan_time_s"]
    assert {k: v[-1] for k, v in timeline.items() if k != "t_s"} == {k: m[k] for k in timeline if k != "t_s"}
    assert np.all(np.diff(timeline["coverage_pct"]) >= 0.0) and np.all(np.diff(timeline["chamfer_mm"]) <= 0.0)
    assert m["coverage_pct"] >= m_online["coverage_pct"] - 3.0
    assert m["chamfer_mm"] <= m_online["chamfer_mm"] + 0.2

    reg = out["registration"]
    assert reg["fk_prior_edges"] == out["n_frames"] and reg["pair_edges"] >= 1
    assert reg["edges"] == reg["fk_prior_edges"] + reg["pair_edges"]
    assert reg["edges_after_pruning"] + reg["pruned_edges"] == reg["edges"]
    # the simulated job's poses are off by a calibrated cell's error only (0.5 mm, 0.1 deg at the hand-eye):
    # the optimization must not move them by more than a millimetre
    assert reg["max_pose_change_mm"] < 1.0 and reg["max_pose_change_deg"] < 0.2


def test_back_project_matches_the_simulated_points(cube_job):
    job, _ = cube_job
    with np.load(sorted((job / "frames").glob("0*.npz"))[0]) as f:
        pts = back_project(f["depth"], f["K"])
    assert pts.shape[0] > 1000 and np.all(pts[:, 2] > 0.0)
    K = np.array([[475.0, 0, 319.5], [0, 475.0, 239.5], [0, 0, 1]])
    depth = np.zeros((480, 640), dtype=np.float32)
    depth[239, 319] = 0.5  # half a pixel up-left of the principal point
    assert np.allclose(back_project(depth, K), [[-0.5 * 0.5 / 475.0, -0.5 * 0.5 / 475.0, 0.5]])


def test_not_a_job_folder_raises(tmp_path):
    with pytest.raises(JobError, match="not a job folder"):
        reprocess_job(tmp_path, crop=CROP)
    with pytest.raises(JobError, match="missing does not exist"):
        reprocess_job(tmp_path / "missing", crop=CROP)
    (tmp_path / "result.json").write_text("{}")
    with pytest.raises(JobError, match="no recorded frames"):
        reprocess_job(tmp_path, crop=CROP)


@pytest.fixture
def job_copy(cube_job, tmp_path):
    job, online = cube_job
    copy = tmp_path / "job"
    shutil.copytree(job, copy)
    return copy, online


# Every pair of frames close enough for a loop closure, output at 2.5 mm. Pairwise ICP at its default
# 2.5 mm: on 5 mm clouds (a few tenths of a second faster) the optimization moved one recording's exact
# simulated poses by 1.2 mm and 0.35 deg, against 0.1 mm and 0.02 deg at 2.5 mm.
EVERY_PAIR = {"loop_max_distance_m": 1.0, "loop_max_angle_deg": 180.0, "loop_max_per_frame": 1000}


def test_loop_closures_are_the_nearest_earlier_frames_up_to_the_cap():
    """Frames 1 cm apart along x, all looking down +z but frame 3 turned away: each frame pairs with
    its predecessor and its ``loop_max_per_frame`` nearest earlier frames in range and in angle."""
    poses = [np.eye(4) for _ in range(8)]
    for k, T in enumerate(poses):
        T[0, 3] = 0.01 * k
    poses[3][:3, :3] = np.diag([1.0, -1.0, -1.0])  # optical axis reversed
    pairs = _pairs(poses, MultiwayParams(loop_max_per_frame=2, loop_max_distance_m=0.045))
    assert [(i, j) for i, j, loop in pairs if not loop] == [(k, k + 1) for k in range(7)]
    loops = {j: [i for i, jj, loop in pairs if loop and jj == j] for j in range(8)}
    assert loops == {0: [], 1: [], 2: [0], 3: [], 4: [1, 2], 5: [1, 2], 6: [2, 4], 7: [4, 5]}


def test_reprocess_adds_loop_closures_between_close_frames(job_copy):
    job, online = job_copy
    out = reprocess_job(job, crop=CROP, voxel_m=0.0025, params=MultiwayParams(**EVERY_PAIR))
    reg, n = out["registration"], out["n_frames"]
    assert reg["pair_edges"] + len(reg["rejected_pairs"]) == n * (n - 1) // 2  # every pair was tried
    loops_rejected = sum(r["loop_closure"] for r in reg["rejected_pairs"])
    assert reg["loop_closure_edges"] + loops_rejected == (n - 1) * (n - 2) // 2  # all but consecutive
    assert reg["loop_closure_edges"] >= 1
    assert reg["edges"] == reg["fk_prior_edges"] + reg["pair_edges"]
    assert reg["max_pose_change_mm"] < 1.0 and reg["max_pose_change_deg"] < 0.2
    assert out["metrics"]["coverage_pct"] >= online["metrics"]["coverage_pct"] - 3.0


def test_a_job_whose_cell_file_is_gone_is_refused_until_it_is_given(job_copy):
    """A job folder copied off the cell names a cell file that is not there (the service's copy,
    ``../../cells/<digest>.yaml``, stays in the data dir): cell reprocess went on with the paper's crop box,
    and the cloud differed from the job's without a word. It refuses, naming the file and --config, writes
    nothing, and with --config uses that file's crop box."""
    job, _ = job_copy
    for name in ("result_hires.json", "cloud_hires.ply"):  # a test before may have made them in the original
        (job / name).unlink(missing_ok=True)
    result = json.loads((job / "result.json").read_text())
    result["config"] = "../../cells/0123abcd.yaml"
    (job / "result.json").write_text(json.dumps(result))
    res = CliRunner().invoke(app, ["reprocess", str(job)])
    assert res.exit_code == 1, res.output
    assert "the job's cell file ../../cells/0123abcd.yaml is not found" in res.output
    assert "--config FILE" in res.output
    assert not (job / "result_hires.json").exists() and not (job / "cloud_hires.ply").exists()

    res = CliRunner().invoke(app, ["reprocess", str(job), "--config", str(FRANKA)])
    assert res.exit_code == 0, res.output
    crop = json.loads((job / "result_hires.json").read_text())["crop_box"]
    assert crop == {"x_m": list(CROP.x_m), "y_m": list(CROP.y_m), "z_m": list(CROP.z_m),
                    "source": str(FRANKA)}


def test_a_job_without_ground_truth_is_rebuilt_without_metrics(job_copy):
    job, _ = job_copy
    result = json.loads((job / "result.json").read_text())
    del result["object_pose"]  # as on a real cell: nothing to compare with
    (job / "result.json").write_text(json.dumps(result))
    res = CliRunner().invoke(app, ["reprocess", str(job)])
    assert res.exit_code == 0, res.output
    assert "cloud coverage (eq. 13): - (no ground truth)" in res.output
    written = json.loads((job / "result_hires.json").read_text())
    assert written["metrics"] is None and written["timeline"] is None
    assert read_ply(job / "cloud_hires.ply").shape[0] == written["n_cloud_points"] > 0


def test_a_lost_result_is_rebuilt_from_the_frames_with_progress_lines(job_copy):
    job, online = job_copy
    (job / "result.json").unlink()  # as after a crash before the job could write it
    res = CliRunner().invoke(app, ["reprocess", str(job)])
    assert res.exit_code == 0, res.output
    n = online["n_captures"]
    assert f"result.json was missing: rebuilt from {n} frames (status interrupted)" in res.stdout
    rebuilt = json.loads((job / "result.json").read_text())
    assert rebuilt["status"] == "interrupted" and rebuilt["n_captures"] == n
    assert {k: rebuilt[k] for k in ("planner", "object", "seed", "config", "object_pose")} == {
        k: online[k] for k in ("planner", "object", "seed", "config", "object_pose")}
    # the object's pose came back with the result: the rebuilt cloud is measured against the ground truth
    hires = json.loads((job / "result_hires.json").read_text())
    assert hires["metrics"]["coverage_pct"] >= online["metrics"]["coverage_pct"] - 3.0
    # not on a terminal: lines on standard error, at the start and the end of each stage
    lines = res.stderr.splitlines()
    for stage in (f"load frames 0/{n}", f"load frames {n}/{n}", "optimize the pose graph 1/1", "metrics 1/1"):
        assert f"reprocess: {stage}" in lines
    assert any(line.startswith("reprocess: register pairs ") for line in lines)


def test_a_folder_without_result_or_frames_is_not_a_job(tmp_path):
    (tmp_path / "frames").mkdir()
    res = CliRunner().invoke(app, ["reprocess", str(tmp_path)])
    assert res.exit_code == 1 and "no result.json and no recorded frames" in res.output
    assert not (tmp_path / "result.json").exists()


def test_reprocess_prunes_uncertain_edges_only(job_copy):
    """The line process prunes pair edges whose weight falls below ``edge_prune_threshold``: at 1 every
    pair edge goes (any residual weighs less than 1) and the certain FK priors alone hold the poses; at 0
    none goes."""
    job, _ = job_copy
    reg = reprocess_job(job, crop=CROP, voxel_m=0.0025,
                        params=MultiwayParams(**EVERY_PAIR, edge_prune_threshold=1.0))["registration"]
    assert reg["pair_edges"] >= 2
    assert reg["pruned_edges"] == reg["pair_edges"] == len(reg["pruned_pairs"])
    assert reg["edges_after_pruning"] == reg["fk_prior_edges"]
    assert reg["max_pose_change_mm"] < 0.01  # only the priors, at the recorded poses, are left
    reg = reprocess_job(job, crop=CROP, voxel_m=0.0025,
                        params=MultiwayParams(**EVERY_PAIR, edge_prune_threshold=0.0))["registration"]
    assert reg["pruned_edges"] == 0 and reg["pruned_pairs"] == []


def test_pair_correction_keeps_only_constrained_directions():
    """Two views of one plane: a pair's ICP correction that slides along the plane and moves 1 mm along
    its normal keeps the normal part only (3 of 6 directions constrained), as online registration."""
    g = np.arange(-0.05, 0.05, 0.0025)
    X, Y = np.meshgrid(g, g)
    plane = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, 0.3)])
    normals = estimate_normals(plane, plane, 0.005)
    T = np.eye(4)
    T[:3, 3] = [0.002, -0.001, 0.001]
    pairs = np.column_stack([np.arange(plane.shape[0])] * 2).astype(np.int32)
    kept, eigval = constrain_icp(IcpResult(T, 1.0, 0.0, pairs), plane, normals[pairs[:, 1]], 0.003)
    assert kept_directions(eigval, 0.003) == 3
    np.testing.assert_allclose(kept[:3, 3], [0.0, 0.0, 0.001], atol=1e-9)
    np.testing.assert_allclose(kept[:3, :3], np.eye(3), atol=1e-9)


def test_pair_information_counts_only_what_the_plane_constrains():
    """A pair edge's information is that of its point-to-plane residuals: a plane measures its normal
    offset and its tilts, nothing of a slide along it or a turn about its normal (those stay with the
    FK prior), where Open3D's point-to-point information would count every direction."""
    g = np.arange(-0.05, 0.05, 0.0025)
    X, Y = np.meshgrid(g, g)
    plane = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, 0.3)])
    info = _point_to_plane_information(plane, np.tile([0.0, 0.0, 1.0], (plane.shape[0], 1)))
    # Open3D's order: rotation about x, y, z, then translation along x, y, z
    np.testing.assert_allclose(np.diag(info)[[2, 3, 4]], 0.0, atol=1e-12)
    assert info[5, 5] == plane.shape[0] and info[0, 0] > 0.0 and info[1, 1] > 0.0
