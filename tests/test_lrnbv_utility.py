"""LR-NBV utility (paper section 3.3, eqs. 2-6) on hand-computed cases."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from cell.config.load import load_config
from cell.perception.occupancy import OccupancyMap, OccupancyParams, logit
from cell.planning.lrnbv.sensor import sensor_rays
from cell.planning.lrnbv.utility import UtilityField, VisitedGrid, Weights, evaluate
from drivers.clock import SimClock
from drivers.depth.base import SensorModel
from drivers.errors import PlanningError
from drivers.factory import SimWorld, make_sensor
from drivers.sim.objects import load_object
from drivers.sim.scene import SimScene
from drivers.transforms import look_at
from tests.conftest import FRANKA, UR5E

RES = 0.01
VOXEL = RES**3
# Sensor z (the optical axis) along base +x: columns are the sensor's x, y, z axes in the base frame.
R_PLUS_X = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
AXIS_RAY = np.array([[0.0, 0.0, 1.0]])
# On y = z = 0.055 a ray along +x samples x = -0.495 + 0.01 k: k = 50..59 fall in the box [0, 0.1)^3,
# one sample in each of the ten voxels of the row.
ORIGIN = np.array([[-0.495, 0.055, 0.055]])


def _map() -> OccupancyMap:
    return OccupancyMap(OccupancyParams(resolution_m=RES))


def _field(occupancy: OccupancyMap, objects: np.ndarray, r_d: float = 0.015) -> UtilityField:
    return UtilityField(occupancy, objects, np.zeros(3), np.full(3, 0.1), resolution=RES,
                        density_radius_m=r_d)


def test_unknown_row_without_object() -> None:
    f = _field(_map(), np.zeros((0, 3)))
    g_e, g_d = f.ray_gains(ORIGIN, R_PLUS_X[None], AXIS_RAY, ray_length_m=1.0)
    assert g_e[0] == pytest.approx(10 * VOXEL)  # 10 unknown voxels, weight 1 each
    assert g_d[0] == pytest.approx(10.0)  # rho = 0 everywhere


def test_occlusion_and_density() -> None:
    # One object point in the 4th voxel (x index 3): samples 0..3 are valid (eq. 2, up to t*).
    f = _field(_map(), np.array([[0.035, 0.055, 0.055]]))
    g_e, g_d = f.ray_gains(ORIGIN, R_PLUS_X[None], AXIS_RAY, ray_length_m=1.0)
    assert g_e[0] == pytest.approx(4 * VOXEL)
    # rho at x = 0.005, 0.015, 0.025, 0.035 within r_d = 0.015 of x = 0.035: 0, 0, 1, 1.
    assert g_d[0] == pytest.approx(1.0 + 1.0 + 0.5 + 0.5)


def test_ray_too_short_or_looking_away() -> None:
    f = _field(_map(), np.zeros((0, 3)))
    # A 0.5 m ray reaches k <= 50: one sample in the box.
    g_e, g_d = f.ray_gains(ORIGIN, R_PLUS_X[None], AXIS_RAY, ray_length_m=0.5)
    assert g_d[0] == pytest.approx(1.0)
    away = R_PLUS_X @ np.diag([-1.0, 1.0, -1.0])  # optical axis along -x
    g_e, g_d = f.ray_gains(ORIGIN, away[None], AXIS_RAY, ray_length_m=1.0)
    assert g_e[0] == 0.0 and g_d[0] == 0.0


def test_exploration_weight_is_the_voxel_entropy() -> None:
    occupancy = _map()
    p = 0.97
    occupancy.set_logodds(np.array([[2, 5, 5]]), np.array([logit(p)]))  # voxel x index 2 of the row
    f = _field(occupancy, np.zeros((0, 3)))
    g_e, _ = f.ray_gains(ORIGIN, R_PLUS_X[None], AXIS_RAY, ray_length_m=1.0)
    h = -(p * math.log(p) + (1 - p) * math.log(1 - p)) / math.log(2.0)
    assert g_e[0] == pytest.approx((9 + h) * VOXEL, rel=1e-5)


def test_quality_visited_and_weights() -> None:
    f = _field(_map(), np.array([[0.05, 0.05, 0.05], [0.05, 0.05, 0.07]]))  # centre (0.05, 0.05, 0.06)
    origins = np.array([[0.05, 0.05, 1.06], [0.05, 0.05, 0.36]])
    np.testing.assert_allclose(f.quality_gain(origins), [0.5, 1.0 / 1.3])
    visited = VisitedGrid(0.18)
    visited.mark(np.array([0.1, 0.1, 0.4]))  # cell (0, 0, 2): 0.36 m is in it, 1.06 m is not
    rays = AXIS_RAY
    rot = np.repeat(R_PLUS_X[None], 2, axis=0)
    g = evaluate(f, visited, origins, rot, rays, 1.0)
    np.testing.assert_array_equal(g.g_v, [0.0, -1.0])
    u = Weights(w_e=500.0, w_d=0.05, w_q=0.08, w_v=500.0).utility(g)
    np.testing.assert_allclose(u, 500 * g.g_e + 0.05 * g.g_d + 0.08 * g.g_q + 500 * g.g_v)


def _sensor_model(cell: Path) -> SensorModel:
    """The viewing geometry of the cell's (simulated) sensor, as a session reports it."""
    world = SimWorld(clock=SimClock(), rng=np.random.default_rng(0),
                     scene=SimScene(load_object("cube"), np.eye(4)))
    return make_sensor(load_config(cell).sensor, world, lambda: np.eye(4)).model


