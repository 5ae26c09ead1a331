"""Per-frame filters (visual-servoing paper II-A "Filtering"): SOR, ToF status filter, frame chain,
centroid low-pass."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from cell.config.models import CropBoxConfig
from cell.perception.filters import (
    GRAZING_DEG,
    CentroidLowPass,
    FilterParams,
    carved_lengths,
    continuous_depth_mask,
    filter_frame,
    knn_mean_distances,
    no_target_directions,
    statistical_outlier_mask,
    statistical_outlier_removal,
    valid_tof_returns,
)
from drivers.depth.base import DepthFrame, ToFZones


def _plane(n_side: int = 60, step: float = 0.0025, z: float = 0.3) -> np.ndarray:
    g = (np.arange(n_side) - n_side / 2) * step
    X, Y = np.meshgrid(g, g)
    return np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, z)])


def test_sor_drops_outliers_keeps_plane() -> None:
    rng = np.random.default_rng(0)
    plane = _plane() + rng.normal(0.0, 0.0003, (3600, 3))
    outliers = rng.uniform([-0.07, -0.07, 0.1], [0.07, 0.07, 0.25], (40, 3))
    pts = np.vstack([plane, outliers])
    mask = statistical_outlier_mask(pts, 20, 2.0)
    assert not np.any(mask[3600:])
    assert np.count_nonzero(mask[:3600]) >= 0.99 * 3600
    kept = statistical_outlier_removal(pts, 20, 2.0)
    np.testing.assert_array_equal(kept, pts[mask])


def test_sor_matches_brute_force_definition() -> None:
    rng = np.random.default_rng(1)
    pts = rng.normal(0.0, 0.05, (300, 3))
    k, ratio = 8, 1.0
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    mean_d = np.sort(d, axis=1)[:, 1:k + 1].mean(axis=1)
    expected = mean_d <= mean_d.mean() + ratio * mean_d.std(ddof=1)
    np.testing.assert_array_equal(statistical_outlier_mask(pts, k, ratio), expected)


def _brute_knn_mean(pts: np.ndarray, k: int) -> np.ndarray:
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return np.sort(d, axis=1)[:, :k].mean(axis=1)


@pytest.mark.parametrize("shape", ["plane_and_outliers", "duplicates", "line", "far_apart", "blob"])
def test_knn_mean_distances_match_brute_force(shape: str) -> None:
    rng = np.random.default_rng(2)
    if shape == "plane_and_outliers":
        pts = np.vstack([_plane(30) + rng.normal(0.0, 0.0003, (900, 3)),
                         rng.uniform(-0.2, 0.2, (30, 3))])
    elif shape == "duplicates":  # exact copies: distance 0 counts, the point itself does not
        base = rng.normal(0.0, 0.01, (200, 3))
        pts = np.vstack([base, base[:50], base[:10]])
    elif shape == "line":
        pts = np.column_stack([np.linspace(0.0, 1.0, 400), np.zeros(400), np.zeros(400)])
    elif shape == "far_apart":  # two tight clusters 10 m apart: the grid cap and the widening search
        pts = np.vstack([rng.normal(0.0, 0.001, (150, 3)), rng.normal(10.0, 0.001, (150, 3))])
    else:
        pts = rng.normal(0.0, 0.05, (700, 3))
    for k in (1, 8, 20):
        np.testing.assert_allclose(knn_mean_distances(pts, k), _brute_knn_mean(pts, k), rtol=1e-12,
                                   atol=1e-15)


def test_sor_small_inputs() -> None:
    assert statistical_outlier_mask(np.zeros((0, 3)), 5, 2.0).shape == (0,)
    assert np.all(statistical_outlier_mask(np.ones((5, 3)), 5, 2.0))
    with pytest.raises(ValueError):
        statistical_outlier_mask(np.ones((5, 3)), 0, 2.0)


@pytest.mark.parametrize("incidence_deg", [0.0, 45.0, GRAZING_DEG - 5.0, GRAZING_DEG + 5.0])
def test_a_plane_s_depths_are_continuous_when_seen_no_flatter_than_grazing(incidence_deg: float) -> None:
    """A plane 40 cm ahead, turned about the camera's y axis, seen at ``incidence_deg`` on the optical axis
    (2.3 deg more or less at the image's sides, 41 pixels of 2 mrad): every pixel but those without a
    return is kept up to ``GRAZING_DEG``; beyond it, each pixel farther than its neighbour along the slope
    is dropped, so only the nearest of each row's runs stays: the last column, and the pixel before the
    hole."""
    f, theta = 500.0, math.radians(incidence_deg)
    u = np.arange(41) - 20.0
    depth = np.tile(0.4 * math.cos(theta) / (math.sin(theta) * u / f + math.cos(theta)), (41, 1))
    depth[5, 7] = 0.0
    keep = continuous_depth_mask(depth, 1.0 / f)
    assert not keep[5, 7]
    if incidence_deg < GRAZING_DEG:
        assert np.count_nonzero(keep) == 41 * 41 - 1
    else:
        assert set(zip(*np.nonzero(keep), strict=True)) == {(row, 40) for row in range(41)} | {(5, 6)}


def _tof_frame() -> DepthFrame:
    status = np.array([5, 9, 255, 6, 5, 12, 9, 255], dtype=np.uint8)
    nb = np.array([1, 1, 0, 1, 1, 1, 1, 0], dtype=np.uint8)
    dist = np.array([0.30, 0.31, np.nan, 0.5, 0.40, 0.2, 0.35, np.nan])
    angles = np.linspace(-0.3, 0.3, 8)
    directions = np.column_stack([np.sin(angles), np.zeros(8), np.cos(angles)])
    zones = ToFZones(distance_m=dist, sigma_m=np.arange(1, 9) * 0.001, status=status, nb_targets=nb,
                     reflectance_pct=np.full(8, 40.0), directions=directions)
    with_target = nb > 0
    points = dist[with_target, None] * directions[with_target]
    return DepthFrame(seq=3, timestamp=0.1, points=points, zones=zones)


def test_valid_tof_returns_by_status() -> None:
    frame = _tof_frame()
    z = frame.zones
    assert z is not None
    pts, sigma = valid_tof_returns(frame, FilterParams().valid_tof_statuses)
    expected = [0, 1, 4, 6]
    np.testing.assert_allclose(pts, z.distance_m[expected, None] * z.directions[expected])
    np.testing.assert_allclose(np.linalg.norm(pts, axis=1), z.distance_m[expected])
    np.testing.assert_array_equal(sigma, z.sigma_m[expected])
    # configurable: only 5; and a listed no-target status (255) never yields a NaN point
    np.testing.assert_allclose(valid_tof_returns(frame, (5,))[0], frame.points[[0, 3]])
    assert valid_tof_returns(frame, (5, 9, 255))[0].shape == (4, 3)
    with pytest.raises(ValueError):
        valid_tof_returns(DepthFrame(seq=0, timestamp=0.0, points=np.zeros((0, 3))))


def test_no_target_directions() -> None:
    frame = _tof_frame()
    z = frame.zones
    assert z is not None
    rays = no_target_directions(frame)
    np.testing.assert_allclose(rays, z.directions[[2, 7]])
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0)


def test_a_zone_with_no_target_carves_to_the_crop_box_or_the_range_whichever_is_nearer() -> None:
    crop = CropBoxConfig(x_m=(-0.5, 0.5), y_m=(-0.5, 0.5), z_m=(0.02, 1.0))
    tilt = math.radians(30.0)
    rays = np.array([[0.0, 0.0, 1.0],                              # out through the far face
                     [math.sin(tilt), 0.0, math.cos(tilt)],        # out through the side at x = 0.5
                     [0.0, -math.sin(tilt), math.cos(tilt)],       # out through the side at y = -0.5
                     [0.0, 0.0, -1.0]])                            # behind the sensor: never in the box
    np.testing.assert_allclose(carved_lengths(rays, crop, 4.0), [1.0, 1.0, 1.0, 0.0])
    np.testing.assert_allclose(carved_lengths(rays, crop, 0.6), [0.6, 0.6, 0.6, 0.0])


def test_filter_frame_chain() -> None:
    rng = np.random.default_rng(2)
    plane = _plane(n_side=160, step=0.001, z=0.30125) + rng.normal(0.0, 0.0002, (160 * 160, 3))
    outside = np.array([[0.0, 0.0, 0.02], [0.0, 0.0, 0.45], [0.2, 0.0, 0.3], [0.0, -0.16, 0.3]])
    stray = rng.uniform([-0.05, -0.05, 0.15], [0.05, 0.05, 0.25], (10, 3))
    pts = np.vstack([plane, outside, stray])
    crop = CropBoxConfig(x_m=(-0.15, 0.15), y_m=(-0.15, 0.15), z_m=(0.05, 0.40))
    out = filter_frame(pts, crop=crop, voxel_m=0.0025, params=FilterParams())
    assert np.all(np.abs(out[:, 2] - 0.3) < 0.003)  # outside points cropped, strays removed by SOR
    assert 0.9 * 64 * 64 <= out.shape[0] <= 66 * 66  # 16 cm plane at 2.5 mm
    raw = filter_frame(pts, crop=crop, voxel_m=0.0025, params=FilterParams(sor_enabled=False))
    assert raw.shape[0] > out.shape[0] and np.any(raw[:, 2] < 0.26)


def test_filter_params_strict() -> None:
    assert FilterParams().valid_tof_statuses == (5, 9)
    with pytest.raises(ValidationError):
        FilterParams(sor_neighbours=3)
    with pytest.raises(ValidationError):
        FilterParams(sor_neighbors=0)


def test_lowpass_time_constant() -> None:
    lp = CentroidLowPass(tau_s=0.5)
    np.testing.assert_allclose(lp.update(np.zeros(3), 0.0), 0.0)
    target = np.array([1.0, -2.0, 0.5])
    t, dt = 0.0, 0.01
    while t < 0.5 - 1e-9:
        t += dt
        y = lp.update(target, t)
    # step response after one time constant: 1 - 1/e
    np.testing.assert_allclose(y, target * (1.0 - math.exp(-1.0)), rtol=1e-9)
    for _ in range(1500):
        t += dt
        y = lp.update(target, t)
    np.testing.assert_allclose(y, target, atol=1e-6)


def test_lowpass_dt_aware() -> None:
    """The same step response whatever the sampling: one 0.3 s step equals thirty 10 ms steps."""
    a, b = CentroidLowPass(0.2), CentroidLowPass(0.2)
    a.update(np.zeros(3), 1.0)
    b.update(np.zeros(3), 1.0)
    ya = a.update(np.ones(3), 1.3)
    for i in range(1, 31):
        yb = b.update(np.ones(3), 1.0 + 0.01 * i)
    np.testing.assert_allclose(ya, yb, rtol=1e-9)
    np.testing.assert_allclose(ya, 1.0 - math.exp(-0.3 / 0.2))
    # dt = 0 does not move; time backwards raises; reset re-initialises; tau 0 passes through
    np.testing.assert_allclose(a.update(np.full(3, 5.0), 1.3), ya)
    with pytest.raises(ValueError):
        a.update(np.ones(3), 1.0)
    a.reset()
    assert a.value is None
    np.testing.assert_allclose(a.update(np.full(3, 7.0), 0.0), 7.0)
    p = CentroidLowPass(0.0)
    p.update(np.zeros(3), 0.0)
    np.testing.assert_allclose(p.update(np.ones(3), 0.001), 1.0)
    with pytest.raises(ValueError):
        CentroidLowPass(-1.0)
