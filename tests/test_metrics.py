"""Eq. 13 metrics on hand-checkable sets."""

from __future__ import annotations

import numpy as np

from cell.perception.metrics import CoverageTracker, compute_metrics


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
