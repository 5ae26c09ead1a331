"""Known-shape calibration targets: the table plane plus a box of known size standing on it.

A box target is one of the shipped box meshes (``drivers/sim/objects``), whose size is its mesh's extents;
on a real cell the user stands a box of that size on the table near the station. Its pose on the table
(x, y, yaw) and the table's height are not taken as known: the fit estimates them with the mount
(``calibration.shape_fit``), so the box need not be placed precisely.

Frames: the base frame of the robot, z up; a box pose is (x [m], y [m], yaw [rad]) of the centre of its
footprint, its base on the table plane z = ``table_z`` [m].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from drivers.errors import CalibrationError
from drivers.sim.objects import load_object

Array = NDArray[np.float64]

BOX_TARGETS: tuple[str, ...] = ("horizontal_box", "cube", "vertical_box")
"""The shipped meshes that are boxes, usable as a known shape (the first is the default)."""

DEFAULT_BOX = BOX_TARGETS[0]


@dataclass(frozen=True)
class BoxTarget:
    """A box of ``size_m`` (x, y, z) [m] in its own frame (footprint centred on the origin, base at z = 0)."""

    name: str
    size_m: Array

    def signed_distance(self, points_base: Array, pose: Array, table_z: float) -> Array:
        """Signed distance [m] of points (N, 3) [m, base frame] to the union of the table half-space
        (below z = ``table_z``) and the box at ``pose`` (x, y, yaw) standing on it: negative inside."""
        x, y, yaw = pose
        c, s = np.cos(yaw), np.sin(yaw)
        d = points_base - np.array([x, y, table_z + 0.5 * self.size_m[2]])
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
        q = np.abs(local) - 0.5 * self.size_m
        box = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
        return np.minimum(box, points_base[:, 2] - table_z)


def box_target(name: str) -> BoxTarget:
    """The known-shape target ``name`` (one of ``BOX_TARGETS``); ``CalibrationError`` otherwise."""
    if name not in BOX_TARGETS:
        raise CalibrationError(f"unknown known-shape target {name!r}; the box targets are "
                               f"{', '.join(BOX_TARGETS)}")
    return BoxTarget(name=name, size_m=np.asarray(load_object(name).extents_m, dtype=np.float64))
