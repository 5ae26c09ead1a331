"""The secondary tasks of the visual-servoing strategies: VS-Local's gradient (eq. 4-6), VS-Global's goals
(eq. 10-11), Hybrid's switching, the H_ROI termination (eq. 12), and their config."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from cell.config import load_config
from cell.control.servo import DualTaskServo, exploration_speed_mps
from cell.perception.occupancy import OccupancyMap, binary_entropy
from cell.perception.pipeline import PerceptionPipeline
from cell.perception.segmentation import compute_roi
from cell.planning.base import Array
from cell.planning.registry import get_planner
from cell.planning.vs.config import ServoConfig
from cell.planning.vs.goals import GoalSeeker, VSGlobalPlanner, arc_views, sphere_views
from cell.planning.vs.hybrid import VSHybridPlanner
from cell.planning.vs.local import LocalGradient, VSLocalPlanner, orbited
from cell.planning.vs.objective import ray_grid
from cell.planning.vs.servo_scan import (
    Secondary,
    TelemetryRow,
    achieved_fraction,
    held_norm,
    objective_rays,
    start_views,
    translated,
    voxel_entropy,
)
from cell.planning.vs.telemetry import servo_figure, write_servo_outputs
from cell.safety.events import Refusal
from cell.safety.guard import TwistRefused
from drivers.clock import SimClock
from drivers.depth.sim_rgbd import SimRGBD
from drivers.errors import PlanningError
from drivers.sim.objects import load_object
from drivers.sim.scene import SimScene
from drivers.transforms import look_at, make_T

from .conftest import FRANKA, UR5E

CENTRE = np.array([0.45, 0.0, 0.06])
NO_ROWS = np.zeros((0, 6))  # an arm clear of its limits and of the edge of its reach (``limit_rows``)


class LinearObjective:
    """f(r) = f_at + a . (r_o - at): a constant gradient ``a`` in the base frame [nats/m], f_at at ``at``."""

    def __init__(self, a, at=(0.0, 0.0, 0.0), f_at=0.0):
        self.a = np.asarray(a, dtype=float)
        self.at = np.asarray(at, dtype=float)
        self.f_at = f_at

    def __call__(self, T):
        T = np.asarray(T)
        values = self.f_at + (T[..., :3, 3] - self.at) @ self.a
        return float(values) if T.ndim == 2 else values


class FakeSession:
    """Job time, barrier planes as a floor at ``floor_z`` for the camera origin, and an arm that reaches
    the camera origins at x >= ``reach_min_x`` [m]."""

    def __init__(self, floor_z: float = -np.inf, reach_min_x: float = -np.inf):
        self.t = 0.0
        self.floor_z = floor_z
        self.reach_min_x = reach_min_x
        self.pose = np.eye(4)
        self.rng = np.random.default_rng(0)
        self.messages: list[str] = []
        self.n_reach_queries = 0
        self.queried_goals: list[np.ndarray] = []

    def now(self):
        return self.t

    def log(self, message):
        self.messages.append(message)

    def sensor_pose_allowed(self, T):
        return T[2, 3] > self.floor_z

    def sensor_poses_allowed(self, T, from_here=False):
        return np.array([self.sensor_pose_allowed(v) for v in T], dtype=bool)

    def sensor_pose(self):
        return self.pose

    def sensor_path_reachable(self, T, min_singular_value=0.0):
        self.n_reach_queries += 1
        self.queried_goals.append(T[-1, :3, 3])
        return bool(np.all(T[:, 0, 3] >= self.reach_min_x))

    def feasible_sensor_velocity(self, v, activation_m):
        # A floor below the camera: no downward component when within activation_m of it.
        R = self.pose[:3, :3]
        v_base = R @ v
        if self.pose[2, 3] - self.floor_z < activation_m and v_base[2] < 0:
            v_base[2] = 0.0
        return R.T @ v_base


@pytest.fixture(scope="module")
def franka():
    return load_config(FRANKA)


def test_vs_planners_are_registered(franka):
    assert get_planner("vs-local") is VSLocalPlanner
    assert get_planner("vs-global") is VSGlobalPlanner
    assert get_planner("vs-hybrid") is VSHybridPlanner


def test_config_defaults_are_the_papers_values(franka):
    p = franka.planners
    assert (p.vs.servo.lambda_0, p.vs.servo.lambda_inf, p.vs.servo.lambda_0_slope) == (2.0, 0.4, 30.0)
    assert ServoConfig().lambda_g == 0.33 and p.vs.servo.e_converged_m == 0.005
    assert (p.vs.objective.rays_per_side, p.vs.objective.fov_deg) == (23, 30.0)
    assert (p.vs_local.delta_m, p.vs_local.g_max, p.vs_local.window) == (0.05, 1.0, 200)
    assert p.vs_local.converged_fraction == 0.8
    assert (p.vs_global.n_candidates, p.vs_global.slow_radius_m) == (5000, 0.10)
    assert (p.vs.h_roi_window, p.vs.h_roi_std) == (10, 0.001)
    assert franka.scan.standoff_m == 0.25


@pytest.mark.parametrize(("lambda_g", "speed_mps"), [(0.33, 0.019), (None, 0.05)])
def test_lambda_g_moves_the_camera_at_the_speed_its_docstring_gives(franka, lambda_g, speed_mps):
    """The paper's gain explores at 1.9 cm/s; the RGB-D cell's at delta per perception period."""
    if lambda_g is None:
        lambda_g = franka.planners.vs.servo.lambda_g
        speed_mps = franka.planners.vs_local.delta_m * franka.perception.rate_hz
    Z = franka.scan.standoff_m
    servo = DualTaskServo(standoff_m=Z, lambda_0=2.0, lambda_inf=0.4, lambda_0_slope=30.0, lambda_g=lambda_g,
                          e_converged_m=0.005)
    out = servo.step(np.array([0.0, 0.0, Z]), np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
    assert np.linalg.norm(out.v[:3]) == pytest.approx(speed_mps, rel=0.03)


def test_objective_rays_span_the_sensors_field_of_view(franka):
    np.testing.assert_allclose(objective_rays(franka), ray_grid(23, 30.0))
    tof = load_config(UR5E)  # the 8 x 8 ToF over 45 deg: 23 x 23 rays over its 45 deg
    rays = objective_rays(tof)
    np.testing.assert_allclose(rays, ray_grid(23, tof.sensor.fov_deg))
    assert tof.sensor.fov_deg == 45.0 and rays.shape == (529, 3)
    data = tof.model_dump()
    data["planners"]["vs"]["objective"]["use_sensor_fov"] = False
    np.testing.assert_allclose(objective_rays(type(tof).model_validate(data)), ray_grid(23, 30.0))


def test_start_views_look_at_the_station_from_the_standoff(franka):
    T, above = start_views(franka)
    target = np.array([*franka.station.xy_m, franka.planners.vs.start.target_height_m])
    assert np.linalg.norm(T[:3, 3] - target) == pytest.approx(franka.scan.standoff_m)
    np.testing.assert_allclose(T[:3, 2], (target - T[:3, 3]) / franka.scan.standoff_m, atol=1e-12)
    assert T[1, 3] < target[1] - 0.2  # sideways, from -y
    np.testing.assert_allclose(above[:3, 3], target + np.array([0.0, 0.0, franka.scan.standoff_m]))
    np.testing.assert_allclose(above[:3, 2], [0.0, 0.0, -1.0], atol=1e-12)


def test_sphere_views_match_look_at():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(20, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    views = sphere_views(CENTRE, 0.25, u)
    for T, d in zip(views, u, strict=True):
        np.testing.assert_allclose(T, look_at(CENTRE + 0.25 * d, CENTRE), atol=1e-12)


def test_local_gradient_is_the_relative_central_difference_in_the_camera_plane(franka):
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)  # camera x = base x, camera y = -base z
    session = FakeSession()
    session.pose = T
    local = LocalGradient(franka)
    p = franka.planners.vs_local
    f_r = 2.0  # nats at the camera
    a = np.array([1.0, 0.0, 2.0]) * 0.2 * f_r / p.alpha  # a gradient of norm < 1 after scaling
    sec = local(session, T, LinearObjective(a, T[:3, 3], f_r))
    expected = p.alpha * np.array([a[0], -a[2], 0.0]) / (f_r + p.f_eps_nats)
    np.testing.assert_allclose(sec.g[:3], expected, rtol=1e-9)
    assert sec.g_norm == pytest.approx(np.linalg.norm(expected)) and sec.f == pytest.approx(f_r)
    # The same gradient where f is ten times smaller is ten times steeper: clipped to unit length, its
    # norm before clipping is reported.
    steep = local(session, T, LinearObjective(a, T[:3, 3], f_r / 10))
    assert np.linalg.norm(steep.g) == pytest.approx(1.0)
    ratio = (f_r + p.f_eps_nats) / (f_r / 10 + p.f_eps_nats)
    assert steep.g_norm == pytest.approx(np.linalg.norm(expected) * ratio)


def test_orbited_views_turn_on_the_sphere_about_the_point_looked_at():
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)
    views, directions = orbited(T, 0.25, np.pi / 2)
    sides = (T[:3, 0], -T[:3, 0], T[:3, 1], -T[:3, 1])
    for view, side, direction in zip(views[:4], sides, directions[:4], strict=True):
        np.testing.assert_allclose(view[:3, 3], CENTRE + 0.25 * side, atol=1e-12)  # a quarter turn
        np.testing.assert_allclose(T[:3, :3] @ direction, side, atol=1e-12)
    diagonal = (T[:3, 0] + T[:3, 1]) / np.sqrt(2.0)
    np.testing.assert_allclose(views[4][:3, 3], CENTRE + 0.25 * diagonal, atol=1e-12)
    # round the circle of the camera's height: a quarter turn about +z from the -y side is the +x side
    np.testing.assert_allclose(views[-2][:3, 3], CENTRE + np.array([0.25, 0.0, 0.0]), atol=1e-12)
    np.testing.assert_allclose(views[-1][:3, 3], CENTRE - np.array([0.25, 0.0, 0.0]), atol=1e-12)
    np.testing.assert_allclose(directions[-2], [1.0, 0.0, 0.0], atol=1e-12)  # camera x is base x here
    for view in views:
        np.testing.assert_allclose(view[:3, 3] + 0.25 * view[:3, 2], CENTRE, atol=1e-12)  # still looks at it
        np.testing.assert_allclose(view[:3, :3].T @ view[:3, :3], np.eye(3), atol=1e-12)
    down = look_at(CENTRE + np.array([0.0, 0.0, 0.25]), CENTRE, np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(orbited(down, 0.25, 0.5)[1][-2:], 0.0)  # looking straight down: no such circle


def on_the_sides(f: list[float], n: int) -> Array:
    """f (n,) at the n views of the coarse arcs: ``f`` (4,) at each arc's +x, -x, +y and -y views (orbited's
    first four), 1.0 at its others."""
    per_arc = len(orbited(np.eye(4), 0.25, 0.1)[0])
    return np.tile(np.concatenate([f, np.ones(per_arc - 4)]), n // per_arc)


class DeadZoneObjective:
    """f(r) = f_at + max(0, (r_o - at) . e - dead_m): flat within ``dead_m`` [m] of ``at`` along unit
    ``e``, then rising at 1 nat/m: the surroundings of a view whose information the camera has used up."""

    def __init__(self, e, at, f_at, dead_m):
        self.e, self.at, self.f_at, self.dead_m = np.asarray(e, dtype=float), np.asarray(at), f_at, dead_m

    def __call__(self, T):
        T = np.asarray(T)
        values = self.f_at + np.maximum(0.0, (T[..., :3, 3] - self.at) @ self.e - self.dead_m)
        return float(values) if T.ndim == 2 else values


def test_local_gradient_looks_over_longer_arcs_where_f_is_flat_at_delta(franka):
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)  # camera x = base x
    session = FakeSession()
    session.pose = T
    flat_at_delta = DeadZoneObjective([1.0, 0.0, 0.0], T[:3, 3], 0.001, 0.07)  # rises 7 cm away along +x
    sec = LocalGradient(franka)(session, T, flat_at_delta)
    assert sec.g_norm > franka.planners.vs_local.g_max and sec.g[0] == pytest.approx(1.0)
    # Judged on what the camera can follow: with +x blocked (a joint limit) it slides along the limit
    # towards a diagonal view (+x+y or +x-y), and held in every direction the view has converged.
    held = LocalGradient(franka)(session, T, flat_at_delta, lambda v: np.array([min(v[0], 0.0), v[1], v[2]]))
    assert held.g[0] == 0.0 and abs(held.g[1]) == pytest.approx(1.0)
    assert LocalGradient(franka)(session, T, flat_at_delta, lambda v: np.zeros(3)).g_norm == 0.0
    # A longer arc's view beyond a barrier plane is none the camera can take: it offers what r does.
    below = DeadZoneObjective([0.0, 0.0, -1.0], T[:3, 3], 0.001, 0.07)  # rises 7 cm below the camera
    assert LocalGradient(franka)(session, T, below).g_norm > franka.planners.vs_local.g_max
    floored = FakeSession(floor_z=T[2, 3] - 0.06)  # delta's views above it, the longer arcs' below
    floored.pose = T
    assert LocalGradient(franka)(floored, T, below).g_norm == 0.0
    # The paper's single difference over delta sees nothing there and counts the view as converged, as
    # does Hybrid's local phase, whose global goals leave such a plateau.
    data = franka.model_dump()
    data["planners"]["vs_local"]["reach_deg"] = 0.0
    paper = type(franka).model_validate(data)
    assert LocalGradient(paper)(session, T, flat_at_delta).g_norm == 0.0
    assert VSHybridPlanner(franka).local(session, T, flat_at_delta).g_norm == 0.0


class StepObjective:
    """f(r) = f_at plus ``rise`` (nats) once r_o is more than ``beyond_m`` [m] from ``at`` along unit ``e``,
    for each (e, beyond_m, rise) of ``steps``: information lying some distance away on either side."""

    def __init__(self, at, f_at, steps):
        self.at, self.f_at, self.steps = np.asarray(at), f_at, steps

    def __call__(self, T):
        d = np.asarray(T)[..., :3, 3] - self.at
        values = self.f_at + sum(rise * ((d @ np.asarray(e)) > beyond) for e, beyond, rise in self.steps)
        return float(values) if np.asarray(T).ndim == 2 else values


def test_where_delta_is_flat_the_arc_view_whose_f_rises_most_per_metre_leads(franka):
    """A little information just beyond the shortest arc on one side and much more a little further on
    the other: the camera goes for the steeper rise, not the nearer one."""
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)  # camera x = base x
    session = FakeSession()
    session.pose = T
    steps = [([1.0, 0.0, 0.0], 0.09, 0.02), ([-1.0, 0.0, 0.0], 0.13, 0.2)]
    near_and_far = StepObjective(T[:3, 3], 0.001, steps)
    sec = LocalGradient(franka)(session, T, near_and_far)
    assert sec.g_norm > franka.planners.vs_local.g_max and sec.g[0] == pytest.approx(-1.0)
    # the near rise alone is steep enough to be followed
    near = StepObjective(T[:3, 3], 0.001, [([1.0, 0.0, 0.0], 0.09, 0.02)])
    assert LocalGradient(franka)(session, T, near).g[0] == pytest.approx(1.0)


def test_a_camera_crosses_used_up_views_at_the_scale_of_the_arc_that_leads_it(franka):
    """Flat at delta, the camera goes for the view an arc of k deltas away at k times the exploration
    speed (k deltas per perception period), up to the cell's TCP speed limits; the difference over delta
    keeps the exploration speed."""
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)  # camera x = base x
    session = FakeSession()
    session.pose = T
    two_deltas = StepObjective(T[:3, 3], 0.001, [([1.0, 0.0, 0.0], 0.09, 0.2)])  # first passed by 2 deltas
    sec = LocalGradient(franka)(session, T, two_deltas)
    assert sec.g[0] == pytest.approx(1.0) and sec.speed == pytest.approx(2.0)
    # beyond 24 cm along +x: first passed by the arc of 7 deltas (80 deg), crossed at the TCP limits
    seven_deltas = StepObjective(T[:3, 3], 0.001, [([1.0, 0.0, 0.0], 0.24, 0.5)])
    safety, Z = franka.safety, franka.scan.standoff_m
    fastest = min(safety.tcp_max_linear_mps, safety.tcp_max_angular_rps * Z)
    limit = fastest / exploration_speed_mps(franka.planners.vs.servo.lambda_g, Z)
    assert 2.0 < limit < 7.0
    far = LocalGradient(franka)(session, T, seven_deltas)
    assert far.g[0] == pytest.approx(1.0) and far.speed == pytest.approx(limit)
    steep = LinearObjective([1.0, 0.0, 0.0], T[:3, 3], 0.1)  # the difference over delta leads
    assert LocalGradient(franka)(session, T, steep).speed == 1.0


class InMarginSession(FakeSession):
    """A camera sliding along the floor plane inside its margin: a view at its height or above is within
    reach of a motion from here, none is as a pose judged on its own."""

    def sensor_poses_allowed(self, T, from_here=False):
        z = np.asarray(T)[:, 2, 3]
        return z >= self.pose[2, 3] - 1e-9 if from_here else z > self.pose[2, 3] + 0.01


def test_a_camera_in_a_planes_margin_counts_the_views_at_its_height(franka):
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)  # level: its x great circle is level too
    session = InMarginSession()
    session.pose = T
    beyond = StepObjective(T[:3, 3], 0.001, [([1.0, 0.0, 0.0], 0.09, 0.2)])
    sec = LocalGradient(franka)(session, T, beyond)
    assert sec.g[0] == pytest.approx(1.0) and sec.g_norm > franka.planners.vs_local.g_max


def test_a_camera_low_on_the_sphere_goes_round_at_its_height_where_great_circles_dip_under_the_table(franka):
    """The information lies round the object at the camera's height, 10 deg above the table: every great
    circle through the view but the one straight up dips under the floor before it gets there (the one
    straight up stays on the near side), the circle of the camera's height gets there."""
    elevation = np.deg2rad(10.0)
    T = look_at(CENTRE + 0.25 * np.array([0.0, -np.cos(elevation), np.sin(elevation)]), CENTRE)
    session = FakeSession(floor_z=T[2, 3] - 0.01)
    session.pose = T

    class RoundAtHeight:
        """f 0.001, and 0.2 at the views more than 15 cm further along +x at most 1 cm above the camera."""

        def __call__(self, poses):
            d = np.asarray(poses)[..., :3, 3] - T[:3, 3]
            return 0.001 + 0.2 * ((d[..., 0] > 0.15) & (d[..., 2] < 0.01))

    sec = LocalGradient(franka)(session, T, RoundAtHeight())
    assert sec.g_norm > franka.planners.vs_local.g_max
    np.testing.assert_allclose(sec.g[:3], [1.0, 0.0, 0.0], atol=1e-9)  # level, towards +x


