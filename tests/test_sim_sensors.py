"""Simulated depth sensors (sim-rgbd, sim-tof) rendered from a SimScene."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.clock import SimClock
from drivers.depth.config import SimRGBDConfig, SimToFConfig
from drivers.depth.sim_rgbd import SimRGBD
from drivers.depth.sim_tof import STATUS_MERGED, STATUS_NO_TARGET, STATUS_VALID, SimToF
from drivers.errors import DriverError
from drivers.sim.objects import load_object
from drivers.sim.scene import SimScene
from drivers.transforms import make_T

# sensor looking straight down: z_sensor = -z_base, x_sensor = +x_base, y_sensor = -y_base
R_DOWN = np.column_stack([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def pose_down(x: float, y: float, h: float) -> np.ndarray:
    return make_T(R_DOWN, np.array([x, y, h]))


def rgbd_config(sigma0: float = 0.0, k: float = 0.0, *, w: int = 64, h: int = 48, f: float = 60.0,
                grazing_deg: float = 80.0, range_max: float = 3.0) -> SimRGBDConfig:
    return SimRGBDConfig(type="sim-rgbd", width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2, cy=(h - 1) / 2,
                         range_min_m=0.05, range_max_m=range_max,
                         noise={"sigma0_m": sigma0, "k_per_m": k}, grazing_deg=grazing_deg)


def tof_config(sigma0: float = 0.0, **kw: object) -> SimToFConfig:
    return SimToFConfig(type="sim-tof", noise={"sigma0_m": sigma0, "k_per_m": 0.0}, **kw)


@pytest.fixture(scope="module")
def cube_scene() -> SimScene:
    """A 10 cm cube centred at (0.5, 0, 0) on a 3 x 3 m table at z = 0 (x in [-1, 2], y in [-1.5, 1.5])."""
    return SimScene(load_object("cube"), make_T(np.eye(3), np.array([0.5, 0.0, 0.0])),
                    table_center_xy=(0.5, 0.0), table_size_xy=(3.0, 3.0))


def rgbd(scene: SimScene, cfg: SimRGBDConfig, T: np.ndarray, seed: int = 0,
         clock: SimClock | None = None) -> SimRGBD:
    s = SimRGBD(cfg, scene, lambda: T, clock or SimClock(), np.random.default_rng(seed))
    s.connect()
    return s


def tof(scene: SimScene, cfg: SimToFConfig, T: np.ndarray, seed: int = 0) -> SimToF:
    s = SimToF(cfg, scene, lambda: T, SimClock(), np.random.default_rng(seed))
    s.connect()
    return s


# --- sim-rgbd --------------------------------------------------------------------------------------------
def test_rgbd_empty_table_straight_down(cube_scene: SimScene) -> None:
    h = 0.6
    cfg = rgbd_config()
    frame = rgbd(cube_scene, cfg, pose_down(0.0, -0.5, h)).capture()
    assert frame.depth is not None and frame.depth.dtype == np.float32
    assert frame.depth.shape == (48, 64)
    np.testing.assert_allclose(frame.depth, h, atol=1e-5)
    assert frame.points.shape == (48 * 64, 3) and frame.points.dtype == np.float64
    np.testing.assert_allclose(frame.points[:, 2], h, atol=1e-5)
    # back-projection with pixel centres at integer (u, v): x = (u - cx) z / fx
    v, u = np.divmod(np.arange(48 * 64), 64)
    np.testing.assert_allclose(frame.points[:, 0], (u - cfg.cx) * h / cfg.fx, atol=1e-5)
    np.testing.assert_allclose(frame.points[:, 1], (v - cfg.cy) * h / cfg.fy, atol=1e-5)


def test_rgbd_sees_the_cube_top_at_the_right_depth(cube_scene: SimScene) -> None:
    h = 0.6
    frame = rgbd(cube_scene, rgbd_config(), pose_down(0.5, 0.0, h)).capture()
    d = frame.depth
    assert d is not None
    assert d[24, 32] == pytest.approx(h - 0.1, abs=1e-5)  # centre: cube top
    assert d[0, 0] == pytest.approx(h, abs=1e-5)  # corner: table
    on_top = np.isclose(d, h - 0.1, atol=1e-4)
    # the top spans 0.1 m at 0.5 m depth: 12 x 12 pixels at f = 60
    assert 100 <= on_top.sum() <= 170
    rows, cols = np.nonzero(on_top)
    assert abs(rows.mean() - 23.5) < 1.0 and abs(cols.mean() - 31.5) < 1.0


def test_rgbd_range_limits(cube_scene: SimScene) -> None:
    frame = rgbd(cube_scene, rgbd_config(range_max=0.55), pose_down(0.5, 0.0, 0.6)).capture()
    d = frame.depth
    assert d is not None
    assert d[0, 0] == 0.0  # table at 0.6 beyond range
    assert d[24, 32] == pytest.approx(0.5, abs=1e-5)
    assert len(frame.points) == int((d > 0).sum())


def test_rgbd_noise_grows_with_distance(cube_scene: SimScene) -> None:
    sigma0, k = 0.001, 0.01
    cfg = rgbd_config(sigma0, k, w=120, h=100, f=300.0)
    stds = {}
    for h in (0.3, 1.2):
        d = rgbd(cube_scene, cfg, pose_down(0.0, -0.5, h), seed=5).capture().depth
        assert d is not None and np.all(d > 0)
        stds[h] = float(np.std(d.astype(np.float64) - h))
        assert stds[h] == pytest.approx(sigma0 + k * h**2, rel=0.05)
    assert stds[1.2] > 3.0 * stds[0.3]


def test_rgbd_grazing_dropouts() -> None:
    # low camera tilted towards the horizon: incidence on the table sweeps ~50..~88 deg;
    # the cube is behind the camera, out of view
    scene = SimScene(load_object("cube"), make_T(np.eye(3), np.array([-0.8, 0.0, 0.0])),
                     table_center_xy=(0.5, 0.0), table_size_xy=(3.0, 3.0))
    g = 80.0
    tilt = np.deg2rad(70.0)  # optical axis 70 deg from straight down
    z = np.array([np.sin(tilt), 0.0, -np.cos(tilt)])
    x = np.array([0.0, -1.0, 0.0])
    T = make_T(np.column_stack([x, np.cross(z, x), z]), np.array([-0.05, 0.0, 0.05]))
    cfg = rgbd_config(w=160, h=120, f=100.0, grazing_deg=g)
    sensor = rgbd(scene, cfg, T, seed=3)
    d = sensor.capture().depth
    assert d is not None
    rays_base = sensor.rays_sensor @ T[:3, :3].T
    down = rays_base[:, 2] < -1e-6
    inc = np.full(len(rays_base), np.nan)
    inc[down] = np.degrees(np.arccos(-rays_base[down, 2]))  # angle to the table normal
    t = np.where(down, 0.05 / np.maximum(-rays_base[:, 2], 1e-9), np.inf)
    xy = np.array([-0.05, 0.0]) + t[:, None] * rays_base[:, :2]
    on_table = down & (np.abs(xy[:, 0] - 0.5) < 1.45) & (np.abs(xy[:, 1]) < 1.45)
    valid = d.reshape(-1) > 0
    assert not np.any(valid & on_table & (inc > g + 0.5))  # beyond grazing: always dropped
    easy = on_table & (inc < g - 15.5)
    assert easy.sum() > 100 and valid[easy].mean() > 0.97
    band = on_table & (inc > g - 15 + 0.5) & (inc < g - 0.5)
    expected_drop = np.mean((inc[band] - (g - 15)) / 15)
    assert band.sum() > 200
    assert 1.0 - valid[band].mean() == pytest.approx(expected_drop, abs=0.06)


def test_rgbd_same_seed_identical_different_seed_differs(cube_scene: SimScene) -> None:
    cfg = rgbd_config(0.002, 0.01)
    T = pose_down(0.48, 0.02, 0.5)
    sa, sb, sc = (rgbd(cube_scene, cfg, T, seed=seed) for seed in (11, 11, 12))
    for _ in range(2):  # the whole frame sequence, not only the first frame
        a, b, c = sa.capture(), sb.capture(), sc.capture()
        assert a.depth is not None and b.depth is not None and c.depth is not None
        assert a.depth.tobytes() == b.depth.tobytes()
        assert a.points.tobytes() == b.points.tobytes()
        assert a.depth.tobytes() != c.depth.tobytes()


def test_rgbd_seq_timestamp_connection_and_model(cube_scene: SimScene) -> None:
    clock = SimClock()
    cfg = rgbd_config()
    sensor = SimRGBD(cfg, cube_scene, lambda: pose_down(0.5, 0.0, 0.5), clock, np.random.default_rng(0))
    assert not sensor.is_connected
    with pytest.raises(DriverError) as exc:
        sensor.capture()
    assert exc.value.device == "sim-rgbd"
    with sensor:
        f0 = sensor.capture()
        clock.sleep(0.25)
        f1 = sensor.capture()
    assert not sensor.is_connected
    assert (f0.seq, f1.seq) == (0, 1)
    assert (f0.timestamp, f1.timestamp) == (0.0, 0.25)
    m = sensor.model
    assert (m.width, m.height) == (64, 48)
    assert m.fov_x_deg == pytest.approx(2 * np.degrees(np.arctan(32 / 60)))
    assert m.fov_y_deg == pytest.approx(2 * np.degrees(np.arctan(24 / 60)))
    assert (m.range_min_m, m.range_max_m) == (0.05, 3.0)


def test_sim_sensors_errors_name_their_device(cube_scene: SimScene) -> None:
    # the job session names sensor.device in its own errors (a stale frame in a dry run)
    rng = np.random.default_rng(0)
    for sensor in (SimRGBD(rgbd_config(), cube_scene, lambda: np.eye(4), SimClock(), rng),
                   SimToF(tof_config(), cube_scene, lambda: np.eye(4), SimClock(), rng)):
        with pytest.raises(DriverError) as exc:
            sensor.capture()
        assert exc.value.device == sensor.device


def test_rgbd_bad_pose_raises_driver_error(cube_scene: SimScene) -> None:
    sensor = SimRGBD(rgbd_config(), cube_scene, lambda: np.eye(3), SimClock(), np.random.default_rng(0))
    sensor.connect()
    with pytest.raises(DriverError):
        sensor.capture()


# --- sim-tof ---------------------------------------------------------------------------------------------
def test_tof_zone_order_and_directions(cube_scene: SimScene) -> None:
    sensor = tof(cube_scene, tof_config(), pose_down(0.0, -0.5, 0.5))
    d = sensor.directions
    assert d.shape == (64, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    assert d[0, 0] < 0 and d[0, 1] < 0  # top-left
    assert d[7, 0] > 0 and d[7, 1] < 0  # top-right
    assert d[56, 0] < 0 and d[56, 1] > 0  # bottom-left
    # the outermost zone centres sit 7/16 of the FOV off-axis
    assert np.degrees(np.arctan(-d[0, 0] / d[0, 2])) == pytest.approx(45.0 * 7 / 16)
    m = sensor.model
    assert (m.kind, m.width, m.height, m.fov_x_deg, m.fov_y_deg) == ("tof", 8, 8, 45.0, 45.0)


def test_tof_flat_table_gives_64_valid_zones(cube_scene: SimScene) -> None:
    h = 0.5
    frame = tof(cube_scene, tof_config(), pose_down(0.0, -0.5, h)).capture()
    z = frame.zones
    assert z is not None
    assert np.all(z.status == STATUS_VALID)
    assert np.all(z.nb_targets == 1)
    assert frame.points.shape == (64, 3)
    np.testing.assert_allclose(frame.points[:, 2], h, atol=0.003)
    np.testing.assert_allclose(z.distance_m, h / z.directions[:, 2], atol=0.003)
    np.testing.assert_allclose(z.reflectance_pct, 30.0)
    assert np.all(z.sigma_m >= 0.0) and np.all(z.sigma_m < 0.01)


def test_tof_noise_and_seed(cube_scene: SimScene) -> None:
    T = pose_down(0.0, -0.5, 0.5)
    cfg = tof_config(0.005)
    a = tof(cube_scene, cfg, T, seed=1).capture()
    b = tof(cube_scene, cfg, T, seed=1).capture()
    c = tof(cube_scene, cfg, T, seed=2).capture()
    assert a.zones is not None and b.zones is not None and c.zones is not None
    assert a.zones.distance_m.tobytes() == b.zones.distance_m.tobytes()
    assert a.points.tobytes() == b.points.tobytes()
    assert a.zones.distance_m.tobytes() != c.zones.distance_m.tobytes()
    err = a.zones.distance_m - 0.5 / a.zones.directions[:, 2]
    assert 0.002 < np.std(err) < 0.009


def test_tof_nothing_in_range_gives_no_target(cube_scene: SimScene) -> None:
    up = make_T(np.column_stack([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
                np.array([0.5, 0.0, 1.0]))
    far = pose_down(0.0, -0.5, 5.0)  # table 5 m away, range_max 4 m
    for T in (up, far):
        frame = tof(cube_scene, tof_config(), T).capture()
        z = frame.zones
        assert z is not None
        assert np.all(z.status == STATUS_NO_TARGET)
        assert np.all(z.nb_targets == 0)
        assert np.all(np.isnan(z.distance_m)) and np.all(np.isnan(z.sigma_m))
        assert frame.points.shape == (0, 3)


def test_tof_zone_straddling_the_cube_edge_is_status_9(cube_scene: SimScene) -> None:
    # the cube's +x top edge (x = 0.55, 0.4 m below the sensor) on the centre of zone column 4
    x_cam = 0.55 - 0.4 * np.tan(np.deg2rad(45.0 / 16))
    frame = tof(cube_scene, tof_config(), pose_down(x_cam, 0.0, 0.5)).capture()
    z = frame.zones
    assert z is not None
    for row in (3, 4):
        edge = row * 8 + 4
        assert z.status[edge] == STATUS_MERGED
        assert z.nb_targets[edge] == 1
        assert z.sigma_m[edge] > 0.02  # within-zone spread of 0.4 / 0.5 m ranges
        top = row * 8 + 2  # fully on the cube top
        assert z.status[top] == STATUS_VALID
        assert z.distance_m[top] == pytest.approx(0.4 / z.directions[top, 2], abs=0.003)
        assert z.reflectance_pct[top] == pytest.approx(50.0)
    assert z.status[0] == STATUS_VALID  # table corner
    assert len(frame.points) == 64


def test_tof_min_hit_fraction(cube_scene: SimScene) -> None:
    # sensor above the table's +x edge (x = 2) at 0.3 m: the -x half of the zones sees the table
    frame = tof(cube_scene, tof_config(min_hit_fraction=0.6), pose_down(2.0, 0.0, 0.3)).capture()
    z = frame.zones
    assert z is not None
    cols = np.arange(64) % 8
    assert np.all(z.status[cols <= 2] != STATUS_NO_TARGET)  # table side (sensor -x = base -x)
    assert np.all(z.status[cols >= 5] == STATUS_NO_TARGET)  # beyond the edge
    assert len(frame.points) == int((z.nb_targets > 0).sum())


def test_tof_disconnected_raises(cube_scene: SimScene) -> None:
    sensor = SimToF(tof_config(), cube_scene, lambda: np.eye(4), SimClock(), np.random.default_rng(0))
    with pytest.raises(DriverError) as exc:
        sensor.capture()
    assert exc.value.device == "sim-tof"
