"""What planned views would measure of a known shape: ray casting the table and the box from where the
views put the sensor, so that a set of views the calibration could not solve is refused before anything
moves (``calibration.shape_fit.check_observable``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibration.shape_fit import N_MOUNT, Array, ShapeProblem, View, check_observable, jacobian
from calibration.targets import BoxTarget
from drivers.depth.base import SensorModel
from drivers.sim.objects import load_object
from drivers.sim.scene import HIT_NONE, SimScene
from drivers.transforms import T_from_xyz_rpy

RAYS_PER_SIDE = 16
"""At most this many rays across each side of the field of view (fewer for a sensor with fewer zones)."""
NOMINAL_NOISE_M = 0.002
"""The range noise [m] the prediction assumes; the views must observe every axis at this noise."""


def sensor_rays(model: SensorModel) -> Array:
    """Unit rays (K, 3), sensor frame, on an even grid over the sensor's field of view."""
    nx, ny = min(model.width, RAYS_PER_SIDE), min(model.height, RAYS_PER_SIDE)
    ax = np.tan(np.deg2rad(model.fov_x_deg / 2.0)) * ((np.arange(nx) + 0.5) / nx * 2.0 - 1.0)
    ay = np.tan(np.deg2rad(model.fov_y_deg / 2.0)) * ((np.arange(ny) + 0.5) / ny * 2.0 - 1.0)
    gx, gy = np.meshgrid(ax, ay)
    rays = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], axis=1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def predicted_views(model: SensorModel, flange_poses: Sequence[Array], T_mount: Array, target: BoxTarget,
                    box_pose: Array, table_z: float) -> list[View]:
    """The points (sensor frame) each flange pose (4x4, base frame) would measure with the mount
    ``T_mount`` of the box at ``box_pose`` (x, y, yaw) on the table at ``table_z`` [m], noise-free."""
    T_box = T_from_xyz_rpy([box_pose[0], box_pose[1], table_z], [0.0, 0.0, box_pose[2]])
    scene = SimScene(load_object(target.name), T_box, table_z=table_z,
                     table_center_xy=(float(box_pose[0]), float(box_pose[1])), table_size_xy=(4.0, 4.0))
    rays = sensor_rays(model)
    out = []
    for T_bf in flange_poses:
        T = T_bf @ T_mount
        hits = scene.cast(T[:3, 3], rays @ T[:3, :3].T)
        ok = (hits.what != HIT_NONE) & (hits.t >= model.range_min_m) & (hits.t <= model.range_max_m)
        out.append(View(T_bf, hits.t[ok, None] * rays[ok]))
    return out


def check_views_observable(model: SensorModel, flange_poses: Sequence[Array], T_mount: Array,
                           target: BoxTarget, box_pose: Array, table_z: float) -> None:
    """Raise ``CalibrationError`` when the planned flange poses could not observe every mount axis
    (predicted points, ``NOMINAL_NOISE_M`` noise)."""
    views = predicted_views(model, flange_poses, T_mount, target, box_pose, table_z)
    problem = ShapeProblem.from_views(views, T_mount, target)
    x = np.concatenate([np.zeros(N_MOUNT), box_pose, [table_z]])
    check_observable(jacobian(problem.residuals, x), NOMINAL_NOISE_M)
