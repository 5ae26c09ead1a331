"""The packing box's faces seen head on and at the outline (cell.packing.faces) and the zone grid's
surface normals (cell.packing.zones), on captures rendered along an 8x8 ToF sensor's zone rays."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from cell.config.load import load_config
from cell.packing.box import PackingBox, box_from_faces, box_from_points
from cell.packing.faces import face_at, head_on_plane, outline_gap, sample_end
from cell.packing.uncertainty import ErrorModel, Seen, Sighting
from cell.packing.zones import NEIGHBOURS, outline_sides, surface_normals, zone_grid
from drivers.clock import WallClock
from drivers.depth.sim_tof import SimToF, zone_directions
from drivers.sim.objects import load_object
from drivers.sim.scene import SimScene
from drivers.transforms import look_at, make_T
from tests.conftest import UR5E

ZONE = math.radians(45.0 / 8)
HALF_FOV = (math.radians(22.5), math.radians(22.5))
MODEL = ErrorModel(zone_rad=ZONE, sigma0_m=0.004, k_per_m=0.01, bias_m=0.002, voxel_m=0.01, pose_m=0.002,
                   pose_rad=0.0035, coverage=2.0, half_fov_rad=HALF_FOV)
RAYS = zone_directions(8, 45.0, 1)[:, 0, :]  # the 64 zones' central rays, sensor frame


def _looking_down(x: float, y: float, height: float, tilt_deg: float = 0.0) -> np.ndarray:
    """T_base_sensor of a sensor at (x, y, height) looking down, tilted about the base x axis."""
    t = math.radians(tilt_deg)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(t), -math.sin(t)], [0.0, math.sin(t), math.cos(t)]])
    T = np.eye(4)
    T[:3, :3] = rx @ np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [x, y, height]
    return T


def _capture(T: np.ndarray, top_z: float, half: float, rng: np.random.Generator,
             noise: bool = True) -> np.ndarray:
    """The points (K, 3) [base] an 8x8 sensor at T ranges on a square top |x|, |y| <= ``half`` at height
    ``top_z``: each zone's central ray to the plane, off along the ray by the model's range noise."""
    d = RAYS @ T[:3, :3].T
    t = (top_z - T[2, 3]) / d[:, 2]
    hit = T[:3, 3] + t[:, None] * d
    on = np.all(np.abs(hit[:, :2]) <= half, axis=1)
    r = t[on]
    if noise:
        r = r + (MODEL.sigma0_m + MODEL.k_per_m * r**2) * rng.standard_normal(r.shape[0])
    return T[:3, 3] + r[:, None] * d[on]


def _top_scan(top_z: float, half: float, seed: int) -> list[Sighting]:
    rng = np.random.default_rng(seed)
    poses = [_looking_down(dx, dy, top_z + 0.3, tilt) for dx in (-0.02, 0.0, 0.02) for dy in (-0.02, 0.02)
             for tilt in (-10.0, 0.0, 10.0)]
    return [Sighting(T, _capture(T, top_z, half, rng)) for T in poses]


def _seen(sightings: list[Sighting]) -> Seen:
    keep = np.ones(sum(s.points.shape[0] for s in sightings), dtype=bool)
    return Seen.of(sightings, keep, MODEL)


def test_zone_grid_finds_each_central_ray_its_zone() -> None:
    row, col = zone_grid(RAYS * 0.3, ZONE, HALF_FOV)
    np.testing.assert_array_equal(row * 8 + col, np.arange(64))
    behind = zone_grid(np.array([[0.0, 0.0, -0.3], [1.0, 0.0, 0.1]]), ZONE, HALF_FOV)
    assert list(behind[0]) == [-1, -1]


def test_surface_normals_of_a_tilted_plane_face_the_sensor() -> None:
    T = _looking_down(0.0, 0.0, 0.4, tilt_deg=20.0)
    rng = np.random.default_rng(0)
    flat = _capture(T, 0.1, 1.0, rng, noise=False)
    normals = surface_normals(T, flat, ZONE, HALF_FOV)
    assert np.all(np.isfinite(normals))
    np.testing.assert_allclose(normals, np.tile([0.0, 0.0, 1.0], (64, 1)), atol=1e-9)
    # With the range noise, still within the 35 deg that tells a top from a side.
    noisy = surface_normals(T, _capture(T, 0.1, 1.0, rng), ZONE, HALF_FOV)
    assert np.median(noisy[:, 2]) > math.cos(math.radians(20.0))
    # Two points in one zone are not that zone's range; a lone point has no neighbours.
    doubled = surface_normals(T, np.vstack([flat[:1], flat[:1] * 1.001]), ZONE, HALF_FOV)
    assert np.all(np.isnan(doubled))


def _inside(T: np.ndarray, points: np.ndarray, on_object: np.ndarray, margin) -> np.ndarray:
    """The points on the object whose zone straddles the outline on no side."""
    return on_object & ~outline_sides(T, points, on_object, margin, ZONE, HALF_FOV).any(axis=1)


def test_zones_inside_the_outline_have_the_object_or_something_nearer_all_around() -> None:
    T = _looking_down(0.0, 0.0, 0.4)
    d = RAYS @ T[:3, :3].T
    on_top = np.all(np.abs(T[:2, 3] + (0.1 - 0.4) / d[:, 2:] * d[:, :2]) <= 0.06, axis=1)
    t = np.where(on_top, 0.3, 0.4) / -d[:, 2]  # the top at z = 0.1, the table beyond it at z = 0
    points = T[:3, 3] + t[:, None] * d
    def margin(ranges: np.ndarray) -> np.ndarray:
        return np.full(ranges.shape, 0.01)

    grid = on_top.reshape(8, 8)
    # Each side straddles where the neighbour on that side (+x, -x, +y, -y in the image) is the table.
    sides = outline_sides(T, points, on_top, margin, ZONE, HALF_FOV).reshape(8, 8, 4)
    for side, (dr, dc) in enumerate(NEIGHBOURS):
        beyond = np.zeros((10, 10), dtype=bool)
        beyond[1:9, 1:9] = ~grid
        beyond[[0, 9], :] = beyond[:, [0, 9]] = False  # past the grid's border: the field of view's edge
        np.testing.assert_array_equal(sides[:, :, side] & grid, beyond[1 + dr:9 + dr, 1 + dc:9 + dc] & grid)
    around = grid.copy()
    around[1:] &= grid[:-1]
    around[:-1] &= grid[1:]
    around[:, 1:] &= grid[:, :-1]
    around[:, :-1] &= grid[:, 1:]
    assert 0 < np.count_nonzero(around) < np.count_nonzero(on_top)
    np.testing.assert_array_equal(_inside(T, points, on_top, margin), around.ravel())
    # Something nearer beside a zone (the table in front of a side's foot) is not past the object; a
    # zone that ranged nothing is not known to be nearer.
    nearer = np.where(on_top[:, None], points, T[:3, 3] + (0.25 / -d[:, 2:]) * d)
    np.testing.assert_array_equal(_inside(T, nearer, on_top, margin), on_top)
    silent = np.flatnonzero(on_top)[0] - 1  # the zone left of the top's first
    assert not on_top[silent]
    kept = np.delete(np.arange(64), silent)
    lone = _inside(T, nearer[kept], on_top[kept], margin)
    assert np.count_nonzero(lone) == np.count_nonzero(on_top) - 1
    # The field of view's edge is not the object's: a top filling the grid is inside it everywhere.
    everywhere = np.ones(64, dtype=bool)
    assert _inside(T, points, everywhere, margin).all()
    # Two points in one zone are not its range: such a zone straddles on every side.
    assert outline_sides(T, np.vstack([points[:1], points[:1] * 1.001]), np.ones(2, dtype=bool), margin,
                         ZONE, HALF_FOV).all()


def _sim_tof_views(name: str, centre: np.ndarray, aim: np.ndarray, distance: float,
                   views: list[tuple[float, float]]) -> list[Sighting]:
    """The captures of the sim VL53L8CX (range noise seeded 0) of the shipped object ``name`` standing at
    ``centre`` [m, base], from ``distance`` [m] away from ``aim`` at each (azimuth, elevation) [deg] of
    ``views``: its returns and the no-target zones' far ends, base frame."""
    cfg = load_config(UR5E)
    scene = SimScene(load_object(name), make_T(np.eye(3), centre))
    pose = [np.eye(4)]
    sensor = SimToF(cfg.sensor, scene, lambda: pose[0], WallClock(), np.random.default_rng(0))
    sensor.connect()
    sightings = []
    for azimuth, elevation in views:
        a, e = math.radians(azimuth), math.radians(elevation)
        T = look_at(aim + distance * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a),
                                                math.sin(e)]), aim)
        pose[0] = T
        frame = sensor.capture()
        free = sensor.directions[~np.isfinite(frame.zones.distance_m)] * cfg.sensor.range_max_m
        sightings.append(Sighting(T, *(p @ T[:3, :3].T + T[:3, 3] for p in (frame.points, free))))
    return sightings


