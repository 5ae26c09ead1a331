"""What planned views would measure of a known shape: ray casting the table and the box from where the
views put the sensor, so that a set of views the calibration could not solve is refused before anything
moves (``calibration.shape_fit.check_observable``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibration.shape_fit import N_MOUNT, Array, ShapeProblem, View, check_observable, jacobian
from calibration.targets import BoxTarget
from cell.planning.lrnbv.sensor import sensor_rays
from drivers.depth.base import SensorModel
from drivers.sim.objects import load_object
from drivers.sim.scene import HIT_NONE, SimScene
from drivers.transforms import T_from_xyz_rpy

RAYS_PER_SIDE = 16
"""A camera's rays across the width of its image (a ToF sensor casts one per zone)."""
NOMINAL_NOISE_M = 0.002
"""The range noise [m] the prediction assumes; the views must observe every axis at this noise."""


def predicted_views(model: SensorModel, flange_poses: Sequence[Array], T_mount: Array, target: BoxTarget,
                    box_pose: Array, table_z: float) -> list[View]:
    """The points (sensor frame) each flange pose (4x4, base frame) would measure with the mount
    ``T_mount`` of the box at ``box_pose`` (x, y, yaw) on the table at ``table_z`` [m], noise-free."""
    T_box = T_from_xyz_rpy([box_pose[0], box_pose[1], table_z], [0.0, 0.0, box_pose[2]])
    scene = SimScene(load_object(target.name), T_box, table_z=table_z,
                     table_center_xy=(float(box_pose[0]), float(box_pose[1])), table_size_xy=(4.0, 4.0))
    rays = sensor_rays(model, RAYS_PER_SIDE).reshape(-1, 3)
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
