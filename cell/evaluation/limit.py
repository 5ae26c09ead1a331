"""The coverage limit of an object on a cell: the share of its surface that some reachable view can see.

The surface is eq. 13's A (``cell.perception.metrics.ground_truth_points``: 10,000 points uniform on the
posed mesh, faces pointing down left out), so the limit is on the same scale as a scan's coverage. A
point counts as seeable when, from at least one view,

- it lies inside the sensor's field of view (``fov_x_deg`` x ``fov_y_deg`` of its ``SensorModel``) and
  within its range (distance from the sensor origin in [range_min_m, range_max_m]),
- the angle between its surface normal and the ray back to the sensor is at most the sensor's grazing
  limit (``grazing_deg`` of a simulated RGB-D camera; 90 degrees, no limit, for a sensor without one),
- the ray from the sensor to it meets the mesh first at the point (Open3D ``RaycastingScene``; the
  table under the object hides nothing a view above it could see, and views stay above it).

The views (choice of this module, the issue leaves it open): the sensor on hemispheres around the centre
of the object's bounding box, looking at that centre, at ``n_directions`` directions spread evenly over
the upper hemisphere (a Fibonacci lattice) and at ``RADIUS_FACTORS`` times the cell's ``scan.standoff_m``
(the planners view from about there; the LR-NBV planner's views are 0.2 to 0.6 m from the object),
each radius clipped to the sensor's range. A view counts when the cell could take it, by the checks a
scan's planner uses before it moves (``ScanSession.sensor_view_reachable``, here seeded from
the home joints, with the barrier planes of ``sensor_pose_allowed``): the TCP and the sensor inside every
barrier plane and the workspace box, an inverse-kinematics solution from the home joints with every joint
inside the guard's position margins, and no collision of the arm and its tool with the table, the static
obstacles or the object's box (the guard's ROI, from the true bounding box). The arm's own model and the
cell's own safety section decide; nothing is assumed about the arm. A view's roll about its optical axis
is free: it counts when the arm can take it at any of the rolls ``ROLL_STEP_DEG`` apart (the first one,
nearest to upright, is the one whose field of view is used). A view held upright only (``look_at``'s
roll) leaves out two views in three on the visual-servoing cell: 334 of 900 reachable for the teapot,
against 575 with the roll free, and its limit falls from 99.7 to 96.7 % (of the upright views the Panda
cannot take, most have no inverse-kinematics solution from the home joints; the rest collide, cross a
barrier plane or leave a joint's margin, most often joint 7's). ``reachable=False`` skips the check:
every view on the hemispheres counts (a sensor that could be anywhere).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from cell.config.models import CellConfig
from cell.jobs.runner import object_pose_in_base
from cell.perception.metrics import ground_truth_points
from cell.safety.guard import MotionGuard
from drivers.arm.config import SimArmConfig
from drivers.clock import SimClock
from drivers.depth.base import SensorModel
from drivers.errors import CellError, KinematicsError
from drivers.factory import SimWorld, make_arm, make_sensor
from drivers.robots import get_robot_model
from drivers.sim.objects import ObjectMesh
from drivers.sim.scene import SimScene
from drivers.transforms import T_from_xyz_rpy, inv_T, look_at, transform_points

Array = NDArray[np.float64]

RADIUS_FACTORS = (0.5, 1.0, 1.5)
"""View distances as multiples of the cell's ``scan.standoff_m``."""
DEFAULT_DIRECTIONS = 300
"""View directions per hemisphere (``cell eval limit --directions``)."""
HIT_TOLERANCE_M = 5e-4
"""A ray reaching the mesh this much before the point still sees it (the point lies on a triangle)."""
ROLL_STEP_DEG = 30.0
"""The rolls about a view's optical axis tried for it: 0, +30, -30, +60, ... up to 180 degrees."""