def test_a_side_is_at_its_plane_without_the_zones_that_straddle_its_outline() -> None:
    """The shipped vertical box (10 cm square) seen by the sim VL53L8CX (its sub-rays and their median
    range per zone, its range noise) from 50-70 deg beside its +x side's normal: a zone straddling the
    side's vertical edge ranges the side, but its point lies on a central ray that passes beside the
    box, beyond the side's plane. Fitted without them the plane lies within a millimetre of the side;
    with them, 2.6 mm out."""
    centre = np.array([0.45, 0.0, 0.0])
    views = [(a, e) for a in (-70.0, -60.0, -50.0, 50.0, 60.0, 70.0) for e in (15.0, 35.0)]
    sightings = _sim_tof_views("vertical_box", centre, centre + np.array([0.0, 0.0, 0.12]), 0.35, views)
    # The box's points as the segmentation keeps them: within its voxels beside it, above the table.
    keep = np.concatenate([np.all(np.abs(s.points[:, :2] - centre[:2]) < 0.07, axis=1)
                           & (s.points[:, 2] > 0.01) for s in sightings])
    seen = Seen.of(sightings, keep, MODEL)
    assert seen.inside is not None and 0.3 < seen.inside.mean() < 0.7
    n = np.array([1.0, 0.0, 0.0])
    side = centre[0] + 0.05
    quantile_face = float(np.quantile(seen.points @ n, 0.98))
    assert quantile_face - side > 0.004
    plane = head_on_plane(MODEL, seen, n, quantile_face)
    assert plane == pytest.approx(side, abs=0.001)
    with_outline = head_on_plane(MODEL, replace(seen, straddles=None), n, quantile_face)
    assert with_outline is not None and with_outline - side > 0.002