def test_tof_rays_see_the_box_from_a_look_at_pose() -> None:
    grid = sensor_rays(_sensor_model(UR5E), 16)
    assert grid.shape == (8, 8, 3)
    rays = grid.reshape(-1, 3)
    assert rays[7, 0] > 0.0 and rays[56, 1] > 0.0  # row-major from the top-left: x right, y down
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0)
    half = math.tan(math.radians(22.5) * 7 / 8)  # outermost zone centre, 45 deg over 8 zones
    assert np.max(rays[:, 0] / rays[:, 2]) == pytest.approx(half, rel=1e-6)
    f = _field(_map(), np.array([[0.05, 0.05, 0.05]]))
    towards = look_at(np.array([0.05, -0.3, 0.3]), np.array([0.05, 0.05, 0.05]))
    away = look_at(np.array([0.05, -0.3, 0.3]), np.array([0.05, -0.6, 0.5]))
    g_e, g_d = f.ray_gains(np.array([towards[:3, 3], away[:3, 3]]),
                           np.array([towards[:3, :3], away[:3, :3]]), rays, 1.0)
    assert g_e[0] > 0.0 and g_d[0] > 0.0
    assert g_e[1] == 0.0 and g_d[1] == 0.0


def test_rgbd_rays_thinned_over_the_image() -> None:
    model = _sensor_model(FRANKA)
    grid = sensor_rays(model, 16)
    assert grid.shape == (12, 16, 3)
    rays = grid.reshape(-1, 3)
    # cell centres across the field of view: inside it, symmetric about the optical axis, half a cell in
    tan_x = math.tan(math.radians(model.fov_x_deg) / 2.0)
    assert np.max(rays[:, 0] / rays[:, 2]) == pytest.approx(tan_x * 15 / 16, rel=1e-12)
    np.testing.assert_allclose(grid[:, ::-1, 0], -grid[:, :, 0], atol=1e-15)
    np.testing.assert_allclose(grid[::-1, :, 1], -grid[:, :, 1], atol=1e-15)
    with pytest.raises(PlanningError, match="no ray model"):
        sensor_rays(dataclasses.replace(model, kind="lidar"), 16)


def test_chunks_give_the_same_gains() -> None:
    f = _field(_map(), np.array([[0.035, 0.055, 0.055], [0.06, 0.02, 0.01]]))
    rng = np.random.default_rng(0)
    eyes = rng.uniform([-0.3, -0.3, 0.2], [0.4, 0.4, 0.5], size=(40, 3))
    poses = [look_at(e, np.array([0.05, 0.05, 0.05])) for e in eyes]
    rays = sensor_rays(_sensor_model(UR5E), 16).reshape(-1, 3)
    rot = np.array([T[:3, :3] for T in poses])
    together = f.ray_gains(eyes, rot, rays, 1.0)
    one_by_one = np.array([f.ray_gains(eyes[i:i + 1], rot[i:i + 1], rays, 1.0) for i in range(40)])[:, :, 0]
    np.testing.assert_allclose(together[0], one_by_one[:, 0])
    np.testing.assert_allclose(together[1], one_by_one[:, 1])


def test_a_voxel_seen_often_and_still_ambiguous_stops_drawing_views() -> None:
    """A voxel of the row hit once and carved twice in turn, 39 times, stays near p = 0.5 (a hit's log-odds
    about twice a miss's), as does an unknown one; the paper's weight counts it almost fully, the
    observation-aware one hardly."""
    occupancy = _map()
    origin = np.array([-0.2, 0.055, 0.055])
    for k in range(39):
        end = np.array([[0.025, 0.055, 0.055]]) if k % 3 == 0 else np.array([[0.045, 0.055, 0.055]])
        occupancy.integrate(origin, end)
    hits, misses = occupancy.observation_counts(np.array([[0.025, 0.055, 0.055]]))
    assert hits[0] == 13 and misses[0] == 26
    assert occupancy.entropy(np.array([[0.025, 0.055, 0.055]]))[0] > 0.6
    paper = _field(occupancy, np.zeros((0, 3)))
    aware = UtilityField(occupancy, np.zeros((0, 3)), np.zeros(3), np.full(3, 0.1), resolution=RES,
                         density_radius_m=0.015, observation_aware=True)
    assert paper.W[2, 5, 5] > 0.8 * VOXEL
    assert aware.W[2, 5, 5] < 0.1 * VOXEL  # about 1 / (2 n) over ln 2 - 1/2, n = 39
    # Unknown voxels weigh the same in both.
    assert aware.W[9, 5, 5] == paper.W[9, 5, 5] == pytest.approx(VOXEL)
