"""What the sensor has seen standing on the table, kept for the guard as obstacles.

The pipeline keeps only what its crop box holds (section II-A, a box about the sensor's axis) and
segmentation keeps only the object; a part placed off the station, a second part, a fixture or a hand is
in neither, and the guard's collision world (``cell.safety.collision``), which knows the table, the
object's ROI and the configured obstacles, would let the arm run into it. So every return of every frame,
before the crop, that stands above the table is kept here on a coarse grid (base frame), and the guard
treats what lies outside the object's ROI as an obstacle (``CollisionWorld.set_seen``). Of a camera's
returns, the pipeline leaves out the farther pixel at each jump of its depth image
(``cell.perception.filters.continuous_depth_mask``): the flying pixels between an edge and what lies
behind it, which outside the crop box no other filter takes off, would be phantom obstacles; a thin
foreground (a wire) is nearer than both its neighbours and stays.

A return counts as standing on the table when it lies within the arm's reach (what no body of the arm can
come to, the room's far returns, would only cost cells, each grown by its reach) and higher than
segmentation's table band (``perception.segmentation.plane_distance_m``, the height below
which segmentation takes a point for the table) plus, for a sensor that reports range sigmas (a ToF
zone's ``sigma_m``), three times the frame's median sigma: the table's own returns, noise included, stay
out. The frame's median stands for its range noise; a single zone's sigma also holds the spread of the
surfaces it straddles, which is what a part's edge, or a curved part seen from afar, looks like.

A return marks the cell of the grid it falls in. The returns of a sparse sensor lie further apart than a
cell (the 8x8 ToF: a zone's pitch, 45 deg / 8, is 2.9 cm at 0.3 m), and an obstacle between two zones'
central rays would fall through the gaps: such a return also marks the cells within half the gap to its
neighbours along each axis (its reach, in cells). What lies within a cell of the object's ROI is the
object's, which the guard's ROI holds (:meth:`SeenObstacles.outside`).

Nothing seen is ever forgotten: a cell stays an obstacle for the rest of the scan (a part does not walk
away, and the arm stops before a phantom as it would before a part), but for the cells the arm stands in
when an update comes, which the guard leaves out.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property

import fcl
import numpy as np
from numpy.typing import NDArray

from cell.perception.cloud import key_steps, point_keys, unpack_keys
from drivers.depth.base import DepthFrame
from drivers.fcl_bodies import mesh_bvh

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

CHUNK_CELLS = 16
"""The edge [cells] of the blocks the cells are checked in, one body each (:attr:`SeenCells.chunks`): a
body's enclosing sphere (14 cm across a 16 cm block) is what the guard's cheap test sees of it, and the
cells a block holds (at most 16^3) are what the guard builds again when it leaves out those the arm
stands in."""

SIGMA_BAND = 3.0
"""The frame's median range sigmas [1] above the table band a return must stand to count: a table return's
range noise passes it once in about 700 (one-sided Gaussian tail)."""

_FACES = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.int64)
"""The steps to a cell's six face neighbours."""


