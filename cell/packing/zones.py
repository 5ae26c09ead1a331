"""A capture's points on its sensor's zone grid, the local surface normal each zone's neighbours give, and
whether those neighbours hold the object all around.

A multizone ToF sensor (the VL53L8CX: 8 x 8 zones over 45 x 45 deg) reports one range per zone along the
zone's central ray, so a capture's points sit on a grid of known angles: the point of zone (row i, column
j) lies at the angles theta_x = -fov_x / 2 + (j + 1/2) w and theta_y = -fov_y / 2 + (i + 1/2) w from the
optical axis (w the zone's angle, x right, y down: ``drivers.depth.sim_tof``). The grid is recovered from
the points themselves, in the frame of the pose the capture was taken from, so no zone numbers need to be
stored with them. A pinhole camera's pixels are the same grid at a pixel's angle.

Neighbouring zones range neighbouring patches of the surface: the cross product of the steps to the
zones beside and below a zone is the surface normal there, to within the range noise over one zone's
step (sigma about 5 mm over 3-4 cm at 0.3-0.4 m: about 10 deg, 20 deg at twice that). It tells a point
on a box's top from one on its side whatever the view, which the view ray alone does not: a view 40 deg
above the table sees a top and a side both at 40-50 deg.

A zone whose neighbour saw past the object (further off, or nothing) lies on the object's outline in that
capture, on that neighbour's side: part of its footprint may fall beside the object, and its range, the
object's part of it, is placed on a central ray that may miss the object (:func:`outline_sides`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def zone_grid(local: Array, zone_rad: float, half_fov_rad: tuple[float, float]) -> tuple[NDArray[np.int64],
                                                                                          NDArray[np.int64]]:
    """Row and column (K,) of the zone whose cone holds each point ``local`` (K, 3) [m, sensor frame: z
    along the optical axis], for zones of ``zone_rad`` [rad] over a field of view of twice
    ``half_fov_rad`` (across, down) [rad]; -1 outside the field of view or behind the sensor."""
    across = np.arctan2(local[:, 0], local[:, 2])
    down = np.arctan2(local[:, 1], local[:, 2])
    n_cols = round(2.0 * half_fov_rad[0] / zone_rad)
    n_rows = round(2.0 * half_fov_rad[1] / zone_rad)
    col = np.floor((across + half_fov_rad[0]) / zone_rad).astype(np.int64)
    row = np.floor((down + half_fov_rad[1]) / zone_rad).astype(np.int64)
    inside = (local[:, 2] > 0.0) & (col >= 0) & (col < n_cols) & (row >= 0) & (row < n_rows)
    return np.where(inside, row, -1), np.where(inside, col, -1)


@dataclass(frozen=True)
class ZoneNeighbours:
    """Where one capture's points sit on its sensor's ``n_rows`` x ``n_cols`` zone grid (:func:`zone_grid`):
    ``owner`` (n_rows + 2, n_cols + 2) the index of a point in each zone (-1: none), the grid padded by a
    ring of empty zones so that every zone has four neighbours in it; ``single`` (K',) the points alone in
    their zone and ``row``, ``col`` (K',) their zones in the padded grid (the sensor's plus one)."""

    single: NDArray[np.int64]
    owner: NDArray[np.int64]
    row: NDArray[np.int64]
    col: NDArray[np.int64]
    n_rows: int
    n_cols: int

    @staticmethod
    def of(T_base_sensor: Array, points: Array, zone_rad: float,
           half_fov_rad: tuple[float, float]) -> ZoneNeighbours:
        """The grid of one capture's ``points`` (K, 3) [m, base frame] taken from ``T_base_sensor``, for
        zones of ``zone_rad`` [rad] over a field of view of twice ``half_fov_rad`` (across, down) [rad]."""
        R, origin = T_base_sensor[:3, :3], T_base_sensor[:3, 3]
        row, col = zone_grid((points - origin) @ R, zone_rad, half_fov_rad)
        n_cols = round(2.0 * half_fov_rad[0] / zone_rad)
        n_rows = round(2.0 * half_fov_rad[1] / zone_rad)
        on_grid = np.flatnonzero(row >= 0)
        shape = (n_rows + 2, n_cols + 2)
        count = np.zeros(shape, dtype=np.int64)
        np.add.at(count, (row[on_grid] + 1, col[on_grid] + 1), 1)
        owner = np.full(shape, -1, dtype=np.int64)
        owner[row[on_grid] + 1, col[on_grid] + 1] = on_grid
        single = on_grid[count[row[on_grid] + 1, col[on_grid] + 1] == 1]
        return ZoneNeighbours(single, owner, row[single] + 1, col[single] + 1, n_rows, n_cols)


def surface_normals(T_base_sensor: Array, points: Array, zone_rad: float,
                    half_fov_rad: tuple[float, float]) -> Array:
    """Unit surface normal (K, 3) [base frame] at each point of one capture ``points`` (K, 3) [m, base
    frame] taken from ``T_base_sensor``, from the points of the zones on either side of it across and
    down the grid (:func:`zone_grid`), turned towards the sensor; NaN where a point has no neighbour
    across or none down, or shares its zone with another point (then it is not a zone's single range)."""
    normals = np.full(points.shape, np.nan)
    if points.shape[0] == 0:
        return normals
    grid = ZoneNeighbours.of(T_base_sensor, points, zone_rad, half_fov_rad)
    single, owner, r, c = grid.single, grid.owner, grid.row, grid.col

    def step(after: NDArray[np.int64], before: NDArray[np.int64]) -> tuple[Array, NDArray[np.bool_]]:
        """The mean step to the neighbour after and from the one before (K', 3), and where either is."""
        has_after, has_before = after >= 0, before >= 0
        p = points[single]
        total = np.where(has_after[:, None], points[after] - p, 0.0) \
            + np.where(has_before[:, None], p - points[before], 0.0)
        n = np.maximum(has_after.astype(int) + has_before.astype(int), 1)
        return total / n[:, None], has_after | has_before

    across, has_across = step(owner[r, c + 1], owner[r, c - 1])
    down, has_down = step(owner[r + 1, c], owner[r - 1, c])
    cross = np.cross(across, down)
    length = np.linalg.norm(cross, axis=1)
    ok = has_across & has_down & (length > 0.0)
    unit = cross[ok] / length[ok, None]
    towards = np.einsum("kj,kj->k", unit, points[single[ok]] - T_base_sensor[:3, 3]) > 0.0
    normals[single[ok]] = np.where(towards[:, None], -unit, unit)
    return normals


# The four neighbours of a zone on the grid, the columns of :func:`outline_sides`: across the image (+x,
# -x: the next and the previous column) and down it (+y, -y: the next and the previous row).
NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0))


