"""The table's noise band: which of the captures' points the table's own range noise explains.

The segmentation cuts the map at ``plane_distance_m`` (12 mm) above the known table height
(:func:`cell.packing.objects.table_cut_z`), on voxels of the map's resolution. A single sighting can tell a
point from the table more finely, from its own range noise:

A point p of a capture seen from origin o at range r = |p - o| lies above the table when its height over
the table, as that capture saw the table, is more than ``ErrorModel.coverage`` c times its own noise std
along z, ``|d_z| sqrt(sigma(r)^2 + b^2)`` (d the unit ray, sigma(r) the range noise, b the per-zone bias):
a table point passes with probability 1 - Phi(c) (2.3 % at c = 2, the factor the upper bound uses). The
table as the capture saw it is the median height of its points outside the object's extent (the box of
every ROI, :func:`cell.packing.objects.extent_box`) and within the cut: the capture's pose error and the
common range offset move its table points as they move its object points, so they leave no term in the
band; with fewer than ``MIN_TABLE_POINTS`` such points the known table height stands in.

Two uses:

1. **Below the cut** (:func:`above_table`). A part whose lowest surfaces stand lower than about 2 cm loses
   them to the cut: a flange's 15 mm rim, seen through the range noise (sigma about 5 mm at 0.35 m) and
   through zones that straddle its outline (their range the median of a rim and a table, in between),
   leaves most of its outermost points between 5 and 10 mm, and the box came out 1-2.4 cm narrow on every
   NBV scan of the packing paper's grid. Points below the cut that stand above the band join the box's,
   those inside the extent's footprint only (in the table plane): what stands on the table there is the
   object (the extent's own argument), and a table point outside it that passes the band by chance is not.
   Inside the footprint too, a point joins only beside another point of its capture above the band (in its
   zone or one of the 8 around it on the zone grid): a table point that passes the band by chance (1 in
   44 at c = 2) has table points around it, all 8 of which stay in the band with probability
   (1 - 1/44)^8 = 0.83, while a low rim's points have the rim and the part beside them. On the packing
   grids' LR-NBV and NBV scans, 35 faces moved closer to the truth by over 1 mm and 12 further.
2. **Above the cut** (:func:`clear_of_table`, :func:`off_table`). The table's noise reaches over the cut
   too: seen from 0.45 m straight above, its height std is 6.3 mm and 2 std is 12.6 mm, and over a scan's
   thousands of table points some dozens pass 12 mm, fill voxels of the layer above the cut next to the
   object (DBSCAN joins them within ``dbscan_eps_m``) and the ROI's box. A few centimetres beyond the part
   they are more than the trim allows for on a face: a gripper's end came out 3.2 cm long on an LR-NBV
   scan of the packing paper's grid, its points 4-7 cm beyond the end at 8-15 mm. A point within its own
   capture's band is the table's wherever it lies; a point of the accumulated cloud (the running mean
   of the capture points in its voxel of the cloud's grid, ``perception.voxel_m``) is the table's when
   every capture point of its voxel is.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import convolve

from cell.packing.objects import extent_box, table_cut_z
from cell.packing.uncertainty import ErrorModel, Sighting
from cell.packing.zones import zone_grid
from cell.perception.cloud import point_keys
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


def on_table(perception: PerceptionPipeline, points: Array) -> NDArray[np.bool_]:
    """Mask (K,) of the ``points`` (K, 3) [m, base frame] that a capture's table level is taken on: within
    the segmentation's cut of the known table height and outside the footprint of the object's extent
    (the box of every ROI; before any ROI, all of them within the cut)."""
    cut = table_cut_z(perception.config.segmentation, perception.table_z_m) - perception.table_z_m
    table = np.abs(points[:, 2] - perception.table_z_m) <= cut
    box = extent_box(perception)
    return table if box is None else table & ~_over(points, box)


def clear_of_table(perception: PerceptionPipeline, sightings: list[Sighting],
                   model: ErrorModel) -> NDArray[np.bool_]:
    """Mask over the points of ``sightings`` (concatenated, in order) of those above their own capture's
    table band (the module docstring), wherever they lie; before any ROI, the capture's table is all of
    its points within the cut."""
    masks: list[NDArray[np.bool_]] = []
    for s in sightings:
        p = s.points
        table = on_table(perception, p)
        level = float(np.median(p[table, 2])) if np.count_nonzero(table) >= MIN_TABLE_POINTS \
            else perception.table_z_m
        masks.append(p[:, 2] - level > model.coverage * height_sigma(model, s.T_base_sensor[:3, 3], p))
    return np.concatenate(masks) if masks else np.zeros(0, dtype=bool)


def above_table(perception: PerceptionPipeline, sightings: list[Sighting], clear: NDArray[np.bool_],
                model: ErrorModel) -> NDArray[np.bool_]:
    """Mask over the points of ``sightings`` (concatenated, in order) of those below the segmentation's
    table cut that the module docstring takes for the object's (use 1), ``clear`` the
    :func:`clear_of_table` of the same points, ``model`` giving the zone grid; all False before any
    ROI."""
    box = extent_box(perception)
    if box is None or not sightings:
        return np.zeros(clear.shape[0], dtype=bool)
    p = np.vstack([s.points for s in sightings])
    cut = table_cut_z(perception.config.segmentation, perception.table_z_m)
    return _over(p, box) & (p[:, 2] <= cut) & clear & beside_clear(sightings, clear, model)


def beside_clear(sightings: list[Sighting], clear: NDArray[np.bool_], model: ErrorModel) -> NDArray[np.bool_]:
    """Mask over the points of ``sightings`` (concatenated, in order) of those with another point of their
    capture that is ``clear`` (over all the points) in their zone or one of the 8 around it, on the zone
    grid of ``model`` (:func:`cell.packing.zones.zone_grid`); False for a point outside the field of
    view."""
    masks: list[NDArray[np.bool_]] = []
    start = 0
    for s in sightings:
        own = clear[start:start + s.points.shape[0]]
        start += s.points.shape[0]
        R, origin = s.T_base_sensor[:3, :3], s.T_base_sensor[:3, 3]
        row, col = zone_grid((s.points - origin) @ R, model.zone_rad, model.half_fov_rad)
        on = row >= 0
        if not on.any():
            masks.append(np.zeros(s.points.shape[0], dtype=bool))
            continue
        count = np.zeros((int(row[on].max()) + 1, int(col[on].max()) + 1), dtype=np.int64)
        np.add.at(count, (row[on & own], col[on & own]), 1)  # clear points per zone
        block = convolve(count, np.ones((3, 3), dtype=np.int64), mode="constant")  # ... and around it
        others = block[np.where(on, row, 0), np.where(on, col, 0)] - own.astype(np.int64)
        masks.append(on & (others > 0))
    return np.concatenate(masks) if masks else np.zeros(0, dtype=bool)


def off_table(perception: PerceptionPipeline, points: Array, captured: Array,
              clear: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Mask (K,) of the accumulated cloud's ``points`` (K, 3) [m, base frame] that are not the table's:
    False where the points ``captured`` (N, 3) that fall in a point's voxel of the cloud's grid all lie
    in their capture's band (``clear`` (N,), :func:`clear_of_table`), True where one does not or none
    falls there (the module docstring, use 2)."""
    voxel = perception.config.voxel_m
    own, theirs = point_keys(points, voxel), point_keys(captured, voxel)
    return ~_among(own, theirs) | _among(own, theirs[clear])


def _among(keys: NDArray[np.int64], others: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Mask (K,) of the ``keys`` (K,) found among ``others`` (M,): one sort of ``others`` and a binary
    search each (``np.isin`` sorts both together)."""
    if others.size == 0:
        return np.zeros(keys.shape, dtype=bool)
    ordered = np.sort(others)
    return np.asarray(ordered[np.minimum(np.searchsorted(ordered, keys), ordered.size - 1)] == keys)


def _over(points: Array, box: tuple[Array, Array]) -> NDArray[np.bool_]:
    """Mask (K,) of the ``points`` (K, 3) [m] inside the footprint (in the table plane) of ``box``."""
    lo, hi = box
    return np.all((points[:, :2] > lo[:2]) & (points[:, :2] <= hi[:2]), axis=1)
