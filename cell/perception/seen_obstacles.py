"""What the sensor has seen standing on the table, kept for the guard as obstacles.

The pipeline keeps only what its crop box holds (section II-A, a box about the sensor's axis) and
segmentation keeps only the object; a part placed off the station, a second part, a fixture or a hand is
in neither, and the guard's collision world (``cell.safety.collision``), which knows the table, the
object's ROI and the configured obstacles, would let the arm run into it. So every return of every frame,
before the crop, that stands above the table is kept here on a coarse grid (base frame), and the guard
treats what lies outside the object's ROI as an obstacle (``CollisionWorld.set_seen``).

A return counts as standing above the table when it lies higher than segmentation's table band
(``perception.segmentation.plane_distance_m``, the height below which segmentation takes a point for the
table) plus three times its range sigma when the sensor reports one (a ToF zone's ``sigma_m``): the table's
own returns, noise included, stay out, and so does a zone whose range is the spread of two surfaces.

A return marks the cell of the grid it falls in. The returns of a sparse sensor lie further apart than a
cell (the 8x8 ToF: a zone's pitch, 45 deg / 8, is 2.9 cm at 0.3 m), and an obstacle between two zones'
central rays would fall through the gaps: such a return also marks the cells within half the gap to its
neighbours (its reach, in cells). What lies near the object's ROI is the object's, which the guard's ROI
holds (:meth:`SeenObstacles.outside`).

Nothing is ever removed: a cell once seen stays an obstacle for the rest of the scan (a part does not walk
away, and the arm stops before a phantom as it would before a part).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from cell.perception.cloud import key_steps, point_keys, unpack_keys
from drivers.depth.base import DepthFrame

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

SIGMA_BAND = 3.0
"""Range sigmas [1] above the table band a return must stand to count: a table return's range noise
passes it once in about 700 (one-sided Gaussian tail)."""


_FACES = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.int64)
"""The steps to a cell's six face neighbours."""


@dataclass(frozen=True)
class SeenCells:
    """Cells seen occupied: ``keys`` (M,) their packed indices (``cell.perception.cloud.point_keys``), sorted
    and distinct, on the ``voxel_m`` [m] grid anchored at the base frame's origin (cell i spans
    ``i * voxel_m`` to ``(i + 1) * voxel_m``). Immutable: an update hands it to the control thread as it
    is, its :attr:`surface` already built."""

    voxel_m: float
    keys: IntArray

    def __len__(self) -> int:
        return int(self.keys.shape[0])

    def centers(self) -> Array:
        """The cells' centres (M, 3) [m, base frame]."""
        return (unpack_keys(self.keys) + 0.5).astype(np.float64) * self.voxel_m

    def without(self, drop: NDArray[np.bool_]) -> SeenCells:
        """These cells but those where ``drop`` (M,) is True."""
        return SeenCells(self.voxel_m, self.keys[~drop])

    @cached_property
    def surface(self) -> tuple[Array, NDArray[np.int32]]:
        """The boundary of the cells' union as a triangle mesh: vertices (V, 3) [m, base frame] and
        triangles (F, 3): two per face of a cell whose neighbour across it is not a cell."""
        index = unpack_keys(self.keys)
        quads = []
        for step in _FACES:
            neighbour = self.keys + key_steps(step[None])[0]
            at = np.minimum(np.searchsorted(self.keys, neighbour), max(len(self) - 1, 0))
            open_ = index[self.keys[at] != neighbour] if len(self) else index
            axis = int(np.nonzero(step)[0][0])
            u, v = (axis + 1) % 3, (axis + 2) % 3
            corner = open_.copy()
            corner[:, axis] += max(int(step[axis]), 0)
            corners = np.repeat(corner[:, None, :], 4, axis=1)
            corners[:, 1, u] += 1
            corners[:, 2, u] += 1
            corners[:, 2, v] += 1
            corners[:, 3, v] += 1
            quads.append(corners)
        vertices = np.concatenate(quads).reshape(-1, 3).astype(float) * self.voxel_m
        first = np.arange(0, vertices.shape[0], 4, dtype=np.int32)[:, None]
        triangles = np.vstack([first + np.array([0, 1, 2]), first + np.array([0, 2, 3])]).astype(np.int32)
        return vertices, triangles