@dataclass(frozen=True)
class ViewLimits:
    """What a view sees: its full field of view across and along the image [deg], its range [m] and the
    largest incidence angle [deg] at which a surface still returns (90: any)."""

    fov_x_deg: float
    fov_y_deg: float
    range_min_m: float
    range_max_m: float
    max_incidence_deg: float = 90.0

    @classmethod
    def of(cls, model: SensorModel, max_incidence_deg: float = 90.0) -> ViewLimits:
        return cls(model.fov_x_deg, model.fov_y_deg, model.range_min_m, model.range_max_m, max_incidence_deg)


@dataclass(frozen=True)
class CoverageLimit:
    """The limit [%] of A's points seeable, out of ``n_points``, from ``n_reachable`` of ``n_views``."""

    coverage_pct: float
    n_points: int
    n_views: int
    n_reachable: int


def hemisphere_directions(n: int) -> Array:
    """``n`` unit vectors (n, 3) spread evenly over the upper hemisphere (z > 0), a Fibonacci lattice."""
    k = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def hemisphere_views(centre: Array, radii: tuple[float, ...], n_directions: int) -> Array:
    """Sensor poses T_base_sensor (K, 4, 4) at ``centre + r * u`` for each radius [m] and direction,
    looking at ``centre`` (base frame)."""
    return np.array([look_at(centre + r * u, centre) for r in radii
                     for u in hemisphere_directions(n_directions)])