@dataclass(frozen=True)
class SeenCells:
    """Cells seen occupied: ``keys`` (M,) their packed indices (``cell.perception.cloud.point_keys``), sorted
    and distinct, on the ``voxel_m`` [m] grid anchored at the base frame's origin (cell i spans
    ``i * voxel_m`` to ``(i + 1) * voxel_m``). Immutable: an update hands it to the control thread as it
    is, the bodies of its :attr:`chunks` already built (:meth:`SeenObstacles.outside`)."""

    voxel_m: float
    keys: IntArray
    built: Mapping[bytes, SeenCells] = field(default_factory=dict, repr=False, compare=False)
    """Blocks built before, by their keys' bytes: a block of :attr:`chunks` that holds the same cells as
    one of them is that one, its body with it."""

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

    @cached_property
    def chunks(self) -> tuple[tuple[SeenCells, NDArray[np.intp]], ...]:
        """These cells by blocks of ``CHUNK_CELLS`` cells a side: each block's cells (one of :attr:`built`
        when it holds the same) and their indices into these."""
        blocks = np.floor_divide(unpack_keys(self.keys), CHUNK_CELLS)
        _, which = np.unique(blocks, axis=0, return_inverse=True)
        which = which.ravel()
        chunks = []
        for at in (np.nonzero(which == k)[0] for k in range(int(which.max(initial=-1)) + 1)):
            keys = self.keys[at]
            block = self.built.get(keys.tobytes())
            chunks.append((SeenCells(self.voxel_m, keys) if block is None else block, at))
        return tuple(chunks)

    @cached_property
    def body(self) -> tuple[fcl.BVHModel, Array, float]:
        """The BVH of :attr:`surface` about the centre of its bounding box, that centre (3,) [m, base
        frame] and the radius [m] of a sphere about it that holds it: what the guard checks (one body,
        ``CollisionWorld.set_seen``). Only for cells that are there."""
        vertices, triangles = self.surface
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        center = (lo + hi) / 2.0
        return mesh_bvh(vertices - center, triangles), center, float(np.linalg.norm(hi - lo) / 2.0)


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
    """The cells (``voxel_m`` [m] edge) of every return seen standing on the table (top at ``table_z_m``
    [m] in the base frame, band ``table_band_m`` [m]) within ``reach_m`` [m] of the base frame's origin
    (the arm's reach, ``CollisionWorld.reach_m``; None: anywhere) so far in a scan, each with its reach
    [cells]."""

    def __init__(self, voxel_m: float, table_z_m: float, table_band_m: float,
                 reach_m: float | None = None) -> None:
        self.voxel_m = voxel_m
        self.table_z_m = table_z_m
        self.table_band_m = table_band_m
        self.reach_m = reach_m
        self._keys = np.zeros(0, dtype=np.int64)
        self._reach = np.zeros(0, dtype=np.int64)
        self._blocks: dict[bytes, SeenCells] = {}

    def add(self, points_sensor: Array, T_base_sensor: Array, pitch_rad: float,
            sigma_m: Array | None = None) -> None:
        """Add one frame's returns ``points_sensor`` (N, 3) [m, sensor frame] seen from ``T_base_sensor``,
        ``pitch_rad`` [rad] apart (:func:`sample_pitch_rad`), with their range sigmas ``sigma_m`` (N,) [m]
        when the sensor reports them."""
        points = np.asarray(points_sensor, dtype=float).reshape(-1, 3)
        floor = self.table_z_m + self.table_band_m
        if sigma_m is not None and np.any(np.isfinite(sigma_m)):
            floor += SIGMA_BAND * float(np.nanmedian(sigma_m))
        # the heights first: most of a camera's returns are the table's, and only the rest are moved whole
        points = points[points @ T_base_sensor[2, :3] + T_base_sensor[2, 3] > floor]
        base = points @ T_base_sensor[:3, :3].T + T_base_sensor[:3, 3]
        on = np.isfinite(base).all(axis=1)
        if self.reach_m is not None:
            on &= np.linalg.norm(base, axis=1) <= self.reach_m
        if not np.any(on):
            return
        gap = np.linalg.norm(points[on], axis=1) * pitch_rad
        # returns closer than a cell apart fill neighbouring cells themselves
        reach = np.where(gap > self.voxel_m, np.ceil(gap / (2.0 * self.voxel_m)), 0.0).astype(np.int64)
        keys = np.concatenate([self._keys, point_keys(base[on], self.voxel_m)])
        reach = np.concatenate([self._reach, reach])
        order = np.lexsort((-reach, keys))  # by key, the largest reach first
        keys, reach = keys[order], reach[order]
        first = np.ones(keys.shape[0], dtype=bool)
        first[1:] = keys[1:] != keys[:-1]
        self._keys, self._reach = keys[first], reach[first]

    def outside(self, roi: tuple[Array, Array] | None) -> SeenCells:
        """The cells seen so far that are not the object, each grown by its reach. A cell within a cell of
        the object's ROI box ``roi`` (min, max) [m, base frame] holds a return of the object (on its
        surface, up to the noise and the map's voxels the box was found on), which the guard's ROI holds
        already; any other return, a part's beside it included, is an obstacle with its whole reach. The
        bodies of their blocks are built here (:attr:`SeenCells.chunks`), on the thread that processes
        frames; a block that holds the same cells as one of the previous call's keeps its body."""
        keys, reach = self._keys, self._reach
        if roi is not None and keys.size:
            g = self.voxel_m
            index = unpack_keys(keys)
            meets = np.all(((index + 1) * g >= roi[0] - g) & (index * g <= roi[1] + g), axis=1)
            keys, reach = keys[~meets], reach[~meets]
        grown = [keys[reach == 0]]
        for r in np.unique(reach[reach > 0]):
            span = np.arange(-r, r + 1)
            steps = key_steps(np.stack(np.meshgrid(span, span, span, indexing="ij"), axis=-1).reshape(-1, 3))
            grown.append((keys[reach == r][:, None] + steps[None, :]).ravel())
        cells = SeenCells(self.voxel_m, np.unique(np.concatenate(grown)), self._blocks)
        self._blocks = {chunk.keys.tobytes(): chunk for chunk, _ in cells.chunks}
        for chunk in self._blocks.values():
            _ = chunk.body
        return cells
