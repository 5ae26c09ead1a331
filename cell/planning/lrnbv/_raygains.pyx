# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled inner loop of the LR-NBV utility (built by ``pip install -e .``, see setup.py).

``ray_gains``: G_e and G_d (packing paper eqs. 2-4) of N sensor poses over the dense ROI grid of
``utility.UtilityField``. A plain loop over typed memoryviews (no numpy C API); the caller checks shapes
and dtypes (C-contiguous float64, uint8 occluder) before calling.
"""

from libc.math cimport ceil, floor


def ray_gains(const double[:, ::1] origins, const double[:, :, ::1] rotations,
              const double[:, ::1] rays_sensor, const double[:, :, ::1] weight,
              const double[:, :, ::1] density, const unsigned char[:, :, ::1] occluder,
              const double[::1] lo, const double[::1] hi, double resolution, double step, long n_max,
              long span, double[::1] g_e, double[::1] g_d):
    """Fill ``g_e`` (N,) and ``g_d`` (N,) of poses ``origins`` (N, 3) [m] with R_base_sensor ``rotations``
    (N, 3, 3), rays ``rays_sensor`` (R, 3) unit in the sensor frame.

    A ray r(t) = o + t d is sampled at t_k = k ``step`` [m], k = 0..``n_max``; only the samples inside
    the box [``lo``, ``hi``] (at most ``span`` of them) are visited. A sample in grid cell c counts
    ``weight[c]`` into G_e and ``density[c]`` into G_d while no earlier sample of the ray fell in an
    occluder cell (eq. 2: valid up to and including the first object sample)."""
    cdef Py_ssize_t n_poses = origins.shape[0], n_rays = rays_sensor.shape[0]
    cdef Py_ssize_t sx = weight.shape[0], sy = weight.shape[1], sz = weight.shape[2]
    cdef Py_ssize_t p, r, a
    cdef long k, k0, k1, count, ix, iy, iz
    cdef double d[3]
    cdef double o[3]
    cdef double t0, t1, ta, tb, tmp, scale, se, sd, gx, gy, gz
    cdef bint empty
    scale = step / resolution
    for p in range(n_poses):
        se = 0.0
        sd = 0.0
        for a in range(3):
            o[a] = origins[p, a]
        for r in range(n_rays):
            for a in range(3):
                d[a] = (rotations[p, a, 0] * rays_sensor[r, 0] + rotations[p, a, 1] * rays_sensor[r, 1]
                        + rotations[p, a, 2] * rays_sensor[r, 2])
            # Slab test: the range [t0, t1] [m along d] inside the box.
            t0 = 0.0
            t1 = n_max * step
            empty = False
            for a in range(3):
                if d[a] == 0.0:
                    if o[a] < lo[a] or o[a] > hi[a]:
                        empty = True
                    continue
                ta = (lo[a] - o[a]) / d[a]
                tb = (hi[a] - o[a]) / d[a]
                if ta > tb:
                    tmp = ta
                    ta = tb
                    tb = tmp
                if ta > t0:
                    t0 = ta
                if tb < t1:
                    t1 = tb
            if empty or t1 < t0:
                continue
            k0 = <long>ceil(t0 / step - 1e-9)
            k1 = <long>floor(t1 / step + 1e-9)
            count = k1 - k0 + 1
            if count > span:
                count = span
            for k in range(k0, k0 + count):
                gx = (o[0] - lo[0]) / resolution + (k * scale) * d[0]
                gy = (o[1] - lo[1]) / resolution + (k * scale) * d[1]
                gz = (o[2] - lo[2]) / resolution + (k * scale) * d[2]
                ix = <long>floor(gx)
                iy = <long>floor(gy)
                iz = <long>floor(gz)
                if ix < 0 or iy < 0 or iz < 0 or ix >= sx or iy >= sy or iz >= sz:
                    continue
                se += weight[ix, iy, iz]
                sd += density[ix, iy, iz]
                if occluder[ix, iy, iz]:
                    break
        g_e[p] = se
        g_d[p] = sd