def test_the_coarse_arcs_keep_the_side_they_led_to_while_it_still_offers_a_rise(franka):
    """A camera in a valley between two ridges, the views on both sides higher than its own: it keeps going
    to the side it chose while that side still rises by g_max, rather than turning whenever the other
    side's rise is a little larger (it went to and fro between them)."""

    class Valley:
        """Flat over delta; over the shortest arc, ``up`` towards camera +y and ``down`` towards -y."""

        def __init__(self, up: float, down: float) -> None:
            self.up, self.down = up, down

        def __call__(self, T):
            n = np.asarray(T).shape[0]
            out = np.full(n, 0.001)
            if n != 5:
                out[2], out[3] = self.up, self.down  # orbited's order: +x, -x, +y, -y
            return out

    session = FakeSession()
    session.pose = T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)
    local = LocalGradient(franka)
    assert local(session, T, Valley(0.02, 0.015)).g[1] == pytest.approx(1.0)
    kept = local(session, T, Valley(0.015, 0.02))
    assert kept.g_norm >= franka.planners.vs_local.g_max and kept.g[1] == pytest.approx(1.0)
    assert LocalGradient(franka)(session, T, Valley(0.015, 0.02)).g[1] == pytest.approx(-1.0)
    assert local(session, T, Valley(0.001, 0.02)).g[1] == pytest.approx(-1.0)  # +y has nothing left


