# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled inner loops of the perception layer (built by ``pip install -e .``, see setup.py).

- ``integrate_rays``: one scan into the block-sparse log-odds grid of ``occupancy.OccupancyMap`` with
  OctoMap's sensor model (visual-servoing paper section II-A 3), by exact voxel traversal
  (Amanatides and Woo, 1987);
- ``knn_mean_distances``: the mean distance of each point to its k nearest neighbours, the statistic of
  the statistical outlier removal (``filters.statistical_outlier_mask``), by an exact uniform-grid search.

Both are plain loops over typed memoryviews (no numpy C API): the callers own the arrays and their
layout, and check shapes and dtypes before calling.
"""

from libc.math cimport INFINITY, isnan, sqrt
from libc.stdint cimport int32_t, int64_t, uint8_t, uint32_t
from libc.stdlib cimport free, malloc

cdef enum:
    BLOCK_BITS = 4
    BLOCK_MASK = 15
    BLOCK_VOXELS = 4096

cdef enum:
    K_HIT = 0        # traversed voxels free, end voxel occupied
    K_FREE = 1       # no target (ToF carving): traversed voxels and the end voxel free
    K_TRUNCATED = 2  # beyond max range: traversed voxels free, the (truncated) end voxel not updated

# Ray kinds of integrate_rays, for the callers.
RAY_HIT = K_HIT
RAY_FREE = K_FREE
RAY_TRUNCATED = K_TRUNCATED


cdef struct Grid:
    int32_t* index       # dense block index, C order, -1 = no block
    int64_t sx, sy, sz   # its shape
    int64_t ox, oy, oz   # voxel key of its first corner (block origin * 16)
    float* pool          # log-odds, NaN = unknown
    uint32_t* stamp      # scan number of the last update of each voxel
    int64_t* coords      # (capacity, 3) block keys of each slot
    int64_t n_blocks
    int64_t capacity
    uint32_t scan
    float l_hit, l_miss, l_min, l_max


cdef inline int64_t _voxel(Grid* g, int64_t x, int64_t y, int64_t z) noexcept nogil:
    """Pool index of voxel key (x, y, z), allocating its block; -1 when the pool is full."""
    cdef int64_t lx = x - g.ox, ly = y - g.oy, lz = z - g.oz
    cdef int64_t b = (((lx >> BLOCK_BITS) * g.sy) + (ly >> BLOCK_BITS)) * g.sz + (lz >> BLOCK_BITS)
    cdef int64_t slot = g.index[b]
    if slot < 0:
        if g.n_blocks == g.capacity:
            return -1
        slot = g.n_blocks
        g.index[b] = <int32_t>slot
        g.coords[3 * slot] = (x - (lx & BLOCK_MASK)) >> BLOCK_BITS
        g.coords[3 * slot + 1] = (y - (ly & BLOCK_MASK)) >> BLOCK_BITS
        g.coords[3 * slot + 2] = (z - (lz & BLOCK_MASK)) >> BLOCK_BITS
        g.n_blocks += 1
    return slot * BLOCK_VOXELS + (((lx & BLOCK_MASK) << (2 * BLOCK_BITS))
                                  | ((ly & BLOCK_MASK) << BLOCK_BITS) | (lz & BLOCK_MASK))


cdef inline bint _update(Grid* g, int64_t x, int64_t y, int64_t z, bint hit) noexcept nogil:
    """Apply a hit or a miss to a voxel unless it was already updated in this scan (OctoMap: one update
    per voxel per scan). False when the pool is full."""
    cdef int64_t v = _voxel(g, x, y, z)
    cdef float lo
    if v < 0:
        return False
    if g.stamp[v] == g.scan:
        return True
    g.stamp[v] = g.scan
    lo = g.pool[v]
    if isnan(lo):
        lo = 0.0
    if hit:
        lo = lo + g.l_hit
        g.pool[v] = lo if lo < g.l_max else g.l_max
    else:
        lo = lo + g.l_miss
        g.pool[v] = lo if lo > g.l_min else g.l_min
    return True


cdef bint _traverse(Grid* g, const double* o, const int64_t* k0, const double* e, const int64_t* ke,
                    bint end_free) noexcept nogil:
    """Misses for the voxels of the segment o -> e (grid units) from the voxel k0 of o up to the voxel ke
    of e, ke itself only when ``end_free``. As OctoMap's computeRayKeys, a ray inside one voxel marks
    nothing (unless ``end_free``). The next boundary crossed is the one at the smallest parameter t
    (ties go to the higher axis, as OctoMap); counting the crossings left per axis makes the walk end
    exactly at ke whatever the rounding of t."""
    cdef int64_t left[3]
    cdef int64_t step[3]
    cdef int64_t cur[3]
    cdef double t_max[3]
    cdef double t_delta[3]
    cdef double d
    cdef int64_t total = 0
    cdef int a, best
    for a in range(3):
        cur[a] = k0[a]
        d = e[a] - o[a]
        left[a] = ke[a] - k0[a]
        step[a] = 1
        if left[a] < 0:
            left[a] = -left[a]
            step[a] = -1
        total += left[a]
        if left[a] > 0:
            t_max[a] = (<double>(k0[a] + (1 if step[a] > 0 else 0)) - o[a]) / d
            t_delta[a] = 1.0 / (d if d > 0.0 else -d)
        else:
            t_max[a] = INFINITY
            t_delta[a] = INFINITY
    if total == 0:
        return _update(g, cur[0], cur[1], cur[2], False) if end_free else True
    if not _update(g, cur[0], cur[1], cur[2], False):
        return False
    while total > 1:
        best = 2
        if t_max[0] < t_max[1]:
            if t_max[0] < t_max[2]:
                best = 0
        elif t_max[1] < t_max[2]:
            best = 1
        cur[best] += step[best]
        left[best] -= 1
        t_max[best] = t_max[best] + t_delta[best] if left[best] > 0 else INFINITY
        total -= 1
        if not _update(g, cur[0], cur[1], cur[2], False):
            return False
    if end_free:
        return _update(g, ke[0], ke[1], ke[2], False)
    return True


def integrate_rays(const double[::1] origin, const int64_t[::1] origin_key, const double[:, ::1] ends,
                   const int64_t[:, ::1] end_keys, const uint8_t[::1] kinds, int32_t[:, :, ::1] index,
                   int64_t ox, int64_t oy, int64_t oz, float[::1] pool, uint32_t[::1] stamp,
                   int64_t[:, ::1] block_coords, int64_t n_blocks, uint32_t scan, float l_hit, float l_miss,
                   float l_min, float l_max):
    """Integrate one scan; returns (number of blocks in use, True if done / False if the pool is full).

    ``origin`` (3,) and ``ends`` (N, 3) in grid units (metres / resolution), ``origin_key`` and
    ``end_keys`` their voxel keys floor(.); ``kinds`` (N,) RAY_HIT / RAY_FREE / RAY_TRUNCATED;
    ``index`` the block index covering every key of the scan, its first voxel key (ox, oy, oz);
    ``pool`` / ``stamp`` the log-odds and scan stamps, ``block_coords`` (capacity, 3); ``scan`` a number
    not used by an earlier scan. End voxels of hits are updated first, so that a voxel both hit and
    traversed in the scan is updated as occupied only. When the pool fills up the call stops: grow the
    pool and call again with the same ``scan``; voxels already updated are skipped by their stamp, so
    the result is the same as one uninterrupted call.
    """
    cdef Grid g
    cdef Py_ssize_t i, n = ends.shape[0]
    cdef bint ok = True
    g.index = &index[0, 0, 0]
    g.sx, g.sy, g.sz = index.shape[0], index.shape[1], index.shape[2]
    g.ox, g.oy, g.oz = ox, oy, oz
    g.pool = &pool[0]
    g.stamp = &stamp[0]
    g.coords = &block_coords[0, 0]
    g.n_blocks = n_blocks
    g.capacity = pool.shape[0] // BLOCK_VOXELS
    g.scan = scan
    g.l_hit, g.l_miss, g.l_min, g.l_max = l_hit, l_miss, l_min, l_max
    with nogil:
        for i in range(n):
            if kinds[i] == K_HIT and not _update(&g, end_keys[i, 0], end_keys[i, 1], end_keys[i, 2], True):
                ok = False
                break
        if ok:
            for i in range(n):
                if not _traverse(&g, &origin[0], &origin_key[0], &ends[i, 0], &end_keys[i, 0],
                                 kinds[i] == K_FREE):
                    ok = False
                    break
    return g.n_blocks, bool(ok)


cdef inline int _scan_run(const double* points, Py_ssize_t i, Py_ssize_t first, Py_ssize_t last,
                          double* best, int found, int k) noexcept nogil:
    """Insert the squared distances from point i to points first..last-1 into the sorted k smallest
    ``best``; returns how many it holds."""
    cdef Py_ssize_t j
    cdef double dx, dy, dz, d2
    cdef double px = points[3 * i], py = points[3 * i + 1], pz = points[3 * i + 2]
    cdef int m
    for j in range(first, last):
        if j == i:
            continue
        dx = points[3 * j] - px
        dy = points[3 * j + 1] - py
        dz = points[3 * j + 2] - pz
        d2 = dx * dx + dy * dy + dz * dz
        if found == k and d2 >= best[k - 1]:
            continue
        m = found if found < k else k - 1
        while m > 0 and best[m - 1] > d2:
            best[m] = best[m - 1]
            m -= 1
        best[m] = d2
        if found < k:
            found += 1
    return found


def knn_mean_distances(const double[:, ::1] points, const int64_t[:, ::1] cells, const int64_t[::1] starts,
                       int64_t nx, int64_t ny, int64_t nz, double cell_m, const double[::1] lo, int k,
                       double[::1] out):
    """Mean Euclidean distance of each point to its ``k`` nearest other points, into ``out`` (N,).

    The points (N, 3) lie in a grid of ``cell_m`` cells with corner ``lo`` and shape (nx, ny, nz), sorted
    by flat cell index (x, y, z) so that a cell's points, and a column of cells along z, are contiguous;
    ``cells`` (N, 3) their cell indices, ``starts`` (nx * ny * nz + 1,) where each cell's run begins.
    The search scans the cube of 3^3 cells around a point's cell, then the shells of cells at Chebyshev
    distance r = 2, 3, ..., and stops when k points are found and the k-th distance is within the
    distance from the point to the outside of the scanned cube, so the result is exact. Needs N > k.
    """
    cdef Py_ssize_t n = points.shape[0]
    cdef double* best = <double*>malloc((k + 1) * sizeof(double))
    cdef Py_ssize_t i
    cdef int found, m
    cdef int64_t r, cx, cy, cz, x, y, x0, x1, y0, y1, z0, z1, c
    cdef double reach, s
    cdef const double* pts = &points[0, 0]
    if best == NULL:
        raise MemoryError()
    try:
        with nogil:
            for i in range(n):
                cx, cy, cz = cells[i, 0], cells[i, 1], cells[i, 2]
                found = 0
                r = 1
                while True:
                    x0, x1 = max(cx - r, 0), min(cx + r, nx - 1)
                    y0, y1 = max(cy - r, 0), min(cy + r, ny - 1)
                    z0, z1 = max(cz - r, 0), min(cz + r, nz - 1)
                    for x in range(x0, x1 + 1):
                        for y in range(y0, y1 + 1):
                            c = (x * ny + y) * nz
                            if r == 1 or x == cx - r or x == cx + r or y == cy - r or y == cy + r:
                                found = _scan_run(pts, i, starts[c + z0], starts[c + z1 + 1], best, found, k)
                            else:  # inside the shell's x-y extent: only its two z caps are new
                                if cz - r >= 0:
                                    found = _scan_run(pts, i, starts[c + cz - r], starts[c + cz - r + 1],
                                                      best, found, k)
                                if cz + r < nz:
                                    found = _scan_run(pts, i, starts[c + cz + r], starts[c + cz + r + 1],
                                                      best, found, k)
                    # distance from the point to the nearest face of the scanned cube with cells beyond it
                    reach = INFINITY
                    if cx - r > 0:
                        reach = min(reach, points[i, 0] - (lo[0] + (cx - r) * cell_m))
                    if cx + r < nx - 1:
                        reach = min(reach, lo[0] + (cx + r + 1) * cell_m - points[i, 0])
                    if cy - r > 0:
                        reach = min(reach, points[i, 1] - (lo[1] + (cy - r) * cell_m))
                    if cy + r < ny - 1:
                        reach = min(reach, lo[1] + (cy + r + 1) * cell_m - points[i, 1])
                    if cz - r > 0:
                        reach = min(reach, points[i, 2] - (lo[2] + (cz - r) * cell_m))
                    if cz + r < nz - 1:
                        reach = min(reach, lo[2] + (cz + r + 1) * cell_m - points[i, 2])
                    if reach == INFINITY or (found == k and best[k - 1] <= reach * reach):
                        break  # exact: nothing unscanned is closer (or nothing is left to scan)
                    r += 1
                s = 0.0
                for m in range(found):
                    s += sqrt(best[m])
                out[i] = s / found if found > 0 else INFINITY
    finally:
        free(best)
