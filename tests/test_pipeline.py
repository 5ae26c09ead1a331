"""The per-frame pipeline: one frame through every stage, and the threaded runner of real mode."""

from __future__ import annotations

import numpy as np
import pytest

from cell.config import load_config
from cell.perception.pipeline import AsyncPerception, PerceptionPipeline
from cell.perception.segmentation import compute_roi
from drivers.clock import SimClock
from drivers.depth.sim_rgbd import SimRGBD
from drivers.factory import SimWorld, make_sensor
from drivers.sim.objects import load_object
from drivers.sim.scene import SimScene
from drivers.transforms import look_at, make_T

from .conftest import CONFIG_DIR, wait_for


@pytest.fixture
def rig():
    cfg = load_config(CONFIG_DIR / "sim-franka-rgbd.yaml")
    scene = SimScene(load_object("cube"), make_T(np.eye(3), np.array([0.45, 0.0, 0.0])))
    pose = {"T": look_at(np.array([0.25, -0.1, 0.2]), np.array([0.45, 0.0, 0.05]))}
    camera = SimRGBD(cfg.sensor, scene, lambda: pose["T"], SimClock(), np.random.default_rng(0))
    camera.connect()
    pipeline = PerceptionPipeline(cfg.perception, table_z_m=0.0, range_max_m=cfg.sensor.range_max_m,
                                  rng=np.random.default_rng(1))
    return camera, pipeline, pose["T"]


def test_one_frame_through_every_stage(rig):
    camera, pipeline, T = rig
    update = pipeline.process(camera.capture(), T)
    assert update.registration.reason == "no target yet"
    np.testing.assert_array_equal(update.T_base_sensor, T)
    assert 1000 < pipeline.cloud.points.shape[0] <= update.points_base.shape[0]
    assert pipeline.map.occupied_centers().shape[0] > 100
    assert update.roi is not None
    np.testing.assert_allclose(update.roi.centroid[:2], [0.45, 0.0], atol=0.03)
    assert 0.0 < update.h_roi < np.log(2)
    # The object was once seen 2 cm taller: H_ROI averages over the box of every ROI so far.
    taller = np.vstack([update.object_points, update.roi.aabb_max + np.array([0.0, 0.0, 0.02])])
    pipeline.extent.add(compute_roi(taller, table_z=0.0))
    second = pipeline.process(camera.capture(), T)
    assert second.registration.accepted and second.registration.correction_m < 0.002
    assert second.roi.aabb_max[2] < update.roi.aabb_max[2] + 0.01
    assert pipeline.extent.max_m[2] == pytest.approx(update.roi.aabb_max[2] + 0.02)
    assert second.h_roi == pipeline.map.mean_entropy_in_box(pipeline.extent.min_m, pipeline.extent.max_m)
    assert second.h_roi != pipeline.map.mean_entropy_in_box(second.roi.aabb_min, second.roi.aabb_max)


def test_h_roi_is_in_the_pipelines_form(rig):
    camera, _, T = rig
    cfg = load_config(CONFIG_DIR / "sim-franka-rgbd.yaml")
    pipeline = PerceptionPipeline(cfg.perception, table_z_m=0.0, range_max_m=cfg.sensor.range_max_m,
                                  rng=np.random.default_rng(1), h_roi_entropy="observation_aware")
    pipeline.process(camera.capture(), T)
    update = pipeline.process(camera.capture(), T)
    box = (pipeline.extent.min_m, pipeline.extent.max_m)
    assert update.h_roi == pipeline.map.mean_entropy_in_box(*box, observation_aware=True)
    assert update.h_roi < pipeline.map.mean_entropy_in_box(*box)


def test_async_perception_processes_in_its_own_thread(rig):
    camera, pipeline, T = rig
    runner = AsyncPerception(pipeline)
    runner.start()
    try:
        assert runner.latest() is None
        runner.submit(camera.capture(), T)
        assert wait_for(lambda: runner.latest() is not None)
        assert runner.latest().roi is not None
    finally:
        runner.stop()