def test_local_direction_slides_along_a_barrier(franka):
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)
    session = FakeSession(floor_z=T[2, 3] - 0.01)  # 1 cm above the floor, within the activation
    session.pose = T
    local = LocalGradient(franka)
    sec = local(session, T, LinearObjective([0.0, 0.0, -5.0], T[:3, 3], 1.0))
    np.testing.assert_allclose(sec.g, 0.0, atol=1e-12)  # straight down is all into the floor
    assert sec.g_norm == pytest.approx(0.0, abs=1e-12)


def _sweep(n: int, speed_mps: float = 0.05, rate_hz: float = 50.0) -> list[Array]:
    """Camera positions (3,) [m] of n servo evaluations moving straight along x."""
    return [np.array([0.4 + i * speed_mps / rate_hz, 0.0, 0.3]) for i in range(n)]


def test_local_convergence_needs_a_full_window_mostly_below_one(franka):
    local = LocalGradient(franka)
    moving = _sweep(240)
    for p in moving[:199]:
        local.record(0.5, p)
    assert not local.converged()  # 199 of 200
    local.record(0.5, moving[199])
    assert local.converged()
    for p in moving[200:]:  # 160 weak, 40 strong: exactly 80 %, not more
        local.record(3.0, p)
    assert not local.converged()
    local.reset()
    assert not local.converged()


def test_a_camera_going_to_and_fro_within_delta_judges_its_gradient_flat_there(franka):
    """||g|| above 1 over delta, but the camera has not left a ball of delta for a whole window: eq. 5-6
    cannot tell its views apart, so the difference counts as flat and the camera holds, unless a longer
    arc offers a way on."""

    class DeltaNoise:
        """f with a strong difference over delta around the camera; over longer arcs ``arc`` (4,)."""

        def __init__(self, arc: list[float]) -> None:
            self.arc = np.array(arc)

        def __call__(self, T):
            n = np.asarray(T).shape[0]
            return np.array([1.0, 1.5, 0.5, 1.0, 1.0]) if n == 5 else on_the_sides(self.arc, n)

    delta = franka.planners.vs_local.delta_m
    session = FakeSession(floor_z=0.0)
    session.pose = T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)
    flat, strong = DeltaNoise([1.0] * 4), DeltaNoise([1.5, 0.5, 1.0, 1.0])
    dither, sweep = LocalGradient(franka), LocalGradient(franka)
    for i, p in enumerate(_sweep(200)):
        to_and_fro = [0.4 + 0.4 * delta * np.sin(i / 7.0), 0.2 * delta * np.cos(i / 5.0), 0.3]
        dither.record(1.5, np.array(to_and_fro))
        sweep.record(1.5, p)  # 20 cm in the window
    assert dither.dithering() and not sweep.dithering()
    moving = sweep(session, T, flat)
    assert moving.g_norm > 1.0 and moving.g[0] > 0.0
    held = dither(session, T, flat)
    assert held.g_norm == 0.0 and not np.any(held.g)
    on = dither(session, T, strong)  # the first longer arc: 2 delta's
    assert on.g_norm >= 1.0 and on.g[0] > 0.0
    for _ in range(161):
        dither.record(held.g_norm, np.array([0.4, 0.0, 0.3]))
    assert dither.converged()


