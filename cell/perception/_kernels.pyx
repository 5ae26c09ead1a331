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

from libc.math cimport INFINITY, NAN, floor, isnan, sqrt
from libc.stdint cimport int32_t, int64_t, uint8_t, uint32_t
from libc.stdlib cimport free, malloc, realloc

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
    int32_t* n_occupied  # occupied voxels per block
    int64_t* coords      # (capacity, 3) block keys of each slot
    int64_t n_blocks
    int64_t capacity
    uint32_t scan
    float l_hit, l_miss, l_min, l_max, l_occ


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
    cdef float lo, old
    if v < 0:
        return False
    if g.stamp[v] == g.scan:
        return True
    g.stamp[v] = g.scan
    old = g.pool[v]
    lo = 0.0 if isnan(old) else old
    if hit:
        lo = lo + g.l_hit
        lo = lo if lo < g.l_max else g.l_max
    else:
        lo = lo + g.l_miss
        lo = lo if lo > g.l_min else g.l_min
    g.pool[v] = lo
    # NaN (unknown) compares False: not occupied
    if (lo > g.l_occ) != (old > g.l_occ):
        g.n_occupied[v // BLOCK_VOXELS] += 1 if lo > g.l_occ else -1
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
                   int32_t[::1] n_occupied, int64_t[:, ::1] block_coords, int64_t n_blocks, uint32_t scan,
                   float l_hit, float l_miss, float l_min, float l_max, float l_occ):
    """Integrate one scan; returns (number of blocks in use, True if done / False if the pool is full).

    ``origin`` (3,) and ``ends`` (N, 3) in grid units (metres / resolution), ``origin_key`` and
    ``end_keys`` their voxel keys floor(.); ``kinds`` (N,) RAY_HIT / RAY_FREE / RAY_TRUNCATED;
    ``index`` the block index covering every key of the scan, its first voxel key (ox, oy, oz);
    ``pool`` / ``stamp`` the log-odds and scan stamps, ``n_occupied`` (capacity,) the occupied voxels
    (log-odds above ``l_occ``) of each block, kept up to date, ``block_coords`` (capacity, 3); ``scan`` a number
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
    g.n_occupied = &n_occupied[0]
    g.coords = &block_coords[0, 0]
    g.n_blocks = n_blocks
    g.capacity = pool.shape[0] // BLOCK_VOXELS
    g.scan = scan
    g.l_hit, g.l_miss, g.l_min, g.l_max, g.l_occ = l_hit, l_miss, l_min, l_max, l_occ
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


cdef struct Buf:
    double* d2       # squared distances of the candidates found so far
    Py_ssize_t n
    Py_ssize_t cap


cdef bint _push_run(const double* points, Py_ssize_t i, Py_ssize_t first, Py_ssize_t last,
                    Buf* buf) noexcept nogil:
    """Append the squared distances from point i to points first..last-1 (i itself excluded); False when
    memory runs out."""
    cdef Py_ssize_t j, need = buf.n + (last - first)
    cdef double dx, dy, dz
    cdef double px = points[3 * i], py = points[3 * i + 1], pz = points[3 * i + 2]
    cdef double* grown
    if need > buf.cap:
        grown = <double*>realloc(buf.d2, 2 * need * sizeof(double))
        if grown == NULL:
            return False
        buf.d2, buf.cap = grown, 2 * need
    for j in range(first, last):
        if j == i:
            continue
        dx = points[3 * j] - px
        dy = points[3 * j + 1] - py
        dz = points[3 * j + 2] - pz
        buf.d2[buf.n] = dx * dx + dy * dy + dz * dz
        buf.n += 1
    return True


cdef double _select(double* a, Py_ssize_t n, Py_ssize_t k) noexcept nogil:
    """Rearrange a[0..n-1] so that a[0..k-1] are its k smallest values (k <= n); returns the k-th smallest
    (Hoare's quickselect, median-of-three pivots)."""
    cdef Py_ssize_t lo = 0, hi = n - 1, i, j, mid
    cdef double pivot, t
    while hi > lo:
        mid = lo + (hi - lo) // 2
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[lo]:
            a[hi], a[lo] = a[lo], a[hi]
        if a[hi] < a[mid]:
            a[hi], a[mid] = a[mid], a[hi]
        pivot = a[mid]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                t = a[i]
                a[i] = a[j]
                a[j] = t
                i += 1
                j -= 1
        if k - 1 <= j:
            hi = j
        elif k - 1 >= i:
            lo = i
        else:
            break
    t = a[0]
    for i in range(1, k):
        if a[i] > t:
            t = a[i]
    return t


cdef double _knn_mean_one(const double* pts, const int64_t[:, ::1] cells, const int64_t[::1] starts,
                          int64_t nx, int64_t ny, int64_t nz, double cell_m, const double[::1] lo, int k,
                          Py_ssize_t i, Buf* buf) noexcept nogil:
    """knn_mean_distances for point i, with the caller's buffer; NaN when memory runs out."""
    cdef int64_t r = 1, cx = cells[i, 0], cy = cells[i, 1], cz = cells[i, 2]
    cdef int64_t x, y, x0, x1, y0, y1, z0, z1, c
    cdef double reach, s = 0.0
    cdef bint ok = True
    cdef int m
    buf.n = 0
    while True:
        x0, x1 = max(cx - r, 0), min(cx + r, nx - 1)
        y0, y1 = max(cy - r, 0), min(cy + r, ny - 1)
        z0, z1 = max(cz - r, 0), min(cz + r, nz - 1)
        for x in range(x0, x1 + 1):
            for y in range(y0, y1 + 1):
                c = (x * ny + y) * nz
                if r == 1 or x == cx - r or x == cx + r or y == cy - r or y == cy + r:
                    ok = ok and _push_run(pts, i, starts[c + z0], starts[c + z1 + 1], buf)
                else:  # inside the shell's x-y extent: only its two z caps are new
                    if cz - r >= 0:
                        ok = ok and _push_run(pts, i, starts[c + cz - r], starts[c + cz - r + 1], buf)
                    if cz + r < nz:
                        ok = ok and _push_run(pts, i, starts[c + cz + r], starts[c + cz + r + 1], buf)
        if not ok:
            return NAN
        # distance from the point to the nearest face of the scanned cube with cells beyond it
        reach = INFINITY
        if cx - r > 0:
            reach = min(reach, pts[3 * i] - (lo[0] + (cx - r) * cell_m))
        if cx + r < nx - 1:
            reach = min(reach, lo[0] + (cx + r + 1) * cell_m - pts[3 * i])
        if cy - r > 0:
            reach = min(reach, pts[3 * i + 1] - (lo[1] + (cy - r) * cell_m))
        if cy + r < ny - 1:
            reach = min(reach, lo[1] + (cy + r + 1) * cell_m - pts[3 * i + 1])
        if cz - r > 0:
            reach = min(reach, pts[3 * i + 2] - (lo[2] + (cz - r) * cell_m))
        if cz + r < nz - 1:
            reach = min(reach, lo[2] + (cz + r + 1) * cell_m - pts[3 * i + 2])
        if buf.n >= k and _select(buf.d2, buf.n, k) <= reach * reach:
            break  # exact: nothing unscanned is closer
        if reach == INFINITY:
            break  # nothing is left to scan
        r += 1
    m = k if buf.n >= k else <int>buf.n
    for c in range(m):
        s += sqrt(buf.d2[c])
    return s / m if m > 0 else INFINITY


def knn_mean_distances(const double[:, ::1] points, const int64_t[:, ::1] cells, const int64_t[::1] starts,
                       int64_t nx, int64_t ny, int64_t nz, double cell_m, const double[::1] lo, int k,
                       double[::1] out):
    """Mean Euclidean distance of each point to its ``k`` nearest other points, into ``out`` (N,).

    The points (N, 3) lie in a grid of ``cell_m`` cells with corner ``lo`` and shape (nx, ny, nz), sorted
    by flat cell index (x, y, z) so that a cell's points, and a column of cells along z, are contiguous;
    ``cells`` (N, 3) their cell indices, ``starts`` (nx * ny * nz + 1,) where each cell's run begins.
    The search gathers the distances to the points of the cube of 3^3 cells around a point's cell, then
    of the shells of cells at Chebyshev distance r = 2, 3, ..., and stops when k are gathered and the
    k-th smallest (a quickselect) is within the distance from the point to the outside of the scanned
    cube, so the result is exact. Needs N > k.
    """
    cdef Py_ssize_t i, n = points.shape[0]
    cdef Buf buf
    cdef const double* pts = &points[0, 0]
    buf.cap = 256
    buf.d2 = <double*>malloc(buf.cap * sizeof(double))
    if buf.d2 == NULL:
        raise MemoryError()
    try:
        with nogil:
            for i in range(n):
                out[i] = _knn_mean_one(pts, cells, starts, nx, ny, nz, cell_m, lo, k, i, &buf)
                if isnan(out[i]):
                    break
        if n and isnan(out[i]):
            raise MemoryError()
    finally:
        free(buf.d2)


def nearest_within(const double[:, ::1] points, const int64_t[::1] starts, int64_t nx, int64_t ny, int64_t nz,
                   double cell_m, const double[::1] lo, const double[:, ::1] queries, double max_m,
                   int64_t[::1] out_index, double[::1] out_d2):
    """Nearest point within ``max_m`` [m] of each query (Q, 3): its index into ``points`` and squared
    distance into ``out_index`` / ``out_d2`` (Q,), or -1 / inf when there is none.

    ``points`` (N, 3) sorted by the flat index of their cell in a grid of ``cell_m`` cells with corner
    ``lo`` and shape (nx, ny, nz); ``starts`` (nx * ny * nz + 1,) where each cell's run begins. The cubes
    of cells around the query's cell grow until the nearest point found is within the distance from the
    query to the outside of the cube, or that distance reaches ``max_m``: the result is exact. Ties go to
    the point scanned first (lowest cell, then lowest index).
    """
    cdef Py_ssize_t q, j, nq = queries.shape[0]
    cdef int64_t r, cx, cy, cz, x, y, z, x0, x1, y0, y1, z0, z1, c, best_j
    cdef double px, py, pz, dx, dy, dz, d2, best, reach, max2 = max_m * max_m
    cdef const double* pts = &points[0, 0]
    with nogil:
        for q in range(nq):
            px, py, pz = queries[q, 0], queries[q, 1], queries[q, 2]
            cx = <int64_t>floor((px - lo[0]) / cell_m)
            cy = <int64_t>floor((py - lo[1]) / cell_m)
            cz = <int64_t>floor((pz - lo[2]) / cell_m)
            best = INFINITY
            best_j = -1
            r = 0
            while True:
                x0, x1 = max(cx - r, 0), min(cx + r, nx - 1)
                y0, y1 = max(cy - r, 0), min(cy + r, ny - 1)
                z0, z1 = max(cz - r, 0), min(cz + r, nz - 1)
                for x in range(x0, x1 + 1):
                    for y in range(y0, y1 + 1):
                        c = (x * ny + y) * nz
                        for z in range(z0, z1 + 1):
                            # only the shell at Chebyshev distance r is new
                            if (r > 0 and x != cx - r and x != cx + r and y != cy - r and y != cy + r
                                    and z != cz - r and z != cz + r):
                                continue
                            for j in range(starts[c + z], starts[c + z + 1]):
                                dx = pts[3 * j] - px
                                dy = pts[3 * j + 1] - py
                                dz = pts[3 * j + 2] - pz
                                d2 = dx * dx + dy * dy + dz * dz
                                if d2 < best:
                                    best = d2
                                    best_j = j
                # distance from the query to the outside of the scanned cube
                reach = min(min(px - (lo[0] + (cx - r) * cell_m), lo[0] + (cx + r + 1) * cell_m - px),
                            min(min(py - (lo[1] + (cy - r) * cell_m), lo[1] + (cy + r + 1) * cell_m - py),
                                min(pz - (lo[2] + (cz - r) * cell_m), lo[2] + (cz + r + 1) * cell_m - pz)))
                if best <= reach * reach or reach >= max_m:
                    break
                r += 1
            if best <= max2:
                out_index[q] = best_j
                out_d2[q] = best
            else:
                out_index[q] = -1
                out_d2[q] = INFINITY


def k_nearest_within(const double[:, ::1] points, const int64_t[::1] starts, int64_t nx, int64_t ny,
                     int64_t nz, double cell_m, const double[::1] lo, const double[:, ::1] queries,
                     double radius_m, int64_t[:, ::1] out_index):
    """The at most k = out_index.shape[1] nearest points within ``radius_m`` [m] of each query (Q, 3):
    their indices into ``points``, nearest first, -1 after the last (ties: the point scanned first).

    ``points``, ``starts``, the grid shape, ``cell_m`` and ``lo`` as for ``nearest_within``; the cell
    must be at least ``radius_m``, so that the 3^3 cells around a query hold every point within reach.
    """
    cdef Py_ssize_t q, j, nq = queries.shape[0]
    cdef int k = out_index.shape[1]
    cdef int m, found
    cdef int64_t cx, cy, cz, x, y, c
    cdef double px, py, pz, dx, dy, dz, d2, r2 = radius_m * radius_m
    cdef const double* pts = &points[0, 0]
    cdef double* best = <double*>malloc(k * sizeof(double))
    cdef int64_t* best_j = <int64_t*>malloc(k * sizeof(int64_t))
    if best == NULL or best_j == NULL:
        free(best)
        free(best_j)
        raise MemoryError()
    with nogil:
        for q in range(nq):
            px, py, pz = queries[q, 0], queries[q, 1], queries[q, 2]
            cx = <int64_t>floor((px - lo[0]) / cell_m)
            cy = <int64_t>floor((py - lo[1]) / cell_m)
            cz = <int64_t>floor((pz - lo[2]) / cell_m)
            found = 0
            for x in range(max(cx - 1, 0), min(cx + 1, nx - 1) + 1):
                for y in range(max(cy - 1, 0), min(cy + 1, ny - 1) + 1):
                    c = (x * ny + y) * nz
                    if cz + 1 < 0 or cz - 1 > nz - 1:
                        continue
                    for j in range(starts[c + max(cz - 1, 0)], starts[c + min(cz + 1, nz - 1) + 1]):
                        dx = pts[3 * j] - px
                        dy = pts[3 * j + 1] - py
                        dz = pts[3 * j + 2] - pz
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 > r2 or (found == k and d2 >= best[k - 1]):
                            continue
                        m = found if found < k else k - 1
                        while m > 0 and best[m - 1] > d2:
                            best[m] = best[m - 1]
                            best_j[m] = best_j[m - 1]
                            m -= 1
                        best[m] = d2
                        best_j[m] = j
                        if found < k:
                            found += 1
            for m in range(k):
                out_index[q, m] = best_j[m] if m < found else -1
    free(best)
    free(best_j)
