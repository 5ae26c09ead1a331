"""Point-cloud filters and accumulation (visual-servoing paper section II-A, "Filtering" and
"Registration": voxel filter, crop box, concatenate then re-voxelize).

Bit-for-bit reproducible: the voxel filter (a compiled one-pass kernel) orders its output by voxel key,
independent of the order of its hash table, and sums each voxel's points in input order.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated

import numpy as np
from numpy.typing import NDArray

from cell.perception import _kernels as _k
from drivers.atomic_file import write_bytes_atomic
from drivers.config_base import Bounds

Array = NDArray[np.float64]

VOXEL_EDGE_M = (0.0005, 0.05)
"""The edge [m] a voxel grid of the perception pipeline (filtering, registration, the occupancy map) may
have: from half a millimetre, finer than any of the cell's depth sensors measures (their noise is
millimetres), to 5 cm, where an object of a few centimetres is a voxel or two; 2.5 (millimetres written in
a metres field) is refused."""

VoxelEdge = Annotated[float, Bounds(*VOXEL_EDGE_M, "m", "a voxel's edge is half a millimetre to a few "
                                    "centimetres")]
"""[m] the edge of a voxel grid (:data:`VOXEL_EDGE_M`)."""

PERCEPTION_DISTANCE_M = (0.0001, 0.2)
"""The range [m] of a distance parameter of the perception pipeline (a normal's radius, a correspondence
or cluster distance, a plane's thickness, a correction of a pose): from a tenth of a millimetre, under any
of the sensors' noise, to 20 cm, the size of the objects the cells scan, beyond which it joins an object
to everything around it; 12 (millimetres written in a metres field) is refused."""

PerceptionDistance = Annotated[float, Bounds(*PERCEPTION_DISTANCE_M, "m", "a distance of perception is "
                                             "0.1 mm to 20 cm")]
"""[m] a distance parameter of the perception pipeline (:data:`PERCEPTION_DISTANCE_M`)."""


_KEY_BITS = 21
"""Bits per axis of the packed voxel keys of ``_kernels.voxel_groups`` (offset by 2^20)."""


def _voxel_groups(points: Array, voxel_m: float, box: tuple[Array, Array] | None = None,
                  ) -> tuple[NDArray[np.int64], Array]:
    """(the packed voxel keys (K,) and the voxel centroids (K, 3), both in key order (x, then y, then
    z)) of the points (N, 3) [m]. ``box`` (lo, hi) (3,) [m] keeps only the points strictly inside it.
    Each centroid is the sum of its points in input order over their number, whatever the hashing
    inside ``_kernels.voxel_groups``."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    n = pts.shape[0]
    keys = np.empty(n, dtype=np.int64)
    sums = np.empty((n, 3))
    counts = np.empty(n, dtype=np.int64)
    lo, hi = (np.zeros(3), np.zeros(3)) if box is None else (np.asarray(box[0], dtype=np.float64),
                                                            np.asarray(box[1], dtype=np.float64))
    k = _k.voxel_groups(pts, float(voxel_m), lo, hi, box is not None, keys, sums, counts)
    if k < 0:
        raise ValueError(f"points are not finite or lie too far from the origin for a {voxel_m} m voxel grid")
    order = np.argsort(keys[:k])
    return keys[order], sums[order] / counts[order][:, None]


def first_voxels(clouds: Sequence[Array], voxel_m: float) -> tuple[Array, NDArray[np.int64]]:
    """The clouds (each (N_i, 3) [m]) concatenated and voxel filtered at ``voxel_m`` [m] (K, 3), as
    ``voxel_downsample`` of their concatenation, and for each voxel the index (K,) of the first cloud
    with a point in it."""
    if not clouds:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    centroids = _voxel_groups(np.vstack(clouds), voxel_m)[1]
    own = [_voxel_groups(c, voxel_m)[0] for c in clouds]
    # both in key order; np.unique keeps a key's first occurrence, in cloud order the earliest cloud's
    _, first = np.unique(np.concatenate(own), return_index=True)
    cloud_of = np.repeat(np.arange(len(clouds)), [k.size for k in own])
    return centroids, cloud_of[first]


def point_keys(points: Array, voxel_m: float) -> NDArray[np.int64]:
    """The packed voxel key (N,) of each point (N, 3) [m] on the ``voxel_m`` [m] grid anchored at the
    origin, packed as ``_kernels.voxel_groups`` packs them: points share a key when they share a voxel.
    Points not finite or too far from the origin for the grid raise ValueError, as there."""
    scaled = np.asarray(points, dtype=np.float64).reshape(-1, 3) / voxel_m
    off = 1 << (_KEY_BITS - 1)
    if not np.all((scaled >= -off) & (scaled < off)):  # NaN fails both
        raise ValueError(f"points are not finite or lie too far from the origin for a {voxel_m} m voxel grid")
    index = np.floor(scaled).astype(np.int64) + off
    return np.asarray((index[:, 0] << (2 * _KEY_BITS)) | (index[:, 1] << _KEY_BITS) | index[:, 2])


def unpack_keys(packed: NDArray[np.int64]) -> NDArray[np.int64]:
    """The voxel indices floor(p / voxel_m) (K, 3) of packed voxel keys (K,) (:func:`point_keys`)."""
    mask = (1 << _KEY_BITS) - 1
    return np.column_stack([packed >> (2 * _KEY_BITS), (packed >> _KEY_BITS) & mask, packed & mask]
                           ) - (1 << (_KEY_BITS - 1))


def key_steps(steps: NDArray[np.int64]) -> NDArray[np.int64]:
    """What adding each of the voxel index steps ``steps`` (K, 3) adds to a packed key (K,): the key of a
    neighbour, as long as it stays on the grid."""
    return np.asarray((steps[:, 0] << (2 * _KEY_BITS)) + (steps[:, 1] << _KEY_BITS) + steps[:, 2])


def voxel_keys(points: Array, voxel_m: float) -> NDArray[np.int64]:
    """The distinct voxel keys floor(p / voxel_m) (K, 3) of points (N, 3) [m], sorted (x, then y, then z)."""
    return unpack_keys(_voxel_groups(points, voxel_m)[0])


def voxel_downsample(points: Array, voxel_m: float) -> Array:
    """Replace the points of each ``voxel_m`` [m] cube (a grid anchored at the frame origin) by their
    centroid. Output sorted by voxel index; an empty input gives an empty (0, 3) array."""
    return _voxel_groups(points, voxel_m)[1]


def crop_voxel_downsample(points: Array, x: tuple[float, float], y: tuple[float, float],
                          z: tuple[float, float], voxel_m: float) -> Array:
    """``voxel_downsample(crop_box(points, x, y, z), voxel_m)`` in one pass over the points (a raw
    640x480 frame holds ~250k of them)."""
    box = (np.array([x[0], y[0], z[0]]), np.array([x[1], y[1], z[1]]))
    return _voxel_groups(points, voxel_m, box)[1]


def bounds(points: NDArray[np.floating] | NDArray[np.integer]) -> tuple[NDArray, NDArray]:
    """(min, max) (3,) over the points (N >= 1, 3), column by column: numpy's axis-0 reduction of an
    (N, 3) array is some 10x slower than three reductions of its columns."""
    return (np.array([points[:, a].min() for a in range(3)]),
            np.array([points[:, a].max() for a in range(3)]))


def cross_rows(a: Array, b: Array) -> Array:
    """Row-wise cross products (N, 3) of (N, 3) arrays, the same arithmetic as ``np.cross``, whose axis
    handling costs ~0.2 ms a call (ICP calls it every iteration)."""
    return np.column_stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]])


