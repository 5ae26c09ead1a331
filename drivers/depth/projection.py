"""Back-projection of depth images, shared by every backend and tool that turns depth into points.

Pinhole model, sensor frame (z along the optical axis, x right, y down), pixel (u, v) = (column, row) with
its centre at integer coordinates: a depth z [m] at (u, v) is the point
((u - cx) z / fx, (v - cy) z / fy, z) for the intrinsics K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] [px].
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def back_project(depth: NDArray[np.floating], K: Array) -> Array:
    """Points (N, 3) [m, sensor frame] of the pixels with depth > 0, row-major pixel order."""
    v, u = np.nonzero(depth > 0.0)
    z = depth[v, u].astype(np.float64)
    pts = np.empty((z.size, 3))
    pts[:, 0] = (u - K[0, 2]) * z / K[0, 0]
    pts[:, 1] = (v - K[1, 2]) * z / K[1, 1]
    pts[:, 2] = z
    return pts


def pinhole_fov_deg(K: Array, width: int, height: int) -> tuple[float, float]:
    """Full horizontal and vertical field of view [deg] of a ``width`` x ``height`` image with intrinsics
    ``K``, from the outer edges of the border pixels (half a pixel beyond their centres)."""
    fov_x = np.arctan((K[0, 2] + 0.5) / K[0, 0]) + np.arctan((width - 0.5 - K[0, 2]) / K[0, 0])
    fov_y = np.arctan((K[1, 2] + 0.5) / K[1, 1]) + np.arctan((height - 0.5 - K[1, 2]) / K[1, 1])
    return float(np.degrees(fov_x)), float(np.degrees(fov_y))