def test_a_top_seen_head_on_lies_where_its_points_scatter_not_at_their_noise_tail() -> None:
    sightings = _top_scan(0.1, 0.1, seed=1)
    seen = _seen(sightings)
    quantile_top = float(np.quantile(seen.points[:, 2], 0.98))
    assert quantile_top - 0.1 > 0.006  # the range noise's tail: about 2 sigma (4.9 mm) out
    top = head_on_plane(MODEL, seen, np.array([0.0, 0.0, 1.0]), quantile_top)
    assert top == pytest.approx(0.1, abs=0.002)


def test_no_plane_without_facing_points_normals_or_one_level() -> None:
    seen = _seen(_top_scan(0.1, 0.1, seed=2))
    # The sides of a top seen from above: no point faces them.
    assert head_on_plane(MODEL, seen, np.array([1.0, 0.0, 0.0]), 0.1) is None
    # Without normals (no zone grid) no point is known to face the top.
    assert head_on_plane(MODEL, Seen(seen.points, seen.origins, seen.axes), np.array([0.0, 0.0, 1.0]),
                         0.11) is None
    # A small hub 2.5 cm over a wide rim (18 cm across: zones inside its outline), both facing up within
    # the band: one quantile would put the top between the two; the median says two levels, and the
    # box's face (the hub's) stays.
    rng = np.random.default_rng(3)
    rim = _top_scan(0.015, 0.09, seed=4)
    hub = [Sighting(s.T_base_sensor, _capture(s.T_base_sensor, 0.04, 0.025, rng)) for s in rim]
    mixed = [Sighting(r.T_base_sensor, np.vstack([r.points[np.any(np.abs(r.points[:, :2]) > 0.025, axis=1)],
                                                  h.points])) for r, h in zip(rim, hub, strict=True)]
    seen = _seen(mixed)
    up = np.array([0.0, 0.0, 1.0])
    hub_top = float(np.quantile(seen.points[:, 2], 0.98))
    assert head_on_plane(MODEL, seen, up, hub_top) is None
    # Seen head on: no gap, and the noisy points' end lies a fraction of their noise (5 mm) beyond.
    assert face_at(MODEL, seen, up, hub_top) == pytest.approx(hub_top, abs=0.003)


