"""The scan's calibration residual measured on the table (``cell.packing.table_calibration``)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from cell.config.load import load_config
from cell.packing import result
from cell.packing.box import PackingBox
from cell.packing.result import ReconstructionHistory, packing_section, section_box
from cell.packing.table_calibration import TableCorrection, corrected_perception, table_correction
from cell.packing.uncertainty import Sighting
from cell.perception.pipeline import PerceptionPipeline
from cell.perception.segmentation import compute_roi
from drivers.depth.sim_tof import zone_directions
from drivers.sim.objects import load_object
from drivers.sim.scene import SimScene
from drivers.transforms import T_from_xyz_rpy, look_at
from tests.conftest import UR5E
from tests.test_packing import _Planner, _Session, _session
from tests.test_packing_table_band import CENTRE, MODEL

# The sensor really sits at the believed pose times this (rotation vector [rad], translation [m], sensor
# frame) and reports every range 2 mm long: about the ToF cell's hand-eye residual (drivers.sim.errors).
ROTATION = np.array([0.0026, -0.0020, 0.0015])
TRANSLATION = np.array([0.0012, -0.0015, 0.0010])
OFFSET_M = 0.002
PLATE_Z = 0.008  # a plate 8 mm tall under the ROI: within the table cut, not the table


def _views(distance_m: float = 0.3, roll_deg: float = 30.0) -> list[np.ndarray]:
    """Twelve views of the station, ``distance_m`` from its centre at 30, 50 and 70 deg elevation from
    four sides, each rolled about its axis as the planners' views are when a roll reaches them (0,
    ``roll_deg`` and twice that [deg])."""
    views = []
    sides = [(a, e) for a in (0.0, 90.0, 180.0, 270.0) for e in (30.0, 50.0, 70.0)]
    for k, (azimuth, elevation) in enumerate(sides):
        a, e = math.radians(azimuth + 15.0 * k), math.radians(elevation)
        eye = CENTRE + distance_m * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a),
                                              math.sin(e)])
        T = look_at(eye, CENTRE)
        roll = math.radians(roll_deg * (k % 3))
        R_roll = np.array([[math.cos(roll), -math.sin(roll), 0.0], [math.sin(roll), math.cos(roll), 0.0],
                           [0.0, 0.0, 1.0]])
        T[:3, :3] = T[:3, :3] @ R_roll
        views.append(T)
    return views


def _error() -> np.ndarray:
    return TableCorrection(ROTATION, TRANSLATION, OFFSET_M, 0).transform()


def _sighting(T_believed: np.ndarray, rng: np.random.Generator | None) -> tuple[Sighting, np.ndarray]:
    """What a capture at the believed pose records when the sensor is really at ``T_believed @ error``:
    each zone's central ray ranged to the table (or the plate under the ROI), 2 mm long and, with
    ``rng``, with the sim VL53L8CX's range noise, placed along the believed ray; and the true points."""
    rays = zone_directions(8, 45.0)[:, 0]
    T_true = T_believed @ _error()
    world = rays @ T_true[:3, :3].T
    origin = T_true[:3, 3]
    ranges = origin[2] / -world[:, 2]
    on_plate = np.all(np.abs(origin[:2] + ranges[:, None] * world[:, :2] - CENTRE[:2]) < 0.04, axis=1)
    ranges = np.where(on_plate, (origin[2] - PLATE_Z) / -world[:, 2], ranges)
    sigma = MODEL.sigma0_m + MODEL.k_per_m * ranges**2
    reported = ranges + OFFSET_M + (0.0 if rng is None else sigma * rng.standard_normal(ranges.size))
    recorded = (reported[:, None] * rays) @ T_believed[:3, :3].T + T_believed[:3, 3]
    return Sighting(T_believed, recorded), origin + ranges[:, None] * world


