# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled inner loops of the perception layer (built by ``pip install -e .``, see setup.py).

- ``integrate_rays``: one scan into the block-sparse log-odds grid of ``occupancy.OccupancyMap`` with
  OctoMap's sensor model (visual-servoing paper section II-A 3), by exact voxel traversal
  (Amanatides and Woo, 1987), several rays at once in the SIMD lanes of ``_ray_lanes.h`` where the
  processor has them;
- ``knn_mean_distances``: the mean distance of each point to its k nearest neighbours, the statistic of
  the statistical outlier removal (``filters.statistical_outlier_mask``), by an exact uniform-grid search;
- ``nearest_within`` / ``k_nearest_within``: exact grid searches for ICP correspondences and normals;
- ``voxel_groups``: crop box and voxel filter in one pass over a raw frame (``cloud.voxel_downsample``);
- ``plane_normals``: covariance and smallest eigenvector per neighbourhood (``registration.estimate_normals``);
- ``radius_components``: Euclidean clusters by union-find (``segmentation.euclidean_cluster_labels``).

All are plain loops over typed memoryviews (no numpy C API): the callers own the arrays and their
layout, and check shapes and dtypes before calling.
"""

from libc.math cimport INFINITY, NAN, fabs, floor, isnan, sqrt
from libc.stdint cimport int32_t, int64_t, uint8_t, uint32_t, uint64_t
from libc.stdlib cimport calloc, free, llabs, malloc
from libc.string cimport memcpy

cdef enum:
    BLOCK_BITS = 4
    BLOCK_MASK = 15
    BLOCK_VOXELS = 4096

cdef enum:
    COUNT_BITS = 16
    COUNT_MASK = 0xFFFF  # a count saturates there

cdef enum:
    # integrate_rays marks the misses in a dense box only when it holds at most this many voxels per
    # step of the walks: a voxel of the box costs a byte to clear and to sweep (8 at a time), a step of
    # the walk in the pool several nanoseconds
    DENSE_PER_STEP = 16

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
    uint32_t* counts     # scans that updated each voxel: hits in the low 16 bits, misses in the high 16
    float* sides         # (3 per voxel) sum of the unit directions of its hits; NaN: hit from both sides
    int32_t* n_occupied  # occupied voxels per block
    int64_t* coords      # (capacity, 3) block keys of each slot
    int64_t n_blocks
    int64_t capacity
    uint32_t scan
    float l_hit, l_miss, l_min, l_max, l_occ


cdef inline int64_t _block(Grid* g, int64_t lx, int64_t ly, int64_t lz) noexcept nogil:
    """Entry of the block index for the voxel (lx, ly, lz), its key less the index's first (ox, oy, oz)."""
    return (((lx >> BLOCK_BITS) * g.sy) + (ly >> BLOCK_BITS)) * g.sz + (lz >> BLOCK_BITS)


cdef inline int64_t _in_slot(int64_t slot, int64_t lx, int64_t ly, int64_t lz) noexcept nogil:
    """Pool index of the voxel (lx, ly, lz) (as for ``_block``) in the block stored at ``slot``."""
    return slot * BLOCK_VOXELS + (((lx & BLOCK_MASK) << (2 * BLOCK_BITS))
                                  | ((ly & BLOCK_MASK) << BLOCK_BITS) | (lz & BLOCK_MASK))


cdef inline int64_t _local_voxel(Grid* g, int64_t lx, int64_t ly, int64_t lz) noexcept nogil:
    """Pool index of the voxel (lx, ly, lz) (as for ``_block``), allocating its block; -1 when the pool
    is full."""
    cdef int64_t b = _block(g, lx, ly, lz)
    cdef int64_t slot = g.index[b]
    if slot < 0:
        if g.n_blocks == g.capacity:
            return -1
        slot = g.n_blocks
        g.index[b] = <int32_t>slot
        g.coords[3 * slot] = (g.ox + lx) >> BLOCK_BITS
        g.coords[3 * slot + 1] = (g.oy + ly) >> BLOCK_BITS
        g.coords[3 * slot + 2] = (g.oz + lz) >> BLOCK_BITS
        g.n_blocks += 1
    return _in_slot(slot, lx, ly, lz)