def _flank(T: np.ndarray, radius: float | None, rng: np.random.Generator) -> np.ndarray:
    """The points (K, 3) [base] an 8x8 sensor at T ranges on the cylinder x^2 + z^2 = ``radius``^2 (its
    axis along y, |y| <= 0.1 m, x > 0: a rounded flank facing +x; None: the plane x = 0.06 m, |z| <=
    0.06 m), off along the rays by the range noise."""
    o, d = T[:3, 3], RAYS @ T[:3, :3].T
    if radius is None:
        t = (0.06 - o[0]) / d[:, 0]
        on = np.abs(o[2] + t * d[:, 2]) <= 0.06
    else:  # |o_xz + t d_xz|^2 = radius^2, the nearer root
        a = d[:, 0] ** 2 + d[:, 2] ** 2
        b = 2.0 * (o[0] * d[:, 0] + o[2] * d[:, 2])
        disc = b**2 - 4.0 * a * (o[0] ** 2 + o[2] ** 2 - radius**2)
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
        on = disc > 0.0
    on &= np.abs(o[1] + t * d[:, 1]) <= 0.1
    r = t[on] + (MODEL.sigma0_m + MODEL.k_per_m * t[on] ** 2) * rng.standard_normal(np.count_nonzero(on))
    return o + r[:, None] * d[on]


def test_a_rounded_flank_seen_head_on_is_not_put_at_a_plane_inside_it() -> None:
    """A flank curving away over its height (radius 6 cm) seen head on from 0.3 m: its facing points lie
    up to a fifth of the radius inside its extreme (a plane through them came out 3.9 mm inside); more of
    them lie deep than a plane's noise puts there, and the face is the box's own, the trimmed quantile at
    the extreme plus the noise's tail. A flat side seen alike stays a plane, the tail taken out."""
    rng = np.random.default_rng(11)
    poses = [look_at(np.array([0.36, dy, dz]), np.array([0.0, dy, 0.0])) for dy in (-0.04, 0.0, 0.04)
             for dz in (-0.03, 0.0, 0.03)]
    side = np.array([1.0, 0.0, 0.0])
    seen = _seen([Sighting(T, _flank(T, 0.06, rng)) for T in poses])
    quantile = float(np.quantile(seen.points @ side, 0.98))
    assert head_on_plane(MODEL, seen, side, quantile) == quantile
    assert abs(quantile - 0.06) < 0.006
    flat = _seen([Sighting(T, _flank(T, None, rng)) for T in poses])
    quantile = float(np.quantile(flat.points @ side, 0.98))
    plane = head_on_plane(MODEL, flat, side, quantile)
    assert plane is not None and plane != quantile and abs(plane - 0.06) < 0.003


def test_a_side_seen_at_a_slant_by_views_off_by_their_own_pose_error_is_one_plane() -> None:
    """A flat side seen 65 deg off its normal (|n.d| 0.42) from six views, each capture moved along n by its
    own pose error (the model's pose terms at 0.3 m, 3 mm std): the range noise along n is 2 mm, and the
    views' offsets spread the facing points about their plane as far again. Judged against the range
    noise alone, the noise-corrected quantile lay over 1.5 std above the points' median and they read as
    two levels (the box's quantile face stayed, 9.6 mm out); against their scatter, noise and pose, they
    are one plane."""
    rng = np.random.default_rng(4)
    side = np.array([1.0, 0.0, 0.0])
    poses = [look_at(np.array([0.16, sy * 0.25, dz]), np.array([0.06, 0.0, 0.0])) for sy in (-1, 1)
             for dz in (-0.04, 0.0, 0.04)]
    pose_std = MODEL.pose_m + 0.3 * MODEL.pose_rad
    seen = _seen([Sighting(T, _flank(T, None, rng) + rng.normal(0.0, pose_std) * side) for T in poses])
    quantile = float(np.quantile(seen.points @ side, 0.98))
    plane = head_on_plane(MODEL, seen, side, quantile)
    assert quantile - 0.06 > 0.008
    assert plane is not None and abs(plane - 0.06) < 0.005 and plane < quantile - 0.004