def outline_sides(T_base_sensor: Array, points: Array, on_object: NDArray[np.bool_],
                  margin_m: Callable[[Array], Array], zone_rad: float,
                  half_fov_rad: tuple[float, float]) -> NDArray[np.bool_]:
    """Mask (K, 4) of the sides (:data:`NEIGHBOURS`: +x, -x, +y, -y in the image) on which the zone of each
    point of one capture ``points`` (K, 3) [m, base frame: its returns and the ends of its rays with no
    target] taken from ``T_base_sensor`` straddles the object's outline: the zone's neighbour there saw
    past the object, having ranged something not ``on_object`` (K,) and further than the zone's own range
    r plus ``margin_m(r)`` [m] (elementwise over the ranges; nearer is the table in front of a side's
    foot), or nothing. A neighbour beyond the grid's border does not count (the field of view's edge is
    not the object's). A point that shares its zone with another is not its zone's range, and its
    neighbours are not known: it straddles on every side. A zone that straddles the outline ranges the
    part of its footprint on the object, on a central ray that may miss it."""
    past = np.ones((points.shape[0], len(NEIGHBOURS)), dtype=bool)
    if points.shape[0] == 0:
        return past
    grid = ZoneNeighbours.of(T_base_sensor, points, zone_rad, half_fov_rad)
    ranges = np.linalg.norm(points - T_base_sensor[:3, 3], axis=1)
    margin = margin_m(ranges)
    r, c, own = grid.row, grid.col, grid.single
    for side, (dr, dc) in enumerate(NEIGHBOURS):
        nr, nc = r + dr, c + dc
        off_grid = (nr < 1) | (nr > grid.n_rows) | (nc < 1) | (nc > grid.n_cols)
        other = grid.owner[nr, nc]
        seen = other >= 0
        near = seen & (on_object[other] | (ranges[other] <= ranges[own] + margin[own]))
        past[own, side] = ~(off_grid | near)
    return past
