"""Probabilistic occupancy voxel map (visual-servoing paper section II-A 3, "Accumulation").

The paper accumulates the registered clouds in OctoMap at 5 mm. This module re-implements OctoMap's
sensor model (numpy for storage and queries, a compiled kernel for the rays), with OctoMap's semantics and
defaults:

- log-odds per voxel, l = log(p / (1 - p)); unknown voxels have p = 0.5 (l = 0) and are not stored;
- a hit adds logit(p_hit) (0.7), a miss adds logit(p_miss) (0.4); the result is clamped to
  [logit(clamp_min), logit(clamp_max)] = [logit(0.12), logit(0.97)];
- a voxel is occupied when p > occupied_threshold (0.5), free when known and not occupied;
- one scan (``integrate``) updates every voxel at most once: the voxels a ray traverses get a miss, its end
  voxel a hit, and a voxel that is both an end voxel and traversed in the same scan is updated as occupied
  only (OctoMap ``computeUpdate`` / ``insertPointCloud`` with ``discretize=false``);
- rays longer than ``max_range_m`` are truncated: the traversed voxels up to the truncated end get a miss,
  the truncated end voxel is not updated and nothing is marked occupied (OctoMap's ``maxrange``).

Grid: voxel keys k = floor(x / resolution_m) on a grid anchored at the base-frame origin; voxel centre
(k + 0.5) * resolution_m. Storage is block-sparse: 16^3-voxel blocks of float32 log-odds (NaN = unknown)
in one pool, addressed through a dense int32 index over the bounding box of the blocks, which grows on
demand. Memory is bounded by the blocks that rays have touched; a query is two gathers.

Ray traversal is OctoMap's incremental voxel traversal (Amanatides and Woo, 1987; ``computeRayKeys``) in the
compiled kernel ``_kernels.integrate_rays``: from the origin's voxel, step across the boundary met at the
smallest ray parameter t until the end voxel, |k(e) - k(o)|_1 steps (ties, where a ray passes exactly through
an edge of the grid, step the higher axis first, as OctoMap). The once-per-scan rule is kept with a per-voxel
stamp of the last scan that updated it; hits are applied before the traversals, so occupied wins. Each voxel
also counts the scans that updated it as occupied and as free (``observation_counts``, beyond OctoMap): with
the log-odds clamped, they tell a voxel seen often and still ambiguous (a surface that partly fills its voxel,
hit by some views and crossed by others) from one barely seen. The rays of a scan share most of their voxels:
when the box of the scan is small enough (``_MAX_DENSE_VOXELS``), the kernel only marks the traversed voxels
in a dense byte box (walking several rays at once in SIMD lanes where the processor has them, ``_RAY_LANES``)
and applies the misses in one sweep of it, the same voxels as walking the pool. The kernel
allocates blocks as it updates them; the Python side only grows the block index to the box of the scan and the
pool when it fills.

Each voxel also keeps the side it was hit from (``hit_sides``, beyond OctoMap): the sum of the unit
directions of the rays that hit it, one per scan, turned NaN for good once a hit comes against that sum
(the voxel was then hit from both sides). A surface voxel of a solid can only be hit from the side its
surface faces; but both faces of a wall thinner than a voxel (an open cup's 4 mm wall in the 5 mm map)
share voxels, and once one face is seen the map holds no trace that the other is not:
``cell.planning.vs.objective`` reads the sides to count such a voxel as unseen for a ray from the other
side. Kept where the hits are applied (one direction per hit voxel and scan), not in the ray walk.
Building the kernel: ``pip install -e .`` (``make setup``).

Entropy is the binary Shannon entropy of eq. 8 in nats; ``mean_entropy_in_box`` is H_ROI of eq. 12, or its
observation-aware form (each voxel's entropy weighted by ``observation_weight``) that the visual-servoing
planners' termination uses with their observation-aware objective.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from pydantic import model_validator
from scipy.special import digamma

from cell.perception import _kernels as _k
from cell.perception.cloud import VoxelEdge, bounds, voxel_keys
from drivers.config_base import StrictModel
from drivers.depth.config import SensorRange

Array = NDArray[np.float64]

_BLOCK_BITS = 4
_BLOCK = 1 << _BLOCK_BITS  # voxels per block edge
_BLOCK_MASK = _BLOCK - 1
_BLOCK_VOXELS = _BLOCK**3
_GROW_MARGIN_BLOCKS = 4  # extra blocks on each side when the block index grows
_COUNT_BITS = 16  # observation counts: hits in the low 16 bits of a uint32, misses in the high 16
_COUNT_MASK = (1 << _COUNT_BITS) - 1
_PACK_BITS = 21  # per axis when keys are packed into one int64 for sorting: +-2^20 voxels (10 km at 1 cm)
_PACK_OFFSET = 1 << (_PACK_BITS - 1)
# The largest box [voxels, one byte each] in which the kernel marks a scan's misses before applying them
# (``_kernels.integrate_rays``); a scan with a larger box walks the pool directly.
_MAX_DENSE_VOXELS = 1 << 25
# Walk the rays of a scan several at once in SIMD lanes where the processor has them (the same voxels).
_RAY_LANES = True


def logit(p: float) -> float:
    """log(p / (1 - p))."""
    return math.log(p / (1.0 - p))


def from_logodds(logodds: NDArray[np.floating]) -> Array:
    """Probabilities 1 / (1 + exp(-l)) of log-odds ``logodds``, the inverse of ``logit``."""
    return 1.0 / (1.0 + np.exp(-np.asarray(logodds, dtype=np.float64)))


class OccupancyParams(StrictModel):
    """Sensor model and grid of the occupancy map.

    ``p_hit`` and ``p_miss`` default to OctoMap's defaults (0.7, 0.4). ``clamp_min`` / ``clamp_max``
    default to 0.12 / 0.97, which are not OctoMap's: its defaults are log-odds -2 and 3.5 (probabilities
    0.1192 and 0.971 in its source), and 0.12 / 0.97 are those rounded to two decimals (log-odds -1.992 and
    3.476). Neither paper of the specification gives clamping thresholds (the visual-servoing paper uses
    OctoMap at 5 mm, the packing paper at 1 cm, both with no other parameter); the cell files set these
    values explicitly. ``benchmarks/map_vs_octomap.py`` sets an OctoMap to the same four values.

    ``resolution_m`` [m] is the voxel edge (5 mm RGB-D cell, 1 cm ToF cell, from the cell config);
    ``max_range_m`` [m] truncates longer rays (their end is then not marked occupied); None: no limit;
    ``discretize`` OctoMap's ``insertPointCloud(..., discretize=true)``: a scan of hits casts one ray per
    distinct end voxel, to its centre, instead of one per point (a 2.5 mm RGB-D cloud holds ~4 points
    per 5 mm voxel: a quarter of the rays, nearly the same map; off by default, as OctoMap's);
    ``keep_surface`` (a departure from OctoMap, off by default): a voxel the map holds occupied gets no
    miss from a scan that hits one of its 26 neighbours. Rays passing a surface at a grazing angle cross
    the voxels of its one-voxel shell on their way to the points beyond, and OctoMap carves them; the
    surface voxels then flicker between hit and miss, a piece of a curved object splits off its cluster,
    and the flickering voxels keep an entropy that no view removes (in VS-Local's cube scan the gradient
    chased voxels at p = 0.63-0.72 on an already measured face for 15 s without a gain in coverage). A
    surface within a voxel of what this scan measured is still there; free space, and occupied voxels
    away from every hit (noise, an object that moved), are carved as before.
    """

    resolution_m: VoxelEdge
    p_hit: float = 0.7
    """[1] the occupancy probability a hit gives its voxel."""
    p_miss: float = 0.4
    """[1] the occupancy probability a ray passing through gives a voxel."""
    clamp_min: float = 0.12
    """[1] the lowest occupancy probability a voxel is held at."""
    clamp_max: float = 0.97
    """[1] the highest occupancy probability a voxel is held at."""
    occupied_threshold: float = 0.5
    """[1] the occupancy probability above which a voxel counts as occupied."""
    max_range_m: SensorRange | None = None
    discretize: bool = False
    keep_surface: bool = False

    @model_validator(mode="after")
    def _check_probabilities(self) -> OccupancyParams:
        if not 0.0 < self.p_miss < 0.5 < self.p_hit < 1.0:
            raise ValueError(f"need 0 < p_miss < 0.5 < p_hit < 1, got p_miss={self.p_miss}, "
                             f"p_hit={self.p_hit}")
        if not 0.0 < self.clamp_min < self.clamp_max < 1.0:
            raise ValueError(f"need 0 < clamp_min < clamp_max < 1, got clamp_min={self.clamp_min}, "
                             f"clamp_max={self.clamp_max}")
        if not self.clamp_min <= self.occupied_threshold <= self.clamp_max:
            raise ValueError(f"occupied_threshold {self.occupied_threshold} must lie in "
                             f"[clamp_min, clamp_max] = [{self.clamp_min}, {self.clamp_max}]")
        return self


def binary_entropy(p: Array) -> Array:
    """Binary Shannon entropy of eq. 8 in nats: H(p) = -p ln p - (1 - p) ln(1 - p); H(0) = H(1) = 0."""
    p = np.asarray(p, dtype=np.float64)
    q = 1.0 - p
    with np.errstate(divide="ignore", invalid="ignore"):
        h = -(np.where(p > 0, p * np.log(p), 0.0) + np.where(q > 0, q * np.log(q), 0.0))
    return h


def observation_information(hits: NDArray[np.integer], misses: NDArray[np.integer]) -> Array:
    """I(h, m) [nats]: the information one more observation of a voxel gives about its hit rate after
    ``hits`` and ``misses`` (arrays of the same shape; ``OccupancyMap.observation_counts``).

    The voxel's outcome is Bernoulli(theta), theta its hit rate, with a uniform prior; after h hits and m
    misses theta ~ Beta(a, b), a = 1 + h, b = 1 + m, s = a + b, mean mu = a / s. The entropy of the next
    outcome, H(mu), splits into what would remain if theta were known, E[H(theta)], and the mutual
    information I(h, m) = H(mu) - E[H(theta)] = H(mu) - psi(s + 1) + mu psi(a + 1) + (1 - mu) psi(b + 1)
    (psi the digamma function; E[theta ln theta] = mu (psi(a + 1) - psi(s + 1))). Only I can be removed by
    looking again: it is ln 2 - 1/2 for an unseen voxel and falls like 1 / (2 (h + m + 3)) whatever the hit
    rate, where the log-odds entropy of a voxel the views keep disagreeing on stays near ln 2."""
    a = 1.0 + np.asarray(hits, dtype=np.float64)
    b = 1.0 + np.asarray(misses, dtype=np.float64)
    s = a + b
    mu = a / s
    expected_entropy = digamma(s + 1.0) - mu * digamma(a + 1.0) - (1.0 - mu) * digamma(b + 1.0)
    return np.maximum(binary_entropy(mu) - expected_entropy, 0.0)


# I(0, 0) = ln 2 - 1/2: an unseen voxel's.
_UNSEEN_INFORMATION = float(np.log(2.0) - 0.5)


def observation_weight(hits: NDArray[np.integer], misses: NDArray[np.integer]) -> Array:
    """w(h, m) = I(h, m) / I(0, 0) in (0, 1]: the share of an unseen voxel's information that one more
    observation of a voxel seen ``hits`` times occupied and ``misses`` times free still gives
    (:func:`observation_information`); 1 for a voxel never seen."""
    return observation_information(hits, misses) / _UNSEEN_INFORMATION


class OccupancyMap:
    """Log-odds occupancy voxel grid in the robot base frame; see the module docstring."""

    def __init__(self, params: OccupancyParams) -> None:
        self.params = params
        self.resolution_m = float(params.resolution_m)
        self._l_hit = np.float32(logit(params.p_hit))
        self._l_miss = np.float32(logit(params.p_miss))
        self._l_min = np.float32(logit(params.clamp_min))
        self._l_max = np.float32(logit(params.clamp_max))
        self._l_occ = np.float32(logit(params.occupied_threshold))
        # Block index: dense int32 over blocks [_origin, _origin + shape); -1 = no block.
        self._index: NDArray[np.int32] = np.full((0, 0, 0), -1, dtype=np.int32)
        self._origin = np.zeros(3, dtype=np.int64)
        # Pool of blocks: log-odds (n_blocks * 4096,), NaN = unknown; block coordinates per slot; per voxel
        # the number of the last scan that updated it (one update per voxel per scan).
        self._pool = np.zeros(0, dtype=np.float32)
        self._stamp = np.zeros(0, dtype=np.uint32)
        self._counts = np.zeros(0, dtype=np.uint32)  # per voxel: hits (low 16 bits), misses (high 16)
        self._sides = np.zeros(0, dtype=np.float32)  # per voxel 3: sum of its hits' ray directions, NaN: both
        self._n_occupied = np.zeros(0, dtype=np.int32)  # occupied voxels per block
        self._block_coords = np.zeros((0, 3), dtype=np.int64)
        self._n_blocks = 0
        self._scan = 0

    # ------------------------------------------------------------------ keys and storage

    def keys_of(self, points_base: Array) -> NDArray[np.int64]:
        """Voxel keys floor(x / resolution) of points (M, 3) [m] in the base frame."""
        return np.floor(np.asarray(points_base, dtype=np.float64) / self.resolution_m).astype(np.int64)

    def centers_of(self, keys: NDArray[np.int64]) -> Array:
        """Voxel centres (k + 0.5) * resolution [m] of keys (K, 3)."""
        return (np.asarray(keys, dtype=np.float64) + 0.5) * self.resolution_m

    def _grow_index(self, kmin: NDArray[np.int64], kmax: NDArray[np.int64]) -> None:
        """Make the block index cover the voxel keys in [kmin, kmax] (inclusive)."""
        bmin = kmin >> _BLOCK_BITS
        bmax = kmax >> _BLOCK_BITS
        shape = np.array(self._index.shape, dtype=np.int64)
        if self._index.size and np.all(bmin >= self._origin) and np.all(bmax < self._origin + shape):
            return
        if self._index.size:
            lo = np.minimum(bmin - _GROW_MARGIN_BLOCKS, self._origin)
            hi = np.maximum(bmax + 1 + _GROW_MARGIN_BLOCKS, self._origin + shape)
        else:
            lo, hi = bmin - _GROW_MARGIN_BLOCKS, bmax + 1 + _GROW_MARGIN_BLOCKS
        new = np.full(tuple(int(v) for v in hi - lo), -1, dtype=np.int32)
        if self._index.size:
            o = self._origin - lo
            new[o[0]:o[0] + shape[0], o[1]:o[1] + shape[1], o[2]:o[2] + shape[2]] = self._index
        self._index, self._origin = new, lo

    def _slots(self, keys: NDArray[np.int64], allocate: bool) -> NDArray[np.int64]:
        """Flat pool indices of voxel keys (M, 3); -1 where the block does not exist (allocate=False)."""
        b = (keys >> _BLOCK_BITS) - self._origin
        sx, sy, sz = self._index.shape
        if not allocate:
            inside = ((b[:, 0] >= 0) & (b[:, 0] < sx) & (b[:, 1] >= 0) & (b[:, 1] < sy)
                      & (b[:, 2] >= 0) & (b[:, 2] < sz))
            b = np.where(inside[:, None], b, 0)
        flat = (b[:, 0] * sy + b[:, 1]) * sz + b[:, 2]
        slot = self._index.reshape(-1)[flat] if self._index.size else np.full(flat.shape, -1, np.int32)
        if allocate:
            missing = slot < 0
            if np.any(missing):
                self._allocate(np.unique(flat[missing]))
                slot = self._index.reshape(-1)[flat]
        else:
            slot = np.where(inside, slot, -1)
        local = (((keys[:, 0] & _BLOCK_MASK) << (2 * _BLOCK_BITS))
                 | ((keys[:, 1] & _BLOCK_MASK) << _BLOCK_BITS) | (keys[:, 2] & _BLOCK_MASK))
        out = slot.astype(np.int64) * _BLOCK_VOXELS + local
        if not allocate:
            out[slot < 0] = -1
        return out

    def _reserve(self, n_blocks: int) -> None:
        """Make the pool (and the scan stamps, observation counts and block coordinates) hold at least
        ``n_blocks`` blocks, at least doubling it so that growth is amortised."""
        if n_blocks * _BLOCK_VOXELS <= self._pool.size:
            return
        cap = max(n_blocks, 2 * (self._pool.size // _BLOCK_VOXELS), 8)
        pool = np.full(cap * _BLOCK_VOXELS, np.nan, dtype=np.float32)
        pool[:self._pool.size] = self._pool
        stamp = np.zeros(cap * _BLOCK_VOXELS, dtype=np.uint32)
        stamp[:self._stamp.size] = self._stamp
        counts = np.zeros(cap * _BLOCK_VOXELS, dtype=np.uint32)
        counts[:self._counts.size] = self._counts
        sides = np.zeros(3 * cap * _BLOCK_VOXELS, dtype=np.float32)
        sides[:self._sides.size] = self._sides
        coords = np.zeros((cap, 3), dtype=np.int64)
        coords[:self._n_blocks] = self._block_coords[:self._n_blocks]
        n_occupied = np.zeros(cap, dtype=np.int32)
        n_occupied[:self._n_blocks] = self._n_occupied[:self._n_blocks]
        self._pool, self._stamp, self._counts, self._sides = pool, stamp, counts, sides
        self._block_coords, self._n_occupied = coords, n_occupied

    def _allocate(self, flat_blocks: NDArray[np.int64]) -> None:
        n_new = flat_blocks.size
        self._reserve(self._n_blocks + n_new)
        slots = np.arange(self._n_blocks, self._n_blocks + n_new, dtype=np.int32)
        self._index.reshape(-1)[flat_blocks] = slots
        self._block_coords[self._n_blocks:self._n_blocks + n_new] = (
            np.stack(np.unravel_index(flat_blocks, self._index.shape), axis=1) + self._origin)
        self._n_blocks += n_new

    # ------------------------------------------------------------------ integration

    def integrate(self, origin_base: Array, endpoints_base: Array, *,
                  free_only: NDArray[np.bool_] | None = None) -> None:
        """Integrate one scan: rays from the sensor origin ``origin_base`` (3,) [m] to ``endpoints_base``
        (N, 3) [m], both in the base frame.

        Traversed voxels get a miss, each end voxel a hit; rays flagged in ``free_only`` (N,) have no
        target (a ToF zone without a return, carved to the sensor's range): all their voxels, the end voxel
        included, get a miss. Each voxel is updated at most once per scan, occupied winning over free.
        With ``discretize`` (params) a scan without ``free_only`` casts one ray per distinct end voxel.
        """
        o = np.ascontiguousarray(origin_base, dtype=np.float64).reshape(3)
        e = checked = np.ascontiguousarray(endpoints_base, dtype=np.float64).reshape(-1, 3)
        # a NaN or an infinity among the ends shows in their box: cheaper than a mask of every coordinate
        lo, hi = bounds(e) if e.shape[0] else (o, o)
        if not (np.all(np.isfinite(o)) and np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError("integrate: origin and endpoints must be finite")
        if e.shape[0] == 0:
            return
        if self.params.discretize and free_only is None:
            e = self.centers_of(voxel_keys(e, self.resolution_m))
        n = e.shape[0]
        kinds = np.full(n, _k.RAY_HIT, dtype=np.uint8)
        if free_only is not None:
            kinds[np.asarray(free_only, dtype=bool).reshape(n)] = _k.RAY_FREE
        if self.params.max_range_m is not None:
            d = e - o
            length = np.sqrt(np.einsum("ij,ij->i", d, d))
            far = length > self.params.max_range_m
            if np.any(far):
                e = e.copy()
                e[far] = o + d[far] * (self.params.max_range_m / length[far])[:, None]
                kinds[far & (kinds == _k.RAY_HIT)] = _k.RAY_TRUNCATED
        if e is not checked:
            lo, hi = bounds(e)
        # A segment lies in the box of its ends: the index covers every voxel of the scan. Division by
        # the resolution is monotonic, so the keys of the box's corners bound the keys of the ends,
        # which the kernel computes as keys_of does.
        self._grow_index(self.keys_of(np.minimum(lo, o)), self.keys_of(np.maximum(hi, o)))
        self._scan += 1
        corner = self._origin * _BLOCK
        while True:
            n_blocks, done = _k.integrate_rays(
                o, e, self.resolution_m, kinds, self._index, int(corner[0]), int(corner[1]), int(corner[2]),
                self._pool, self._stamp, self._counts, self._sides, self._n_occupied, self._block_coords,
                self._n_blocks, self._scan, self._l_hit, self._l_miss, self._l_min, self._l_max, self._l_occ,
                self.params.keep_surface, _MAX_DENSE_VOXELS, _RAY_LANES)
            self._n_blocks = n_blocks
            if done:
                return
            self._reserve(self._n_blocks + 1)  # the pool is full: grow it (doubling), finish the same scan

    # ------------------------------------------------------------------ queries

    def logodds(self, points_base: Array) -> NDArray[np.float32]:
        """Log-odds at points (M, 3) [m]; 0 for unknown voxels."""
        lo = self._raw(points_base)
        return np.nan_to_num(lo, nan=0.0)

    def _raw(self, points_base: Array) -> NDArray[np.float32]:
        pts = np.asarray(points_base, dtype=np.float64).reshape(-1, 3)
        if self._n_blocks == 0 or pts.shape[0] == 0:
            return np.full(pts.shape[0], np.nan, dtype=np.float32)
        idx = self._slots(self.keys_of(pts), allocate=False)
        lo = self._pool[np.maximum(idx, 0)]
        lo[idx < 0] = np.nan
        return lo

    def observation_counts(self, points_base: Array) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """(hits, misses) (M,) of the voxels of points (M, 3) [m]: how many scans updated each voxel as
        occupied and as free (0 and 0 for unknown voxels, and for voxels set by ``set_logodds``, such as a
        map read from a .bt file, which holds no counts); each saturates at 65535."""
        pts = np.asarray(points_base, dtype=np.float64).reshape(-1, 3)
        if self._n_blocks == 0 or pts.shape[0] == 0:
            zero = np.zeros(pts.shape[0], dtype=np.int64)
            return zero, zero.copy()
        idx = self._slots(self.keys_of(pts), allocate=False)
        c = np.where(idx >= 0, self._counts[np.maximum(idx, 0)], 0).astype(np.int64)
        return c & _COUNT_MASK, c >> _COUNT_BITS

    def hit_sides(self, points_base: Array) -> Array:
        """(M, 3) per voxel of points (M, 3) [m]: the sum of the unit directions (base frame) of the rays
        that hit it, one per scan; NaN once it was hit from both sides (a ray against that sum); 0 for
        voxels never hit, unknown, or set by ``set_logodds``. See the module docstring."""
        pts = np.asarray(points_base, dtype=np.float64).reshape(-1, 3)
        if self._n_blocks == 0 or pts.shape[0] == 0:
            return np.zeros((pts.shape[0], 3))
        idx = self._slots(self.keys_of(pts), allocate=False)
        sides = self._sides.reshape(-1, 3)[np.maximum(idx, 0)].astype(np.float64)
        sides[idx < 0] = 0.0
        return sides

    def probability(self, points_base: Array) -> Array:
        """Occupancy probability at points (M, 3) [m]; 0.5 for unknown voxels."""
        return from_logodds(self.logodds(points_base))

    def entropy(self, points_base: Array) -> Array:
        """Binary entropy of eq. 8 [nats] of the occupancy at points (M, 3) [m]; ln 2 for unknown."""
        return binary_entropy(self.probability(points_base))

    def is_known(self, points_base: Array) -> NDArray[np.bool_]:
        """True where the voxel of a point (M, 3) [m] has been observed."""
        return ~np.isnan(self._raw(points_base))

    def is_occupied(self, points_base: Array) -> NDArray[np.bool_]:
        """True where the voxel is known and p > occupied_threshold."""
        return self._raw(points_base) > self._l_occ  # NaN compares False

    # ------------------------------------------------------------------ whole-map views

    def _known(self, blocks: NDArray[np.int64] | None = None, occupied_only: bool = False,
               ) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
        """Keys (K, 3) sorted by key (x, then y, then z) and log-odds (K,) of the known (or only the
        occupied) voxels of the given block slots (default: all)."""
        if blocks is None:
            blocks = np.arange(self._n_blocks)
        lo_all = self._pool.reshape(-1, _BLOCK_VOXELS)[blocks].reshape(-1)
        flat = np.flatnonzero(lo_all > self._l_occ if occupied_only else ~np.isnan(lo_all))
        slot = blocks[flat >> (3 * _BLOCK_BITS)]
        local = flat & (_BLOCK_VOXELS - 1)
        keys = self._block_coords[slot] << _BLOCK_BITS
        keys[:, 0] |= local >> (2 * _BLOCK_BITS)
        keys[:, 1] |= (local >> _BLOCK_BITS) & _BLOCK_MASK
        keys[:, 2] |= local & _BLOCK_MASK
        # one sort of the keys packed into an int64 (21 bits an axis, offset to be non-negative)
        k = keys + _PACK_OFFSET
        packed = (k[:, 0] << (2 * _PACK_BITS)) | (k[:, 1] << _PACK_BITS) | k[:, 2]
        order = np.argsort(packed, kind="stable")
        return keys[order], lo_all[flat[order]]

    def known_keys(self) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
        """Keys (K, 3) and log-odds (K,) of every observed voxel, sorted by key (x, then y, then z)."""
        return self._known()

    def classify_logodds(self, logodds: NDArray[np.floating]) -> NDArray[np.bool_]:
        """Occupied (True) or free (False) for log-odds of known voxels: p > occupied_threshold."""
        return np.asarray(logodds) > self._l_occ

    def occupied_keys(self) -> NDArray[np.int64]:
        """Keys (K, 3) of the occupied voxels, sorted by key; only blocks holding one are read (a count
        per block kept by the integration kernel), so the cost follows the surface, not the free space."""
        return self._known(np.flatnonzero(self._n_occupied[:self._n_blocks] > 0), occupied_only=True)[0]

    def free_keys(self) -> NDArray[np.int64]:
        keys, lo = self._known()
        return keys[lo <= self._l_occ]

    def occupied_centers(self) -> Array:
        """Centres (K, 3) [m] of the occupied voxels, base frame, sorted by key."""
        return self.centers_of(self.occupied_keys())

    def free_centers(self) -> Array:
        """Centres (K, 3) [m] of the known free voxels, base frame, sorted by key."""
        return self.centers_of(self.free_keys())

    @property
    def n_known(self) -> int:
        """Number of observed voxels."""
        return int(np.count_nonzero(~np.isnan(self._pool[:self._n_blocks * _BLOCK_VOXELS])))

    def bounds(self) -> tuple[Array, Array] | None:
        """(min, max) corners [m] of the axis-aligned box of the observed voxels; None for an empty map."""
        keys, _ = self._known()
        if keys.shape[0] == 0:
            return None
        return keys.min(axis=0) * self.resolution_m, (keys.max(axis=0) + 1) * self.resolution_m

    def set_logodds(self, keys: NDArray[np.int64], logodds: NDArray[np.floating]) -> None:
        """Set the log-odds of voxels (K, 3) directly (clamped); used by the .bt reader and tests."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
        if keys.shape[0] == 0:
            return
        self._grow_index(keys.min(axis=0), keys.max(axis=0))
        idx = self._slots(keys, allocate=True)
        self._pool[idx] = np.clip(np.asarray(logodds, dtype=np.float32), self._l_min, self._l_max)
        blocks = self._pool[:self._n_blocks * _BLOCK_VOXELS].reshape(-1, _BLOCK_VOXELS)
        self._n_occupied[:self._n_blocks] = np.count_nonzero(blocks > self._l_occ, axis=1)

    def voxel_keys_in_box(self, min_m: Array, max_m: Array) -> NDArray[np.int64]:
        """Keys of all voxels (known or not) whose interior intersects the box [min_m, max_m] [m]."""
        lo = np.floor(np.asarray(min_m, dtype=np.float64) / self.resolution_m).astype(np.int64)
        hi = np.ceil(np.asarray(max_m, dtype=np.float64) / self.resolution_m).astype(np.int64) - 1
        hi = np.maximum(hi, lo)
        axes = [np.arange(lo[i], hi[i] + 1) for i in range(3)]
        grid = np.meshgrid(*axes, indexing="ij")
        return np.stack([g.reshape(-1) for g in grid], axis=1)

    def voxels_in_box(self, min_m: Array, max_m: Array) -> Array:
        """Centres (K, 3) [m] of all voxels (known or unknown) whose interior intersects the axis-aligned
        box [min_m, max_m] [m] (base frame); a box inside one voxel gives that voxel."""
        return self.centers_of(self.voxel_keys_in_box(min_m, max_m))

    def mean_entropy_in_box(self, min_m: Array, max_m: Array, observation_aware: bool = False) -> float:
        """H_ROI of eq. 12 [nats]: the mean binary entropy (eq. 8) over the voxels V_ROI of the box
        (``voxels_in_box``, corners [m] in the base frame); unknown voxels count ln 2. Only the known ones
        are looked at: the box's keys go straight to the pool, and unknown voxels (most of an early ROI)
        add ln 2 each.

        ``observation_aware`` (a departure from eq. 8 in eq. 12): each known voxel's H(p) is weighted by
        :func:`observation_weight` of its counts, the measure the visual-servoing objective uses with
        ``planners.vs.objective.entropy: observation_aware``. A voxel the views keep disagreeing on (a
        surface crossing it at a slant, a calibration error moving the surface by a voxel between views)
        flips between occupied and free however often it is seen, and its H(p) with it: H_ROI of eq. 8 then
        never flattens (a cube's VS-Global scan, RGB-D cell, seed 0: 0.535-0.56 nats with a 15 s period
        after its coverage reached 100 %, until the time budget), while its weight falls like 1 / n. Unseen
        voxels and voxels without counts (set by ``set_logodds``) keep eq. 8's H."""
        keys = self.voxel_keys_in_box(min_m, max_m)
        h_known: NDArray[np.floating] = np.zeros(0)
        if self._n_blocks:
            idx = self._slots(keys, allocate=False)
            idx = idx[idx >= 0]
            lo = self._pool[idx]
            known = ~np.isnan(lo)
            h_known = binary_entropy(from_logodds(lo[known]))
            if observation_aware:
                counts = self._counts[idx[known]].astype(np.int64)
                h_known = h_known * observation_weight(counts & _COUNT_MASK, counts >> _COUNT_BITS)
        return float((h_known.sum() + (keys.shape[0] - h_known.size) * math.log(2.0)) / keys.shape[0])