def test_a_camera_leaving_a_spot_it_went_to_and_fro_on_follows_the_arcs_for_their_length(franka):
    """Once a longer arc has offered the way off a spot gone to and fro on, a difference over delta that
    points back to the spot is not followed until the camera is that arc's length from the spot."""

    class BackToTheSpot:
        """The difference over delta points along -x, the longer arcs along +x."""

        def __call__(self, T):
            n = np.asarray(T).shape[0]
            return np.array([1.0, 0.5, 1.5, 1.0, 1.0]) if n == 5 else on_the_sides([1.5, 0.5, 1.0, 1.0], n)

    delta = franka.planners.vs_local.delta_m
    session = FakeSession(floor_z=0.0)
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)  # camera x = base x
    local = LocalGradient(franka)
    spot = T[:3, 3].copy()
    for i in range(200):
        to_and_fro = np.array([0.4 * delta * np.sin(i / 7.0), 0.0, 0.2 * delta * np.cos(i / 5.0)])
        local.record(1.5, spot + to_and_fro)
    leaving = local(session, T, BackToTheSpot())
    assert leaving.g[0] > 0.0  # the first arc's length, 2 delta's, away from the spot
    for i in range(1, 200):  # the camera moves on along +x at 5 cm/s
        local.record(leaving.g_norm, spot + np.array([i * 0.001, 0.0, 0.0]))
    on_the_way = T.copy()
    on_the_way[0, 3] += 1.9 * delta
    assert local(session, on_the_way, BackToTheSpot()).g[0] > 0.0
    arrived = T.copy()
    arrived[0, 3] += 2.1 * delta
    assert local(session, arrived, BackToTheSpot()).g[0] < 0.0  # delta leads again


def test_achieved_fraction_measures_what_the_arm_realized_along_the_command():
    v = np.array([0.02, 0.0, 0.0, 0.0, 0.1, 0.0])
    assert achieved_fraction(v, v) == 1.0
    assert achieved_fraction(v, 0.25 * v) == pytest.approx(0.25)
    assert achieved_fraction(v, np.zeros(6)) == 0.0  # held by a joint limit
    assert achieved_fraction(np.zeros(6), np.zeros(6)) == 1.0
    # turned by the arm's differential IK near a singularity: what counts is the part along the command
    turned = np.array([0.002, 0.0075, 0.0, 0.0, 0.0, 0.0])
    assert achieved_fraction(v, turned) == pytest.approx(0.1)
    assert achieved_fraction(v, -v) == 0.0


def test_a_crossing_slowed_to_the_exploration_speed_is_not_held():
    """||g|| counts as the arm could follow it against the exploration speed: a crossing at three times
    that speed which the guard's speed limits slow to it is still on its way, one slowed further is held
    in part."""
    v = np.array([0.15, 0.0, 0.0, 0.0, 0.6, 0.0])
    crossing = Secondary(np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0]), 2.0, 0.01, "local", 3.0)
    assert held_norm(crossing, v, v) == pytest.approx(2.0)
    assert held_norm(crossing, v, v / 3.0) == pytest.approx(2.0)
    assert held_norm(crossing, v, v / 6.0) == pytest.approx(1.0)
    exploring = Secondary(crossing.g, 2.0, 0.01, "local")
    assert held_norm(exploring, v, v / 3.0) == pytest.approx(2.0 / 3.0)


def test_the_secondary_speed_reaches_the_streamed_twist(franka):
    planner = VSLocalPlanner(franka)
    planner.servo.secondary_active = True
    s = np.array([0.0, 0.0, franka.scan.standoff_m])
    session = StreamSession()
    g = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)
    planner._command(session, T, s, Secondary(g, 1.0, 0.01, "local"))
    planner._command(session, T, s, Secondary(g, 3.0, 0.01, "local", 3.0))
    exploring, crossing = session.twists
    speed = exploration_speed_mps(franka.planners.vs.servo.lambda_g, franka.scan.standoff_m)
    assert np.linalg.norm(exploring[:3]) == pytest.approx(speed)
    np.testing.assert_allclose(crossing, 3.0 * exploring, atol=1e-12)


def test_goal_is_the_best_allowed_candidate_and_g_follows_eq_11(franka):
    seeker = GoalSeeker(franka)
    session = FakeSession(floor_z=0.1)
    objective = LinearObjective([-1.0, 0.0, 0.0])  # best views are at small x: behind the object
    seeker.sample(session, CENTRE, objective)
    goal = seeker.goal
    assert goal[2, 3] > 0.1 and np.linalg.norm(goal[:3, 3] - CENTRE) == pytest.approx(0.25)
    assert goal[0, 3] < CENTRE[0] - 0.2  # near the best point of the allowed cap
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)
    session.pose = T
    far = seeker(session, T, objective)
    assert np.linalg.norm(far.g[:3]) == pytest.approx(1.0) and far.g[2] == 0.0
    to_goal = T[:3, :3].T @ (goal[:3, 3] - T[:3, 3])
    assert far.g[:2] @ to_goal[:2] > 0.99 * np.linalg.norm(to_goal[:2])
    # Within 10 cm the magnitude decays linearly with the distance.
    near = translated(goal, np.array([[0.07, 0.0, 0.0]]))[0]
    session.pose = near
    assert np.linalg.norm(seeker(session, near, objective).g) == pytest.approx(0.7, rel=1e-6)
    assert not seeker.done(session, near)
    session.pose = arrived = translated(goal, np.array([[0.045, 0.0, 0.0]]))[0]
    assert seeker.done(session, arrived)  # within arrival_m (5 cm)


def test_no_goal_is_sampled_within_the_arrival_distance_of_the_camera(franka):
    """A camera at the best view of the sphere gets a goal ``arrival_m`` or more away, not one it has
    already reached (the best candidates lie around it)."""
    arrival = franka.planners.vs_global.arrival_m
    seeker = GoalSeeker(franka)
    session = FakeSession(floor_z=0.1)
    objective = LinearObjective([-1.0, 0.0, 0.0])
    seeker.sample(session, CENTRE, objective)
    session.pose = seeker.goal
    for _ in range(5):
        seeker.sample(session, CENTRE, objective)
        assert np.linalg.norm(seeker.goal[:3, 3] - session.pose[:3, 3]) >= arrival
        assert not seeker.done(session, session.pose)


def toward_goal(seeker: GoalSeeker, arc_m: float) -> np.ndarray:
    """The camera pose on the goal's sphere ``arc_m`` [m] from the goal along the great circle over the
    top, looking at the centre."""
    radius = seeker.radius_m
    g = (seeker.goal[:3, 3] - CENTRE) / radius
    over = np.array([0.0, 0.0, 1.0]) - g * g[2]
    over /= np.linalg.norm(over)
    angle = arc_m / radius
    return look_at(CENTRE + radius * (np.cos(angle) * g + np.sin(angle) * over), CENTRE)


def test_a_goal_the_camera_stops_approaching_is_given_up(franka):
    """Progress along the sphere of less than ``stall_progress_m`` (1 cm) within ``stall_time_s`` (3 s)
    gives the goal up; steady progress at the slow approach speed does not, however long it takes."""
    p = franka.planners.vs_global
    seeker = GoalSeeker(franka)
    session = FakeSession(floor_z=0.1)
    seeker.sample(session, CENTRE, LinearObjective([-1.0, 0.0, 0.0]))
    for k in range(400):  # 1.2 cm per 3 s towards the goal: 8 s at 50 Hz
        session.t = k * 0.02
        if seeker.done(session, toward_goal(seeker, 0.2 - 0.004 * session.t)):
            break
    assert session.t == pytest.approx(0.02 * 399) and not any("given up" in m for m in session.messages)
    held = toward_goal(seeker, 0.15)
    start = session.t
    while not seeker.done(session, held):
        session.t += 0.02
    assert session.t - start == pytest.approx(p.stall_time_s, abs=0.03)
    assert "goal 1 given up" in session.messages[-1] and "m away on the sphere" in session.messages[-1]


