"""Voxel filter, crop box and accumulation."""

from __future__ import annotations

import numpy as np
import pytest

from cell.perception.cloud import (
    CloudAccumulator,
    PointGrid,
    crop_box,
    first_voxels,
    point_keys,
    read_ply,
    voxel_downsample,
    voxel_keys,
    write_ply,
)
from drivers.transforms import T_from_xyz_rpy, transform_points


def test_voxel_downsample_averages_each_voxel():
    pts = np.array([[0.001, 0.001, 0.001], [0.002, 0.002, 0.002], [0.011, 0.0, 0.0]])
    out = voxel_downsample(pts, 0.01)
    assert out.shape == (2, 3)
    np.testing.assert_allclose(out[0], [0.0015, 0.0015, 0.0015])
    np.testing.assert_allclose(out[1], [0.011, 0.0, 0.0])


def test_voxel_downsample_is_order_independent():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-0.1, 0.1, (2000, 3))
    a = voxel_downsample(pts, 0.0025)
    b = voxel_downsample(pts[rng.permutation(2000)], 0.0025)
    np.testing.assert_allclose(a, b, atol=1e-15)
    assert voxel_downsample(np.zeros((0, 3)), 0.01).shape == (0, 3)


def test_first_voxels_filters_the_concatenation_and_names_each_voxels_first_cloud():
    a = np.array([[0.001, 0.001, 0.001], [0.031, 0.0, 0.0]])
    b = np.array([[0.002, 0.002, 0.002], [0.015, 0.0, 0.0]])
    c = np.array([[0.018, 0.001, 0.0], [0.035, 0.0, 0.0], [0.05, 0.05, 0.05]])
    centroids, first = first_voxels([a, np.zeros((0, 3)), b, c], 0.01)
    np.testing.assert_array_equal(centroids, voxel_downsample(np.vstack([a, b, c]), 0.01))
    # voxels in key order: (0, 0, 0) from cloud 0, (1, 0, 0) from cloud 2, (3, 0, 0) from 0, (5, 5, 5) from 3
    np.testing.assert_array_equal(first, [0, 2, 0, 3])
    empty_centroids, empty_first = first_voxels([], 0.01)
    assert empty_centroids.shape == (0, 3) and empty_first.shape == (0,)


def test_point_keys_name_each_points_voxel_as_the_voxel_filter_packs_it():
    rng = np.random.default_rng(4)
    pts = rng.uniform(-0.3, 0.3, (5000, 3))
    keys = point_keys(pts, 0.01)
    # one key per voxel of the filter, and points share a key exactly when they share a voxel
    assert np.unique(keys).size == voxel_keys(pts, 0.01).shape[0]
    index = np.floor(pts / 0.01)
    same = keys[:, None] == keys[None, :1000]
    np.testing.assert_array_equal(same, np.all(index[:, None] == index[None, :1000], axis=2))
    with pytest.raises(ValueError, match="not finite"):
        point_keys(np.array([[0.0, np.nan, 0.0]]), 0.01)
    with pytest.raises(ValueError, match="too far"):
        point_keys(np.array([[0.0, 0.0, 1.1e4]]), 0.01)


def test_crop_box_uses_open_intervals():
    pts = np.array([[0.0, 0.0, 0.05], [0.0, 0.0, 0.06], [0.2, 0.0, 0.1], [0.0, 0.0, 0.39]])
    out = crop_box(pts, (-0.15, 0.15), (-0.15, 0.15), (0.05, 0.40))
    np.testing.assert_array_equal(out, pts[[1, 3]])


def test_accumulator_merges_frames_in_the_base_frame():
    acc = CloudAccumulator(0.01)
    T = T_from_xyz_rpy([1.0, 0.0, 0.0], [0.0, 0.0, np.pi / 2])
    acc.add(transform_points(T, np.array([[0.1, 0.0, 0.0]])))
    np.testing.assert_allclose(acc.points, [[1.0, 0.1, 0.0]], atol=1e-12)
    acc.add(transform_points(T, np.array([[0.1, 0.0, 0.0]])))
    assert acc.points.shape == (1, 3)


def test_accumulator_marks_new_voxels_and_keeps_old_ones_in_order():
    acc = CloudAccumulator(0.01)
    acc.add(np.array([[0.001, 0.0, 0.0], [0.021, 0.0, 0.0]]))
    assert acc.new.tolist() == [True, True]
    before = acc.points.copy()
    acc.add(np.array([[0.011, 0.0, 0.0], [0.003, 0.0, 0.0], [0.031, 0.0, 0.0]]))
    assert acc.new.tolist() == [False, True, False, True]
    old = acc.points[~acc.new]
    np.testing.assert_allclose(old[0], [0.002, 0.0, 0.0])  # averaged with the new point of its voxel
    np.testing.assert_array_equal(old[1], before[1])  # untouched voxels keep their exact centroid


def test_ply_round_trip_and_refusal(tmp_path):
    pts = np.random.default_rng(3).normal(size=(50, 3))
    write_ply(tmp_path / "c.ply", pts)
    np.testing.assert_array_equal(read_ply(tmp_path / "c.ply"), pts)
    (tmp_path / "ascii.ply").write_text("ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(ValueError, match="not a cloud written by cell"):
        read_ply(tmp_path / "ascii.ply")


def test_point_grid_searches_match_brute_force_inside_and_far_outside() -> None:
    """Queries inside the grid's box and far beyond each face (its cube of cells then misses the grid on
    some axes) find the same nearest point within reach as a brute-force search."""
    rng = np.random.default_rng(7)
    pts = rng.uniform(0.0, 0.1, (500, 3))
    grid = PointGrid(pts, 0.01)
    queries = np.vstack([rng.uniform(-0.02, 0.12, (300, 3)),
                         np.array([[0.05, 0.05, 0.3], [0.05, 0.05, -0.2], [0.3, 0.05, 0.05],
                                   [-0.2, -0.2, 0.05], [0.05, 0.105, 0.05], [0.12, 0.12, 0.12]])])
    for reach in (0.004, 0.02, 0.5):
        index, dist = grid.nearest_within(queries, reach)
        d = np.linalg.norm(queries[:, None, :] - pts[None, :, :], axis=2)
        best = d.min(axis=1)
        found = best <= reach
        np.testing.assert_array_equal(index >= 0, found)
        np.testing.assert_allclose(dist[found], best[found], rtol=1e-12)
        assert np.all(np.isinf(dist[~found]))
