"""Eq. 13 metrics on hand-checkable sets."""

from __future__ import annotations

import numpy as np
import pytest

from cell.perception import metrics
from cell.perception.cloud import CloudAccumulator
from cell.perception.metrics import (
    METRICS_KEYS,
    CloudCoverage,
    compute_metrics,
    ground_truth_points,
    measure,
    metrics_timeline,
    register_ground_truth,
)
from drivers.sim.objects import load_object, sample_surface
from drivers.transforms import T_from_xyz_rpy, rotvec, transform_points


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


def test_the_live_coverage_is_eq_13_of_the_cloud_as_it_stands():
    """Frames of dense points, each over a part of A, go into the voxel-filtered cloud: after each, the
    live figure is eq. 13's coverage of that cloud (unregistered), never that of the union of the frames'
    own points, which covers more of A than the cloud's voxel centroids do."""
    rng = np.random.default_rng(0)
    gt = np.column_stack([rng.uniform(0.0, 0.1, 2000), rng.uniform(0.0, 0.1, 2000), np.zeros(2000)])
    cloud = CloudAccumulator(0.005)
    live = CloudCoverage(gt)
    frames = [np.column_stack([rng.uniform(x0, x0 + 0.05, 20000), rng.uniform(0.0, 0.1, 20000),
                               rng.normal(0.0, 0.0005, 20000)]) for x0 in (0.0, 0.03, 0.06)]
    frames.append(np.array([[5.0, 5.0, 5.0]]))  # far from A: it cannot count
    for frame in frames:
        cloud.add(frame)
        measured = live.update(cloud.points)
        assert measured == live.coverage_pct == compute_metrics(gt, cloud.points).coverage_pct
    union = compute_metrics(gt, np.vstack(frames)).coverage_pct
    assert union > 99.0 and live.coverage_pct < union - 10.0
    assert CloudCoverage(gt).update(np.zeros((0, 3))) == 0.0


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


def _partial_bunny(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 13's A of the bunny at a station, and a noisy cloud of its +x half (what a few views see)."""
    mesh = load_object("bunny", 1.0)
    T = T_from_xyz_rpy([0.45, 0.0, 0.0], [0.0, 0.0, 0.0])
    gt = ground_truth_points(mesh, T)
    pts = transform_points(T, sample_surface(mesh, 20_000, rng))
    half = pts[pts[:, 0] > pts[:, 0].mean()]
    return gt, half + rng.normal(0.0, 0.0005, half.shape)


def test_registration_removes_a_common_offset_but_not_disagreeing_views():
    gt, cloud = _partial_bunny(np.random.default_rng(3))
    exact = measure(gt, cloud)
    # a calibration error: every view moved alike by 3 mm and 0.3 deg about the base origin
    offset = T_from_xyz_rpy([0.003, -0.002, 0.002], np.deg2rad([0.1, -0.2, 0.2]))
    moved = measure(gt, transform_points(offset, cloud))
    assert moved.unregistered.coverage_pct < exact.unregistered.coverage_pct - 15.0
    assert abs(moved.registered.coverage_pct - exact.registered.coverage_pct) < 0.5
    assert abs(exact.registered.coverage_pct - exact.unregistered.coverage_pct) < 1.0
    # A moved by the offset itself, to 0.5 mm at the object and 0.1 deg
    centre = cloud.mean(axis=0)[None]
    assert np.linalg.norm(transform_points(moved.T, centre) - transform_points(offset, centre)) < 5e-4
    assert np.degrees(np.linalg.norm(rotvec(moved.T[:3, :3].T @ offset[:3, :3]))) < 0.1
    # views that disagree: the cube's +x face seen 3 mm too far out and its -x face 3 mm too far out the
    # other way (two views, each with its own error): the cube looks 6 mm wider, which no rigid motion
    # undoes, so both faces stay beyond the 2.5 mm radius
    cube = load_object("cube", 1.0)
    gt_cube = ground_truth_points(cube, np.eye(4))
    pts = sample_surface(cube, 20_000, np.random.default_rng(4))
    lo, hi = pts[:, 0].min(), pts[:, 0].max()
    consistent = measure(gt_cube, pts)
    wide = pts.copy()
    wide[np.isclose(pts[:, 0], hi), 0] += 0.003
    wide[np.isclose(pts[:, 0], lo), 0] -= 0.003
    disagree = measure(gt_cube, wide)
    # the x faces are 40 % of A; their points within 2.5 mm of an edge are still covered by the others
    assert disagree.registered.coverage_pct < consistent.registered.coverage_pct - 30.0
    summary = disagree.as_dict()
    assert set(summary) == set(METRICS_KEYS)
    assert summary["coverage_unregistered_pct"] == disagree.unregistered.coverage_pct


def test_a_registration_that_leaves_a_and_the_cloud_fitting_worse_is_refused(monkeypatch: pytest.MonkeyPatch):
    """ICP minimises only the cloud's distance to A; a motion within its 10 mm gate that leaves A and the
    cloud fitting each other worse (a slide along a partial cloud) is refused: A stays where it was."""
    gt, cloud = _partial_bunny(np.random.default_rng(3))
    slide = T_from_xyz_rpy([0.005, 0.0, 0.0], [0.0, 0.0, 0.0])
    monkeypatch.setattr(metrics, "constrain_icp", lambda *_args: (slide, None))
    np.testing.assert_array_equal(register_ground_truth(gt, cloud), np.eye(4))