def sample_pitch_rad(frame: DepthFrame) -> float:
    """The angle [rad] between the rays of neighbouring returns of ``frame``: a ToF's zone pitch (from its
    zones' central rays), a camera's pixel (1 / fx of its intrinsics); 0 when the frame says neither."""
    if frame.zones is not None and frame.zones.directions.shape[0] > 1:
        d = frame.zones.directions
        return float(np.arccos(np.clip(d[0] @ d[1], -1.0, 1.0)))
    if frame.intrinsics is not None:
        return float(1.0 / frame.intrinsics[0, 0])
    return 0.0


class SeenObstacles:
    """The cells (``voxel_m`` [m] edge) of every return seen above the table (top at ``table_z_m`` [m] in
    the base frame, band ``table_band_m`` [m]) so far in a scan, each with its reach [cells]."""

    def __init__(self, voxel_m: float, table_z_m: float, table_band_m: float) -> None:
        self.voxel_m = voxel_m
        self.table_z_m = table_z_m
        self.table_band_m = table_band_m
        self._keys = np.zeros(0, dtype=np.int64)
        self._reach = np.zeros(0, dtype=np.int64)

    def add(self, points_sensor: Array, T_base_sensor: Array, pitch_rad: float,
            sigma_m: Array | None = None) -> None:
        """Add one frame's returns ``points_sensor`` (N, 3) [m, sensor frame] seen from ``T_base_sensor``,
        ``pitch_rad`` [rad] apart (:func:`sample_pitch_rad`), with their range sigmas ``sigma_m`` (N,) [m]
        when the sensor reports them."""
        points = np.asarray(points_sensor, dtype=float).reshape(-1, 3)
        base = points @ T_base_sensor[:3, :3].T + T_base_sensor[:3, 3]
        floor = self.table_z_m + self.table_band_m
        if sigma_m is not None:
            floor = floor + SIGMA_BAND * np.nan_to_num(np.asarray(sigma_m, dtype=float), nan=np.inf)
        above = np.isfinite(base).all(axis=1) & (base[:, 2] > floor)
        if not np.any(above):
            return
        gap = np.linalg.norm(points[above], axis=1) * pitch_rad
        # returns closer than a cell apart fill neighbouring cells themselves
        reach = np.where(gap > self.voxel_m, np.ceil(gap / (2.0 * self.voxel_m)), 0.0).astype(np.int64)
        keys = np.concatenate([self._keys, point_keys(base[above], self.voxel_m)])
        reach = np.concatenate([self._reach, reach])
        order = np.lexsort((-reach, keys))  # by key, the largest reach first
        keys, reach = keys[order], reach[order]
        first = np.ones(keys.shape[0], dtype=bool)
        first[1:] = keys[1:] != keys[:-1]
        self._keys, self._reach = keys[first], reach[first]

    def outside(self, roi: tuple[Array, Array] | None) -> SeenCells:
        """The cells seen so far that are not the object, each grown by its reach: a cell whose grown cube
        meets the object's ROI box ``roi`` (min, max) [m, base frame] is taken for the object (its return
        lies within its reach of it), which the guard's ROI, grown by its margin, holds already. The
        mesh of their surface is built here (:attr:`SeenCells.surface`), off the control thread."""
        keys, reach = self._keys, self._reach
        if roi is not None and keys.size:
            g = self.voxel_m
            index = unpack_keys(keys)
            lo, hi = (index - reach[:, None]) * g, (index + 1 + reach[:, None]) * g
            meets = np.all((lo <= roi[1]) & (hi >= roi[0]), axis=1)
            keys, reach = keys[~meets], reach[~meets]
        grown = [keys[reach == 0]]
        for r in np.unique(reach[reach > 0]):
            span = np.arange(-r, r + 1)
            steps = key_steps(np.stack(np.meshgrid(span, span, span, indexing="ij"), axis=-1).reshape(-1, 3))
            grown.append((keys[reach == r][:, None] + steps[None, :]).ravel())
        cells = SeenCells(self.voxel_m, np.unique(np.concatenate(grown)))
        _ = cells.surface
        return cells