def test_async_perception_reraises_worker_errors(rig):
    camera, pipeline, _ = rig
    runner = AsyncPerception(pipeline)
    runner.start()
    try:
        runner.submit(camera.capture(), np.full((4, 4), np.nan))

        def raised():
            try:
                runner.latest()
            except ValueError as exc:
                return "not a finite 4x4 pose" in str(exc)
            return False

        assert wait_for(raised)
    finally:
        runner.stop()


def test_tof_box_top_is_not_taken_for_the_table():
    """8x8 ToF frames of the horizontal box from above: its top outnumbers the table in the map, but
    RANSAC only looks near the configured table height, so the ROI is the box (issue 3)."""
    cfg = load_config(CONFIG_DIR / "sim-ur5e-tof.yaml")
    station = np.array([*cfg.station.xy_m, cfg.station.table_z_m])
    scene = SimScene(load_object("horizontal_box"), make_T(np.eye(3), station),
                     table_center_xy=cfg.sim.table_center_xy_m, table_size_xy=cfg.sim.table_size_m)
    pose = {"T": np.eye(4)}
    world = SimWorld(clock=SimClock(), rng=np.random.default_rng(0), scene=scene)
    sensor = make_sensor(cfg.sensor, world, lambda: pose["T"])
    pipeline = PerceptionPipeline(cfg.perception, table_z_m=cfg.station.table_z_m,
                                  range_max_m=sensor.model.range_max_m, rng=np.random.default_rng(1))
    top = station + np.array([0.0, 0.0, 0.1])
    with sensor:
        for dx, dy in ((0.0, 0.0), (0.03, 0.0), (0.0, 0.03), (-0.03, 0.0), (0.0, -0.03)):
            pose["T"] = look_at(top + np.array([dx, dy, 0.25]), top + np.array([0.0, 0.0, -0.1]))
            update = pipeline.process(sensor.capture(), pose["T"])
    assert update.roi is not None
    assert update.roi.aabb_max[2] == pytest.approx(top[2], abs=0.02)
    assert update.roi.z_min == pytest.approx(station[2], abs=1e-9)


def test_tof_zones_with_no_target_carve_free_space_no_further_than_the_crop_box():
    """8x8 ToF frame over the table's far edge into open space: no zone has a target. Their rays carve the
    map free up to the crop box's far face (1 m ahead), not on to the sensor's 4 m range, whose blocks
    no query reads (1.0-1.6 GB of peak memory on a simulated scan)."""
    cfg = load_config(CONFIG_DIR / "sim-ur5e-tof.yaml")
    scene = SimScene(load_object("cube"), make_T(np.eye(3), np.array([*cfg.station.xy_m, 0.0])),
                     table_center_xy=cfg.sim.table_center_xy_m, table_size_xy=cfg.sim.table_size_m)
    T = look_at(np.array([0.45, 0.0, 0.3]), np.array([2.0, 0.0, 0.3]))
    world = SimWorld(clock=SimClock(), rng=np.random.default_rng(0), scene=scene)
    sensor = make_sensor(cfg.sensor, world, lambda: T)
    pipeline = PerceptionPipeline(cfg.perception, table_z_m=0.0, range_max_m=sensor.model.range_max_m,
                                  rng=np.random.default_rng(1))
    with sensor:
        frame = sensor.capture()
    assert frame.zones is not None and np.all(frame.zones.nb_targets == 0)
    update = pipeline.process(frame, T)
    far = (update.free_ends_base - T[:3, 3]) @ T[:3, :3]
    assert far.shape == (64, 3)
    np.testing.assert_allclose(far[:, 2], cfg.perception.crop_box.z_m[1])
    keys, _ = pipeline.map.known_keys()
    depth = (pipeline.map.centers_of(keys) - T[:3, 3]) @ T[:3, 2]
    assert depth.max() <= cfg.perception.crop_box.z_m[1] + cfg.perception.occupancy.resolution_m
    assert depth.max() >= cfg.perception.crop_box.z_m[1] - cfg.perception.occupancy.resolution_m
    assert pipeline.map.occupied_keys().shape[0] == 0