def test_progress_to_a_far_goal_is_measured_along_the_sphere(franka):
    """A camera orbiting at the exploration speed of eq. 1 (1.9 cm/s) towards a goal 175 deg away keeps
    it: along the sphere it gets 5.8 cm closer in its first 3 s, in straight line only 0.6 cm."""
    seeker = GoalSeeker(franka)
    session = FakeSession(floor_z=0.0)
    seeker.sample(session, CENTRE, LinearObjective([-1.0, 0.0, 0.0]))
    start_m = np.radians(175.0) * seeker.radius_m
    for k in range(250):  # 5 s at 50 Hz
        session.t = k * 0.02
        assert not seeker.done(session, toward_goal(seeker, start_m - 0.0194 * session.t))
    assert not any("given up" in m for m in session.messages)


def test_goal_is_the_best_candidate_the_arm_reaches(franka):
    """Best views at small x (behind the object), which the arm reaches only from x = 0.21 m on: the goal
    is the best one the arm servos to along the arc from the camera, found in descending f within
    ``reachability_checks``, one candidate checked per ``arrival_m``; with no reachable candidate among
    them, the best allowed is taken and the log says so."""
    objective = LinearObjective([-1.0, 0.0, 0.0])
    seeker = GoalSeeker(franka)
    session = FakeSession(floor_z=0.1, reach_min_x=0.21)
    session.pose = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)
    seeker.sample(session, CENTRE, objective)
    assert 0.21 <= seeker.goal[0, 3] < 0.215
    assert 1 < session.n_reach_queries <= franka.planners.vs_global.reachability_checks
    assert "goal 1: sensor at" in session.messages[-1]
    unchecked = GoalSeeker(franka.model_copy(update={"planners": franka.planners.model_copy(update={
        "vs_global": franka.planners.vs_global.model_copy(update={"reachability_checks": 0})})}))
    session = FakeSession(floor_z=0.1, reach_min_x=0.21)
    unchecked.sample(session, CENTRE, objective)
    assert unchecked.goal[0, 3] < CENTRE[0] - 0.2 and session.n_reach_queries == 0
    session = FakeSession(floor_z=0.1, reach_min_x=10.0)
    seeker.sample(session, CENTRE, objective)
    assert seeker.goal[0, 3] < CENTRE[0] - 0.2
    assert any("none of the 50 goal candidates checked" in m for m in session.messages)
    goals = np.array(session.queried_goals)
    apart = np.linalg.norm(goals[:, None] - goals[None], axis=2) + np.eye(len(goals))
    assert len(goals) == 50 and apart.min() >= franka.planners.vs_global.arrival_m


def test_the_path_to_a_goal_follows_the_great_circle_arc():
    start, goal = CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE + np.array([0.0, 0.0, 0.25])
    views = arc_views(CENTRE, 0.25, look_at(start, CENTRE), goal, 0.03)
    positions = views[:, :3, 3]
    assert len(views) == 14  # a quarter circle, 0.393 m of arc, in 14 steps of at most 3 cm
    np.testing.assert_allclose(np.linalg.norm(positions - CENTRE, axis=1), 0.25)
    np.testing.assert_allclose(positions[-1], goal, atol=1e-12)
    steps = np.linalg.norm(np.diff(np.vstack([start, positions]), axis=0), axis=1)
    assert np.all(steps <= 0.03) and np.allclose(positions[:, 0], CENTRE[0])  # in the plane x = 0.45
    np.testing.assert_allclose(views[:, :3, 2], -(positions - CENTRE) / 0.25, atol=1e-12)  # looking in
    for T in views:  # proper rotations
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    opposite = arc_views(CENTRE, 0.25, look_at(start, CENTRE), CENTRE + np.array([0.0, 0.25, 0.0]), 0.03)
    assert opposite[:, 2, 3].max() == pytest.approx(CENTRE[2] + 0.25, abs=1e-3)  # over the top


def test_the_path_to_a_goal_keeps_the_cameras_roll():
    """Along the arc the camera turns only about axes across its optical axis, as the servo turns it: a
    camera rolled by 180 deg stays rolled, whatever roll the goal candidates have."""
    start, goal = CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE + np.array([0.2, 0.0, 0.15])
    upright = look_at(start, CENTRE)
    rolled = upright.copy()
    rolled[:3, :2] *= -1.0  # 180 deg about the optical axis
    plain, turned = (arc_views(CENTRE, 0.25, T, goal, 0.03) for T in (upright, rolled))
    np.testing.assert_allclose(turned[:, :3, 2], plain[:, :3, 2], atol=1e-12)
    np.testing.assert_allclose(turned[:, :3, :2], -plain[:, :3, :2], atol=1e-12)
    for views, T in ((plain, upright), (turned, rolled)):
        R = np.concatenate([T[None, :3, :3], views[:, :3, :3]])
        # each step turns the camera by the angle its optical axis turns, no more: no roll
        turn = np.arccos(np.clip((np.einsum("kij,kij->k", R[1:], R[:-1]) - 1.0) / 2.0, -1.0, 1.0))
        axis = np.arccos(np.clip(np.einsum("ki,ki->k", R[1:, :, 2], R[:-1, :, 2]), -1.0, 1.0))
        np.testing.assert_allclose(turn[1:], axis[1:], atol=1e-9)


def test_no_allowed_candidate_is_a_planning_error(franka):
    seeker = GoalSeeker(franka)
    with pytest.raises(PlanningError, match="barrier"):
        seeker.sample(FakeSession(floor_z=10.0), CENTRE, LinearObjective([1.0, 0.0, 0.0]))


def test_goal_sampling_is_repeatable(franka):
    goals = []
    for _ in range(2):
        seeker = GoalSeeker(franka)
        seeker.sample(FakeSession(floor_z=0.1), CENTRE, LinearObjective([0.3, -1.0, 0.2]))
        goals.append(seeker.goal)
    np.testing.assert_array_equal(goals[0], goals[1])


def sideways(planner_class, franka):
    """A planner of ``planner_class`` with its centroid at CENTRE, a session with a floor at 0.1 m, and
    the camera pose T looking at CENTRE from 25 cm on its -y side (the session's pose)."""
    planner = planner_class(franka)
    planner.centroid = CENTRE
    session = FakeSession(floor_z=0.1)
    session.pose = T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)
    return planner, session, T


def test_hybrid_goes_global_after_local_converges_then_back(franka):
    planner, session, T = sideways(VSHybridPlanner, franka)
    weak = LinearObjective([0.5 / franka.planners.vs_local.alpha, 0.0, 0.0], T[:3, 3], 1.0)
    modes = []
    for _ in range(201):
        sec = planner.secondary(session, T, weak, NO_ROWS)
        planner.observe(sec, sec.g_norm, T[:3, 3])
        modes.append(sec.mode)
    assert modes[:200] == ["local"] * 200 and modes[200] == "global"
    assert planner.goals.n_goals == 1
    session.pose = planner.goals.goal
    # arrived: local again
    assert planner.secondary(session, planner.goals.goal, weak, NO_ROWS).mode == "local"
    assert not planner.local.converged()


def test_h_roi_termination_needs_ten_flat_values(franka):
    planner = VSGlobalPlanner(franka)
    planner.open_entropy_window()
    planner.h_roi = [0.6, 0.5, 0.45] + [0.4] * 9
    assert planner.finished(FakeSession()) is None
    planner.h_roi.append(0.4005)
    reason = planner.finished(FakeSession())
    assert reason is not None and "H_ROI settled" in reason