def in_box(points: Array, lo: Array, hi: Array) -> NDArray[np.bool_]:
    """Mask (N,) of the points (N, 3) inside the closed box [lo, hi], column by column (see ``bounds``)."""
    return ((points[:, 0] >= lo[0]) & (points[:, 0] <= hi[0]) & (points[:, 1] >= lo[1])
            & (points[:, 1] <= hi[1]) & (points[:, 2] >= lo[2]) & (points[:, 2] <= hi[2]))


class PointGrid:
    """Points (N, 3) [m] bucketed in a uniform grid of cubic cells for the compiled searches
    (``_kernels``): sorted by flat cell index (x, then y, then z; a compiled counting sort) so that a
    cell's points, and a column of cells along z, are contiguous. The cell edge is ``cell_m``, widened
    by 1.5x steps until the grid over the points' box has at most ``max_cells`` cells (8 bytes of run
    offsets each).

    ``points`` the sorted points, ``order`` their indices in the input, ``cells`` (N, 3) their cells,
    ``starts`` (n_cells + 1,) where each cell's run begins, ``dims`` the grid shape, ``lo`` its corner.
    """

    def __init__(self, points: Array, cell_m: float, max_cells: int = 4_000_000) -> None:
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if pts.shape[0] == 0:
            raise ValueError("PointGrid: no points")
        self.lo, hi = bounds(pts)
        extent = hi - self.lo
        cell = float(cell_m)
        dims = np.floor(extent / cell).astype(np.int64) + 1
        while np.prod(dims.astype(np.float64)) > max_cells:
            cell *= 1.5
            dims = np.floor(extent / cell).astype(np.int64) + 1
        n = pts.shape[0]
        self.starts = np.empty(int(np.prod(dims)) + 1, dtype=np.int64)
        self.order = np.empty(n, dtype=np.int64)
        self.cells = np.empty((n, 3), dtype=np.int64)
        self.points = np.empty((n, 3))
        _k.grid_sort(pts, self.lo, cell, int(dims[0]), int(dims[1]), int(dims[2]), self.starts, self.order,
                     self.cells, self.points)
        self.dims = dims
        self.cell_m = cell

    def nearest_within(self, queries: Array, max_m: float) -> tuple[NDArray[np.int64], Array]:
        """For each query (Q, 3) [m] the input index of its nearest point within ``max_m`` [m] and the
        distance [m], or -1 and inf (exact search)."""
        q = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
        index = np.empty(q.shape[0], dtype=np.int64)
        d2 = np.empty(q.shape[0])
        nx, ny, nz = (int(v) for v in self.dims)
        _k.nearest_within(self.points, self.starts, nx, ny, nz, self.cell_m, self.lo, q, max_m, index, d2)
        found = index >= 0
        index[found] = self.order[index[found]]
        return index, np.sqrt(d2)

    def k_nearest_within(self, queries: Array, k: int, radius_m: float) -> NDArray[np.int64]:
        """Input indices (Q, k) of the at most ``k`` nearest points within ``radius_m`` [m] of each query
        (Q, 3) [m], nearest first, -1 after the last. The cell edge must be at least ``radius_m``."""
        if self.cell_m < radius_m:
            raise ValueError(f"grid cell {self.cell_m} m is smaller than the radius {radius_m} m")
        q = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
        index = np.empty((q.shape[0], k), dtype=np.int64)
        nx, ny, nz = (int(v) for v in self.dims)
        _k.k_nearest_within(self.points, self.starts, nx, ny, nz, self.cell_m, self.lo, q, radius_m, index)
        found = index >= 0
        index[found] = self.order[index[found]]
        return index


