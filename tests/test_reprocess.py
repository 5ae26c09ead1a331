"""Offline re-processing of a recorded job (visual-servoing paper section III-B): a short simulated
scan rebuilt at 1 mm with multiway registration and pose-graph optimization."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cell.config import load_config
from cell.jobs.runner import ScanRequest, run_scan
from cell.perception.cloud import read_ply
from cell.perception.reprocess import back_project, reprocess_job
from drivers.errors import JobError

from .conftest import FRANKA


@pytest.fixture(scope="module")
def cube_job(tmp_path_factory):
    out = tmp_path_factory.mktemp("reprocess") / "job"
    outcome = run_scan(ScanRequest(config=load_config(FRANKA), config_path=str(FRANKA), object="cube",
                                   max_time_s=8.0, out=out))
    assert outcome.result["n_captures"] >= 3
    return out, outcome.result


def test_reprocess_writes_hires_cloud_and_metrics(cube_job):
    job, online = cube_job
    out = reprocess_job(job)

    assert (job / "cloud_hires.ply").is_file() and (job / "result_hires.json").is_file()
    written = json.loads((job / "result_hires.json").read_text())
    assert written == out
    assert out["n_frames"] == online["n_captures"] and out["voxel_m"] == 0.001
    assert out["crop_box"]["source"] == str(FRANKA)
    cloud = read_ply(job / "cloud_hires.ply")
    assert cloud.shape[0] == out["n_cloud_points"] > online["n_cloud_points"]  # 1 mm vs 2.5 mm

    m, m_online = out["metrics"], online["metrics"]
    assert set(m) == {"chamfer_mm", "hausdorff_mm", "coverage_pct"}
    assert m["coverage_pct"] >= m_online["coverage_pct"] - 3.0
    assert m["chamfer_mm"] <= m_online["chamfer_mm"] + 0.2

    reg = out["registration"]
    assert reg["fk_prior_edges"] == out["n_frames"] and reg["pair_edges"] >= 1
    assert reg["edges"] == reg["fk_prior_edges"] + reg["pair_edges"]
    assert reg["edges_after_pruning"] + reg["pruned_edges"] == reg["edges"]
    # the simulated job's poses are exact: the optimization must not move them by more than a millimetre
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
        reprocess_job(tmp_path)
    with pytest.raises(JobError, match="not a job folder"):
        reprocess_job(tmp_path / "missing")
    (tmp_path / "result.json").write_text("{}")
    with pytest.raises(JobError, match="no recorded frames"):
        reprocess_job(tmp_path)
