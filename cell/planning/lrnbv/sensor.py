"""The ray set R(x_T, FoV, res) of eqs. 3-4: unit directions in the sensor frame (z optical axis, x right,
y down) from the connected sensor's viewing geometry."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from drivers.depth.base import SensorModel
from drivers.depth.sim_tof import zone_directions
from drivers.errors import PlanningError

Array = NDArray[np.float64]


def sensor_rays(sensor: SensorModel, rgbd_rays_per_side: int) -> Array:
    """Unit rays (rows, columns, 3), sensor frame, row-major from the top-left of the image.

    A multizone ToF sensor (kind ``tof``) casts one ray per zone through the zone centre, as many as its
    resolution (8 x 8 over 45 x 45 degrees for the paper's VL53L8CX). A pinhole camera (``rgbd``) is
    thinned to ``rgbd_rays_per_side`` rays across its width, through the centres of as many equal cells
    of the image over its field of view (principal point at the image centre): the utility is a relative
    score and a full 640 x 480 image per candidate is too costly.
    """
    if sensor.kind == "tof":
        n = sensor.width
        return zone_directions(n, sensor.fov_x_deg, 1)[:, 0, :].reshape(n, n, 3)
    if sensor.kind == "rgbd":
        n_u = rgbd_rays_per_side
        n_v = max(1, round(rgbd_rays_per_side * sensor.height / sensor.width))
        x = ((np.arange(n_u) + 0.5) / n_u * 2.0 - 1.0) * np.tan(np.radians(sensor.fov_x_deg) / 2.0)
        y = ((np.arange(n_v) + 0.5) / n_v * 2.0 - 1.0) * np.tan(np.radians(sensor.fov_y_deg) / 2.0)
        xx, yy = np.meshgrid(x, y)
        d = np.column_stack([xx.ravel(), yy.ravel(), np.ones(xx.size)])
        return (d / np.linalg.norm(d, axis=1, keepdims=True)).reshape(n_v, n_u, 3)
    raise PlanningError(f"the LR-NBV utility has no ray model for a sensor of kind {sensor.kind!r} "
                        "(known: tof, rgbd)")