@pytest.mark.parametrize("entropy, settles", [("observation_aware", True), ("paper", False)])
def test_the_observation_aware_h_roi_settles_where_eq8s_swings(franka, entropy, settles):
    """A face of the object whose voxels the views keep disagreeing on (a calibration error: hit from one
    view, crossed by the next): eq. 8's H_ROI swings with them for good, the observation-aware one (the
    objective's choice, ``ObjectiveConfig.entropy``, in which the job's pipeline computes it) settles as
    they are seen again."""
    data = franka.model_dump()
    data["planners"]["vs"]["objective"]["entropy"] = entropy
    planner = VSGlobalPlanner(type(franka).model_validate(data))
    planner.open_entropy_window()
    occupancy = OccupancyMap(franka.perception.occupancy)
    extent = (CENTRE - np.array([0.02, 0.0225, 0.02]), CENTRE + np.array([0.02, -0.0175, 0.02]))  # the face
    roi = compute_roi(np.vstack(extent), table_z=0.0)
    face = CENTRE + np.stack(np.meshgrid(np.linspace(-0.02, 0.02, 9), [-0.02], np.linspace(-0.02, 0.02, 9),
                                         indexing="ij"), axis=-1).reshape(-1, 3)
    eye = CENTRE + np.array([0.0, -0.25, 0.0])
    reasons = []
    for seq in range(120):
        occupancy.integrate(eye, face, free_only=np.full(len(face), seq % 2 == 1))
        update = SimpleNamespace(seq=seq, timestamp=float(seq), roi=roi, centroid=roi.centroid, extent=extent,
                                 h_roi=occupancy.mean_entropy_in_box(
                                     *extent, observation_aware=entropy == "observation_aware"),
                                 h_roi_entropy=entropy, map=occupancy)
        planner._perceive(PerceivingSession(update))
        reasons.append(planner.finished(FakeSession()))
    assert (reasons[-1] is not None) == settles
    assert reasons[:20] == [None] * 20  # not at once: the face's voxels are new


def test_global_h_roi_termination_waits_for_the_first_goal_reached(franka):
    planner, session, T = sideways(VSGlobalPlanner, franka)
    objective = LinearObjective([-1.0, 0.0, 0.0])
    planner.secondary(session, T, objective, NO_ROWS)  # first goal sampled, far from T
    planner.h_roi = [0.4] * 12  # flat while travelling
    assert planner.goals.n_goals == 1 and planner.finished(session) is None
    session.pose = planner.goals.goal
    # arrived: the window opens, a new goal
    planner.secondary(session, planner.goals.goal, objective, NO_ROWS)
    assert planner.goals.n_goals == 2 and planner.finished(session) is None
    planner.h_roi += [0.4] * 9
    assert planner.finished(session) is None  # nine values since the arrival
    planner.h_roi.append(0.4)
    assert "H_ROI settled" in planner.finished(session)


def test_servo_outputs_are_written(tmp_path):
    rows = [TelemetryRow(t=0.02 * i, e_norm=0.01 / (i + 1), f=1.5, g_norm=2.0 if i > 3 else 0.0,
                         h_roi=None if i < 2 else 0.6, mode="primary" if i <= 3 else "local")
            for i in range(20)]
    write_servo_outputs(tmp_path, rows, "observation_aware", np.cumsum(np.full((50, 3), 0.001), axis=0),
                        CENTRE, coverage=[(0.05, 40.0), (0.2, 55.5)])
    lines = (tmp_path / "servo.csv").read_text().splitlines()
    # H_ROI's column names its form, the termination's
    assert lines[0] == "t,e_norm_m,f_nats,g_norm,h_roi_observation_aware_nats,mode,coverage_pct"
    assert len(lines) == 21
    assert lines[1].split(",")[4] == "" and lines[1].endswith(",primary,")  # before the first capture
    assert lines[4].endswith(",primary,40.00") and lines[-1].endswith(",local,55.50")
    for name in ("servo.png", "path.png"):
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"


def test_servo_png_says_what_it_shows_with_units():
    """servo.png has a title naming the paper's figure and a unit on every axis (||g|| is dimensionless,
    its panel had none)."""
    rows = [TelemetryRow(t=0.1 * i, e_norm=0.01, f=1.0, g_norm=0.5, h_roi=0.5, mode="local")
            for i in range(5)]
    fig = servo_figure(rows, "paper", coverage=[(0.0, 10.0), (0.4, 50.0)])
    assert "Fig. 4" in fig.get_suptitle()
    labels = [ax.get_ylabel() for ax in fig.axes]
    units = ("[m]", "[nats]", "[1]", "[%]")
    assert len(labels) == 5 and all(label.endswith(units) for label in labels), labels
    assert "||g|| before clipping [1]" in labels


def test_servo_csv_without_coverage_has_no_coverage_column(tmp_path):
    rows = [TelemetryRow(t=0.0, e_norm=0.01, f=1.0, g_norm=0.0, h_roi=0.5, mode="primary")]
    write_servo_outputs(tmp_path, rows, "paper", np.zeros((2, 3)), None)
    assert (tmp_path / "servo.csv").read_text().splitlines()[0] == "t,e_norm_m,f_nats,g_norm,h_roi_nats,mode"


def test_residual_voxel_entropy_is_zero_at_the_map_clamps(franka):
    occ = franka.perception.occupancy
    h = voxel_entropy(franka)
    p = np.array([occ.clamp_min, 0.3, 0.5, 0.8, occ.clamp_max])
    out = h(p)
    assert out[0] == pytest.approx(0.0, abs=1e-12) and out[-1] == pytest.approx(0.0, abs=1e-12)
    assert out[2] == pytest.approx(np.log(2.0) - binary_entropy(np.array([occ.clamp_max]))[0])
    assert np.all(out[1:4] > 0.0)
    data = franka.model_dump()
    data["planners"]["vs"]["objective"]["voxel_entropy"] = "shannon"
    np.testing.assert_array_equal(voxel_entropy(type(franka).model_validate(data))(p), binary_entropy(p))


def test_entropy_choice_reaches_the_objective(franka):
    # a map whose voxels were all scanned many times, ambiguously: the paper's form counts them fully,
    # the observation-aware default discounts them
    occupancy = OccupancyMap(franka.perception.occupancy)
    origin = CENTRE + np.array([0.0, 0.0, 0.3])
    ends = occupancy.voxels_in_box(CENTRE - 0.04, CENTRE + 0.04)
    for k in range(30):
        occupancy.integrate(origin, ends, free_only=np.full(len(ends), k % 2 == 1))
    T = look_at(origin, CENTRE)
    values = {}
    for choice in ("paper", "observation_aware"):
        update = SimpleNamespace(seq=1, extent=(CENTRE - 0.02, CENTRE + 0.02), centroid=CENTRE, timestamp=0.0,
                                 map=occupancy, h_roi=None, h_roi_entropy=choice)
        data = franka.model_dump()
        data["planners"]["vs"]["objective"]["entropy"] = choice
        planner = VSLocalPlanner(type(franka).model_validate(data))
        planner._perceive(PerceivingSession(update))
        values[choice] = planner.objective(T)
    assert franka.planners.vs.objective.entropy == "observation_aware"
    assert 0.0 < values["observation_aware"] < 0.5 * values["paper"]


class StreamSession(FakeSession):
    """Records the sensor twists streamed to it, and lets them through."""

    def __init__(self):
        super().__init__()
        self.twists = []

    def command_sensor_twist(self, v):
        self.twists.append(np.array(v))
        return np.array(v)


class JointLimitSession(FakeSession):
    """Joints at their limits (``rows`` of ``joint_limit_twists``) and an arm at the edge of its reach
    (``singular``, of ``singularity_twists``) that sensor twists v with a . v > 0 drive further into."""

    def __init__(self, rows, singular=()):
        super().__init__()
        self.rows = np.asarray(rows, dtype=float).reshape(-1, 6)
        self.singular = np.asarray(singular, dtype=float).reshape(-1, 6)

    def joint_limit_twists(self, activation_rad):
        return self.rows

    def singularity_twists(self, activation):
        return self.singular


def within_limits(planner, session, T, s, sec):
    """``planner._within_limits`` with the rows of ``session``'s arm, as the servo loop gives them."""
    return planner._within_limits(session, T, s, sec, planner.limit_rows(session))