def test_the_table_seen_from_around_gives_back_the_mount_error_and_the_range_offset() -> None:
    rng = np.random.default_rng(5)
    sightings = [_sighting(T, rng)[0] for T in _views()]
    perception = _session(len(sightings), np.zeros((0, 3))).perception
    assert table_correction(perception, sightings, MODEL).n_table_points == 0  # type: ignore[arg-type]  # no ROI
    perception.extent.add(compute_roi(np.array([[0.41, -0.04, 0.015], [0.49, 0.04, 0.03]])))
    got = table_correction(perception, sightings, MODEL)  # type: ignore[arg-type]
    assert got.n_table_points > 600
    assert got.range_offset_m == pytest.approx(OFFSET_M, abs=0.0006)
    np.testing.assert_allclose(got.rotation_vector[:2], ROTATION[:2], atol=0.0005)
    # Every point of the captures (noise aside), the plate's too, moves to within a third of its error.
    for T in _views():
        recorded, truth = _sighting(T, None)
        before = np.linalg.norm(recorded.points - truth, axis=1)
        after = np.linalg.norm(got.apply(recorded).points - truth, axis=1)
        assert float(np.mean(after)) < float(np.mean(before)) / 3.0
    # The plate under the ROI was not taken for the table: it is still 8 mm up.
    plate = np.vstack([got.apply(s).points for s in sightings])
    plate = plate[np.all(np.abs(plate[:, :2] - CENTRE[:2]) < 0.03, axis=1)]
    assert float(np.median(plate[:, 2])) == pytest.approx(PLATE_Z, abs=0.001)


def test_apply_moves_a_capture_to_where_the_sensor_really_was() -> None:
    T = _views()[4]
    truth = np.array([[0.45, 0.02, 0.0], [0.50, -0.03, 0.0]])
    T_true = T @ _error()
    local_true = (truth - T_true[:3, 3]) @ T_true[:3, :3]
    ranges = np.linalg.norm(local_true, axis=1, keepdims=True)
    recorded = Sighting(T, (local_true * (1.0 + OFFSET_M / ranges)) @ T[:3, :3].T + T[:3, 3])
    moved = TableCorrection(ROTATION, TRANSLATION, OFFSET_M, 0).apply(recorded)
    np.testing.assert_allclose(moved.points, truth, atol=1e-9)
    np.testing.assert_allclose(moved.T_base_sensor, T_true, atol=1e-12)
    assert not np.allclose(recorded.points, truth, atol=0.001)


def _scan(T_error: np.ndarray, offset_m: float) -> tuple[ReconstructionHistory, PerceptionPipeline]:
    """Twelve captures of the shipped vertical box at the station on the sim VL53L8CX's zone grid (no
    noise), the sensor really at each believed pose times ``T_error`` and every range ``offset_m`` long,
    fed to a pipeline of the sim ToF cell as the job feeds them."""
    cfg = load_config(UR5E)
    scene = SimScene(load_object("vertical_box"), T_from_xyz_rpy(CENTRE, [0.0, 0.0, 0.3]), table_z=0.0,
                     table_center_xy=(0.4, 0.0), table_size_xy=(1.2, 1.2))
    perception = PerceptionPipeline(cfg.perception, table_z_m=0.0, range_max_m=4.0,
                                    rng=np.random.default_rng(0))
    history = ReconstructionHistory()
    rays = zone_directions(8, 45.0)[:, 0]
    for T in _views(0.4):
        T_true = T @ T_error
        hits = scene.cast(T_true[:3, 3], rays @ T_true[:3, :3].T)
        seen = np.isfinite(hits.t) & (hits.t < 1.0)
        points = ((hits.t[seen] + offset_m)[:, None] * rays[seen]) @ T[:3, :3].T + T[:3, 3]
        history.sightings.append(Sighting(T, points))
        perception.add_capture(T, points, np.zeros((0, 3)))
    return history, perception


def _apart(a: PackingBox, b: PackingBox) -> float:
    """How far [m] the boxes ``a`` and ``b`` lie apart: the furthest corner of either footprint from the
    nearest of the other's (a square footprint's L and W may swap), or the difference of their tops."""
    gaps = np.linalg.norm(a.footprint()[:, None, :] - b.footprint()[None, :, :], axis=2)
    tops = abs(a.z_min + a.dims[2] - b.z_min - b.dims[2])
    return float(max(gaps.min(axis=1).max(), gaps.min(axis=0).max(), tops))


