"""The table's noise band (``cell.packing.table_band``): the object's points below the segmentation's table
cut that stand above it, and the table's own points above the cut that do not."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cell.config.load import load_config
from cell.packing.result import ReconstructionHistory, packing_section
from cell.packing.table_band import above_table, clear_of_table, height_sigma, off_table
from cell.packing.uncertainty import ErrorModel, Sighting
from cell.perception.pipeline import PerceptionPipeline
from cell.perception.segmentation import compute_roi
from drivers.depth.sim_tof import zone_directions
from drivers.transforms import look_at
from tests.conftest import UR5E
from tests.test_packing import _Planner, _Session, _session, _voxelise

MODEL = ErrorModel(zone_rad=math.radians(45.0 / 8), sigma0_m=0.004, k_per_m=0.01, bias_m=0.002, voxel_m=0.01,
                   pose_m=0.002, pose_rad=0.0035, coverage=2.0,
                   half_fov_rad=(math.radians(22.5), math.radians(22.5)))
CENTRE = np.array([0.45, 0.0, 0.0])


def _oblique(azimuth_deg: float) -> np.ndarray:
    """A view 0.4 m away from the centre, 0.1 m above the table: about 14 deg down onto it."""
    a = math.radians(azimuth_deg)
    eye = CENTRE + np.array([0.4 * math.cos(a), 0.4 * math.sin(a), 0.1])
    return look_at(eye, CENTRE)


def test_height_sigma_is_the_range_noise_along_z() -> None:
    origin = np.array([0.0, 0.0, 0.4])
    down = height_sigma(MODEL, origin, np.array([[0.0, 0.0, 0.0]]))
    assert down[0] == pytest.approx(math.sqrt((0.004 + 0.01 * 0.16) ** 2 + 0.002**2))
    sideways = height_sigma(MODEL, origin, np.array([[0.4, 0.0, 0.4]]))  # a horizontal ray: no z noise
    assert sideways[0] == pytest.approx(0.0)


def test_above_table_takes_points_over_the_views_own_table_band_inside_the_extent() -> None:
    session = _session(1, np.zeros((0, 3)))
    perception = session.perception
    ring = np.linspace(0.0, 2.0 * math.pi, 20, endpoint=False)
    table = CENTRE + np.column_stack([0.15 * np.cos(ring), 0.15 * np.sin(ring), np.full(20, 0.004)])
    probes = np.array([[0.45, 0.0, 0.009],   # 5 mm over the view's table (band ~2.6 mm): the object's
                       [0.45, 0.0, 0.006],   # 2 mm over it: the table's noise
                       [0.60, 0.0, 0.009],   # outside the extent
                       [0.45, 0.0, 0.020]])  # above the cut: the segmentation's own
    sightings = [Sighting(_oblique(0.0), np.vstack([probes, table]))]
    clear = clear_of_table(perception, sightings, MODEL)  # type: ignore[arg-type]
    assert not above_table(perception, sightings, clear, MODEL).any()  # type: ignore[arg-type]  # no ROI yet
    perception.extent.add(compute_roi(np.array([[0.405, -0.045, 0.015], [0.495, 0.045, 0.035]])))
    clear = clear_of_table(perception, sightings, MODEL)  # type: ignore[arg-type]
    np.testing.assert_array_equal(clear[:4], [True, False, True, True])
    got = above_table(perception, sightings, clear, MODEL)  # type: ignore[arg-type]
    np.testing.assert_array_equal(got[:4], [True, False, False, False])
    assert not got[4:].any()
    # Without the view's table the known height stands in: 6 mm is then above the band.
    alone = [Sighting(_oblique(0.0), probes)]
    clear = clear_of_table(perception, alone, MODEL)  # type: ignore[arg-type]
    got = above_table(perception, alone, clear, MODEL)  # type: ignore[arg-type]
    np.testing.assert_array_equal(got, [True, True, False, False])


def test_a_table_point_over_the_band_by_chance_among_table_points_is_not_the_objects() -> None:
    """One capture, a range per zone (the VL53L8CX's 8 x 8 over 45 deg) of a 10 x 10 cm plate 10 mm tall
    on the table, seen 45 deg down from 0.28 m: the plate's zones stand over the view's band (7.4 mm)
    and below the 12 mm cut, and count. A table zone two zones off the plate, inside the ROI's footprint,
    comes out 9 mm high (over the band, as 1 in 44 of the table's do by chance): among table zones, it
    does not count."""
    session = _session(1, np.zeros((0, 3)))
    perception = session.perception
    T = look_at(CENTRE + np.array([0.2, 0.0, 0.2]), CENTRE)
    rays = zone_directions(8, 45.0)[:, 0] @ T[:3, :3].T
    origin = T[:3, 3]

    def hit(height: float) -> np.ndarray:
        return origin - ((origin[2] - height) / rays[:, 2])[:, None] * rays

    plate = np.all(np.abs(hit(0.01)[:, :2] - CENTRE[:2]) <= 0.05, axis=1)
    points = np.where(plate[:, None], hit(0.01), hit(0.0))
    lo, hi = np.array([0.38, -0.17, 0.015]), np.array([0.52, 0.07, 0.035])
    inside = np.all((points[:, :2] > lo[:2]) & (points[:, :2] < hi[:2]), axis=1)
    zone = np.column_stack(np.divmod(np.arange(64), 8))
    apart = np.array([np.abs(zone[plate] - z).max(axis=1).min() >= 2 for z in zone])
    chance = int(np.flatnonzero(inside & apart)[0])
    points[chance, 2] = 0.009
    sightings = [Sighting(T, points)]
    perception.extent.add(compute_roi(np.array([lo, hi])))
    clear = clear_of_table(perception, sightings, MODEL)  # type: ignore[arg-type]
    assert clear[chance] and clear[plate].all() and np.count_nonzero(plate) >= 4
    got = above_table(perception, sightings, clear, MODEL)  # type: ignore[arg-type]
    np.testing.assert_array_equal(np.flatnonzero(got), np.flatnonzero(plate))


def test_a_plates_rim_below_the_table_cut_still_counts() -> None:
    """A 12 x 12 cm plate 25 mm tall whose outer 8 mm the oblique views saw 7 mm over the table (zones
    that straddle its outline, as on a flange's rim), below the 12 mm cut, while the rest of its points,
    and so the map's voxels out to its edge, stand above it: the box is the plate's width, not that of
    the points above the cut (10.4 cm)."""
    cfg = load_config(UR5E)
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.06, 0.06, size=(3000, 2))
    rim = np.abs(xy).max(axis=1) > 0.052
    plate = np.column_stack([xy + CENTRE[:2], np.where(rim, 0.007, 0.025)])
    around = np.linspace(-0.2, 0.2, 41)
    table = np.column_stack([*(g.ravel() + c for g, c in zip(np.meshgrid(around, around), CENTRE[:2],
                                                               strict=True)), np.zeros(around.size**2)])
    table = table[np.abs(table[:, :2] - CENTRE[:2]).max(axis=1) > 0.07]
    history = ReconstructionHistory()
    for k, azimuth in enumerate((0.0, 90.0, 180.0, 270.0)):
        history.sightings.append(Sighting(_oblique(azimuth), np.vstack([plate[k::4], table])))
    perception = PerceptionPipeline(cfg.perception, table_z_m=0.0, range_max_m=4.0,
                                    rng=np.random.default_rng(0))
    for s in history.sightings:
        perception.add_capture(s.T_base_sensor, s.points, s.free_ends)
    session = _Session(4, perception)  # type: ignore[arg-type]
    section = packing_section(cfg, session, _Planner(history), None, None, None)  # type: ignore[arg-type]
    np.testing.assert_allclose(section["dims_m"][:2], [0.12, 0.12], atol=0.01)


def test_a_cloud_point_is_the_tables_when_every_capture_point_of_its_voxel_is() -> None:
    session = _session(1, np.zeros((0, 3)))
    captured = np.array([[0.451, 0.0011, 0.0131], [0.4512, 0.0013, 0.0133],  # one voxel, both the table's
                         [0.501, 0.0011, 0.0131], [0.5012, 0.0013, 0.0133]])  # one voxel, one the object's
    clear = np.array([False, False, False, True])
    cloud = np.vstack([captured[:2].mean(axis=0), captured[2:].mean(axis=0), [[0.6, 0.0, 0.05]]])
    got = off_table(session.perception, cloud, captured, clear)  # type: ignore[arg-type]
    np.testing.assert_array_equal(got, [False, True, True])  # the last: no capture point in its voxel
    nothing = off_table(session.perception, cloud, np.zeros((0, 3)), np.zeros(0, dtype=bool))  # type: ignore[arg-type]
    np.testing.assert_array_equal(nothing, [True, True, True])


def test_table_noise_over_the_cut_beyond_the_part_does_not_lengthen_its_box() -> None:
    """A 10 x 10 x 5 cm block seen from 0.5 m straight above, where the table's height std is 6.8 mm: a
    cluster of table points 12.5 mm up (1.8 std, over the 12 mm cut) 5-7 cm beyond its end fills
    voxels the segmentation joined to the block and the ROI's box, and holds more than the trim's 2 % of
    the points. They are within their capture's table band: the box is the block's."""
    cfg = load_config(UR5E)
    grid = np.linspace(-0.0475, 0.0475, 20)
    top = np.column_stack([*(g.ravel() for g in np.meshgrid(grid + CENTRE[0], grid)), np.full(400, 0.05)])
    noise = np.column_stack([np.repeat(CENTRE[0] + np.linspace(0.1, 0.12, 5), 4),
                             np.tile(np.linspace(-0.03, 0.03, 4), 5), np.full(20, 0.0125)])
    ring = np.linspace(0.0, 2.0 * math.pi, 40, endpoint=False)
    table = CENTRE + np.column_stack([0.2 * np.cos(ring), 0.2 * np.sin(ring), np.zeros(40)])
    history = ReconstructionHistory()
    for k in range(4):
        eye = CENTRE + np.array([0.002 * k, 0.0, 0.5])
        history.sightings.append(Sighting(look_at(eye, CENTRE),
                                          np.vstack([top[k::4], noise[k::4], table])))
    voxels = _voxelise(np.vstack([top, noise]), 0.01)
    session = _session(4, voxels, np.vstack([top, noise]))
    session.perception.extent.add(compute_roi(voxels))
    section = packing_section(cfg, session, _Planner(history), None, None, None)  # type: ignore[arg-type]
    np.testing.assert_allclose(section["dims_m"], [0.1, 0.1, 0.05], atol=0.01)
