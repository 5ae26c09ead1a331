"""Segmentation (visual-servoing paper II-A "Segmentation"; LR-NBV paper 3.2): table removal, largest
cluster (Euclidean and DBSCAN), ROI boxes, on every shipped object."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cell.perception.segmentation import (
    ROI,
    ObjectExtent,
    SegmentationParams,
    compute_roi,
    dbscan_labels,
    fit_table_plane,
    largest_cluster,
    min_area_rectangle,
    remove_table_plane,
    segment_object,
    threshold_occupancy,
)
from drivers.sim.objects import list_objects, load_object, sample_surface

NAMES = [o.name for o in list_objects()]
CENTRE = np.array([0.45, 0.0, 0.0])
YAW = 0.4


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _table(centre_xy=(0.45, 0.0), half=0.3, step=0.005) -> np.ndarray:
    g = np.arange(-half, half, step)
    X, Y = np.meshgrid(g + centre_xy[0], g + centre_xy[1])
    return np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])


def _scene(name: str, seed: int = 1, yaw: float = YAW, n: int = 3000):
    """Occupied-voxel-like cloud: object surface samples at CENTRE with ``yaw`` + a 0.6 m table patch at
    z = 0 (5 mm grid) + 0.7 mm Gaussian noise. Returns (cloud, clean object points, object vertices)."""
    rng = np.random.default_rng(seed)
    mesh = load_object(name)
    R = _rot_z(yaw)
    obj = sample_surface(mesh, n, rng) @ R.T + CENTRE
    verts = mesh.vertices @ R.T + CENTRE
    cloud = np.vstack([obj, _table()])
    cloud = cloud + rng.normal(0.0, 0.0007, cloud.shape)
    return cloud, obj, verts


@pytest.mark.parametrize("method", ["euclidean", "dbscan"])
@pytest.mark.parametrize("name", NAMES)
def test_segments_every_shipped_object(name: str, method: str) -> None:
    cloud, obj, verts = _scene(name)
    res = segment_object(cloud, SegmentationParams(method=method), np.random.default_rng(0))
    pts = res.object_points
    assert res.roi is not None
    # (nearly) nothing of the table, most of the object
    assert np.count_nonzero(pts[:, 2] <= 0.003) == 0
    above = np.count_nonzero(obj[:, 2] > 0.008)
    assert pts.shape[0] >= 0.97 * above
    assert res.n_table >= _table().shape[0]
    # AABB within 1 cm of the true one (the bottom 6 mm are cut with the table)
    roi = res.roi
    assert np.all(np.abs(roi.aabb_min - verts.min(axis=0)) < 0.01)
    assert np.all(np.abs(roi.aabb_max - verts.max(axis=0)) < 0.01)
    # oriented box: footprint of the true mesh, height from the table
    _, true_ext, _ = min_area_rectangle(verts[:, :2])
    assert np.all(np.abs(roi.obb_extent_xy - true_ext) < 0.01)
    assert roi.obb_extent_xy[0] >= roi.obb_extent_xy[1]
    assert abs(roi.z_min) < 0.002 and res.table_z is not None
    assert abs(roi.z_max - verts[:, 2].max()) < 0.005
    assert -math.pi / 2 < roi.obb_yaw_rad <= math.pi / 2


@pytest.mark.parametrize("method", ["euclidean", "dbscan"])
def test_box_obb_dims_and_yaw(method: str) -> None:
    cloud, _, _ = _scene("horizontal_box", yaw=YAW)
    roi = segment_object(cloud, SegmentationParams(method=method)).roi
    assert roi is not None
    np.testing.assert_allclose(roi.obb_dims, [0.30, 0.20, 0.10], atol=0.01)
    assert abs(roi.obb_yaw_rad - YAW) < math.radians(2.0)
    np.testing.assert_allclose(roi.obb_center_xy, CENTRE[:2], atol=0.005)
    # L axis along y: yaw wraps into (-pi/2, pi/2]
    cloud, _, _ = _scene("horizontal_box", yaw=YAW + math.pi / 2 + 0.3)
    roi = segment_object(cloud, SegmentationParams(method=method)).roi
    assert roi is not None
    expected = YAW + 0.3 + math.pi / 2 - math.pi
    assert abs(roi.obb_yaw_rad - expected) < math.radians(2.0)


@pytest.mark.parametrize("name", ["cube", "vertical_box"])
def test_square_boxes_obb_dims(name: str) -> None:
    cloud, _, _ = _scene(name, yaw=0.7)
    roi = segment_object(cloud, SegmentationParams()).roi
    assert roi is not None
    ext = load_object(name).extents_m
    np.testing.assert_allclose(roi.obb_dims, [ext[0], ext[1], ext[2]], atol=0.01)


def test_deterministic() -> None:
    cloud, _, _ = _scene("bunny")
    a = segment_object(cloud, SegmentationParams(method="dbscan", seed=3))
    b = segment_object(cloud, SegmentationParams(method="dbscan", seed=3))
    assert np.array_equal(a.object_points, b.object_points)
    assert a.plane is not None and b.plane is not None and np.array_equal(a.plane, b.plane)


@pytest.mark.parametrize("method", ["euclidean", "dbscan"])
def test_two_objects_larger_wins(method: str) -> None:
    rng = np.random.default_rng(2)
    big = sample_surface(load_object("horizontal_box"), 3000, rng) + np.array([0.45, 0.0, 0.0])
    small = sample_surface(load_object("baseball"), 800, rng) + np.array([0.45, 0.25, 0.0])
    cloud = np.vstack([big, small, _table()]) + rng.normal(0.0, 0.0005, (3800 + _table().shape[0], 3))
    res = segment_object(cloud, SegmentationParams(method=method))
    assert res.roi is not None
    assert res.roi.aabb_max[1] < 0.11  # the baseball (y >= 0.21) is not in the ROI
    assert res.roi.aabb_max[2] > 0.095
    assert res.n_other >= 700


def test_empty_and_table_only_give_no_roi() -> None:
    res = segment_object(np.zeros((0, 3)), SegmentationParams())
    assert res.roi is None and res.object_points.shape == (0, 3) and res.plane is None
    res = segment_object(_table(), SegmentationParams())
    assert res.roi is None and res.plane is not None


def test_tilted_plane_is_not_the_table() -> None:
    """A wall (normal along x) is not accepted as the table; the floor is found even if smaller."""
    rng = np.random.default_rng(0)
    g = np.arange(-0.3, 0.3, 0.005)
    Y, Z = np.meshgrid(g, g + 0.32)  # from z = 2 cm up
    wall = np.column_stack([np.full(Y.size, 0.8), Y.ravel(), Z.ravel()])
    floor = _table(half=0.2)
    plane = fit_table_plane(np.vstack([wall, floor]), SegmentationParams(plane_ransac_iterations=400), rng)
    assert plane is not None
    assert plane[2] > 0.999 and abs(plane[3]) < 1e-6
    assert fit_table_plane(wall, SegmentationParams(), rng) is None


def test_remove_table_plane_drops_points_below() -> None:
    rng = np.random.default_rng(0)
    table = _table(half=0.1)
    below = np.array([[0.45, 0.0, -0.05], [0.46, 0.0, -0.02]])
    above = np.array([[0.45, 0.0, 0.05]])
    cand, plane = remove_table_plane(np.vstack([table, below, above]), SegmentationParams(), rng)
    assert plane is not None
    np.testing.assert_allclose(cand, above)


def test_euclidean_cluster_tolerance() -> None:
    a = np.column_stack([np.arange(0, 0.1, 0.01), np.zeros(10), np.zeros(10)])
    b = a[:5] + np.array([0.5, 0.0, 0.0])
    pts = np.vstack([b, a])
    params = SegmentationParams(method="euclidean", cluster_tolerance_m=0.011, min_cluster_points=1)
    np.testing.assert_allclose(largest_cluster(pts, params), a)
    assert largest_cluster(pts, params.model_copy(update={"min_cluster_points": 11})).shape == (0, 3)
    # a gap of 2 cm splits the line in two
    gap = np.vstack([a[:6], a[6:] + np.array([0.02, 0.0, 0.0])])
    assert largest_cluster(gap, params).shape[0] == 6


def test_dbscan_core_border_noise() -> None:
    line = np.column_stack([np.arange(0, 0.1, 0.01), np.zeros(10), np.zeros(10)])
    noise = np.array([[1.0, 1.0, 1.0]])
    border = np.array([[0.0995, 0.0, 0.0]])  # within eps of the last line point only
    pts = np.vstack([line, border, noise])
    labels = dbscan_labels(pts, 0.0105, 3)
    assert np.all(labels[:10] == 0) and labels[10] == 0 and labels[11] == -1
    # min_points too high: no core point, everything noise
    assert np.all(dbscan_labels(pts, 0.0105, 4) == -1)
    params = SegmentationParams(method="dbscan", dbscan_eps_m=0.0105, dbscan_min_points=3,
                                min_cluster_points=1)
    np.testing.assert_allclose(largest_cluster(pts, params), np.vstack([line, border]))


def test_min_area_rectangle_and_roi_helpers() -> None:
    rng = np.random.default_rng(4)
    local = rng.uniform([-0.1, -0.03], [0.1, 0.03], (500, 2))
    local = np.vstack([local, [[-0.1, -0.03], [0.1, -0.03], [0.1, 0.03], [-0.1, 0.03]]])
    yaw = -1.2
    R = _rot_z(yaw)[:2, :2]
    xy = local @ R.T + [0.4, -0.1]
    centre, ext, got_yaw = min_area_rectangle(xy)
    np.testing.assert_allclose(ext, [0.2, 0.06], atol=1e-9)
    np.testing.assert_allclose(centre, [0.4, -0.1], atol=1e-9)
    assert abs(got_yaw - yaw) < 1e-9
    # degenerate inputs
    _, ext, _ = min_area_rectangle(np.array([[0.0, 0.0], [0.1, 0.1], [0.2, 0.2]]))
    np.testing.assert_allclose(ext, [math.hypot(0.2, 0.2), 0.0], atol=1e-12)
    _, ext, _ = min_area_rectangle(np.array([[0.3, 0.2]]))
    np.testing.assert_allclose(ext, [0.0, 0.0])

    pts = np.column_stack([xy, rng.uniform(0.01, 0.05, xy.shape[0])])
    roi = compute_roi(pts, table_z=0.0)
    assert isinstance(roi, ROI) and roi.n_points == pts.shape[0]
    assert roi.z_min == 0.0 and roi.z_max == pts[:, 2].max()
    assert np.all(roi.contains(pts))
    assert not np.any(roi.contains(pts + np.array([0.0, 0.0, 1.0])))
    corners = roi.obb_corners()
    assert corners.shape == (8, 3)
    np.testing.assert_allclose(corners[:4, 2], 0.0)
    # every point lies inside the oriented footprint
    local_back = (pts[:, :2] - roi.obb_center_xy) @ _rot_z(roi.obb_yaw_rad)[:2, :2]
    assert np.all(np.abs(local_back) <= roi.obb_extent_xy / 2 + 1e-9)
    # corners span the extents
    edges = np.linalg.norm(np.diff(corners[:4, :2], axis=0), axis=1)
    np.testing.assert_allclose(sorted(edges), sorted([0.2, 0.06, 0.2]), atol=1e-9)
    with pytest.raises(ValueError):
        compute_roi(np.zeros((0, 3)))


def test_object_extent_keeps_what_a_split_off_piece_took_and_restarts_on_another_object() -> None:
    rng = np.random.default_rng(2)
    ball = rng.normal(size=(400, 3))
    ball = CENTRE + np.array([0.0, 0.0, 0.037]) + 0.037 * ball / np.linalg.norm(ball, axis=1, keepdims=True)
    extent = ObjectExtent()
    lo, hi = extent.add(compute_roi(ball, table_z=0.0))
    np.testing.assert_array_equal(lo, ball.min(axis=0))
    np.testing.assert_array_equal(hi, ball.max(axis=0))
    # Carving splits the +y side and the bottom off: the segmented box shrinks, the extent does not.
    kept = ball[(ball[:, 1] < 0.02) & (ball[:, 2] > 0.02)]
    lo, hi = extent.add(compute_roi(kept, table_z=0.0))
    np.testing.assert_array_equal(lo, ball.min(axis=0))
    np.testing.assert_array_equal(hi, ball.max(axis=0))
    # More of the object seen: the extent grows.
    grown = np.vstack([kept, CENTRE + np.array([0.0, 0.0, 0.09])])
    _, hi = extent.add(compute_roi(grown, table_z=0.0))
    assert hi[2] == pytest.approx(0.09)
    # A box that does not touch the extent is another object: the extent starts again from it.
    other = kept + np.array([0.0, 0.3, 0.0])
    lo, hi = extent.add(compute_roi(other, table_z=0.0))
    np.testing.assert_array_equal(lo, other.min(axis=0))
    np.testing.assert_array_equal(hi, other.max(axis=0))


def test_object_extent_takes_a_piece_over_its_footprint_for_the_same_object() -> None:
    """A 4 x 4 x 18 cm post that carving split at mid-height: its top piece was the largest cluster, then
    its lower one. Both stand over one footprint, so the extent holds the whole post; a piece beside the
    footprint at the same height is another object."""
    rng = np.random.default_rng(3)
    post = CENTRE + rng.uniform([-0.02, -0.02, 0.0], [0.02, 0.02, 0.18], size=(3000, 3))
    top, lower = post[post[:, 2] > 0.125], post[(post[:, 2] > 0.015) & (post[:, 2] < 0.095)]
    extent = ObjectExtent()
    extent.add(compute_roi(top, table_z=0.0))
    lo, hi = extent.add(compute_roi(lower, table_z=0.0))
    np.testing.assert_array_equal(lo, np.minimum(top.min(axis=0), lower.min(axis=0)))
    np.testing.assert_array_equal(hi, np.maximum(top.max(axis=0), lower.max(axis=0)))
    beside = top + np.array([0.05, 0.0, 0.0])
    lo, hi = extent.add(compute_roi(beside, table_z=0.0))
    np.testing.assert_array_equal(lo, beside.min(axis=0))


def test_threshold_occupancy() -> None:
    c = np.arange(12.0).reshape(4, 3)
    np.testing.assert_array_equal(threshold_occupancy(c, np.array([0.2, 0.5, 0.51, 0.9])), c[2:])


@pytest.mark.parametrize(("res", "params"), [
    (0.005, SegmentationParams()),
    (0.01, SegmentationParams(plane_distance_m=0.012, cluster_tolerance_m=0.015)),
    (0.01, SegmentationParams(method="dbscan", plane_distance_m=0.012)),
])
@pytest.mark.parametrize("name", ["bunny", "horizontal_box", "mustard", "banana"])
def test_on_voxel_centres(name: str, res: float, params: SegmentationParams) -> None:
    """On occupied voxel centres (the map's output), the table at z = 0 straddles two voxel layers."""
    cloud, _, verts = _scene(name, n=20000)
    centres = (np.unique(np.floor(cloud / res).astype(np.int64), axis=0) + 0.5) * res
    res_ = segment_object(centres, params)
    assert res_.roi is not None
    assert np.count_nonzero(res_.object_points[:, 2] <= 0.003) == 0
    assert np.all(np.abs(res_.roi.aabb_max - verts.max(axis=0)) < 0.015)
    assert np.all(np.abs(res_.roi.aabb_min[:2] - verts.min(axis=0)[:2]) < 0.015)


def test_box_top_is_not_the_table_when_its_height_is_known() -> None:
    """Occupied 1 cm voxels of the horizontal box seen from above with a thin rim of table: the top
    (0.3 x 0.2 m) outnumbers the table, so unconstrained RANSAC takes it for the table and leaves no
    object; with the table height known, only planes near it are drawn and the box is found."""
    res = 0.01
    rng = np.random.default_rng(4)
    mesh = load_object("horizontal_box")
    obj = sample_surface(mesh, 40000, rng) + CENTRE
    obj = obj[obj[:, 2] > 0.005]  # the bottom face is not seen
    rim = _table(half=0.17, step=0.01)
    rim = rim[np.any(np.abs(rim[:, :2] - CENTRE[:2]) > [0.16, 0.11], axis=1)]
    centres = (np.unique(np.floor(np.vstack([obj, rim]) / res).astype(np.int64), axis=0) + 0.5) * res
    params = SegmentationParams(method="dbscan", plane_distance_m=0.012)
    free = segment_object(centres, params, np.random.default_rng(0))
    assert free.plane is not None and -free.plane[3] > 0.09  # the top taken for the table
    known = segment_object(centres, params, np.random.default_rng(0), table_z=0.0)
    assert known.plane is not None and abs(known.plane[3]) < 0.01
    assert known.roi is not None
    np.testing.assert_allclose(known.roi.obb_dims, mesh.extents_m, atol=0.015)
    # no table in view at all: the known height stands in for it
    top_only = centres[centres[:, 2] > 0.05]
    alone = segment_object(top_only, params, np.random.default_rng(0), table_z=0.0)
    assert alone.roi is not None and alone.object_points.shape[0] == top_only.shape[0]