def test_the_box_of_a_cell_with_a_mount_error_comes_out_as_the_exact_cells(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The same twelve captures of a box by a cell with the mount error and range offset above and by an
    exact one: with the table correction the box lies nearer the exact cell's than without it (a corner
    1.0 mm off against 2.0 mm here; what is left is the share of the range offset and of the translation
    along the optical axis that the table cannot tell apart)."""
    cfg = load_config(UR5E)
    exact_history, exact_perception = _scan(np.eye(4), 0.0)
    exact = packing_section(cfg, _Session(12, exact_perception), _Planner(exact_history),  # type: ignore[arg-type]
                            None, None, None)
    history, perception = _scan(_error(), OFFSET_M)
    session = _Session(12, perception)  # type: ignore[arg-type]
    corrected = packing_section(cfg, session, _Planner(history), None, None, None)  # type: ignore[arg-type]
    assert corrected["table_correction"]["n_table_points"] > 300
    assert exact["table_correction"]["range_offset_mm"] == pytest.approx(0.0, abs=0.3)
    monkeypatch.setattr(result, "table_correction", lambda *_: TableCorrection.none())
    as_recorded = packing_section(cfg, session, _Planner(history), None, None, None)  # type: ignore[arg-type]
    off = [_apart(section_box(s), section_box(exact)) for s in (corrected, as_recorded)]
    assert off[0] < off[1] / 1.5


def test_a_correction_that_loses_the_object_is_not_applied(monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = load_config(UR5E)
    history, perception = _scan(_error(), OFFSET_M)
    session = _Session(12, perception)  # type: ignore[arg-type]
    monkeypatch.setattr(result, "table_correction", lambda *_: TableCorrection.none())
    as_recorded = packing_section(cfg, session, _Planner(history), None, None, None)  # type: ignore[arg-type]
    monkeypatch.undo()
    empty = PerceptionPipeline(cfg.perception, table_z_m=0.0, range_max_m=4.0, rng=np.random.default_rng(0))
    monkeypatch.setattr(result, "corrected_perception", lambda *_: empty)
    got = packing_section(cfg, session, _Planner(history), None, None, None)  # type: ignore[arg-type]
    assert got["dims_m"] == as_recorded["dims_m"]
    assert got["table_correction"]["n_table_points"] == 0


def test_the_corrected_perception_keeps_the_pipelines_settings_and_h_roi_form() -> None:
    """The rebuilt pipeline computes H_ROI in the scan's form (the servo termination's), not the default."""
    cfg = load_config(UR5E)
    scan = PerceptionPipeline(cfg.perception, table_z_m=0.01, range_max_m=2.5, rng=np.random.default_rng(0),
                              h_roi_entropy="observation_aware")
    rebuilt = corrected_perception(scan, [])
    assert (rebuilt.config, rebuilt.table_z_m, rebuilt.range_max_m) == (cfg.perception, 0.01, 2.5)
    assert rebuilt.h_roi_entropy == "observation_aware"


def test_each_capture_s_own_pose_error_does_not_pass_for_the_mount_s() -> None:
    """A camera (1200 rays a capture, ranges within a millimetre) whose mount is exact, every capture
    off by an error of its own of the arm's size (0.4 mm, 0.5 mrad per axis), its views rolled by at most
    4 deg: fitted as if the mount alone were off, the translation along the image axis the views keep
    nearly level comes out several times the mount's prior (2 mm); with each capture's own error taken
    out it stays within the prior."""
    camera = replace(MODEL, zone_rad=math.atan(1 / 475), sigma0_m=0.0005, k_per_m=0.002,
                     half_fov_rad=(math.atan(320 / 475), math.atan(240 / 475)))
    x, y = np.meshgrid(np.linspace(-0.6, 0.6, 40), np.linspace(-0.45, 0.45, 30))
    rays = np.column_stack([x.ravel(), y.ravel(), np.ones(x.size)])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rng = np.random.default_rng(11)
    sightings = []
    for T in _views(0.25, roll_deg=2.0):
        own = TableCorrection(rng.normal(0.0, 0.0005, 3), rng.normal(0.0, 0.0004, 3), 0.0, 0)
        T_true = T @ own.transform()
        world = rays @ T_true[:3, :3].T
        down = world[:, 2] < -0.05
        ranges = T_true[2, 3] / -world[down, 2]
        ranges += (camera.sigma0_m + camera.k_per_m * ranges**2) * rng.standard_normal(ranges.size)
        sightings.append(Sighting(T, (ranges[:, None] * rays[down]) @ T[:3, :3].T + T[:3, 3]))
    perception = _session(len(sightings), np.zeros((0, 3))).perception
    perception.extent.add(compute_roi(np.array([[0.41, -0.04, 0.015], [0.49, 0.04, 0.03]])))
    common_only = table_correction(perception, sightings, camera)  # type: ignore[arg-type]
    per_capture = table_correction(perception, sightings,  # type: ignore[arg-type]
                                   replace(camera, capture_pose_m=0.0004, capture_pose_rad=0.0005))
    assert per_capture.n_table_points > 10000
    assert np.abs(common_only.translation_m).max() > 3.0 * camera.pose_m
    assert np.abs(per_capture.translation_m).max() < camera.pose_m
    assert np.abs(per_capture.rotation_vector).max() < camera.pose_rad