def test_a_flank_that_leans_over_its_height_is_not_put_at_a_plane_mid_slope() -> None:
    """The shipped gripper's flank (31.4 mm from its centre near the foot, 15.7 mm at 76 mm height) seen
    by the sim VL53L8CX from three views 30 deg up: the plane of its facing points lies mid-slope, 6 mm
    inside, and too few of them lie deeper still for the rounded test. Their trend with height tells it
    leans, and the face is the box's own, the trimmed quantile at the flank's foot."""
    centre = np.array([0.45, 0.0, 0.0])
    sightings = _sim_tof_views("gripper", centre, centre + np.array([0.0, 0.0, 0.04]), 0.3,
                               [(a, 30.0) for a in (-45.0, 0.0, 45.0)])
    keep = np.concatenate([(np.abs(s.points[:, 0] - centre[0]) < 0.045) & (np.abs(s.points[:, 1]) < 0.11)
                           & (s.points[:, 2] > 0.005) for s in sightings])
    seen = Seen.of(sightings, keep, MODEL)
    n = np.array([1.0, 0.0, 0.0])
    flank = centre[0] + 0.0314
    quantile = float(np.quantile(seen.points @ n, 0.98))
    assert head_on_plane(MODEL, seen, n, quantile) == quantile
    assert abs(quantile - flank) < 0.002


def test_a_face_seen_at_the_outline_lies_a_footprint_over_its_points_plus_one_beyond_their_end() -> None:
    """A 20 cm square top seen from above by 6 sensor positions (3 tilts each): its sides are seen only
    as the top's outline, the outermost zones inside it by up to a footprint (about 3 cm at 0.3 m)."""
    sightings = _top_scan(0.1, 0.1, seed=5)
    seen = _seen(sightings)
    side = np.array([1.0, 0.0, 0.0])
    x, face = seen.face(side)
    ranges, _, sideways = seen.geometry(side)
    gap = outline_gap(MODEL, seen, side)
    assert gap == pytest.approx(MODEL.footprint(ranges[face], sideways[face]) / (np.count_nonzero(face) + 1))
    quantile = float(np.quantile(x, 0.98))
    estimate = face_at(MODEL, seen, side, quantile)
    assert estimate == pytest.approx(sample_end(seen, side, quantile) + gap)
    assert 0.1 - quantile > 0.005 and abs(estimate - 0.1) < 0.003
    # Views unknown: no gap.
    assert outline_gap(MODEL, Seen(seen.points, range_m=0.3), side) == 0.0


def test_the_samples_end_where_a_surface_running_out_ends_whatever_its_size() -> None:
    """A 30 cm top sampled evenly, its normals up: 2 % of its points are its last 6 mm, where the trimmed
    quantile stops; the points beyond it span as much as as many inside, so they end at the edge. Gross
    outliers fewer than the trimmed points do not carry it out; the end is never beyond the outermost point.
    A wall or rounded end at the face (normals towards it) is where its points crowd: no step; without
    normals, none."""
    rng = np.random.default_rng(8)
    top = np.column_stack([rng.uniform(-0.15, 0.15, 2000), rng.uniform(-0.1, 0.1, 2000), np.full(2000, 0.1)])
    points = np.vstack([top, [[0.2, 0.0, 0.1], [0.22, 0.05, 0.1], [0.25, -0.05, 0.1]]])
    up = np.tile([0.0, 0.0, 1.0], (points.shape[0], 1))
    side = np.array([1.0, 0.0, 0.0])
    quantile = float(np.quantile(points @ side, 0.98))
    assert 0.15 - quantile > 0.005
    assert sample_end(Seen(points, normals=up), side, quantile) == pytest.approx(0.15, abs=0.002)
    assert sample_end(Seen(points, normals=up), side, 0.3) == 0.3  # nothing beyond the face
    assert sample_end(Seen(points), side, quantile) == quantile
    assert sample_end(Seen(points, normals=np.tile(side, (points.shape[0], 1))), side, quantile) == quantile
    # A rounded end 50 deg off the face's normal turns towards it as well: no step.
    rounded = np.tile([math.cos(math.radians(50.0)), 0.0, math.sin(math.radians(50.0))], (points.shape[0], 1))
    assert sample_end(Seen(points, normals=rounded), side, quantile) == quantile
    # Half the outermost points on a wall facing the face: half the step.
    half = up.copy()
    half[np.argsort(-(points @ side))[:80:2]] = side
    step = sample_end(Seen(points, normals=up), side, quantile) - quantile
    halved = sample_end(Seen(points, normals=half), side, quantile) - quantile
    assert halved == pytest.approx(step / 2, rel=0.1)
    few = Seen(top[:3], normals=up[:3])
    assert sample_end(few, side, float(np.quantile(top[:3, 0], 0.5))) <= top[:3, 0].max()