def test_secondary_slides_along_a_joint_limit(franka):
    planner = VSLocalPlanner(franka)
    s = np.array([0.0, 0.0, franka.scan.standoff_m])
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)
    sec = Secondary(np.array([0.6, 0.8, 0.0, 0.0, 0.0, 0.0]), 2.0, 1.0, "local")
    limit = JointLimitSession([1.0, 0, 0, 0, 0, 0])
    # g before clipping, (1.2, 1.6), projected: (0, 1.6), clipped again: the camera slides at full speed
    blocked = within_limits(planner, limit, T, s, sec)
    np.testing.assert_allclose(blocked.g, [0.0, 1.0, 0.0, 0.0, 0.0, 0.0], atol=1e-12)
    assert blocked.g_norm == pytest.approx(1.6)
    # (0.66, 0.88) projected: (0, 0.88), below the clipping norm: slower, and counted as converging
    weak = within_limits(planner, limit, T, s, Secondary(sec.g, 1.1, 1.0, "local"))
    np.testing.assert_allclose(weak.g[:2], [0.0, 0.88], atol=1e-12)
    assert weak.g_norm == pytest.approx(0.88)
    unclipped = within_limits(planner, limit, T, s, Secondary(sec.g * 0.5, 0.5, 1.0, "local"))
    np.testing.assert_allclose(unclipped.g[:2], [0.0, 0.4], atol=1e-12)
    assert unclipped.g_norm == pytest.approx(0.4)
    free = within_limits(planner, JointLimitSession(np.zeros((0, 6))), T, s, sec)
    assert free is sec
    away = within_limits(planner, JointLimitSession([-1.0, 0, 0, 0, 0, 0]), T, s, sec)
    np.testing.assert_allclose(away.g, sec.g)  # moving away from the limit is not blocked
    # along the edge of the reach a crossing slides as fast as it was crossing
    reach = JointLimitSession(np.zeros((0, 6)), [1.0, 0, 0, 0, 0, 0])
    crossing = within_limits(planner, reach, T, s, Secondary(sec.g, 2.0, 1.0, "local", 3.0))
    np.testing.assert_allclose(crossing.g, [0.0, 1.0, 0.0, 0.0, 0.0, 0.0], atol=1e-12)
    assert crossing.speed == 3.0


def test_secondary_slides_along_the_edge_of_the_reach_and_a_joint_limit_together(franka):
    planner = VSLocalPlanner(franka)
    s = np.array([0.0, 0.0, franka.scan.standoff_m])
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)
    sec = Secondary(np.array([0.6, 0.8, 0.0, 0.0, 0.0, 0.0]), 2.0, 1.0, "local")
    # the reach alone: as a joint limit, g before clipping (1.2, 1.6) loses its +x part
    reach = within_limits(planner, JointLimitSession(np.zeros((0, 6)), [1.0, 0, 0, 0, 0, 0]), T, s, sec)
    np.testing.assert_allclose(reach.g, [0.0, 1.0, 0.0, 0.0, 0.0, 0.0], atol=1e-12)
    assert reach.g_norm == pytest.approx(1.6)
    # the reach against +x and a joint against +y: held in the corner, and counted as converging
    corner = within_limits(planner, JointLimitSession([0, 1.0, 0, 0, 0, 0], [1.0, 0, 0, 0, 0, 0]), T, s, sec)
    np.testing.assert_allclose(corner.g, 0.0, atol=1e-12)
    assert corner.g_norm == pytest.approx(0.0, abs=1e-12)


class MarginSession(FakeSession):
    """A joint ``distance_rad`` from its position margin, which sensor twists v with ``row`` . v > 0 drive
    it towards: a row of ``joint_limit_twists`` once the activation exceeds that distance."""

    def __init__(self, row, distance_rad, floor_z=-np.inf):
        super().__init__(floor_z=floor_z)
        self.row, self.distance_rad = np.asarray(row, dtype=float), distance_rad

    def joint_limit_twists(self, activation_rad):
        return self.row[None] if self.distance_rad < activation_rad else np.zeros((0, 6))

    def singularity_twists(self, activation):
        return np.zeros((0, 6))


def test_a_crossing_slows_to_the_exploration_speed_near_the_limits_it_moves_towards(franka):
    """The activation distances of the joint margins and barrier planes are the arm's seconds of travel
    at the exploration speed: a crossing at k times that speed slows to it within k times them, when g
    moves towards the limit."""
    planner = VSLocalPlanner(franka)
    s = np.array([0.0, 0.0, franka.scan.standoff_m])
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)  # camera x = base x, camera y = base -z
    vs = franka.planners.vs
    along_x = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    joint = MarginSession(along_x, 2.0 * vs.joint_activation_rad)
    joint.pose = T
    crossing = Secondary(along_x, 2.0, 0.01, "local", 3.0)
    assert within_limits(planner, joint, T, s, crossing).speed == 1.0
    np.testing.assert_allclose(within_limits(planner, joint, T, s, crossing).g, along_x)  # not yet sliding
    assert within_limits(planner, joint, T, s, replace(crossing, speed=1.5)).speed == 1.5  # not that near
    away = Secondary(-along_x, 2.0, 0.01, "local", 3.0)
    assert within_limits(planner, joint, T, s, away).speed == 3.0
    floor = MarginSession(along_x, np.inf, floor_z=T[2, 3] - 2.5 * vs.barrier_activation_m)
    floor.pose = T
    down = Secondary(np.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.0]), 2.0, 0.01, "local", 3.0)
    assert within_limits(planner, floor, T, s, down).speed == 1.0
    assert within_limits(planner, floor, T, s, replace(down, speed=2.0)).speed == 2.0
    assert within_limits(planner, floor, T, s, crossing).speed == 3.0  # along the floor


class BackOffSession(JointLimitSession):
    """Records the retraces asked for; ``can_retrace`` says whether the arm could."""

    def __init__(self, pose, can_retrace=True):
        super().__init__(np.zeros((0, 6)))
        self.pose = pose
        self.can_retrace = can_retrace
        self.retraced = []
        self.lines = []

    def sensor_pose(self):
        return self.pose

    def log(self, message):
        self.lines.append(message)

    def retrace(self, duration_s):
        self.retraced.append(duration_s)
        return self.can_retrace


def test_after_a_refusal_the_arm_retraces_and_the_camera_avoids_that_direction(franka):
    planner = VSLocalPlanner(franka)
    planner.centroid = CENTRE
    planner.servo.secondary_active = True
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)
    session = BackOffSession(T)
    refused = Secondary(np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0]), 1.0, 0.5, "local")
    refusal = TwistRefused("refused: link6 would touch the table", Refusal("collision", "link6"))
    planner._back_off(session, refused, refusal)
    vs = franka.planners.vs
    assert session.retraced == [vs.backoff_s]
    assert "retracing" in session.lines[0]
    s = np.array([0.0, 0.0, franka.scan.standoff_m])
    towards = within_limits(planner, session, T, s, Secondary(np.array([0.6, 0.8, 0, 0, 0, 0.0]), 2.0, 0.5,
                                                              "local"))
    np.testing.assert_allclose(towards.g[:2], [0.0, 1.0], atol=1e-12)  # slides past the refused direction
    session.pose = far = translated(T, np.array([[-2.0 * vs.refusal_radius_m, 0.0, 0.0]]))[0]
    sec = Secondary(np.array([0.6, 0.8, 0, 0, 0, 0.0]), 2.0, 0.5, "local")
    assert within_limits(planner, session, far, s, sec) is sec  # blocked only near where it was refused


def test_a_refusal_after_g_fell_to_zero_avoids_the_way_the_camera_came(franka):
    """g projected out near a joint limit while the arm still slowed down along it: the direction it had
    followed is the refused one (without that the camera went back to the same refusal every 2 s, 67
    times, in a teapot scan)."""
    planner = VSLocalPlanner(franka)
    planner.centroid = CENTRE
    planner.servo.secondary_active = True
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)  # camera x = base x
    session = BackOffSession(T)
    s = np.array([0.0, 0.0, franka.scan.standoff_m])
    planner._command(StreamSession(), T, s, Secondary(np.array([0.6, 0.8, 0, 0, 0, 0.0]), 2.0, 0.5, "local"))
    planner._command(StreamSession(), T, s, Secondary(np.zeros(6), 0.0, 0.5, "local"))
    refusal = TwistRefused("refused: link1 would touch link5b", Refusal("collision", "link1"))
    planner._back_off(session, Secondary(np.zeros(6), 0.0, 0.5, "local"), refusal)
    [(_, direction, _)] = planner._refused
    np.testing.assert_allclose(direction, T[:3, :3] @ [0.6, 0.8, 0.0], atol=1e-12)
    towards = within_limits(planner, session, T, s, Secondary(np.array([0.6, 0.8, 0, 0, 0, 0.0]), 2.0, 0.5,
                                                              "local"))
    np.testing.assert_allclose(towards.g, 0.0, atol=1e-12)  # held