cdef inline void _apply(Grid* g, int64_t v, bint hit) noexcept nogil:
    """Apply a hit or a miss to pool voxel v, not yet updated in this scan, and stamp it."""
    cdef float lo, old
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
    if hit:
        if (g.counts[v] & COUNT_MASK) != COUNT_MASK:
            g.counts[v] += 1
    elif (g.counts[v] >> COUNT_BITS) != COUNT_MASK:
        g.counts[v] += 1 << COUNT_BITS
    # NaN (unknown) compares False: not occupied
    if (lo > g.l_occ) != (old > g.l_occ):
        g.n_occupied[v // BLOCK_VOXELS] += 1 if lo > g.l_occ else -1


cdef enum:
    POOL_FULL = -1  # _update: the pool is full
    UPDATED = -2    # _update: the voxel was already updated in this scan


cdef inline int64_t _update(Grid* g, int64_t x, int64_t y, int64_t z, bint hit) noexcept nogil:
    """Apply a hit or a miss to voxel key (x, y, z) unless it was already updated in this scan (OctoMap:
    one update per voxel per scan). Its pool index when applied, else ``UPDATED`` or ``POOL_FULL``."""
    cdef int64_t v = _local_voxel(g, x - g.ox, y - g.oy, z - g.oz)
    if v < 0:
        return POOL_FULL
    if g.stamp[v] == g.scan:
        return UPDATED
    _apply(g, v, hit)
    return v


cdef inline bint _hit(Grid* g, int64_t x, int64_t y, int64_t z, const double* og, const double* pg
                      ) noexcept nogil:
    """``_update`` of the end voxel (x, y, z) of a ray from ``og`` to ``pg`` (grid units) with a hit; the
    scan's first hit of the voxel also adds the ray's unit direction to its ``sides``, or marks them NaN
    (hit from both sides, for good) when it points against their sum. False when the pool is full."""
    cdef int64_t v = _update(g, x, y, z, True)
    cdef double h[3]
    cdef double norm = 0.0, along = 0.0
    cdef float* m
    cdef int a
    if v < 0:
        return v != POOL_FULL
    m = g.sides + 3 * v
    if isnan(m[0]):
        return True
    for a in range(3):
        h[a] = pg[a] - og[a]
        norm += h[a] * h[a]
    if norm == 0.0:
        return True
    norm = sqrt(norm)
    for a in range(3):
        h[a] /= norm
        along += m[a] * h[a]
    if along < 0.0:
        m[0] = m[1] = m[2] = NAN
    else:
        for a in range(3):
            m[a] += <float>h[a]
    return True


cdef inline void _keep_surface(Grid* g, int64_t x, int64_t y, int64_t z) noexcept nogil:
    """Stamp the occupied voxels among the 26 neighbours of hit voxel (x, y, z), so that no ray of this
    scan carves them (see ``OccupancyParams.keep_surface``); neighbours outside the block index or in
    blocks not allocated are unknown, not occupied, and are left alone."""
    cdef int64_t dx, dy, dz, lx, ly, lz, slot, v
    for dx in range(-1, 2):
        lx = x + dx - g.ox
        if lx < 0 or lx >= (g.sx << BLOCK_BITS):
            continue
        for dy in range(-1, 2):
            ly = y + dy - g.oy
            if ly < 0 or ly >= (g.sy << BLOCK_BITS):
                continue
            for dz in range(-1, 2):
                lz = z + dz - g.oz
                if lz < 0 or lz >= (g.sz << BLOCK_BITS):
                    continue
                slot = g.index[_block(g, lx, ly, lz)]
                if slot < 0:
                    continue
                v = _in_slot(slot, lx, ly, lz)
                if g.pool[v] > g.l_occ:
                    g.stamp[v] = g.scan


cdef inline int64_t _run_length(int64_t c, int64_t s, int64_t n) noexcept nogil:
    """Steps an axis of a walk takes from voxel coordinate c (step s, n crossings left) before its next
    event: its last crossing, or the step into the next block."""
    cdef int64_t edge = (BLOCK_MASK + 1 - (c & BLOCK_MASK)) if s > 0 else (c & BLOCK_MASK) + 1
    return n if n < edge else edge


cdef inline bint _run_ends(int64_t c, int64_t s, int64_t* n, int64_t* run, double* t) noexcept nogil:
    """An axis' run has ended at coordinate c: start its next one (``run`` steps, ``n`` crossings left
    after it; its next crossing t never when none is left); True when the run ended by a step into
    another block (the pool index is then stale: look it up)."""
    if n[0] == 0:
        t[0] = INFINITY
    run[0] = _run_length(c, s, n[0])
    n[0] -= run[0]
    return (c & BLOCK_MASK) == (0 if s > 0 else BLOCK_MASK)


cdef inline bint _step_run(int64_t* c, int64_t s, int64_t* v, int64_t dv, double* t, double dt, int64_t* run,
                           int64_t* n) noexcept nogil:
    """One crossing of an axis of ``_traverse``'s walk: its coordinate c moves by its step s, the pool index
    v by dv, its next crossing t by dt, and its run counts down; True when the run ended by a step into
    another block (``_run_ends``: the pool index is then stale)."""
    c[0] += s
    v[0] += dv
    t[0] += dt
    run[0] -= 1
    return _run_ends(c[0], s, n, run, t) if run[0] == 0 else False


cdef inline int _next_axis(double tx, double ty, double tz) noexcept nogil:
    """The axis (0, 1, 2) whose boundary a walk crosses next: the smallest t; OctoMap's order on ties,
    y before x, z before both."""
    if ty <= tx:
        return 1 if ty < tz else 2
    return 0 if tx < tz else 2


cdef inline int64_t _ray_setup(const double* o, const int64_t* k0, const double* e, const int64_t* ke,
                               int64_t* left, int64_t* step, double* t_max, double* t_delta) noexcept nogil:
    """Start of the walk o -> e (grid units) from voxel k0 to voxel ke: per axis the crossings ``left``,
    the ``step`` (+-1), the parameter t of the first crossing ``t_max`` and between crossings ``t_delta``
    (never, INFINITY, for an axis without crossings); returns the crossings in all, |ke - k0|_1."""
    cdef double d
    cdef int64_t total = 0
    cdef int a
    for a in range(3):
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
    return total


cdef bint _traverse(Grid* g, const double* o, const int64_t* k0, const double* e, const int64_t* ke,
                    bint end_free) noexcept nogil:
    """Misses for the voxels of the segment o -> e (grid units) from the voxel k0 of o up to the voxel ke
    of e, ke itself only when ``end_free``. As OctoMap's computeRayKeys, a ray inside one voxel marks
    nothing (unless ``end_free``). The next boundary crossed is the one at the smallest parameter t
    (ties go to the higher axis, as OctoMap); counting the crossings left per axis makes the walk end
    exactly at ke whatever the rounding of t.

    A step does the least it can: the pool index moves by a constant per axis, and each axis counts down
    the steps of its run, up to its next event (``_run_length``): only then is the block index looked
    up or the axis retired."""
    cdef int64_t left[3]
    cdef int64_t step[3]
    cdef double t_max[3]
    cdef double t_delta[3]
    cdef int64_t total = _ray_setup(o, k0, e, ke, left, step, t_max, t_delta), v
    cdef int a
    if total == 0:
        return _update(g, k0[0], k0[1], k0[2], False) != POOL_FULL if end_free else True
    # the walk's state in scalars, so that it stays in registers
    cdef int64_t x = k0[0] - g.ox, y = k0[1] - g.oy, z = k0[2] - g.oz
    cdef int64_t sx = step[0], sy = step[1], sz = step[2]
    cdef int64_t rx = _run_length(x, sx, left[0]), ry = _run_length(y, sy, left[1])
    cdef int64_t rz = _run_length(z, sz, left[2])
    cdef int64_t nx = left[0] - rx, ny = left[1] - ry, nz = left[2] - rz
    cdef int64_t dvx = sx << (2 * BLOCK_BITS), dvy = sy << BLOCK_BITS, dvz = sz
    cdef double tx = t_max[0], ty = t_max[1], tz = t_max[2]
    cdef double dtx = t_delta[0], dty = t_delta[1], dtz = t_delta[2]
    cdef bint stale
    # in locals: the compiler would reload them from g after every call of _apply
    cdef const uint32_t* stamp = g.stamp
    cdef uint32_t scan = g.scan
    v = _local_voxel(g, x, y, z)
    if v < 0:
        return False
    if stamp[v] != scan:
        _apply(g, v, False)
    while total > 1:
        a = _next_axis(tx, ty, tz)
        if a == 1:
            stale = _step_run(&y, sy, &v, dvy, &ty, dty, &ry, &ny)
        elif a == 0:
            stale = _step_run(&x, sx, &v, dvx, &tx, dtx, &rx, &nx)
        else:
            stale = _step_run(&z, sz, &v, dvz, &tz, dtz, &rz, &nz)
        total -= 1
        if stale:
            v = _local_voxel(g, x, y, z)
            if v < 0:
                return False
        if stamp[v] != scan:
            _apply(g, v, False)
    if end_free:
        return _update(g, ke[0], ke[1], ke[2], False) != POOL_FULL
    return True


cdef struct Marks:
    uint8_t* seen       # one byte per voxel of the box, x slowest, z fastest: 1 = a ray of the scan crossed it
    int64_t lx, ly, lz  # voxel key of the box's first corner
    int64_t nx, ny, nz  # its shape, nz a multiple of 8 (a row is swept 8 voxels at a time)


cdef extern from "_ray_lanes.h" nogil:
    ctypedef struct RayWalk:
        double t[3]
        double dt[3]
        int64_t n[3]
        int64_t dv[3]
        int64_t v
        int64_t total
    enum: RAY_LANES
    bint ray_lanes_available()
    void ray_lanes_walk(RayWalk* w, uint8_t* seen, int64_t steps)


cdef inline int64_t _mark_index(Marks* m, int64_t x, int64_t y, int64_t z) noexcept nogil:
    return ((x - m.lx) * m.ny + (y - m.ly)) * m.nz + (z - m.lz)


cdef inline int64_t _cross(double* t, double dt, int64_t* n, int64_t dv) noexcept nogil:
    """One crossing of an axis: its next crossing ``t`` moves on by ``dt``, or to never (INFINITY) after
    its last of ``n``; returns the move ``dv`` of the voxel index."""
    t[0] += dt
    n[0] -= 1
    if n[0] == 0:
        t[0] = INFINITY
    return dv


cdef void _mark_start(Marks* m, const double* o, const int64_t* k0, const double* e, const int64_t* ke,
                      RayWalk* w) noexcept nogil:
    """Start in ``w`` the walk of ``_traverse`` for the segment o -> e (grid units), k0 -> ke, in the
    dense box ``m``, and mark its first voxel (k0, unless the ray stays in it)."""
    cdef int64_t left[3]
    cdef int64_t step[3]
    cdef int64_t stride[3]
    cdef int a
    w.total = _ray_setup(o, k0, e, ke, left, step, w.t, w.dt)
    stride[0], stride[1], stride[2] = m.ny * m.nz, m.nz, 1
    for a in range(3):
        w.n[a] = left[a]
        w.dv[a] = step[a] * stride[a]
    w.v = _mark_index(m, k0[0], k0[1], k0[2])
    if w.total > 0:
        m.seen[w.v] = 1


cdef void _mark_walk(const RayWalk* w, uint8_t* seen) noexcept nogil:
    """Walk on from ``w`` up to the voxel before the end one, marking each voxel in ``seen``: the walk of
    ``_traverse`` (same arithmetic, same order on ties, the same crossings per axis), but in a dense box,
    where a step is a constant move of the index per axis and a store of 1, whether or not an earlier ray
    of the scan marked the voxel: no block runs, no stamp to read, no branch on it."""
    # the state in locals, so that it stays in registers (a store to seen may alias *w)
    cdef int64_t v = w.v, total = w.total
    cdef int64_t nx = w.n[0], ny = w.n[1], nz = w.n[2]
    cdef int64_t dvx = w.dv[0], dvy = w.dv[1], dvz = w.dv[2]
    cdef double tx = w.t[0], ty = w.t[1], tz = w.t[2]
    cdef double dtx = w.dt[0], dty = w.dt[1], dtz = w.dt[2]
    cdef int a
    while total > 1:
        a = _next_axis(tx, ty, tz)
        if a == 1:
            v += _cross(&ty, dty, &ny, dvy)
        elif a == 0:
            v += _cross(&tx, dtx, &nx, dvx)
        else:
            v += _cross(&tz, dtz, &nz, dvz)
        total -= 1
        seen[v] = 1


cdef inline void _mark_end(Marks* m, const int64_t* ke, bint end_free) noexcept nogil:
    """The end voxel of a ray is marked only for a ray without a target (``_traverse``'s end_free)."""
    if end_free:
        m.seen[_mark_index(m, ke[0], ke[1], ke[2])] = 1


cdef void _mark_ray(Marks* m, const double* o, const int64_t* k0, const double* e, const int64_t* ke,
                    bint end_free) noexcept nogil:
    """Mark in ``m`` the voxels ``_traverse`` would give a miss."""
    cdef RayWalk w
    _mark_start(m, o, k0, e, ke, &w)
    _mark_walk(&w, m.seen)
    _mark_end(m, ke, end_free)


cdef int64_t* _order_by_crossings(const int64_t* keys, Py_ssize_t n, const int64_t* k0) noexcept nogil:
    """The rays' indices (malloc'd, n) sorted by their crossings |ke - k0|_1, by a counting sort; NULL
    when memory fails."""
    cdef int64_t* total = <int64_t*>malloc(n * sizeof(int64_t) + 1)
    cdef int64_t* order = <int64_t*>malloc(n * sizeof(int64_t) + 1)
    cdef int64_t* start = NULL
    cdef int64_t longest = 0
    cdef Py_ssize_t i
    if total != NULL and order != NULL:
        for i in range(n):
            total[i] = (llabs(keys[3 * i] - k0[0]) + llabs(keys[3 * i + 1] - k0[1])
                        + llabs(keys[3 * i + 2] - k0[2]))
            longest = max(longest, total[i])
        start = <int64_t*>calloc(longest + 2, sizeof(int64_t))
    if start == NULL:
        free(total)
        free(order)
        return NULL
    for i in range(n):
        start[total[i] + 1] += 1
    for i in range(longest + 1):
        start[i + 1] += start[i]
    for i in range(n):
        order[start[total[i]]] = i
        start[total[i]] += 1
    free(total)
    free(start)
    return order


cdef void _mark_rays(Marks* m, const double* og, const int64_t* k0, const double* pg, const int64_t* keys,
                     const uint8_t* kinds, Py_ssize_t n, bint lanes) noexcept nogil:
    """Mark in ``m`` the voxels of all the rays (ends ``pg`` / ``keys`` (n, 3), grid units / voxels).

    With ``lanes``, where the processor has those of ``_ray_lanes.h``, the rays go there RAY_LANES at a time: sorted
    by their number of crossings, so that the walks of a group are about as long, the group walks
    together as far as its shortest walk goes less one crossing, then each walk finishes alone (a few
    crossings at most). Otherwise, and for the rays left over, one ray at a time."""
    cdef RayWalk w[RAY_LANES]
    cdef int64_t* order = _order_by_crossings(keys, n, k0) if lanes and ray_lanes_available() else NULL
    cdef int64_t j, r, steps
    cdef Py_ssize_t i = 0
    cdef int l
    if order != NULL:
        while i + RAY_LANES <= n:
            steps = -1
            for l in range(RAY_LANES):
                r = order[i + l]
                _mark_start(m, og, k0, pg + 3 * r, keys + 3 * r, &w[l])
                steps = w[l].total - 1 if steps < 0 else min(steps, w[l].total - 1)
            if steps > 0:
                ray_lanes_walk(w, m.seen, steps)
            for l in range(RAY_LANES):
                r = order[i + l]
                _mark_walk(&w[l], m.seen)
                _mark_end(m, keys + 3 * r, kinds[r] == K_FREE)
            i += RAY_LANES
    for j in range(i, n):
        r = order[j] if order != NULL else j
        _mark_ray(m, og, k0, pg + 3 * r, keys + 3 * r, kinds[r] == K_FREE)
    free(order)


cdef bint _miss_marked(Grid* g, Marks* m) noexcept nogil:
    """A miss for every voxel marked in ``m`` that this scan has not updated yet, swept in key order;
    False when the pool is full. Along a row (x, y fixed) the voxels of one block are consecutive in the
    pool: the block index is read once a block, not once a voxel."""
    cdef int64_t x, y, z, w, lz, bz, v0 = 0
    cdef uint64_t word
    cdef const uint8_t* row
    cdef uint32_t scan = g.scan
    for x in range(m.nx):
        for y in range(m.ny):
            row = m.seen + (x * m.ny + y) * m.nz
            bz = -1  # the block of the row last looked up (relative z >> BLOCK_BITS), none yet
            for w in range(0, m.nz, 8):
                memcpy(&word, row + w, 8)
                if word == 0:  # most of the box: 8 voxels at a time
                    continue
                for z in range(w, w + 8):
                    if not row[z]:
                        continue
                    lz = m.lz + z - g.oz
                    if (lz >> BLOCK_BITS) != bz:
                        bz = lz >> BLOCK_BITS
                        v0 = _local_voxel(g, m.lx + x - g.ox, m.ly + y - g.oy, lz)
                        if v0 < 0:
                            return False
                        v0 -= lz & BLOCK_MASK
                    if g.stamp[v0 + (lz & BLOCK_MASK)] != scan:
                        _apply(g, v0 + (lz & BLOCK_MASK), False)
    return True


cdef inline void _grid_point(const double* p, double resolution, double* pg, int64_t* key) noexcept nogil:
    """A point p [m] in grid units (p / resolution) and its voxel key floor(p / resolution), the same
    arithmetic as ``OccupancyMap.keys_of``, so that a query finds the voxel a ray updated."""
    cdef int a
    for a in range(3):
        pg[a] = p[a] / resolution
        key[a] = _floor(pg[a])


cdef bint _dense_box(Marks* m, const int64_t* keys, Py_ssize_t n, const int64_t* k0,
                     int64_t max_dense_voxels) noexcept nogil:
    """Allocate ``m`` (zeroed) over the box of the voxel k0 of the origin and the end voxels ``keys``
    (n, 3) of the rays, if it holds at most ``max_dense_voxels`` voxels and at most DENSE_PER_STEP per
    step of the walks; False when it does not (or the allocation fails): walk the pool instead."""
    cdef int64_t lo[3]
    cdef int64_t hi[3]
    cdef int64_t steps = 0, volume, k
    cdef Py_ssize_t i
    cdef int a
    for a in range(3):
        lo[a] = hi[a] = k0[a]
    for i in range(n):
        for a in range(3):
            k = keys[3 * i + a]
            lo[a] = min(lo[a], k)
            hi[a] = max(hi[a], k)
            steps += llabs(k - k0[a])
    m.lx, m.ly, m.lz = lo[0], lo[1], lo[2]
    m.nx, m.ny, m.nz = hi[0] - lo[0] + 1, hi[1] - lo[1] + 1, (hi[2] - lo[2] + 8) & ~7
    volume = m.nx * m.ny * m.nz
    m.seen = NULL
    if volume <= max_dense_voxels and volume <= DENSE_PER_STEP * steps:
        m.seen = <uint8_t*>calloc(volume, 1)
    return m.seen != NULL


cdef bint _integrate(Grid* g, const double* og, const int64_t* k0, const double* pg, const int64_t* keys,
                     const uint8_t* kinds, Py_ssize_t n, bint keep_surface, int64_t max_dense_voxels,
                     bint lanes) noexcept nogil:
    """``integrate_rays`` on the rays' ends in grid units ``pg`` (n, 3) and their voxels ``keys``
    (n, 3), the origin's ``og`` and ``k0``; False when the pool is full."""
    cdef Py_ssize_t i
    cdef Marks m
    cdef bint ok
    for i in range(n):
        if kinds[i] == K_HIT and not _hit(g, keys[3 * i], keys[3 * i + 1], keys[3 * i + 2], og, pg + 3 * i):
            return False
    if keep_surface:
        for i in range(n):
            if kinds[i] == K_HIT:
                _keep_surface(g, keys[3 * i], keys[3 * i + 1], keys[3 * i + 2])
    if not _dense_box(&m, keys, n, k0, max_dense_voxels):
        for i in range(n):
            if not _traverse(g, og, k0, pg + 3 * i, keys + 3 * i, kinds[i] == K_FREE):
                return False
        return True
    _mark_rays(&m, og, k0, pg, keys, kinds, n, lanes)
    ok = _miss_marked(g, &m)
    free(m.seen)
    return ok


def ray_lanes():
    """True when this processor walks rays in the SIMD lanes of ``_ray_lanes.h`` (x86-64 with AVX2)."""
    return bool(ray_lanes_available())


def integrate_rays(const double[::1] origin, const double[:, ::1] ends, double resolution,
                   const uint8_t[::1] kinds, int32_t[:, :, ::1] index,
                   int64_t ox, int64_t oy, int64_t oz, float[::1] pool, uint32_t[::1] stamp,
                   uint32_t[::1] counts, float[::1] sides, int32_t[::1] n_occupied, int64_t[:, ::1] block_coords,
                   int64_t n_blocks, uint32_t scan,
                   float l_hit, float l_miss, float l_min, float l_max, float l_occ, bint keep_surface,
                   int64_t max_dense_voxels, bint lanes):
    """Integrate one scan; returns (number of blocks in use, True if done / False if the pool is full).

    ``origin`` (3,) and ``ends`` (N, 3) [m] in the grid's frame, ``resolution`` [m] its voxel edge (voxel
    keys floor(x / resolution)); ``kinds`` (N,) RAY_HIT / RAY_FREE / RAY_TRUNCATED;
    ``index`` the block index covering every key of the scan, its first voxel key (ox, oy, oz);
    ``pool`` / ``stamp`` / ``counts`` the log-odds, scan stamps and hit (low 16 bits) and miss (high 16 bits)
    counts of each voxel (saturating at 65535), ``sides`` (3 per voxel) the sum of the unit directions of
    the rays that hit it (one per scan, the first), NaN once a hit came against that sum, ``n_occupied`` (capacity,) the occupied voxels
    (log-odds above ``l_occ``) of each block, kept up to date, ``block_coords`` (capacity, 3); ``scan`` a number
    not used by an earlier scan. End voxels of hits are updated first, so that a voxel both hit and
    traversed in the scan is updated as occupied only; with ``keep_surface``, the occupied neighbours of
    the hit voxels are then stamped too, so that no ray of the scan carves them. When the pool fills up
    the call stops: grow the pool and call again with the same ``scan``; voxels already updated are
    skipped by their stamp, so the result is the same as one uninterrupted call.

    The misses: most rays of a scan share most of their voxels (all leave the sensor's voxel; a 5 mm map
    of an RGB-D frame has ~90 steps a ray and ~40 rays a traversed voxel), so the walk is the cost, not
    the updates. When the box of the scan holds at most ``max_dense_voxels`` voxels and at most
    DENSE_PER_STEP per step of the walks, the rays only mark their voxels in a dense byte box
    (``_mark_rays``; with ``lanes``, several rays at once in SIMD lanes where the processor has them),
    and one sweep of it applies the misses (``_miss_marked``); otherwise each ray updates the pool as it
    walks (``_traverse``). The set of voxels, hence the map, is the same.
    """
    cdef Grid g
    cdef Py_ssize_t i, n = ends.shape[0]
    cdef bint ok
    cdef double og[3]
    cdef int64_t k0[3]
    # the ends in grid units and their voxels, once for the passes over the rays
    cdef double* pg = <double*>malloc(3 * n * sizeof(double) + 1)
    cdef int64_t* keys = <int64_t*>malloc(3 * n * sizeof(int64_t) + 1)
    if pg == NULL or keys == NULL:
        free(pg)
        free(keys)
        raise MemoryError()
    g.index = &index[0, 0, 0]
    g.sx, g.sy, g.sz = index.shape[0], index.shape[1], index.shape[2]
    g.ox, g.oy, g.oz = ox, oy, oz
    g.pool = &pool[0]
    g.stamp = &stamp[0]
    g.counts = &counts[0]
    if sides.shape[0] != 3 * counts.shape[0]:
        raise ValueError("integrate_rays: sides must hold 3 floats per voxel")
    g.sides = &sides[0]
    g.n_occupied = &n_occupied[0]
    g.coords = &block_coords[0, 0]
    g.n_blocks = n_blocks
    g.capacity = pool.shape[0] // BLOCK_VOXELS
    g.scan = scan
    g.l_hit, g.l_miss, g.l_min, g.l_max, g.l_occ = l_hit, l_miss, l_min, l_max, l_occ
    with nogil:
        _grid_point(&origin[0], resolution, og, k0)
        for i in range(n):
            _grid_point(&ends[i, 0], resolution, pg + 3 * i, keys + 3 * i)
        ok = _integrate(&g, og, k0, pg, keys, &kinds[0], n, keep_surface, max_dense_voxels, lanes)
    free(pg)
    free(keys)
    return g.n_blocks, bool(ok)


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



cdef inline Py_ssize_t _scan_run(const double* pts, Py_ssize_t i, Py_ssize_t first, Py_ssize_t last,
                                 double* buf, Py_ssize_t n) noexcept nogil:
    """Append to buf[n..] the squared distances from point i to points first..last-1 (i excluded);
    returns the new length."""
    cdef Py_ssize_t j
    cdef double dx, dy, dz
    cdef double px = pts[3 * i], py = pts[3 * i + 1], pz = pts[3 * i + 2]
    for j in range(first, last):
        dx = pts[3 * j] - px
        dy = pts[3 * j + 1] - py
        dz = pts[3 * j + 2] - pz
        buf[n] = dx * dx + dy * dy + dz * dz
        n += j != i
    return n


cdef Py_ssize_t _scan_box(const double* pts, const int64_t* starts, int64_t nx, int64_t ny, int64_t nz,
                          int64_t x0, int64_t x1, int64_t y0, int64_t y1, int64_t z0, int64_t z1, int64_t cx,
                          int64_t cy, int64_t cz, int64_t r, Py_ssize_t i, double* buf,
                          Py_ssize_t n) noexcept nogil:
    """Append to buf[n..] the squared distances from point i to the points of the cells in the box
    [x0, x1] x [y0, y1] x [z0, z1] (clamped to the grid) outside the cube of Chebyshev radius r around
    cell (cx, cy, cz) (r < 0: none excluded); returns the new length."""
    cdef int64_t x, y, c, e0, e1
    x0, x1 = max(x0, 0), min(x1, nx - 1)
    y0, y1 = max(y0, 0), min(y1, ny - 1)
    z0, z1 = max(z0, 0), min(z1, nz - 1)
    if z0 > z1:
        return n
    for x in range(x0, x1 + 1):
        for y in range(y0, y1 + 1):
            c = (x * ny + y) * nz
            e0, e1 = max(cz - r, z0), min(cz + r, z1)
            if r < 0 or x < cx - r or x > cx + r or y < cy - r or y > cy + r or e0 > e1:
                n = _scan_run(pts, i, starts[c + z0], starts[c + z1 + 1], buf, n)
                continue
            # the column passes through the excluded cube: the runs below and above it
            if z0 < e0:
                n = _scan_run(pts, i, starts[c + z0], starts[c + e0], buf, n)
            if e1 < z1:
                n = _scan_run(pts, i, starts[c + e1 + 1], starts[c + z1 + 1], buf, n)
    return n


cdef inline Py_ssize_t _front(double* buf, Py_ssize_t n, double bound) noexcept nogil:
    """Move the values of buf[0..n-1] at most ``bound`` to its front (branch-free swaps; the order of
    the others is kept behind them); returns how many there are."""
    cdef Py_ssize_t j, m = 0
    cdef double t
    for j in range(n):
        t = buf[j]
        buf[j] = buf[m]
        buf[m] = t
        m += t <= bound
    return m


cdef double _knn_mean_one(const double* pts, const int64_t* cells, const int64_t* starts, int64_t nx,
                          int64_t ny, int64_t nz, double cell_m, const double* lo, int k, Py_ssize_t i,
                          double* buf, double* hint) noexcept nogil:
    """knn_mean_distances for point i, with the caller's buffer buf (N,) and hint (the previous point's
    squared k-th distance, updated); arrays as raw pointers (a memoryview argument costs a reference
    count per call)."""
    cdef int64_t r = 1, cx = cells[3 * i], cy = cells[3 * i + 1], cz = cells[3 * i + 2]
    cdef double px = pts[3 * i], py = pts[3 * i + 1], pz = pts[3 * i + 2]
    cdef double reach, dk, kth, s = 0.0
    cdef Py_ssize_t n, m2
    cdef int m
    n = _scan_box(pts, starts, nx, ny, nz, cx - 1, cx + 1, cy - 1, cy + 1, cz - 1, cz + 1, cx, cy, cz, -1, i,
                  buf, 0)
    # too few yet: grow the cube shell by shell until k are held (N > k: the grid holds them)
    while n < k:
        r += 1
        n = _scan_box(pts, starts, nx, ny, nz, cx - r, cx + r, cy - r, cy + r, cz - r, cz + r, cx, cy, cz, r - 1,
                      i, buf, n)
    # distance from the point to the outside of the scanned cube: nothing beyond it can be closer
    reach = min(min(px - (lo[0] + (cx - r) * cell_m), lo[0] + (cx + r + 1) * cell_m - px),
                min(min(py - (lo[1] + (cy - r) * cell_m), lo[1] + (cy + r + 1) * cell_m - py),
                    min(pz - (lo[2] + (cz - r) * cell_m), lo[2] + (cz + r + 1) * cell_m - pz)))
    # When k candidates lie within a bound, the k nearest are among them: move those to the front (a
    # branch-free pass of swaps, the others kept behind) and select among them only: the mispredicted
    # branches of the selection cost far more than the distances. The bound is first the previous
    # point's k-th distance widened by 20% (points come in grid order: a neighbour's, mostly), then the
    # reach of the cube.
    m2 = _front(buf, n, min(reach * reach, 1.44 * hint[0]))
    if m2 < k:
        m2 = _front(buf, n, reach * reach)
    kth = _select(buf, m2 if m2 >= k else n, k)
    hint[0] = kth
    if kth > reach * reach:
        # exact: add the cells within the k-th distance of the point that the cube left out
        dk = sqrt(kth)
        n = _scan_box(pts, starts, nx, ny, nz,
                      <int64_t>floor((px - dk - lo[0]) / cell_m), <int64_t>floor((px + dk - lo[0]) / cell_m),
                      <int64_t>floor((py - dk - lo[1]) / cell_m), <int64_t>floor((py + dk - lo[1]) / cell_m),
                      <int64_t>floor((pz - dk - lo[2]) / cell_m), <int64_t>floor((pz + dk - lo[2]) / cell_m),
                      cx, cy, cz, r, i, buf, k)
        _select(buf, n, k)
    for m in range(k):
        s += sqrt(buf[m])
    return s / k


def knn_mean_distances(const double[:, ::1] points, const int64_t[:, ::1] cells, const int64_t[::1] starts,
                       int64_t nx, int64_t ny, int64_t nz, double cell_m, const double[::1] lo, int k,
                       double[::1] out):
    """Mean Euclidean distance of each point to its ``k`` nearest other points, into ``out`` (N,).

    The points (N, 3) lie in a grid of ``cell_m`` cells with corner ``lo`` and shape (nx, ny, nz), sorted
    by flat cell index (x, y, z) so that a cell's points, and a column of cells along z, are contiguous;
    ``cells`` (N, 3) their cell indices, ``starts`` (nx * ny * nz + 1,) where each cell's run begins.
    The search gathers the squared distances to the points of the cube of 3^3 cells around a point's
    cell, growing it by shells of cells until k are gathered, and selects the k-th smallest (quickselect)
    among those below a bound when k of them are (the previous point's k-th distance widened by 20%,
    else the distance to the outside of the cube), else among all; when that distance reaches outside
    the cube, the cells of the box of that radius around the point
    that the cube left out are gathered too (after the k kept) and the selection is repeated, so the
    result is exact. The k distances are summed in an order fixed by the points' order. Needs N > k.
    """
    cdef Py_ssize_t i, n = points.shape[0]
    cdef const double* pts = &points[0, 0]
    cdef double hint = INFINITY
    cdef double* buf = <double*>malloc(n * sizeof(double))
    if buf == NULL:
        raise MemoryError()
    with nogil:
        for i in range(n):
            out[i] = _knn_mean_one(pts, &cells[0, 0], &starts[0], nx, ny, nz, cell_m, &lo[0], k, i, buf,
                                   &hint)
    free(buf)


cdef inline void _nearest_in_run(const double* pts, Py_ssize_t first, Py_ssize_t last, double px, double py,
                                 double pz, double* best, Py_ssize_t* best_j) noexcept nogil:
    """Keep in best / best_j the squared distance and index of the nearest of points first..last-1
    to (px, py, pz) if nearer than best (ties: the earlier point)."""
    cdef Py_ssize_t j
    cdef double dx, dy, dz, d2
    for j in range(first, last):
        dx = pts[3 * j] - px
        dy = pts[3 * j + 1] - py
        dz = pts[3 * j + 2] - pz
        d2 = dx * dx + dy * dy + dz * dz
        if d2 < best[0]:
            best[0] = d2
            best_j[0] = j


cdef Py_ssize_t _nearest_one(const double* pts, const int64_t* starts, int64_t nx, int64_t ny, int64_t nz,
                             double cell_m, const double* lo, double px, double py, double pz, double max_m,
                             double* out_d2) noexcept nogil:
    """``nearest_within`` for one query (px, py, pz): the index of its nearest point within ``max_m``
    and its squared distance into out_d2, or -1 and inf."""
    cdef int64_t r = 0, cx, cy, cz, x, y, x0, x1, y0, y1, z0, z1, c
    cdef Py_ssize_t best_j = -1
    cdef double best = INFINITY, reach
    cx = <int64_t>floor((px - lo[0]) / cell_m)
    cy = <int64_t>floor((py - lo[1]) / cell_m)
    cz = <int64_t>floor((pz - lo[2]) / cell_m)
    while True:
        x0, x1 = max(cx - r, 0), min(cx + r, nx - 1)
        y0, y1 = max(cy - r, 0), min(cy + r, ny - 1)
        z0, z1 = max(cz - r, 0), min(cz + r, nz - 1)
        for x in range(x0, x1 + 1):
            for y in range(y0, y1 + 1):
                c = (x * ny + y) * nz
                # only the shell at Chebyshev distance r is new: a whole column on its x-y
                # boundary, else its two z caps
                if r == 0 or x == cx - r or x == cx + r or y == cy - r or y == cy + r:
                    if z0 <= z1:  # else the query's cube lies above or below the grid
                        _nearest_in_run(pts, starts[c + z0], starts[c + z1 + 1], px, py, pz, &best, &best_j)
                    continue
                if 0 <= cz - r < nz:
                    _nearest_in_run(pts, starts[c + cz - r], starts[c + cz - r + 1], px, py, pz, &best,
                                    &best_j)
                if 0 <= cz + r < nz:
                    _nearest_in_run(pts, starts[c + cz + r], starts[c + cz + r + 1], px, py, pz, &best,
                                    &best_j)
        # distance from the query to the outside of the scanned cube
        reach = min(min(px - (lo[0] + (cx - r) * cell_m), lo[0] + (cx + r + 1) * cell_m - px),
                    min(min(py - (lo[1] + (cy - r) * cell_m), lo[1] + (cy + r + 1) * cell_m - py),
                        min(pz - (lo[2] + (cz - r) * cell_m), lo[2] + (cz + r + 1) * cell_m - pz)))
        if best <= reach * reach or reach >= max_m:
            break
        r += 1
    if best <= max_m * max_m:
        out_d2[0] = best
        return best_j
    out_d2[0] = INFINITY
    return -1


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
    cdef Py_ssize_t q, nq = queries.shape[0]
    with nogil:
        for q in range(nq):
            out_index[q] = _nearest_one(&points[0, 0], &starts[0], nx, ny, nz, cell_m, &lo[0], queries[q, 0],
                                        queries[q, 1], queries[q, 2], max_m, &out_d2[q])


def point_to_plane_system(const double[:, ::1] points, const double[:, ::1] normals, const int64_t[::1] starts,
                          int64_t nx, int64_t ny, int64_t nz, double cell_m, const double[::1] lo,
                          const double[:, ::1] source, const double[:, ::1] T, double max_m,
                          double max_tangential_m, double[:, ::1] ata_out, double[::1] atb_out):
    """One linearised point-to-plane ICP system in one pass over the source (N, 3) [m]: each point p
    moved by the 4x4 ``T`` is paired with its nearest target point q within ``max_m`` (as
    ``nearest_within``; ``points`` and ``normals`` (M, 3) sorted by cell, the grid as there), and the
    pair is kept only if p lies within ``max_tangential_m`` [m] of q along q's tangent plane
    (|p - q|^2 - r^2 <= max_tangential_m^2); with the residual r = (p - q) . n and the row
    a = [p x n, n] of the motion (rotation vector, translation), ``ata_out`` (6, 6) receives sum a^T a
    and ``atb_out`` (6,) -sum a r, summed in source order.
    Returns (the number of pairs kept, the sum of r^2 [m^2])."""
    cdef Py_ssize_t i, j, n = source.shape[0], count = 0
    cdef int a, b
    cdef double sx, sy, sz, px, py, pz, nxv, nyv, nzv, r, d2, sse = 0.0
    cdef double t2 = max_tangential_m * max_tangential_m
    cdef double row[6]
    cdef double ata[36]
    cdef double atb[6]
    for a in range(36):
        ata[a] = 0.0
    for a in range(6):
        atb[a] = 0.0
    with nogil:
        for i in range(n):
            sx, sy, sz = source[i, 0], source[i, 1], source[i, 2]
            px = T[0, 0] * sx + T[0, 1] * sy + T[0, 2] * sz + T[0, 3]
            py = T[1, 0] * sx + T[1, 1] * sy + T[1, 2] * sz + T[1, 3]
            pz = T[2, 0] * sx + T[2, 1] * sy + T[2, 2] * sz + T[2, 3]
            j = _nearest_one(&points[0, 0], &starts[0], nx, ny, nz, cell_m, &lo[0], px, py, pz, max_m, &d2)
            if j < 0:
                continue
            nxv, nyv, nzv = normals[j, 0], normals[j, 1], normals[j, 2]
            r = (px - points[j, 0]) * nxv + (py - points[j, 1]) * nyv + (pz - points[j, 2]) * nzv
            if d2 - r * r > t2:
                continue
            row[0] = py * nzv - pz * nyv
            row[1] = pz * nxv - px * nzv
            row[2] = px * nyv - py * nxv
            row[3], row[4], row[5] = nxv, nyv, nzv
            for a in range(6):
                atb[a] -= row[a] * r
                for b in range(a, 6):
                    ata[6 * a + b] += row[a] * row[b]
            sse += r * r
            count += 1
    for a in range(6):
        atb_out[a] = atb[a]
        for b in range(6):
            ata_out[a, b] = ata[6 * a + b] if b >= a else ata[6 * b + a]
    return count, sse


cdef inline int _cell_runs(const int64_t* starts, int64_t nx, int64_t ny, int64_t nz, int64_t cx, int64_t cy,
                           int64_t cz, int64_t* first, int64_t* last) noexcept nogil:
    """Into first / last (at least 9 each) the runs of point indices of the 3^3 cells around cell
    (cx, cy, cz), clipped to the grid (one run per column of cells, x then y); returns their number."""
    cdef int64_t x, y, c
    cdef int n = 0
    if cz + 1 < 0 or cz - 1 > nz - 1:
        return 0
    for x in range(max(cx - 1, 0), min(cx + 1, nx - 1) + 1):
        for y in range(max(cy - 1, 0), min(cy + 1, ny - 1) + 1):
            c = (x * ny + y) * nz
            first[n] = starts[c + max(cz - 1, 0)]
            last[n] = starts[c + min(cz + 1, nz - 1) + 1]
            n += 1
    return n


cdef inline int _neighbour_runs(const int64_t* starts, int64_t nx, int64_t ny, int64_t nz, double cell_m,
                                const double* lo, double px, double py, double pz, int64_t* first,
                                int64_t* last) noexcept nogil:
    """``_cell_runs`` around the cell of the point (px, py, pz)."""
    return _cell_runs(starts, nx, ny, nz, <int64_t>floor((px - lo[0]) / cell_m),
                      <int64_t>floor((py - lo[1]) / cell_m), <int64_t>floor((pz - lo[2]) / cell_m), first,
                      last)


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
    cdef int m, found, run, n_runs
    cdef int64_t first[9]
    cdef int64_t last[9]
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
            n_runs = _neighbour_runs(&starts[0], nx, ny, nz, cell_m, &lo[0], px, py, pz, first, last)
            found = 0
            for run in range(n_runs):
                for j in range(first[run], last[run]):
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


cdef enum:
    KEY_BITS = 21  # per axis of a packed voxel key: +-2^20 voxels


cdef inline int64_t _floor(double x) noexcept nogil:
    """floor(x) as an integer for |x| < 2^62, without a call into libm (no SSE4.1 rounding in the
    baseline x86-64 instruction set)."""
    cdef int64_t t = <int64_t>x
    return t - (x < t)


cdef inline uint64_t _hash(int64_t key) noexcept nogil:
    """Mix the bits of a packed key (the finaliser of splitmix64)."""
    cdef uint64_t h = <uint64_t>key
    h = (h ^ (h >> 30)) * <uint64_t>0xbf58476d1ce4e5b9
    h = (h ^ (h >> 27)) * <uint64_t>0x94d049bb133111eb
    return h ^ (h >> 31)


cdef bint _rehash(int64_t** table_key, int32_t** table_group, int64_t cap, const int64_t* keys,
                  Py_ssize_t n_groups) noexcept nogil:
    """Replace the hash table by one of ``cap`` slots holding the n_groups keys; False when out of
    memory (the old table is kept)."""
    cdef int64_t* tk = <int64_t*>malloc(cap * sizeof(int64_t))
    cdef int32_t* tg = <int32_t*>malloc(cap * sizeof(int32_t))
    cdef uint64_t h, mask = <uint64_t>(cap - 1)
    cdef Py_ssize_t g
    if tk == NULL or tg == NULL:
        free(tk)
        free(tg)
        return False
    for g in range(cap):
        tg[g] = -1
    for g in range(n_groups):
        h = _hash(keys[g]) & mask
        while tg[h] >= 0:
            h = (h + 1) & mask
        tg[h] = <int32_t>g
        tk[h] = keys[g]
    free(table_key[0])
    free(table_group[0])
    table_key[0], table_group[0] = tk, tg
    return True


cdef inline void _accumulate(const double* pts, Py_ssize_t i, int32_t g, double* sums,
                             int64_t* counts) noexcept nogil:
    """Point i joins voxel g."""
    sums[3 * g] += pts[3 * i]
    sums[3 * g + 1] += pts[3 * i + 1]
    sums[3 * g + 2] += pts[3 * i + 2]
    counts[g] += 1


def voxel_groups(const double[:, ::1] points, double voxel_m, const double[::1] box_lo,
                 const double[::1] box_hi, bint crop, int64_t[::1] keys_out, double[:, ::1] sums_out,
                 int64_t[::1] counts_out):
    """Group points (N, 3) [m] by voxel of a ``voxel_m`` grid anchored at the origin, in one pass.

    With ``crop`` only the points strictly inside the box (``box_lo``, ``box_hi``) (3,) count. Voxels are
    numbered in the order of their first point: ``keys_out`` (N,) receives the packed key of each voxel
    (21 bits an axis, x highest, offset to be non-negative, so that sorting the keys sorts by x, then y,
    then z), ``sums_out`` (N, 3) and
    ``counts_out`` (N,) the sum of each voxel's points (added in input order) and their number. Returns
    the number of voxels, -1 when a kept point is not finite or lies beyond the key range, -2 when out
    of memory. Grouping goes through an open-addressing hash table kept at most half full, sized by the
    voxels rather than the points so that it stays in cache (a raw frame has ~15x more points than
    voxels).
    """
    cdef Py_ssize_t i, n = points.shape[0], n_groups = 0
    cdef int64_t cap = 4096, key, off = 1 << (KEY_BITS - 1)
    cdef int64_t ix, iy, iz
    cdef uint64_t mask, h
    cdef double x, y, z
    cdef int64_t* table_key = NULL
    cdef int32_t* table_group = NULL
    cdef int32_t g, last_group = -1
    cdef int64_t last_key = -1
    cdef int status = 0
    cdef const double* pts
    cdef double* sums
    cdef int64_t* counts
    if n == 0:
        return 0
    pts, sums, counts = &points[0, 0], &sums_out[0, 0], &counts_out[0]
    if not _rehash(&table_key, &table_group, cap, &keys_out[0], 0):
        raise MemoryError()
    mask = <uint64_t>(cap - 1)
    with nogil:
        for i in range(n):
            x, y, z = points[i, 0], points[i, 1], points[i, 2]
            if crop and not (box_lo[0] < x < box_hi[0] and box_lo[1] < y < box_hi[1]
                             and box_lo[2] < z < box_hi[2]):
                continue
            x, y, z = x / voxel_m, y / voxel_m, z / voxel_m
            # NaN fails every comparison: refused here with the out-of-range keys
            if not (-off <= x < off and -off <= y < off and -off <= z < off):
                status = -1
                break
            ix, iy, iz = _floor(x) + off, _floor(y) + off, _floor(z) + off
            key = (ix << (2 * KEY_BITS)) | (iy << KEY_BITS) | iz
            if key == last_key:  # neighbouring pixels of a row share a voxel: no lookup
                _accumulate(pts, i, last_group, sums, counts)
                continue
            h = _hash(key) & mask
            while table_group[h] >= 0 and table_key[h] != key:
                h = (h + 1) & mask
            g = table_group[h]
            if g < 0:
                g = <int32_t>n_groups
                n_groups += 1
                table_group[h] = g
                table_key[h] = key
                keys_out[g] = key
                sums_out[g, 0] = 0.0
                sums_out[g, 1] = 0.0
                sums_out[g, 2] = 0.0
                counts_out[g] = 0
                if 2 * n_groups > cap:
                    cap *= 2
                    if not _rehash(&table_key, &table_group, cap, &keys_out[0], n_groups):
                        status = -2
                        break
                    mask = <uint64_t>(cap - 1)
            _accumulate(pts, i, g, sums, counts)
            last_key, last_group = key, g
    free(table_key)
    free(table_group)
    if status == -2:
        raise MemoryError()
    return status if status < 0 else n_groups


cdef void _jacobi_eigen3(double* a, double* v) noexcept nogil:
    """Eigen-decompose the symmetric 3x3 matrix a (row-major, overwritten: its diagonal ends as the
    eigenvalues) by cyclic Jacobi rotations; v (row-major) receives the eigenvectors as columns."""
    cdef int sweep, p, q, r
    cdef double apq, theta, t, c, s, tau, arp, arq, vrp, vrq, off
    for p in range(9):
        v[p] = 0.0
    v[0] = v[4] = v[8] = 1.0
    for sweep in range(50):
        off = a[1] * a[1] + a[2] * a[2] + a[5] * a[5]
        if off <= 1e-30 * (a[0] * a[0] + a[4] * a[4] + a[8] * a[8]) or off == 0.0:
            return
        for p in range(2):
            for q in range(p + 1, 3):
                apq = a[3 * p + q]
                if apq == 0.0:
                    continue
                theta = (a[3 * q + q] - a[3 * p + p]) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (fabs(theta) + sqrt(theta * theta + 1.0))
                c = 1.0 / sqrt(t * t + 1.0)
                s = t * c
                tau = s / (1.0 + c)
                a[3 * p + p] -= t * apq
                a[3 * q + q] += t * apq
                a[3 * p + q] = a[3 * q + p] = 0.0
                for r in range(3):
                    if r != p and r != q:
                        arp, arq = a[3 * r + p], a[3 * r + q]
                        a[3 * r + p] = a[3 * p + r] = arp - s * (arq + tau * arp)
                        a[3 * r + q] = a[3 * q + r] = arq + s * (arp - tau * arq)
                for r in range(3):
                    vrp, vrq = v[3 * r + p], v[3 * r + q]
                    v[3 * r + p] = vrp - s * (vrq + tau * vrp)
                    v[3 * r + q] = vrq + s * (vrp - tau * vrq)


cdef inline void _smallest_eigenvector(double* cov, double* out) noexcept nogil:
    """Into out (3,) the unit eigenvector of the smallest eigenvalue of the symmetric 3x3 matrix whose
    upper triangle is in cov (row-major; overwritten)."""
    cdef double vec[9]
    cdef int best = 0
    cov[3], cov[6], cov[7] = cov[1], cov[2], cov[5]
    _jacobi_eigen3(cov, vec)
    if cov[4] < cov[0]:
        best = 1
    if cov[8] < cov[4 * best]:
        best = 2
    out[0], out[1], out[2] = vec[best], vec[3 + best], vec[6 + best]


def plane_normals(const double[:, ::1] cloud, const int64_t[:, ::1] neighbours, double[:, ::1] out):
    """Unit normal of each row of ``neighbours`` (M, K) (indices into ``cloud`` (N, 3), -1 after the
    last): the eigenvector of the smallest eigenvalue of the neighbours' covariance (mean first, then the
    centred sums), into ``out`` (M, 3); (0, 0, 1) with fewer than 3 neighbours. Its sign is arbitrary."""
    cdef Py_ssize_t i, j, m = neighbours.shape[0], kk = neighbours.shape[1]
    cdef int64_t idx
    cdef int a, b
    cdef double mean[3]
    cdef double d[3]
    cdef double cov[9]
    cdef Py_ssize_t cnt
    with nogil:
        for i in range(m):
            mean[0] = mean[1] = mean[2] = 0.0
            cnt = 0
            for j in range(kk):
                idx = neighbours[i, j]
                if idx < 0:
                    break
                for a in range(3):
                    mean[a] += cloud[idx, a]
                cnt += 1
            if cnt < 3:
                out[i, 0], out[i, 1], out[i, 2] = 0.0, 0.0, 1.0
                continue
            for a in range(3):
                mean[a] /= cnt
            for a in range(9):
                cov[a] = 0.0
            for j in range(cnt):
                idx = neighbours[i, j]
                for a in range(3):
                    d[a] = cloud[idx, a] - mean[a]
                for a in range(3):
                    for b in range(a, 3):
                        cov[3 * a + b] += d[a] * d[b]
            _smallest_eigenvector(cov, &out[i, 0])


def radius_plane_normals(const double[:, ::1] points, const int64_t[::1] starts, int64_t nx, int64_t ny,
                         int64_t nz, double cell_m, const double[::1] lo, const double[:, ::1] queries,
                         double radius_m, double[:, ::1] out):
    """Unit normal at each query (Q, 3) [m] fitted to all ``points`` within ``radius_m`` [m] of it (no
    neighbour cap): the eigenvector of the smallest eigenvalue of their covariance (sums of the offsets
    from the query, in grid order), into ``out`` (Q, 3); (0, 0, 1) with fewer than 3 of them. Its sign
    is arbitrary. ``points``, ``starts``, the grid shape, ``cell_m`` and ``lo`` as for
    ``nearest_within``; the cell must be at least ``radius_m``."""
    cdef Py_ssize_t q, j, nq = queries.shape[0], cnt
    cdef int a, b, run, n_runs
    cdef int64_t first[9]
    cdef int64_t last[9]
    cdef double px, py, pz, d2, r2 = radius_m * radius_m
    cdef double d[3]
    cdef double s[3]
    cdef double cov[9]
    cdef const double* pts = &points[0, 0]
    with nogil:
        for q in range(nq):
            px, py, pz = queries[q, 0], queries[q, 1], queries[q, 2]
            n_runs = _neighbour_runs(&starts[0], nx, ny, nz, cell_m, &lo[0], px, py, pz, first, last)
            cnt = 0
            for a in range(3):
                s[a] = 0.0
            for a in range(9):
                cov[a] = 0.0
            for run in range(n_runs):
                for j in range(first[run], last[run]):
                    d[0] = pts[3 * j] - px
                    d[1] = pts[3 * j + 1] - py
                    d[2] = pts[3 * j + 2] - pz
                    d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                    if d2 > r2:
                        continue
                    for a in range(3):
                        s[a] += d[a]
                        for b in range(a, 3):
                            cov[3 * a + b] += d[a] * d[b]
                    cnt += 1
            if cnt < 3:
                out[q, 0], out[q, 1], out[q, 2] = 0.0, 0.0, 1.0
                continue
            # centred second moments from the sums about the query (offsets are at most the radius)
            for a in range(3):
                for b in range(a, 3):
                    cov[3 * a + b] = cov[3 * a + b] / cnt - s[a] * s[b] / (<double>cnt * cnt)
            _smallest_eigenvector(cov, &out[q, 0])


cdef inline Py_ssize_t _root(int64_t* parent, Py_ssize_t i) noexcept nogil:
    """Root of i in the union-find forest, halving the path on the way."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def radius_components(const double[:, ::1] points, const int64_t[:, ::1] cells, const int64_t[::1] starts,
                      int64_t nx, int64_t ny, int64_t nz, double radius_m, int64_t[::1] root_out):
    """Connected components of the graph linking the points at most ``radius_m`` apart (as a kd-tree's
    pair query with that radius), by union-find.

    ``points`` (N, 3) sorted by grid cell as for ``knn_mean_distances`` (``cells`` (N, 3), ``starts``), the
    cell at least ``radius_m`` so that the 3^3 cells around a point hold all its links. ``root_out`` (N,)
    receives for each point the lowest index (in this sorted order) of its component.
    """
    cdef Py_ssize_t i, j, n = points.shape[0], ri, rj
    cdef int run, n_runs
    cdef int64_t first[9]
    cdef int64_t last[9]
    cdef double px, py, pz, dx, dy, dz, r2 = radius_m * radius_m
    cdef const double* pts = &points[0, 0]
    cdef int64_t* parent = &root_out[0]
    with nogil:
        for i in range(n):
            parent[i] = i
        for i in range(n):
            px, py, pz = pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]
            n_runs = _cell_runs(&starts[0], nx, ny, nz, cells[i, 0], cells[i, 1], cells[i, 2], first, last)
            for run in range(n_runs):
                for j in range(first[run], last[run]):
                    if j <= i:
                        continue
                    dx = pts[3 * j] - px
                    dy = pts[3 * j + 1] - py
                    dz = pts[3 * j + 2] - pz
                    if dx * dx + dy * dy + dz * dz <= r2:
                        ri = _root(parent, i)
                        rj = _root(parent, j)
                        if ri < rj:
                            parent[rj] = ri
                        elif rj < ri:
                            parent[ri] = rj
        for i in range(n):
            parent[i] = _root(parent, i)


def plane_inlier_counts(const double[:, ::1] points, const double[:, ::1] normals, const double[::1] offsets,
                        double max_distance_m, int64_t[::1] out):
    """For each plane n . p + d = 0 (``normals`` (H, 3), ``offsets`` (H,)) the number of points (N, 3)
    within ``max_distance_m`` [m] of it, into ``out`` (H,) (RANSAC scoring, ``segmentation``)."""
    cdef Py_ssize_t h, i, nh = normals.shape[0], n = points.shape[0]
    cdef double a, b, c, d, dist
    cdef int64_t count
    with nogil:
        for h in range(nh):
            a, b, c, d = normals[h, 0], normals[h, 1], normals[h, 2], offsets[h]
            count = 0
            for i in range(n):
                dist = a * points[i, 0] + b * points[i, 1] + c * points[i, 2] + d
                count += -max_distance_m <= dist <= max_distance_m
            out[h] = count


def grid_sort(const double[:, ::1] points, const double[::1] lo, double cell_m, int64_t nx, int64_t ny,
              int64_t nz, int64_t[::1] starts_out, int64_t[::1] order_out, int64_t[:, ::1] cells_out,
              double[:, ::1] points_out):
    """Bucket points (N, 3) [m] in the grid of ``cell_m`` cells with corner ``lo`` and shape (nx, ny, nz)
    (``cloud.PointGrid``) by a counting sort: ``order_out`` (N,) the input index of each point sorted by
    flat cell index (x, then y, then z; input order within a cell, as a stable argsort), ``points_out``
    (N, 3) and ``cells_out`` (N, 3) the points and their cells in that order, ``starts_out``
    (nx * ny * nz + 1,) where each cell's run begins. A coordinate past the last cell (rounding at the
    far face) is clamped into it."""
    cdef Py_ssize_t i, pos, n = points.shape[0]
    cdef int64_t c, n_cells = nx * ny * nz
    cdef int64_t* cell = <int64_t*>malloc(4 * n * sizeof(int64_t) if n else 1)
    if cell == NULL:
        raise MemoryError()
    with nogil:
        for c in range(n_cells + 1):
            starts_out[c] = 0
        # per point: its cell (x, y, z) and flat index
        for i in range(n):
            cell[4 * i] = min(_floor((points[i, 0] - lo[0]) / cell_m), nx - 1)
            cell[4 * i + 1] = min(_floor((points[i, 1] - lo[1]) / cell_m), ny - 1)
            cell[4 * i + 2] = min(_floor((points[i, 2] - lo[2]) / cell_m), nz - 1)
            c = (cell[4 * i] * ny + cell[4 * i + 1]) * nz + cell[4 * i + 2]
            cell[4 * i + 3] = c
            starts_out[c + 1] += 1
        for c in range(n_cells):
            starts_out[c + 1] += starts_out[c]
        # scatter with a running cursor per cell, kept in the run starts shifted by one cell
        for i in range(n):
            c = cell[4 * i + 3]
            pos = starts_out[c]
            starts_out[c] += 1
            order_out[pos] = i
            points_out[pos, 0] = points[i, 0]
            points_out[pos, 1] = points[i, 1]
            points_out[pos, 2] = points[i, 2]
            cells_out[pos, 0] = cell[4 * i]
            cells_out[pos, 1] = cell[4 * i + 1]
            cells_out[pos, 2] = cell[4 * i + 2]
        for c in range(n_cells, 0, -1):
            starts_out[c] = starts_out[c - 1]
        starts_out[0] = 0
    free(cell)


def radius_counts(const double[:, ::1] points, const int64_t[:, ::1] cells, const int64_t[::1] starts,
                  int64_t nx, int64_t ny, int64_t nz, double radius_m, int64_t[::1] out):
    """The number of points (itself included) at most ``radius_m`` from each point, into ``out`` (N,)
    (DBSCAN's core test, ``segmentation.dbscan_labels``); points and grid as for ``radius_components``."""
    cdef Py_ssize_t i, j, n = points.shape[0]
    cdef int run, n_runs
    cdef int64_t first[9]
    cdef int64_t last[9]
    cdef int64_t count
    cdef double px, py, pz, dx, dy, dz, r2 = radius_m * radius_m
    cdef const double* pts = &points[0, 0]
    with nogil:
        for i in range(n):
            px, py, pz = pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]
            n_runs = _cell_runs(&starts[0], nx, ny, nz, cells[i, 0], cells[i, 1], cells[i, 2], first, last)
            count = 0
            for run in range(n_runs):
                for j in range(first[run], last[run]):
                    dx = pts[3 * j] - px
                    dy = pts[3 * j + 1] - py
                    dz = pts[3 * j + 2] - pz
                    count += dx * dx + dy * dy + dz * dz <= r2
            out[i] = count