def slab_interval(origin: Array, direction: Array, lo: Array, hi: Array) -> tuple[Array, Array]:
    """Ray parameters [t_in, t_out] where rays origin + t direction (broadcast, last axis 3) lie inside
    the axis-aligned box [lo, hi]; t_in > t_out when a ray misses it. Ray parameters [m] for unit
    directions."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo - origin) / direction
        tb = (hi - origin) / direction
    # fmin / fmax ignore the NaN of a ray lying exactly in a face plane and parallel to it.
    t_in = np.max(np.fmin(ta, tb), axis=-1)
    t_out = np.min(np.fmax(ta, tb), axis=-1)
    return t_in, t_out


def crop_box(points: Array, x: tuple[float, float], y: tuple[float, float],
             z: tuple[float, float]) -> Array:
    """Keep the points strictly inside the box (open intervals, as the paper's z in (5, 40) cm)."""
    keep = ((points[:, 0] > x[0]) & (points[:, 0] < x[1]) & (points[:, 1] > y[0]) & (points[:, 1] < y[1])
            & (points[:, 2] > z[0]) & (points[:, 2] < z[1]))
    return points[keep]


class CloudAccumulator:
    """The accumulated cloud in the base frame, re-voxelized at ``voxel_m`` after each addition.

    Voxel centroids of earlier additions are averaged again with new points of the same voxel, as the
    paper's concatenate-then-filter step does. ``new`` marks the points of voxels that the last addition
    created; the others are the previous points, in the same order (voxels are sorted by key and never
    removed), some of them moved by the averaging.

    The concatenated cloud holds at most one old centroid and one centroid of the new frame per voxel,
    so re-voxelizing it is a merge of the two key-sorted voxel sets: a voxel in both becomes
    (old + new) / 2, the voxel filter's own arithmetic for those two points (sum in order from zero,
    over their count), and the cloud is not re-grouped.
    """

    def __init__(self, voxel_m: float) -> None:
        self.voxel_m = voxel_m
        self._points = np.zeros((0, 3))
        self._keys = np.zeros(0, dtype=np.int64)
        self._new = np.zeros(0, dtype=bool)

    @property
    def points(self) -> Array:
        """(M, 3) [m], base frame. Each ``add`` builds a new array and publishes it once complete, and
        never changes one handed out before: any thread may take it, at any time, and read it later
        (``cell.jobs.live_cloud``; on the wall clock the perception worker adds while the control thread
        reports)."""
        return self._points

    @property
    def new(self) -> NDArray[np.bool_]:
        """Mask (M,) of the points whose voxel the last ``add`` created."""
        return self._new

    def add(self, points_base: Array) -> Array:
        """Add a frame's points, already in the base frame; returns them after this frame's own voxel
        filter."""
        keys, new = _voxel_groups(points_base, self.voxel_m)
        old_keys, old = self._keys, self._points
        at = np.searchsorted(old_keys, keys)
        shared = at < old_keys.size
        shared[shared] = old_keys[at[shared]] == keys[shared]
        fresh = ~shared
        fresh_keys = keys[fresh]
        # both sets are sorted by key: each voxel's place in the merged set is its rank in its own set
        # plus the number of voxels of the other set before it
        to_old = np.arange(old_keys.size) + np.searchsorted(fresh_keys, old_keys)
        to_fresh = np.arange(fresh_keys.size) + at[fresh]
        n = old_keys.size + fresh_keys.size
        merged_keys = np.empty(n, dtype=np.int64)
        merged_keys[to_old], merged_keys[to_fresh] = old_keys, fresh_keys
        points = np.empty((n, 3))
        points[to_old] = old
        points[to_old[at[shared]]] = (old[at[shared]] + new[shared]) / 2.0
        points[to_fresh] = new[fresh]
        created = np.zeros(n, dtype=bool)
        created[to_fresh] = True
        # published only once complete: another thread reading ``points`` meanwhile gets the previous cloud
        self._keys, self._points, self._new = merged_keys, points, created
        return new


def write_ply(path: Path, points: Array) -> None:
    """Binary little-endian PLY of (N, 3) float64 points; the same points give the same bytes. Written whole
    or not at all (``drivers.atomic_file``)."""
    pts = np.ascontiguousarray(points, dtype="<f8")
    header = ("ply\nformat binary_little_endian 1.0\ncomment cell accumulated cloud, base frame, metres\n"
              f"element vertex {pts.shape[0]}\nproperty double x\nproperty double y\nproperty double z\n"
              "end_header\n")
    write_bytes_atomic(path, header.encode("ascii") + pts.tobytes())


def read_ply(path: Path) -> Array:
    """Read back a cloud written by ``write_ply`` ((N, 3) float64); other PLY layouts, and a file that
    holds fewer or more points than its header says (one being written), raise ValueError."""
    data = path.read_bytes()
    marker = b"end_header\n"
    end = data.find(marker)
    if end < 0 or b"format binary_little_endian" not in data[:end] or b"property double z" not in data[:end]:
        raise ValueError(f"{path} is not a cloud written by cell (binary little-endian x, y, z doubles)")
    count = re.search(rb"^element vertex (\d+)$", data[:end], flags=re.MULTILINE)
    body = data[end + len(marker):]
    if count is None or len(body) != 24 * int(count.group(1)):
        raise ValueError(f"{path} holds {len(body)} bytes of points, not the {count and int(count.group(1))} "
                         "points of its header")
    return np.frombuffer(body, dtype="<f8").reshape(-1, 3).copy()
