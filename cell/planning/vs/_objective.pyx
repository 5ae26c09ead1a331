# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled inner loop of the entropy NBV objective (visual-servoing paper eq. 7-9), built by
``pip install -e .`` (see setup.py); ``objective.EntropyObjective`` is its only caller and documents the
method.

``Scorer.score`` scores a batch of camera poses: per pose, each of the K rays is clipped to the ROI
box and the crop box, sampled every resolution, and its samples' voxels read from a dense snapshot of
the map around the ROI. Poses are independent, so a batch is split over OpenMP threads; every pose is
computed by the same sequential loop whichever thread runs it, so the result does not depend on the
number of threads or their schedule.

Plain loops over typed memoryviews, as ``cell/perception/_kernels.pyx``; ``Scorer`` checks that the
arrays it is given fit together, so that the loops can read them unchecked.
"""

cimport openmp
from cython.parallel cimport prange
from libc.math cimport NAN, ceil, isfinite
from libc.stdint cimport int64_t

# Slack [voxels] of the per-ray check that every sample's grid coordinate lies in the snapshot: far above
# the rounding of the running sum along a ray, far below a voxel.
cdef double SLACK = 1e-6
cdef enum:
    VOXEL = 6  # doubles per voxel of the snapshot: 1 - p, H(p), H from the other side, its side (3)


def max_threads() -> int:
    """The OpenMP thread count a parallel batch uses (OMP_NUM_THREADS, else the number of cores)."""
    return openmp.omp_get_max_threads()


cdef double _pose(const double* T, const double* dirs, Py_ssize_t n_rays, const double* crop_in,
                  const double* crop_out, const double* roi_lo, const double* roi_hi, double res,
                  const int64_t* k_lo, const int64_t* shape, const double* voxels) noexcept nogil:
    """f(r) of eq. 9 for one pose ``T`` (4 x 4, row-major, T_base_cam) [nats]; NaN when a sample falls
    outside the snapshot (the caller's box is wrong)."""
    # Offsets in ``voxels`` (VOXEL doubles per voxel) of one step in x and in y.
    cdef int64_t stride_y = VOXEL * shape[2], stride_x = VOXEL * shape[1] * shape[2]
    cdef double o[3]
    cdef double d[3]
    cdef double g0[3]
    cdef double t_in, t_out, ta, tb, ga, lo, hi, reach, ray, gx, gy, gz, total = 0.0
    cdef const double* vox
    cdef Py_ssize_t k, a, i, n, v
    cdef bint miss
    for a in range(3):
        o[a] = T[4 * a + 3]
    for k in range(n_rays):
        # The ray's direction in the base frame, and its stretch inside the crop box (camera frame,
        # the same for every pose) and the ROI box (base frame), by slabs.
        t_in = crop_in[k]
        t_out = crop_out[k]
        miss = False
        for a in range(3):
            d[a] = T[4 * a] * dirs[3 * k] + T[4 * a + 1] * dirs[3 * k + 1] + T[4 * a + 2] * dirs[3 * k + 2]
            if d[a] == 0.0:
                # Parallel to the slab: inside it or not at all (on a face counts as outside).
                if not (roi_lo[a] < o[a] < roi_hi[a]):
                    miss = True
                continue
            ta = (roi_lo[a] - o[a]) / d[a]
            tb = (roi_hi[a] - o[a]) / d[a]
            if ta > tb:
                ta, tb = tb, ta
            if ta > t_in:
                t_in = ta
            if tb < t_out:
                t_out = tb
        if t_in < 0.0:
            t_in = 0.0
        if miss or not t_out > t_in:
            continue  # the ray misses the ROI: contributes 0, still counts in K
        # Samples t_in + (i + 1/2) res < t_out, i = 0 .. n-1.
        n = <Py_ssize_t>ceil((t_out - t_in) / res - 0.5)
        # Grid coordinates of the samples relative to the snapshot, x / res - k_lo: sample 0's, then a
        # running sum, the samples being one voxel apart. Its rounding (~1e-12 voxel over a ray) can only
        # matter for a sample on a voxel face, which then counts to the voxel on either side.
        for a in range(3):
            g0[a] = (o[a] + (t_in + 0.5 * res) * d[a]) / res - k_lo[a]
            # The coordinates are monotonic along the ray: its ends bound them all.
            ga = g0[a] + (n - 1) * d[a]
            if ga > g0[a]:
                lo, hi = g0[a], ga
            else:
                lo, hi = ga, g0[a]
            if not (SLACK <= lo and hi <= shape[a] - SLACK):
                return NAN
        # Eq. 9 as sum_j H(p_j) S_j, S_j = prod_{i<j} (1 - p_i) the probability of reaching sample j.
        reach = 1.0
        ray = 0.0
        gx, gy, gz = g0[0], g0[1], g0[2]
        for i in range(n):
            # Non-negative coordinates: truncation is floor (libm's floor is a call on baseline x86-64).
            v = <int64_t>gx * stride_x + <int64_t>gy * stride_y + VOXEL * <int64_t>gz
            vox = voxels + v
            if vox[3] * d[0] + vox[4] * d[1] + vox[5] * d[2] < 0.0:
                ray = ray + reach * vox[2]  # hit only ever from the other side
            else:
                ray = ray + reach * vox[1]
            reach = reach * vox[0]
            gx = gx + d[0]
            gy = gy + d[1]
            gz = gz + d[2]
        total = total + ray
    return total / n_rays


cdef class Scorer:
    """The rays and the map snapshot of one objective; ``score`` evaluates eq. 9 for batches of poses.

    ``dirs`` (K, 3) unit rays, camera frame; ``crop_in`` / ``crop_out`` (K,) each ray's parameters [m]
    inside the crop box; ``roi_lo`` / ``roi_hi`` (3,) the ROI box, base frame [m]; ``res`` the sample
    spacing and voxel edge [m]; ``voxels`` (M, 6): per voxel of the snapshot, (1 - p, H(p)) of eq. 7-8,
    the H a ray from the other side reads, and the side it was hit from (a direction, base frame; 0 for
    none), in key order (x, then y, then z) over ``shape`` (3,) voxels starting at key ``k_lo`` (3,); a
    sample whose ray points against its voxel's side reads the third column instead of the second.
    The arrays are held, not copied: the caller does not change them.
    """

    cdef const double[:, ::1] dirs
    cdef const double[::1] crop_in, crop_out, roi_lo, roi_hi
    cdef const int64_t[::1] k_lo, shape
    cdef const double[:, ::1] voxels
    cdef double res

    def __init__(self, const double[:, ::1] dirs, const double[::1] crop_in, const double[::1] crop_out,
                 const double[::1] roi_lo, const double[::1] roi_hi, double res, const int64_t[::1] k_lo,
                 const int64_t[::1] shape, const double[:, ::1] voxels):
        if dirs.shape[1] != 3 or crop_in.shape[0] != dirs.shape[0] or crop_out.shape[0] != dirs.shape[0]:
            raise ValueError("Scorer: dirs must be (K, 3), crop_in and crop_out (K,)")
        if roi_lo.shape[0] != 3 or roi_hi.shape[0] != 3 or k_lo.shape[0] != 3 or shape.shape[0] != 3:
            raise ValueError("Scorer: roi_lo, roi_hi, k_lo and shape must have 3 entries")
        if voxels.shape[1] != VOXEL or voxels.shape[0] != shape[0] * shape[1] * shape[2] or not res > 0.0:
            raise ValueError(f"Scorer: voxels must be (shape[0] * shape[1] * shape[2], {VOXEL}) and res > 0")
        self.dirs, self.crop_in, self.crop_out = dirs, crop_in, crop_out
        self.roi_lo, self.roi_hi, self.res = roi_lo, roi_hi, res
        self.k_lo, self.shape, self.voxels = k_lo, shape, voxels

    def score(self, const double[:, :, ::1] poses, double[::1] out, int n_threads):
        """f of eq. 9 for ``poses`` (B, 4, 4) T_base_cam into ``out`` (B,) [nats], on ``n_threads``
        OpenMP threads; NaN for a pose that is not finite or whose samples leave the snapshot."""
        cdef Py_ssize_t b, j, n_poses = poses.shape[0], n_rays = self.dirs.shape[0]
        cdef const double* T
        if out.shape[0] != n_poses:
            raise ValueError(f"Scorer.score: out has {out.shape[0]} entries for {n_poses} poses")
        if n_poses == 0:
            return
        if n_rays == 0:
            out[:] = 0.0
            return
        for b in prange(n_poses, nogil=True, schedule="dynamic", chunksize=8, num_threads=n_threads):
            T = &poses[b, 0, 0]
            for j in range(12):
                if not isfinite(T[j]):
                    out[b] = NAN
                    break
            else:
                out[b] = _pose(T, &self.dirs[0, 0], n_rays, &self.crop_in[0], &self.crop_out[0],
                               &self.roi_lo[0], &self.roi_hi[0], self.res, &self.k_lo[0], &self.shape[0],
                               &self.voxels[0, 0])
