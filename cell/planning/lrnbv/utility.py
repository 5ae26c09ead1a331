"""The LR-NBV utility (paper section 3.3):

    U(x_T) = w_e G_e(x_T) + w_d G_d(x_T) + w_q G_q(x_T) + w_v G_v(x_T)

evaluated for many candidate sensor poses at once, base frame, metres.

Eq. 2, ray validity. A ray r(t) = o + t d (|d| = ``ray_length_m``, t in [0, 1]) is sampled at t_k every
map voxel. A sample is valid when it lies in the ROI and no object voxel lies on the ray before it. The
paper writes the occlusion condition as "exists t* <= t with r(t*) in O", but its text and Fig. 2a are
clear that portions *beyond* the first object hit t* are the invalid ones, so a sample is valid for
t_k <= t*, the first object sample itself included (it is the surface the sensor would see).

Eq. 3, exploration gain: G_e = sum of V W over the samples, with W the volumetric weight of Selin et
al. (2019): the volume [m^3] of the sample's voxel times its normalised occupancy entropy (1 for an
unknown voxel, 0 for a certain one), i.e. the uncertain volume the ray traverses.

Eq. 4, density gain: G_d = sum of V / (1 + rho), rho the number of object points within ``r_d`` of the
sample (taken at the centre of the sample's voxel).

Eq. 5, quality gain: G_q = 1 / (1 + |p - x_object|), p the sensor position and x_object the centre of
the object points [m].

Eq. 6, visited gain: G_v = -Visited(p) on a coarse grid (cells of ``visited_grid_m``) that marks the cells
where captures were taken.

Everything the map contributes is gathered once per map state into a dense grid over the ROI
(:class:`UtilityField`); a candidate then costs only index arithmetic and gathers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cell.perception.occupancy import OccupancyMap

Array = NDArray[np.float64]

# Candidates evaluated together: bounds the (chunk, rays, samples) work arrays to a few tens of MB.
_CHUNK_SAMPLES = 2_000_000


@dataclass(frozen=True)
class Gains:
    """The four gains (N,) of N candidate poses: G_e [m^3], G_d [samples], G_q [1], G_v (0 or -1)."""

    g_e: Array
    g_d: Array
    g_q: Array
    g_v: Array


@dataclass(frozen=True)
class Weights:
    """w_e, w_d, w_q, w_v of U; a planner that leaves a gain out (the ``nbv`` baseline) sets it to 0."""

    w_e: float
    w_d: float
    w_q: float
    w_v: float

    def utility(self, g: Gains) -> Array:
        return self.w_e * g.g_e + self.w_d * g.g_d + self.w_q * g.g_q + self.w_v * g.g_v


class VisitedGrid:
    """The coarse grid of eq. 6: cells of ``cell_m`` [m] anchored at the base origin, 1 once visited."""

    def __init__(self, cell_m: float) -> None:
        self.cell_m = cell_m
        self._cells: set[tuple[int, int, int]] = set()

    def _keys(self, positions: Array) -> NDArray[np.int64]:
        return np.floor(np.asarray(positions, dtype=float).reshape(-1, 3) / self.cell_m).astype(np.int64)

    def mark(self, position: Array) -> None:
        k = self._keys(position)[0]
        self._cells.add((int(k[0]), int(k[1]), int(k[2])))

    def visited(self, positions: Array) -> NDArray[np.bool_]:
        """Mask (N,) of the positions (N, 3) whose cell was visited."""
        keys = self._keys(positions)
        return np.array([(int(a), int(b), int(c)) in self._cells for a, b, c in keys], dtype=bool)


class UtilityField:
    """The map-derived inputs of eqs. 2-4 on a dense grid over the ROI box, for one map state.

    ``roi_min`` / ``roi_max`` (3,) [m] the ROI box; the grid has the map's ``resolution`` and covers it.
    ``object_points`` (M, 3) [m] the current object O^i. ``W`` per cell: eq. 3's weight; ``density`` per
    cell: 1 / (1 + rho) of eq. 4; ``occluder`` per cell: an object point lies in it.
    """

    def __init__(self, occupancy: OccupancyMap, object_points: Array, roi_min: Array, roi_max: Array,
                 *, resolution: float, density_radius_m: float) -> None:
        self.resolution = resolution
        self.lo = np.floor(np.asarray(roi_min, dtype=float) / resolution) * resolution
        hi = np.ceil(np.asarray(roi_max, dtype=float) / resolution) * resolution
        self.shape = tuple(int(n) for n in np.maximum(np.round((hi - self.lo) / resolution), 1))
        self.hi = self.lo + np.array(self.shape) * resolution
        idx = np.indices(self.shape).reshape(3, -1).T
        centres = self.lo + (idx + 0.5) * resolution
        entropy = occupancy.entropy(centres) / math.log(2.0)
        self.W = (entropy * resolution**3).reshape(self.shape)
        obj = np.asarray(object_points, dtype=float).reshape(-1, 3)
        if obj.shape[0]:
            rho = cKDTree(obj).query_ball_point(centres, density_radius_m, return_length=True)
        else:
            rho = np.zeros(centres.shape[0])
        self.density = (1.0 / (1.0 + np.asarray(rho, dtype=float))).reshape(self.shape)
        self.occluder = np.zeros(self.shape, dtype=bool)
        if obj.shape[0]:
            k = np.floor((obj - self.lo) / resolution).astype(np.int64)
            inside = np.all((k >= 0) & (k < np.array(self.shape)), axis=1)
            self.occluder[tuple(k[inside].T)] = True
        self.object_centre = obj.mean(axis=0) if obj.shape[0] else 0.5 * (self.lo + self.hi)

    def ray_gains(self, origins: Array, rotations: Array, rays_sensor: Array,
                  ray_length_m: float) -> tuple[Array, Array]:
        """G_e and G_d (eqs. 3-4) of N poses: sensor positions ``origins`` (N, 3) and orientations
        ``rotations`` (N, 3, 3) (R_base_sensor), rays ``rays_sensor`` (R, 3) unit, sensor frame."""
        n = origins.shape[0]
        g_e = np.zeros(n)
        g_d = np.zeros(n)
        if n == 0:
            return g_e, g_d
        step = self.resolution
        n_max = math.floor(ray_length_m / step)
        # Samples a ray can spend inside the box: its diagonal over the step, plus the end points.
        span = math.ceil(float(np.linalg.norm(self.hi - self.lo)) / step) + 2
        per_pose = rays_sensor.shape[0] * span
        chunk = max(1, _CHUNK_SAMPLES // per_pose)
        for s in range(0, n, chunk):
            e = slice(s, min(s + chunk, n))
            g_e[e], g_d[e] = self._chunk(origins[e], rotations[e], rays_sensor, step, n_max, span)
        return g_e, g_d

    def _chunk(self, origins: Array, rotations: Array, rays_sensor: Array, step: float, n_max: int,
               span: int) -> tuple[Array, Array]:
        n, n_rays = origins.shape[0], rays_sensor.shape[0]
        d = np.einsum("nij,rj->nri", rotations, rays_sensor).reshape(-1, 3)  # (n R, 3) unit, base frame
        o = np.repeat(origins, n_rays, axis=0)
        # Slab test: the ray parameter range [t0, t1] (metres along d) inside the ROI box.
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            ta = (self.lo - o) * inv
            tb = (self.hi - o) * inv
        ta = np.where(np.isnan(ta), -np.inf, ta)
        tb = np.where(np.isnan(tb), np.inf, tb)
        t0 = np.maximum(np.max(np.minimum(ta, tb), axis=1), 0.0)
        # A ray parallel to a slab outside it gets t1 = -inf: floor it so that it casts to an integer.
        t1 = np.clip(np.min(np.maximum(ta, tb), axis=1), -step, n_max * step)
        k0 = np.ceil(t0 / step - 1e-9).astype(np.int64)
        k1 = np.floor(t1 / step + 1e-9).astype(np.int64)
        count = np.clip(k1 - k0 + 1, 0, span)
        # Only the samples inside the box, flat: ray number and sample number along the ray.
        ray = np.repeat(np.arange(count.size), count)
        first = np.cumsum(count) - count
        k = k0[ray] + (np.arange(ray.size) - first[ray])
        g = (o[ray] - self.lo) / self.resolution + (k * (step / self.resolution))[:, None] * d[ray]
        idx = np.floor(g).astype(np.int64)
        live = np.all((idx >= 0) & (idx < np.array(self.shape)), axis=1)
        flat = np.ravel_multi_index(tuple(np.where(live[:, None], idx, 0).T), self.shape)
        hit = (self.occluder.ravel()[flat] & live).astype(np.int64)
        # Eq. 2: valid up to and including the first object sample along the ray (hits before it = 0).
        before = np.cumsum(hit) - hit
        before -= before[first[ray]] if ray.size else before
        valid = live & (before == 0)
        pose = ray // n_rays
        g_e = np.bincount(pose, weights=np.where(valid, self.W.ravel()[flat], 0.0), minlength=n)
        g_d = np.bincount(pose, weights=np.where(valid, self.density.ravel()[flat], 0.0), minlength=n)
        return g_e, g_d

    def quality_gain(self, origins: Array) -> Array:
        """G_q (eq. 5) of sensor positions (N, 3)."""
        return 1.0 / (1.0 + np.linalg.norm(origins - self.object_centre, axis=1))


def evaluate(field: UtilityField, visited: VisitedGrid, origins: Array, rotations: Array,
             rays_sensor: Array, ray_length_m: float) -> Gains:
    """The four gains of N candidate poses (positions (N, 3), R_base_sensor (N, 3, 3))."""
    g_e, g_d = field.ray_gains(origins, rotations, rays_sensor, ray_length_m)
    g_v = -visited.visited(origins).astype(float)
    return Gains(g_e=g_e, g_d=g_d, g_q=field.quality_gain(origins), g_v=g_v)
