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
unknown voxel, 0 for a certain one), i.e. the uncertain volume the ray traverses (``exploration_weight:
entropy``, the paper's form).

Departure (``exploration_weight: observation``, issue 24): the log-odds entropy cannot tell a voxel that
was never seen from one seen often whose hits and misses keep disagreeing (a surface voxel an 8 x 8 zone
cuts at a grazing angle, ranged in some views and carved free in others): both stay near p = 0.5 and
keep drawing views that resolve nothing. The map's per-voxel counts
(``OccupancyMap.observation_counts``: h scans that updated it as occupied, m as free) tell them apart:
``cell.perception.occupancy.observation_weight`` w(h, m), the Beta-Bernoulli information one more
observation gives about the voxel's hit rate over an unseen voxel's, is 1 for a voxel never seen and falls
like 1 / (h + m) whatever the ratio h / m. The weight is then the paper's normalised entropy capped by
w(h, m): the paper's W for voxels seen a few times, and small for voxels seen often, settled or not.

Eq. 4, density gain: G_d = sum of V / (1 + rho), rho the number of object points within ``r_d`` of the
sample (taken at the centre of the sample's voxel).

Eq. 5, quality gain: G_q = 1 / (1 + |p - x_object|), p the sensor position and x_object the centre of
the object points [m].

Eq. 6, visited gain: G_v = -Visited(p) on a coarse grid (cells of ``visited_grid_m``) that marks the cells
where captures were taken.

Everything the map contributes is gathered once per map state into a dense grid over the ROI
(:class:`UtilityField`); a candidate then costs a compiled walk along its rays (``_raygains.pyx``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cell.perception.occupancy import OccupancyMap, observation_weight
from cell.planning.lrnbv._raygains import ray_gains

Array = NDArray[np.float64]

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
    ``object_points`` (M, 3) [m] the current object O^i. ``W`` per cell: eq. 3's weight (``observation_
    aware``: capped by ``observation_weight``, the module docstring); ``density`` per cell: 1 / (1 + rho)
    of eq. 4; ``occluder`` per cell: an object point lies in it.
    """

    def __init__(self, occupancy: OccupancyMap, object_points: Array, roi_min: Array, roi_max: Array,
                 *, resolution: float, density_radius_m: float, observation_aware: bool = False) -> None:
        self.resolution = resolution
        self.lo = np.floor(np.asarray(roi_min, dtype=float) / resolution) * resolution
        hi = np.ceil(np.asarray(roi_max, dtype=float) / resolution) * resolution
        self.shape = tuple(int(n) for n in np.maximum(np.round((hi - self.lo) / resolution), 1))
        self.hi = self.lo + np.array(self.shape) * resolution
        idx = np.indices(self.shape).reshape(3, -1).T
        centres = self.lo + (idx + 0.5) * resolution
        entropy = occupancy.entropy(centres) / math.log(2.0)
        if observation_aware:
            entropy = np.minimum(entropy, observation_weight(*occupancy.observation_counts(centres)))
        self.W = np.ascontiguousarray((entropy * resolution**3).reshape(self.shape), dtype=np.float64)
        obj = np.asarray(object_points, dtype=float).reshape(-1, 3)
        if obj.shape[0]:
            counts = cKDTree(obj).query_ball_point(centres, density_radius_m, return_length=True)
            rho = np.asarray(counts, dtype=float)
        else:
            rho = np.zeros(centres.shape[0])
        self.density = np.ascontiguousarray((1.0 / (1.0 + rho)).reshape(self.shape))
        self.occluder = np.zeros(self.shape, dtype=np.uint8)
        if obj.shape[0]:
            k = np.floor((obj - self.lo) / resolution).astype(np.int64)
            inside = np.all((k >= 0) & (k < np.array(self.shape)), axis=1)
            self.occluder[tuple(k[inside].T)] = 1
        self.object_centre = obj.mean(axis=0) if obj.shape[0] else 0.5 * (self.lo + self.hi)

    def ray_gains(self, origins: Array, rotations: Array, rays_sensor: Array,
                  ray_length_m: float) -> tuple[Array, Array]:
        """G_e and G_d (eqs. 3-4) of N poses: sensor positions ``origins`` (N, 3) and orientations
        ``rotations`` (N, 3, 3) (R_base_sensor), rays ``rays_sensor`` (R, 3) unit, sensor frame.

        The samples t_k are every map voxel along the ray (``resolution`` [m] apart, k = 0 .. ray length
        / resolution); the compiled loop (``_raygains.ray_gains``) visits only those inside the ROI grid."""
        n = origins.shape[0]
        g_e = np.zeros(n)
        g_d = np.zeros(n)
        step = self.resolution
        # Samples a ray can spend inside the box: its diagonal over the step, plus the end points.
        span = math.ceil(float(np.linalg.norm(self.hi - self.lo)) / step) + 2
        ray_gains(np.ascontiguousarray(origins, dtype=np.float64),
                  np.ascontiguousarray(rotations, dtype=np.float64),
                  np.ascontiguousarray(rays_sensor, dtype=np.float64), self.W, self.density,
                  self.occluder, self.lo, self.hi, self.resolution, step, math.floor(ray_length_m / step),
                  span, g_e, g_d)
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
