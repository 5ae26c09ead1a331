"""The object's points below the segmentation's table cut: those above the table's own noise band.

The segmentation cuts the map at ``plane_distance_m`` (12 mm) above the known table height
(:func:`cell.packing.objects.table_cut_z`) and on voxels of the map's resolution, so a part whose lowest
surfaces stand lower than about 2 cm loses them: a flange's 15 mm rim, seen through the range noise
(sigma about 5 mm at 0.35 m) and through zones that straddle its outline (their range the median of a rim
and a table, in between), leaves most of its outermost points between 5 and 10 mm, and the box came out
1-2.4 cm narrow on every NBV scan of the packing paper's grid. The cut is the right one for the map, whose
voxels cannot tell a point 5 mm above the table from the table; a single sighting can, from its own
range noise:

A point p of a capture seen from origin o at range r = |p - o| lies above the table when its height over
the table, as that capture saw the table, is more than ``ErrorModel.coverage`` c times its own noise std
along z, ``|d_z| sqrt(sigma(r)^2 + b^2)`` (d the unit ray, sigma(r) the range noise, b the per-zone bias):
a table point passes with probability 1 - Phi(c) (2.3 % at c = 2, the factor the upper bound uses). The
table as the capture saw it is the median height of its points outside the object's extent (the box of
every ROI, :func:`cell.packing.objects.extent_box`) and within the cut: the capture's pose error and the
common range offset move its table points as they move its object points, so they leave no term in the
band; with fewer than ``MIN_TABLE_POINTS`` such points the known table height stands in. Only points
inside the extent's footprint (in the table plane) are taken: what stands on the table there is the
object (the extent's own argument), and a table point outside it that passes the band by chance is not.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cell.packing.objects import extent_box, table_cut_z
from cell.packing.uncertainty import ErrorModel, Sighting
from cell.perception.pipeline import PerceptionPipeline

Array = NDArray[np.float64]

# A capture's median table height from fewer points than this is left to the known table height: the
# median of n points has a std of about 1.25 sigma / sqrt(n), a third of the noise at 15 points, and
# a view that sees the table at all sees it in tens of zones.
MIN_TABLE_POINTS = 15


def height_sigma(model: ErrorModel, origin: Array, points: Array) -> Array:
    """The std [m] along z (K,) of each point ``points`` (K, 3) [m, base frame] of one capture from the
    sensor at ``origin`` (3,): |d_z| sqrt(sigma(r)^2 + b^2) (the module docstring)."""
    offset = points - origin
    ranges = np.linalg.norm(offset, axis=1)
    up = np.abs(offset[:, 2]) / np.maximum(ranges, 1e-9)
    return np.asarray(up * np.sqrt(model.range_sigma(ranges) ** 2 + model.bias_m**2))


def above_table(perception: PerceptionPipeline, sightings: list[Sighting],
                model: ErrorModel) -> NDArray[np.bool_]:
    """Mask over the points of ``sightings`` (concatenated, in order) of those below the segmentation's
    table cut that the module docstring takes for the object's; all False before any ROI."""
    masks: list[NDArray[np.bool_]] = []
    box = extent_box(perception)
    cut = table_cut_z(perception.config.segmentation, perception.table_z_m)
    for s in sightings:
        p = s.points
        if box is None:
            masks.append(np.zeros(p.shape[0], dtype=bool))
            continue
        lo, hi = box
        over = np.all((p[:, :2] > lo[:2]) & (p[:, :2] <= hi[:2]), axis=1)
        table = ~over & (np.abs(p[:, 2] - perception.table_z_m) <= cut - perception.table_z_m)
        level = float(np.median(p[table, 2])) if np.count_nonzero(table) >= MIN_TABLE_POINTS \
            else perception.table_z_m
        band = model.coverage * height_sigma(model, s.T_base_sensor[:3, 3], p)
        masks.append(over & (p[:, 2] <= cut) & (p[:, 2] - level > band))
    return np.concatenate(masks) if masks else np.zeros(0, dtype=bool)
