"""Per-frame point filters (visual-servoing paper, section II-A "Filtering").

The paper simplifies each raw cloud to 2.5 mm with a voxel filter, crops it to a box centred on the camera
frustum (x, y within +-15 cm, z in (5, 40) cm in the sensor frame), removes spurious points with a
statistical outlier filter, and low-pass filters the object centroid that drives the servo task. For the
multizone time-of-flight sensor (LR-NBV paper, VL53L8CX) the equivalent of the outlier filter is the
sensor's own per-zone target status: only zones with a valid status (5 and 9 by default) are kept.

The voxel filter and the crop box are reused from :mod:`cell.perception.cloud`; their parameters live in
the cell config's ``perception`` section (``crop_box``, ``voxel_m``) and are passed in as arguments here.
Everything is deterministic (exact grid search, no randomness).
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from cell.perception import _kernels as _k
from cell.perception.cloud import PointGrid, bounds, crop_voxel_downsample, slab_interval
from drivers.config_base import StrictModel
from drivers.depth.base import DepthFrame

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_MAX_GRID_CELLS = 4_000_000
"""Cap on the cells of the kNN search grid (32 MB of run offsets)."""

GRAZING_DEG = 80.0
"""[deg] The largest incidence (between a pixel's ray and the surface's normal) at which a depth camera
returns a surface (:func:`continuous_depth_mask`): ``sim-rgbd`` returns none beyond its ``grazing_deg``
(80 by default), and a stereo or structured-light camera matches no texture or pattern on a surface seen
flatter."""


class FilterParams(StrictModel):
    """Filter settings not already in the cell config's perception section.

    ``sor_neighbors`` k of the statistical outlier removal; ``sor_std_ratio`` the number of standard
    deviations above the mean neighbour distance beyond which a point is an outlier; ``sor_enabled``
    switches the SOR step off (e.g. for the sparse 8x8 ToF); ``valid_tof_statuses`` the VL53L8CX target
    statuses trusted as valid ranges (ST's guidance: 5 = range valid, 9 = range valid with large pulse).
    """

    sor_neighbors: int = Field(20, ge=1)
    sor_std_ratio: float = Field(2.0, gt=0.0)
    """[1] standard deviations above the mean neighbour distance beyond which a point is an outlier."""
    sor_enabled: bool = True
    valid_tof_statuses: tuple[int, ...] = (5, 9)


class CropBox(Protocol):
    """Anything with open-interval bounds ``x_m``, ``y_m``, ``z_m`` [m] in the sensor frame (e.g. the
    config's ``CropBoxConfig``)."""

    @property
    def x_m(self) -> tuple[float, float]: ...
    @property
    def y_m(self) -> tuple[float, float]: ...
    @property
    def z_m(self) -> tuple[float, float]: ...


def statistical_outlier_mask(points: Array, k: int, std_ratio: float) -> BoolArray:
    """Inlier mask (N,) of the statistical outlier removal (paper section II-A "Filtering").

    For each point the mean Euclidean distance to its ``k`` nearest neighbours (the point itself excluded,
    PCL's ``StatisticalOutlierRemoval`` semantics) is computed; a point is kept when that mean is at most
    ``mu + std_ratio * sigma``, with ``mu`` / ``sigma`` the mean and sample standard deviation of the
    per-point means over the cloud. With fewer than ``k + 1`` points every point is kept (no statistics).
    """
    n = points.shape[0]
    if k < 1:
        raise ValueError(f"statistical_outlier_mask: k must be >= 1, got {k}")
    if n <= k:
        return np.ones(n, dtype=bool)
    mean_d = knn_mean_distances(points, k)
    mu = mean_d.mean()
    sigma = mean_d.std(ddof=1)
    return mean_d <= mu + std_ratio * sigma


def knn_mean_distances(points: Array, k: int) -> Array:
    """Mean Euclidean distance (N,) [m] of each point (N, 3) [m] to its ``k`` nearest other points (N > k).

    Exact search on a uniform grid in the compiled kernel (``_kernels.knn_mean_distances``). The cell edge
    only sets the speed (measured best on a 150k-point surface): it is chosen so that a cell holds about
    k / pi points of a surface-like cloud (the k neighbours then lie within about one cell, inside the 27
    cells around a point), from a first count at 1/64 of the cloud's extent (points per cell grow with the
    square of the edge on a surface), then widened until the grid has at most ``_MAX_GRID_CELLS`` cells
    (``PointGrid``).
    """
    if not 0 < k < points.shape[0]:
        raise ValueError(f"knn_mean_distances: need 0 < k < N, got k={k}, N={points.shape[0]}")
    pts = np.ascontiguousarray(points, dtype=np.float64)
    lo, hi = bounds(pts)
    cell = max(float((hi - lo).max()), 1e-9) / 64.0
    c = np.floor((pts - lo) / cell).astype(np.int64)  # at most 65 per axis
    # occupied cells counted on the dense 65^3 grid: a bincount, some 4x faster than np.unique here
    occupied = np.count_nonzero(np.bincount((c[:, 0] * 65 + c[:, 1]) * 65 + c[:, 2], minlength=65 ** 3))
    per_cell = pts.shape[0] / occupied
    grid = PointGrid(pts, cell * math.sqrt((k / math.pi) / per_cell), _MAX_GRID_CELLS)
    sorted_mean = np.empty(pts.shape[0])
    nx, ny, nz = (int(v) for v in grid.dims)
    _k.knn_mean_distances(grid.points, grid.cells, grid.starts, nx, ny, nz, grid.cell_m, grid.lo, k,
                          sorted_mean)
    out = np.empty(pts.shape[0])
    out[grid.order] = sorted_mean
    return out


def statistical_outlier_removal(points: Array, k: int, std_ratio: float) -> Array:
    """The points (M, 3) kept by :func:`statistical_outlier_mask`, in input order."""
    return points[statistical_outlier_mask(points, k, std_ratio)]


def valid_tof_zones(frame: DepthFrame, valid_statuses: tuple[int, ...] | list[int] = (5, 9)
                    ) -> NDArray[np.bool_]:
    """Which of the frame's ToF zones (n_zones,) hold a range: a status in ``valid_statuses``, a target and
    a finite positive distance (whatever the status, a zone without them is dropped). Raises
    ``ValueError`` for a frame without ``zones`` (not a ToF frame)."""
    zones = frame.zones
    if zones is None:
        raise ValueError(f"frame {frame.seq} has no ToF zones: not a ToF frame")
    return np.asarray(np.isin(zones.status, np.asarray(valid_statuses, dtype=np.int64))
                      & (zones.nb_targets > 0) & np.isfinite(zones.distance_m) & (zones.distance_m > 0.0))


def valid_tof_returns(frame: DepthFrame, valid_statuses: tuple[int, ...] | list[int] = (5, 9)
                      ) -> tuple[Array, Array]:
    """Points (K, 3) [m, sensor frame] of the ToF zones that hold a range (:func:`valid_tof_zones`) and
    their range sigmas (K,) [m].

    Rebuilt from ``zones.distance_m * zones.directions`` (distance along each zone's central ray) rather
    than taken from ``frame.points``, which holds every zone with a target whatever its status. Zone order
    is kept."""
    keep = valid_tof_zones(frame, valid_statuses)
    assert frame.zones is not None
    return frame.zones.distance_m[keep, None] * frame.zones.directions[keep], frame.zones.sigma_m[keep]


def continuous_depth_mask(depth: NDArray[np.floating], pitch_rad: float) -> BoolArray:
    """Which pixels (H, W) of a depth image ``depth`` [m] (0: no return) hold a return whose depth no
    neighbour's (4-neighbourhood, those with a return) differs from by more than one surface can give.

    The bound is geometric. Neighbouring pixels' rays are ``pitch_rad`` [rad] apart (a camera's 1 / fx).
    Along two rays that far apart, a plane seen at incidence theta lies at depths z and, to first order,
    z (1 + pitch_rad tan theta); no surface is returned seen beyond ``GRAZING_DEG``, so depths further
    apart than ``z_near * pitch_rad * tan(GRAZING_DEG)`` [m] (z_near the nearer one) are two surfaces, a
    foreground's edge over a background. A pixel at such an edge may mix the two (a flying pixel, its depth
    anywhere between them, as a RealSense gives), so the farther pixel of every such pair is dropped: a
    flying pixel lies beyond the foreground pixel beside it, and the ones in a row of them each beyond the
    one before, while the foreground itself stays, however thin (a rod one pixel wide over the table is
    nearer than both its neighbours: the obstacle the guard must see). Range noise is not in the bound: it
    drops a few pixels of a surface seen at nearly ``GRAZING_DEG``, each one of the many that a centimetre
    holds, where a bound widened by it would keep the flying pixels of a shallow edge."""
    z = np.asarray(depth)
    slope = pitch_rad * math.tan(math.radians(GRAZING_DEG))
    keep = z > 0.0
    for along, kept in ((z, keep), (z.T, keep.T)):  # down the columns, then along the rows (views)
        first, second = along[:-1], along[1:]
        near = np.minimum(first, second)
        edge = (np.abs(second - first) > slope * near) & (near > 0.0)
        kept[:-1] &= ~(edge & (first > second))
        kept[1:] &= ~(edge & (second > first))
    return keep


def no_target_directions(frame: DepthFrame) -> Array:
    """Unit central rays (J, 3) [sensor frame] of the ToF zones that saw no target (``nb_targets == 0``),
    in zone order: free space up to the sensor's range, for carving the occupancy map."""
    zones = frame.zones
    if zones is None:
        raise ValueError(f"no_target_directions: frame {frame.seq} has no ToF zones")
    d = zones.directions[zones.nb_targets == 0]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def crop_interval(directions: Array, crop: CropBox) -> tuple[Array, Array]:
    """Ray parameters [t_in, t_out] [m] where the unit rays ``directions`` (..., 3) from the sensor [sensor
    frame] lie inside the crop box ``crop`` (:func:`cell.perception.cloud.slab_interval`; t_in > t_out
    for a ray that misses it). The box is fixed in the sensor frame: the same for every pose."""
    lo = np.array([crop.x_m[0], crop.y_m[0], crop.z_m[0]])
    hi = np.array([crop.x_m[1], crop.y_m[1], crop.z_m[1]])
    return slab_interval(np.zeros(3), directions, lo, hi)


def carved_lengths(directions: Array, crop: CropBox, range_max_m: float) -> Array:
    """How far [m] each of the unit rays ``directions`` (J, 3) [sensor frame] of the ToF zones that saw no
    target carves free space: to the sensor's range ``range_max_m`` or to where it leaves the crop box
    ``crop`` [sensor frame], whichever is nearer; 0 for a ray that never enters the box.

    A return beyond the crop box is dropped with its ray, so the map holds nothing beyond the box but what
    these rays carve; the planners read it only inside the object's ROI, well inside the box. Carved on to
    the VL53L8CX's 4 m, they filled the map with blocks that no query reads: 1.0-1.6 GB of peak memory on
    one simulated ToF scan."""
    t_in, t_out = crop_interval(directions, crop)
    return np.where(t_out >= t_in, np.clip(t_out, 0.0, range_max_m), 0.0)


def filter_frame(points_sensor: Array, *, crop: CropBox, voxel_m: float, params: FilterParams) -> Array:
    """Filter one RGB-D cloud in the sensor frame: crop box, then voxel filter, then SOR.

    The paper lists voxel filter, crop, SOR; cropping first gives the same points inside the box (the
    voxel grid is anchored at the sensor origin, and a voxel centroid straddling a crop face is the only
    difference) and both are done in one compiled pass over the raw points
    (``cloud.crop_voxel_downsample``). SOR comes last, as in the paper, so that its statistics are computed on
    the uniform-density voxelized cloud, which is what makes a global distance threshold meaningful.
    Output (M, 3) [m, sensor frame], sorted by voxel key.
    """
    pts = crop_voxel_downsample(points_sensor, crop.x_m, crop.y_m, crop.z_m, voxel_m)
    if params.sor_enabled:
        pts = statistical_outlier_removal(pts, params.sor_neighbors, params.sor_std_ratio)
    return pts


class CentroidLowPass:
    """First-order (exponential) low-pass filter on a 3D centroid [m] with time constant ``tau_s`` [s].

    Paper section II-A: "Residual noise in the centroid estimation is mitigated through a low-pass filter,
    ensuring stable convergence of the primary task" (the servo keeps the object centroid on the optical
    axis; a jittery centroid would make the camera twist jitter). The update is dt-aware so that it behaves
    the same at any frame rate: ``alpha = 1 - exp(-dt / tau_s)``, ``y += alpha * (x - y)``. ``tau_s = 0``
    passes the input through. The first sample initialises the state; a sample at the same time as the
    previous one does not move the state; time going backwards raises ``ValueError``.
    """

    def __init__(self, tau_s: float) -> None:
        if not tau_s >= 0.0:
            raise ValueError(f"CentroidLowPass: tau_s must be >= 0 s, got {tau_s}")
        self.tau_s = float(tau_s)
        self._y: Array | None = None
        self._t: float | None = None

    @property
    def value(self) -> Array | None:
        """The filtered centroid (3,) [m], or None before the first update."""
        return None if self._y is None else self._y.copy()

    def reset(self) -> None:
        """Forget the state; the next update re-initialises it."""
        self._y = None
        self._t = None

    def update(self, centroid: Array, t: float) -> Array:
        """Feed the centroid (3,) [m] measured at time ``t`` [s]; returns the filtered centroid (3,)."""
        x = np.asarray(centroid, dtype=np.float64).reshape(3)
        if self._y is None or self._t is None:
            self._y = x.copy()
            self._t = float(t)
            return self._y.copy()
        dt = float(t) - self._t
        if dt < 0.0:
            raise ValueError(f"CentroidLowPass: time went backwards ({self._t} s -> {t} s)")
        alpha = 1.0 if self.tau_s == 0.0 else 1.0 - math.exp(-dt / self.tau_s)
        self._y = self._y + alpha * (x - self._y)
        self._t = float(t)
        return self._y.copy()
