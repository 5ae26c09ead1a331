"""The ray set R(x_T, FoV, res) of eqs. 3-4: unit directions in the sensor frame (z optical axis, x right,
y down) from the cell's sensor config."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from drivers.depth.config import DepthConfig
from drivers.depth.sim_tof import zone_directions
from drivers.errors import PlanningError

Array = NDArray[np.float64]


def sensor_rays(sensor: DepthConfig, rgbd_rays_per_side: int) -> Array:
    """Unit rays (rows, columns, 3), sensor frame, row-major from the top-left of the image.

    A multizone ToF sensor (``sim-tof``, ``vl53l8cx``) casts one ray per zone through the zone centre, as
    many as its resolution (8 x 8 over 45 x 45 degrees for the paper's VL53L8CX). A pinhole camera
    (``sim-rgbd``) is thinned to ``rgbd_rays_per_side`` rays across its wider side over the same field of
    view: the utility is a relative score and a full 640 x 480 image per candidate is too costly.
    """
    if sensor.type in ("sim-tof", "vl53l8cx"):
        n = sensor.resolution
        return zone_directions(n, sensor.fov_deg, 1)[:, 0, :].reshape(n, n, 3)
    if sensor.type == "sim-rgbd":
        n_u = rgbd_rays_per_side
        n_v = max(1, round(rgbd_rays_per_side * sensor.height / sensor.width))
        # Pixel columns and rows spread evenly over the image, at the centres of n_u x n_v cells.
        u = (np.arange(n_u) + 0.5) * sensor.width / n_u - 0.5
        v = (np.arange(n_v) + 0.5) * sensor.height / n_v - 0.5
        uu, vv = np.meshgrid(u, v)
        d = np.column_stack([((uu - sensor.cx) / sensor.fx).ravel(), ((vv - sensor.cy) / sensor.fy).ravel(),
                             np.ones(uu.size)])
        return (d / np.linalg.norm(d, axis=1, keepdims=True)).reshape(n_v, n_u, 3)
    raise PlanningError(f"the LR-NBV utility needs the sensor's field of view; sensor type {sensor.type!r} "
                        "has none in its config (supported: sim-tof, vl53l8cx, sim-rgbd)")