def test_box_from_faces_inverts_faces() -> None:
    box = PackingBox(center_xy=np.array([0.45, -0.02]), dims=np.array([0.3, 0.2, 0.1]),
                     yaw_rad=math.radians(25.0), z_min=0.0)
    again = box_from_faces(box, box.faces())
    np.testing.assert_allclose(again.center_xy, box.center_xy, atol=1e-12)
    np.testing.assert_allclose(again.dims, box.dims, atol=1e-12)
    # Faces that make W the longer side turn the L axis by 90 deg.
    wide = box_from_faces(box, box.faces() + np.array([0.0, 0.0, 0.1, 0.1, 0.0]))
    np.testing.assert_allclose(wide.dims, [0.4, 0.3, 0.1], atol=1e-12)
    assert wide.yaw_rad == pytest.approx(math.radians(25.0 - 90.0))
    points = np.random.default_rng(5).uniform([0.3, -0.1, 0.0], [0.6, 0.1, 0.1], (500, 3))
    trimmed = box_from_points(points, 0.0, trim=0.02)
    np.testing.assert_allclose(box_from_faces(trimmed, trimmed.faces()).dims, trimmed.dims, atol=1e-12)


def test_a_face_seen_only_at_the_outline_may_lie_a_footprint_beyond_it_in_the_image() -> None:
    # A view looking down 53.13 deg: the top's normal +z points up the image (-y), 0.6 of its length.
    e = math.acos(0.6)
    down, ahead = [-math.sin(e), 0.0, -math.cos(e)], [math.cos(e), 0.0, -math.sin(e)]
    R = np.column_stack([[0.0, -1.0, 0.0], down, ahead])  # image x, image y, optical axis
    up = np.array([0.0, 0.0, 1.0])
    n_points = 4
    seen = Seen(points=np.zeros((n_points, 3)), origins=np.tile(-0.3 * R[:, 2], (n_points, 1)),
                axes=np.tile(R, (n_points, 1, 1)),
                normals=np.array([[np.nan] * 3, [np.nan] * 3, up, [0.0, -1.0, 0.0]]),
                straddles=np.array([[0, 0, 0, 1], [1, 0, 1, 0], [0, 0, 0, 1], [0, 0, 0, 1]], dtype=bool))
    # No point of the face lies on the top (no normal, or a side's): the top was seen only at its outline,
    # and moved up by D it moves the outline 0.6 D up the image, so beyond a point straddling the outline
    # up the image it may lie 1 / 0.6 footprints; beyond one straddling elsewhere, 0.6 as for a point
    # ranged on the face.
    outline_only = np.array([True, True, False, True])
    footprints = seen.footprints(up, outline_only)
    np.testing.assert_allclose(footprints[outline_only], [1.0 / 0.6, 0.6, 1.0 / 0.6])
    # A face with a point on it (its normal +z) was ranged as a surface: 0.6 everywhere.
    np.testing.assert_allclose(seen.footprints(up, np.ones(n_points, dtype=bool)), 0.6)
    # The bound takes the median over the face's points.
    median = MODEL.footprint(np.full(3, 0.3), footprints[outline_only])
    assert median == pytest.approx(0.3 * math.tan(ZONE) / 0.6)