def seen_points(mesh: ObjectMesh, T_base_object: Array, points: Array, views: Array,
                limits: ViewLimits) -> NDArray[np.bool_]:
    """Which of ``points`` (N, 3, on the posed mesh, base frame) some view in ``views`` (K, 4, 4) sees
    (module docstring)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(transform_points(T_base_object, mesh.vertices).astype(np.float32)),  # type: ignore[call-overload]
        o3d.core.Tensor(np.asarray(mesh.triangles, dtype=np.uint32)))  # type: ignore[call-overload]
    closest = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))  # type: ignore[call-overload]
    normals = closest["primitive_normals"].numpy().astype(np.float64)
    tan_x = np.tan(np.deg2rad(limits.fov_x_deg) / 2.0)
    tan_y = np.tan(np.deg2rad(limits.fov_y_deg) / 2.0)
    cos_incidence = np.cos(np.deg2rad(limits.max_incidence_deg))
    seen = np.zeros(len(points), dtype=bool)
    for T in views:
        todo = np.flatnonzero(~seen)
        origin = T[:3, 3]
        d = points[todo] - origin
        dist = np.linalg.norm(d, axis=1)
        p_cam = d @ T[:3, :3]
        z = p_cam[:, 2]
        facing = -np.einsum("ij,ij->i", d, normals[todo]) / np.maximum(dist, 1e-12)
        ok = ((z > 0.0) & (np.abs(p_cam[:, 0]) <= tan_x * z) & (np.abs(p_cam[:, 1]) <= tan_y * z)
              & (dist >= limits.range_min_m) & (dist <= limits.range_max_m) & (facing >= cos_incidence)
              & (facing > 0.0))
        candidates = todo[ok]
        if candidates.size == 0:
            continue
        unit = d[ok] / dist[ok, None]
        rays = np.hstack([np.broadcast_to(origin, unit.shape), unit]).astype(np.float32)
        t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()  # type: ignore[call-overload]
        seen[candidates[t_hit >= dist[ok] - HIT_TOLERANCE_M]] = True
    return seen


def view_rolls() -> Array:
    """The rotations (R, 4, 4) about the optical axis (z) a view is tried at, nearest to upright first."""
    steps = round(180.0 / ROLL_STEP_DEG)
    angles = np.deg2rad(ROLL_STEP_DEG) * np.array([0] + [s * k for k in range(1, steps) for s in (1, -1)]
                                                   + [steps])
    return np.array([T_from_xyz_rpy((0.0, 0.0, 0.0), (0.0, 0.0, a)) for a in angles])


def reachable_views(config: CellConfig, views: Array, aabb_min: Array,
                    aabb_max: Array) -> tuple[Array, NDArray[np.bool_]]:
    """Which sensor poses (K, 4, 4) the cell's arm can take, at some roll about the optical axis, with the
    object's box at ``aabb_min`` / ``aabb_max`` (base frame [m]); the checks of the module docstring, on a
    simulated twin of the arm. Returns the views at the first roll the arm can take (upright where it
    can take none) and which are reachable."""
    model = get_robot_model(config.arm.model)
    q_home = model.home(config.arm.home_joints_rad)
    arm = make_arm(SimArmConfig(type="sim", model=config.arm.model, home_joints_rad=list(q_home)), model,
                   SimWorld(clock=SimClock(), rng=np.random.default_rng(0), scene=None))
    guard = MotionGuard.from_config(arm, model, config, SimClock())
    # The full margin on every face: a view's configuration is judged on its own, not from where the
    # twin (never connected, never moved) stands.
    guard.collision.set_roi(aabb_min, aabb_max)
    q_lo, q_hi = guard.joint_bounds
    T_sensor_flange = inv_T(config.mount.matrix())

    def takes(T_sensor: Array) -> bool:
        T_flange = T_sensor @ T_sensor_flange
        if guard.barrier_violation(T_flange) is not None:
            return False
        try:
            q = model.ik_pose(T_flange, q_home, q_bounds=(q_lo, q_hi))
        except KinematicsError:
            return False
        return bool(np.all((q >= q_lo) & (q <= q_hi)) and guard.collision.check(q) is None)

    posed = np.array(views, dtype=float)
    reachable = np.zeros(len(views), dtype=bool)
    rolls = view_rolls()
    for k, T in enumerate(views):
        for rolled in T @ rolls:
            if takes(rolled):
                posed[k], reachable[k] = rolled, True
                break
    return posed, reachable


def sensor_limits(config: CellConfig, mesh: ObjectMesh, T_base_object: Array) -> ViewLimits:
    """The cell's sensor's field of view and range (its ``SensorModel``) and grazing limit."""
    if config.mode not in ("sim", "dry-run"):
        raise CellError("the coverage limit needs the sensor's model from a simulated sensor: give the "
                        "cell file's sim twin (mode: sim)")
    scene = SimScene(mesh, T_base_object, table_z=config.station.table_z_m,
                     table_center_xy=config.sim.table_center_xy_m, table_size_xy=config.sim.table_size_m)
    world = SimWorld(clock=SimClock(), rng=np.random.default_rng(0), scene=scene)
    model = make_sensor(config.sensor, world, lambda: np.eye(4)).model
    return ViewLimits.of(model, float(getattr(config.sensor, "grazing_deg", 90.0)))


def cell_coverage_limit(config: CellConfig, mesh: ObjectMesh, placement: tuple[float, float, float],
                        n_directions: int = DEFAULT_DIRECTIONS, reachable: bool = True) -> CoverageLimit:
    """The coverage limit of ``mesh`` at ``placement`` (x [m], y [m], yaw [deg] from the station) on the
    cell of ``config``; ``CellError`` for fewer than one direction (no view: a limit of 0 % that says
    nothing)."""
    if n_directions < 1:
        raise CellError(f"the coverage limit needs at least 1 view direction per hemisphere, got "
                        f"{n_directions}")
    T_base_object = object_pose_in_base(config, placement)
    limits = sensor_limits(config, mesh, T_base_object)
    corners = transform_points(T_base_object, mesh.vertices)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    radii = tuple(float(np.clip(f * config.scan.standoff_m, limits.range_min_m, limits.range_max_m))
                  for f in RADIUS_FACTORS)
    views = hemisphere_views((lo + hi) / 2.0, radii, n_directions)
    if reachable:
        views, mask = reachable_views(config, views, lo, hi)
        views = views[mask]
    points = ground_truth_points(mesh, T_base_object)
    seen = seen_points(mesh, T_base_object, points, views, limits)
    return CoverageLimit(round(float(100.0 * seen.mean()), 2), len(points), len(radii) * n_directions,
                         len(views))
