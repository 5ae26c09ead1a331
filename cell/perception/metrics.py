"""Reconstruction metrics of the visual-servoing paper, eq. 13, and coverage tracked during a scan.

A is a set of points sampled uniformly on the ground-truth surface (10,000 by default, leaving out faces
whose normal is within 45 degrees of straight down, which no camera above the table can see), B the
captured cloud, both in the base frame [m]. All three are one-sided, over A:

- Chamfer(A, B) = mean over a of min_b d(a, b)
- Hausdorff(A, B) = max over a of min_b d(a, b)
- Coverage(A, B, l) = 100 * share of a with min_b d(a, b) <= l, l = 2.5 mm.

The paper registers the mesh to the cloud first; in simulation the ground-truth pose is known, so the
mesh is placed at it and no registration is needed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from drivers.sim.objects import ObjectMesh, sample_surface
from drivers.transforms import transform_points

Array = NDArray[np.float64]

COVERAGE_RADIUS_M = 0.0025
N_GROUND_TRUTH_POINTS = 10_000
# A is drawn with a fixed seed, so jobs with different seeds, and their offline re-processing, are
# measured against the same points.
GROUND_TRUTH_SEED = 13


def ground_truth_points(mesh: ObjectMesh, T_base_object: Array) -> Array:
    """The sample A of eq. 13 in the base frame: ``N_GROUND_TRUTH_POINTS`` points uniform on the surface
    of ``mesh`` placed at ``T_base_object``, without faces within 45 degrees of straight down."""
    rng = np.random.default_rng(GROUND_TRUTH_SEED)
    return transform_points(T_base_object, sample_surface(mesh, N_GROUND_TRUTH_POINTS, rng))


@dataclass(frozen=True)
class Metrics:
    """Eq. 13 figures in millimetres and percent."""

    chamfer_mm: float
    hausdorff_mm: float
    coverage_pct: float

    def as_dict(self) -> dict[str, float]:
        return {"chamfer_mm": self.chamfer_mm, "hausdorff_mm": self.hausdorff_mm,
                "coverage_pct": self.coverage_pct}


def compute_metrics(ground_truth: Array, cloud: Array, radius_m: float = COVERAGE_RADIUS_M) -> Metrics:
    """Eq. 13 of the visual-servoing paper, A = ``ground_truth``, B = ``cloud`` (both (N, 3) [m]).

    With an empty cloud every distance is infinite: Chamfer and Hausdorff are reported as infinity and
    coverage as 0.
    """
    if cloud.shape[0] == 0:
        return Metrics(float("inf"), float("inf"), 0.0)
    d, _ = cKDTree(cloud).query(ground_truth, k=1)
    return _from_distances(np.asarray(d, dtype=np.float64), radius_m)


def _from_distances(d: Array, radius_m: float) -> Metrics:
    """Eq. 13 from the distances d (|A|,) [m] of the ground-truth points to their nearest cloud point."""
    return Metrics(chamfer_mm=float(np.mean(d) * 1e3), hausdorff_mm=float(np.max(d) * 1e3),
                   coverage_pct=float(100.0 * np.mean(d <= radius_m)))


def metrics_timeline(ground_truth: Array, centroids: Array, first: NDArray[np.int64], n_frames: int,
                     radius_m: float = COVERAGE_RADIUS_M) -> list[Metrics]:
    """Eq. 13 as the scan went on (the curves of the visual-servoing paper's Fig. 5): entry k (k = 0 ..
    ``n_frames`` - 1) measures the voxels of the scan's cloud ``centroids`` (K, 3) [m] that frame k or an
    earlier one filled, ``first`` (K,) the first frame of each (``cloud.first_voxels``).

    The last entry is the whole cloud's figure, exactly. Before it, a voxel stands at its final centroid,
    which later frames' points may have moved within the voxel (by less than its diagonal) from the
    centroid of the points seen so far. Each frame's new voxels are measured only against the
    ground-truth points they can bring closer: within the distance the earlier voxels left (rounded up to
    the next millimetre, so that the points go to the k-d tree in a few groups), a bound that keeps the
    search to the new voxels near each point.
    """
    d = np.full(ground_truth.shape[0], np.inf)
    order = np.argsort(first, kind="stable")
    starts = np.searchsorted(first[order], np.arange(n_frames + 1))
    out: list[Metrics] = []
    for k in range(n_frames):
        new = centroids[order[starts[k]:starts[k + 1]]]
        if new.shape[0]:
            tree = cKDTree(new)
            bound = (np.floor(d / 1e-3) + 1.0) * 1e-3
            for b in np.unique(bound):
                at = np.flatnonzero(bound == b)
                found, _ = tree.query(ground_truth[at], k=1, distance_upper_bound=float(b))
                d[at] = np.minimum(d[at], found)
        out.append(_from_distances(d, radius_m))
    return out


class CoverageTracker:
    """Coverage (eq. 13) updated incrementally as points arrive, for progress display.

    Each new batch is tested against the ground-truth points once, so the cost per capture does not
    grow with the accumulated cloud.
    """

    def __init__(self, ground_truth: Array, radius_m: float = COVERAGE_RADIUS_M) -> None:
        self._gt = ground_truth
        self._covered = np.zeros(ground_truth.shape[0], dtype=bool)
        self._radius = radius_m

    def add(self, points_base: Array) -> float:
        """Mark the ground-truth points within the radius of ``points_base``; returns coverage [%]."""
        if points_base.shape[0]:
            d, _ = cKDTree(points_base).query(self._gt, k=1, distance_upper_bound=self._radius)
            self._covered |= d <= self._radius
        return self.coverage_pct

    @property
    def coverage_pct(self) -> float:
        return float(100.0 * np.mean(self._covered))
