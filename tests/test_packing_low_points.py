"""The object's points below the segmentation's table cut that stand above the table's noise band
(``cell.packing.low_points``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cell.config.load import load_config
from cell.packing.low_points import above_table, height_sigma
from cell.packing.result import ReconstructionHistory, packing_section
from cell.packing.uncertainty import ErrorModel, Sighting
from cell.perception.segmentation import compute_roi
from drivers.transforms import look_at
from tests.conftest import UR5E
from tests.test_packing import _Planner, _session, _voxelise

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
    assert not above_table(perception, sightings, MODEL).any()  # type: ignore[arg-type]  # no ROI yet
    perception.extent.add(compute_roi(np.array([[0.405, -0.045, 0.015], [0.495, 0.045, 0.035]])))
    got = above_table(perception, sightings, MODEL)  # type: ignore[arg-type]
    np.testing.assert_array_equal(got[:4], [True, False, False, False])
    assert not got[4:].any()
    # Without the view's table the known height stands in: 6 mm is then above the band.
    alone = above_table(perception, [Sighting(_oblique(0.0), probes)], MODEL)  # type: ignore[arg-type]
    np.testing.assert_array_equal(alone, [True, True, False, False])


def test_a_plates_rim_below_the_table_cut_still_counts() -> None:
    """A 12 x 12 cm plate whose outer centimetre the oblique views saw 7 mm over the table (zones that
    straddle its outline, as on a flange's rim), below the 12 mm cut, while its inner part's points and
    the map's voxels (their centres half a voxel inside the plate's edge) stand above it: the box is the
    plate's width, not that of the points and voxels above the cut."""
    cfg = load_config(UR5E)
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.06, 0.06, size=(3000, 2))
    rim = np.abs(xy).max(axis=1) > 0.05
    plate = np.column_stack([xy + CENTRE[:2], np.where(rim, 0.007, 0.016)])
    inner = plate[~rim]
    ring = np.linspace(0.0, 2.0 * math.pi, 40, endpoint=False)
    table = CENTRE + np.column_stack([0.12 * np.cos(ring), 0.12 * np.sin(ring), np.zeros(40)])
    history = ReconstructionHistory()
    for k, azimuth in enumerate((0.0, 90.0, 180.0, 270.0)):
        history.sightings.append(Sighting(_oblique(azimuth), np.vstack([plate[k::4], table])))
    voxels = _voxelise(np.column_stack([plate[:, :2], np.full(len(plate), 0.016)]), 0.01)
    session = _session(4, voxels, inner)
    session.perception.extent.add(compute_roi(voxels))
    section = packing_section(cfg, session, _Planner(history), None, None, None)  # type: ignore[arg-type]
    np.testing.assert_allclose(section["dims_m"][:2], [0.12, 0.12], atol=0.01)