@pytest.mark.parametrize("gradient, ends", [
    ([1.0, 0.0, 0.0], "held by a refused motion, not converged: ||g|| < 1 in more than 80% of the last 200 "
                      "servo evaluations, the camera kept from where the gradient leads by a direction the "
                      "guard refused nearby (link1 would touch link5b)"),
    ([0.0, 0.0, 0.0], "local gradient converged: ||g|| < 1 in more than 80% of the last 200 servo "
                      "evaluations"),
])
def test_a_camera_held_by_a_refused_direction_has_not_converged(franka, gradient, ends):
    """After a refusal (a mug scan: link1 would touch link5b) the gradient keeps leading the way the guard
    refused: g is projected to zero there, but the scan says that it was held, not that it converged; a
    gradient flat there converges as before."""
    data = franka.model_dump()
    data["planners"]["vs_local"]["reach_deg"] = 0.0  # the difference over delta alone
    planner = VSLocalPlanner(type(franka).model_validate(data))
    planner.centroid = CENTRE
    T = look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE)  # camera x = base x
    session = BackOffSession(T)
    why = "link1 would touch link5b"
    refusal = TwistRefused(f"refused: {why}", Refusal("collision", why))
    planner._back_off(session, Secondary(np.array([1.0, 0, 0, 0, 0, 0.0]), 2.0, 0.5, "local"), refusal)
    objective = LinearObjective(gradient, at=T[:3, 3], f_at=0.05)
    for _ in range(franka.planners.vs_local.window):
        assert planner.finished(session) is None
        sec = planner.secondary(session, T, objective, planner.limit_rows(session))
        np.testing.assert_allclose(sec.g, 0.0, atol=1e-12)
        planner.observe(sec, sec.g_norm, T[:3, 3])
    assert planner.finished(session) == ends


def test_a_refusal_the_arm_cannot_retrace_from_ends_the_scan(franka):
    planner = VSLocalPlanner(franka)
    session = BackOffSession(look_at(CENTRE + np.array([0.0, -0.25, 0.0]), CENTRE), can_retrace=False)
    refusal = TwistRefused("refused: link6 would touch the table", Refusal("collision", "link6"))
    with pytest.raises(TwistRefused) as ended:
        planner._back_off(session, Secondary(np.array([1.0, 0, 0, 0, 0, 0.0]), 1.0, 0.5, "local"), refusal)
    assert ended.value is refusal


def test_hybrid_h_roi_termination_waits_for_the_end_of_the_first_global_leg(franka):
    planner = VSHybridPlanner(franka)
    planner.h_roi = [0.4] * 12
    assert planner.finished(FakeSession()) is None  # still in its first local phase
    planner.goals.n_goals = 1
    assert planner.finished(FakeSession()) is None  # travelling to the first goal
    planner.open_entropy_window()
    planner.h_roi += [0.4] * 10
    assert "H_ROI settled" in planner.finished(FakeSession())


class PerceivingSession:
    """Serves one perception update."""

    def __init__(self, update):
        self.update = update

    def latest_perception(self):
        return self.update


def test_the_objective_counts_the_objects_extent_so_far_not_the_current_roi(franka):
    # A piece of the object split off in this map: the segmented box is smaller than the extent seen.
    roi = compute_roi(np.array([[0.42, -0.03, 0.0], [0.46, 0.01, 0.05]]), table_z=0.0)
    extent = (np.array([0.41, -0.04, 0.0]), np.array([0.49, 0.04, 0.08]))
    update = SimpleNamespace(seq=1, timestamp=1.0, roi=roi, centroid=roi.centroid, extent=extent, h_roi=0.5,
                             h_roi_entropy="observation_aware", map=OccupancyMap(franka.perception.occupancy))
    planner = VSLocalPlanner(franka)
    planner._perceive(PerceivingSession(update))
    grow = franka.planners.vs.objective.roi_margin_m
    np.testing.assert_allclose(planner.objective.roi_min, extent[0] - [grow, grow, 0.0])
    np.testing.assert_allclose(planner.objective.roi_max, extent[1] + grow)
    assert planner.h_roi == [0.5]  # the update's own, not computed again


def test_h_roi_is_computed_once_per_capture(franka, monkeypatch):
    """The pipeline computes H_ROI in the objective's form, and the servo planner's termination takes
    that value."""
    assert franka.planners.vs.objective.entropy == "observation_aware"
    calls = []
    mean_entropy_in_box = OccupancyMap.mean_entropy_in_box

    def counted(self, *args, **kwargs):
        calls.append(kwargs.get("observation_aware", False))
        return mean_entropy_in_box(self, *args, **kwargs)

    monkeypatch.setattr(OccupancyMap, "mean_entropy_in_box", counted)
    pipeline = PerceptionPipeline(franka.perception, table_z_m=0.0, range_max_m=franka.sensor.range_max_m,
                                  rng=np.random.default_rng(1), h_roi_entropy="observation_aware")
    planner = VSGlobalPlanner(franka)
    update = _capture_of_a_cube(franka, pipeline)
    planner._perceive(PerceivingSession(update))
    assert calls == [True] and planner.h_roi == [update.h_roi]


def _capture_of_a_cube(franka, pipeline: PerceptionPipeline):
    """``pipeline``'s update after one capture of a cube by the Franka cell's RGB-D camera."""
    scene = SimScene(load_object("cube"), make_T(np.eye(3), np.array([0.45, 0.0, 0.0])))
    T = look_at(np.array([0.25, -0.1, 0.2]), np.array([0.45, 0.0, 0.05]))
    camera = SimRGBD(franka.sensor, scene, lambda: T, SimClock(), np.random.default_rng(0))
    camera.connect()
    return pipeline.process(camera.capture(), T)


@pytest.mark.parametrize("planner_class", [VSLocalPlanner, VSGlobalPlanner, VSHybridPlanner])
def test_a_servo_planner_refuses_h_roi_in_another_form_than_its_terminations(franka, planner_class):
    """A pipeline built without the objective's form (its default, eq. 8's) would end Global and Hybrid
    on eq. 8's H_ROI while the config asks for the observation-aware one: the planner says so."""
    assert franka.planners.vs.objective.entropy == "observation_aware"
    pipeline = PerceptionPipeline(franka.perception, table_z_m=0.0, range_max_m=franka.sensor.range_max_m,
                                  rng=np.random.default_rng(1))
    update = _capture_of_a_cube(franka, pipeline)
    assert update.h_roi_entropy == "paper"
    with pytest.raises(PlanningError, match=r"planners\.vs\.objective\.entropy"):
        planner_class(franka)._perceive(PerceivingSession(update))


def test_the_objectives_box_reaches_down_to_the_table_the_object_stands_on(franka):
    # A mushroom's cap hides the top of its stem: the largest cluster is the cap, its extent ends 6 cm
    # above the table, and the stem below it must still count in f.
    table_z = franka.station.table_z_m
    extent = (np.array([0.40, -0.05, table_z + 0.06]), np.array([0.49, 0.05, table_z + 0.09]))
    roi = compute_roi(np.vstack(extent), table_z=table_z)
    update = SimpleNamespace(seq=1, timestamp=1.0, roi=roi, centroid=roi.centroid, extent=extent, h_roi=0.5,
                             h_roi_entropy="observation_aware", map=OccupancyMap(franka.perception.occupancy))
    planner = VSLocalPlanner(franka)
    planner._perceive(PerceivingSession(update))
    # down to the voxel layer above the table's own surface (whose voxels hold the table's hits)
    assert planner.objective.roi_min[2] == pytest.approx(table_z + franka.perception.occupancy.resolution_m)
