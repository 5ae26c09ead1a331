"""Eq. 13 metrics on hand-checkable sets."""

from __future__ import annotations

import numpy as np

from cell.perception.metrics import CoverageTracker, compute_metrics, metrics_timeline


def test_metrics_are_one_sided_over_ground_truth():
    gt = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    cloud = np.array([[0.0, 0.0, 0.001], [5.0, 5.0, 5.0]])  # the far outlier must not count
    m = compute_metrics(gt, cloud)
    d2 = np.hypot(0.01, 0.001)
    assert np.isclose(m.chamfer_mm, (1.0 + d2 * 1e3) / 2)
    assert np.isclose(m.hausdorff_mm, d2 * 1e3)
    assert m.coverage_pct == 50.0


def test_coverage_threshold_is_inclusive_at_2_5_mm():
    gt = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    cloud = np.array([[0.0, 0.0, 0.0024], [1.0, 0.0, 0.0026]])
    assert compute_metrics(gt, cloud).coverage_pct == 50.0


def test_empty_cloud():
    m = compute_metrics(np.zeros((3, 3)), np.zeros((0, 3)))
    assert m.coverage_pct == 0.0 and m.chamfer_mm == float("inf")


def test_tracker_agrees_with_batch_computation():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0, 0.1, (500, 3))
    batches = [gt[:100] + 0.001, gt[100:200] + 0.004, rng.uniform(0, 0.1, (300, 3))]
    tracker = CoverageTracker(gt)
    for b in batches:
        tracker.add(b)
    assert np.isclose(tracker.coverage_pct, compute_metrics(gt, np.vstack(batches)).coverage_pct)


def test_timeline_measures_the_voxels_each_frame_had_filled():
    rng = np.random.default_rng(3)
    gt = rng.uniform(0.0, 0.1, (400, 3))
    centroids = np.vstack([gt[:150] + 0.0005, rng.uniform(-0.05, 0.15, (300, 3)), gt[150:] + 0.003])
    first = np.concatenate([np.full(150, 2), rng.integers(0, 4, 300), np.full(250, 3)])
    steps = metrics_timeline(gt, centroids, first, n_frames=5)
    assert len(steps) == 5
    for k, step in enumerate(steps):
        assert step == compute_metrics(gt, centroids[first <= k]), k
    assert steps[-1] == steps[-2] == compute_metrics(gt, centroids)  # frame 4 filled no voxel
    assert steps[2].coverage_pct > steps[1].coverage_pct and steps[3].chamfer_mm < steps[2].chamfer_mm


def test_timeline_before_the_first_point_is_an_empty_cloud():
    gt = np.zeros((2, 3))
    steps = metrics_timeline(gt, np.array([[0.0, 0.0, 0.001]]), np.array([1]), n_frames=2)
    assert steps[0] == compute_metrics(gt, np.zeros((0, 3)))
    assert steps[1].coverage_pct == 100.0 and np.isclose(steps[1].hausdorff_mm, 1.0)
