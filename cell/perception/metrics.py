"""Reconstruction metrics of the visual-servoing paper, eq. 13, and coverage tracked during a scan.

A is a set of points sampled uniformly on the ground-truth surface (10,000 by default, leaving out faces
whose normal is within 45 degrees of straight down, which no camera above the table can see), B the
captured cloud, both in the base frame [m]. All three are one-sided, over A:

- Chamfer(A, B) = mean over a of min_b d(a, b)
- Hausdorff(A, B) = max over a of min_b d(a, b)
- Coverage(A, B, l) = 100 * share of a with min_b d(a, b) <= l, l = 2.5 mm.

The paper registers the mesh to the cloud first, and so does ``measure``: A, placed at the object's
ground-truth pose, is moved by the rigid transform that best lays the cloud onto it
(``register_ground_truth``), so that the offset a calibration error gives every view alike (the cloud a
little shifted or turned as a whole) is not counted as reconstruction error, while a cloud whose views
disagree still is: no rigid motion brings two copies of a surface onto one. The figures before
registration are kept beside them (``*_unregistered``). ``CloudCoverage``, the live figure during a
scan, is the unregistered coverage of the cloud as it stands.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cell.perception.registration import (
    RegistrationParams,
    constrain_icp,
    estimate_normals,
    point_to_plane_icp,
)
from drivers.sim.objects import ObjectMesh, sample_surface
from drivers.transforms import inv_T, rotvec, transform_points

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


# Registration (``register_ground_truth``): correspondences farther apart than this are outliers. Four times
# the coverage radius: it holds a calibrated cell's error (a few millimetres at the object) with room to
# spare, and leaves out what segmentation let through (table points, noise) a centimetre off the surface.
REGISTRATION_MAX_DISTANCE_M = 4 * COVERAGE_RADIUS_M
_REGISTRATION_ITERATIONS = 50
_MIN_CONSTRAINT: float = RegistrationParams.model_fields["min_constraint"].default  # the online default
_REGISTRATION_CONVERGED_M = 1e-6  # [m] root mean square motion of an update at which a stage ends


def register_ground_truth(ground_truth: Array, cloud: Array,
                          max_distance_m: float = REGISTRATION_MAX_DISTANCE_M) -> Array:
    """The rigid T (4x4, base frame) that moves A (``ground_truth``, (N, 3) [m]) onto the cloud (M, 3) [m].

    Point-to-plane ICP (``registration.point_to_plane_icp``) from the cloud to A: every cloud point lies on
    the seen part of the surface, which A covers whole, so each has a true counterpart on A, while most of
    A has none in a partial cloud. A's normals come from its own points (within ``max_distance_m``); pairs
    farther apart than ``max_distance_m``, then half that, are left out, as are those more than the
    coverage radius beyond A's points along their tangent plane. Starts at the identity (A at the
    ground-truth pose); a stage ends when an update moves the cloud by less than 1 um (mean square).

    Then, as the online registration of frames does (``registration.constrain_icp``), the motion is kept
    only along the directions the pairs constrain (a cloud of one face of a box says nothing about a slide
    along it), and it is refused (the identity) when it would move a point of the cloud's bounding box
    farther than ``max_distance_m``: beyond the gate the pairs it was computed from do not exist, and a
    calibration error is far smaller (a sparse, noisy cloud, such as the 8x8 ToF sensor's, otherwise slides
    A by centimetres). It is refused too when A and the cloud fit each other worse after it than before
    (``_mutual_misfit``): ICP minimises the cloud's distance to A only, and on a partial cloud it can slide
    A along the seen surface away from where the cloud's own views would put it (a standing cylinder's
    cloud from one side moved A by 5.5 mm and halved its coverage).
    """
    if cloud.shape[0] < 3 or ground_truth.shape[0] < 3:
        return np.eye(4)
    normals = estimate_normals(ground_truth, ground_truth, max_distance_m)
    icp = point_to_plane_icp(cloud, ground_truth, normals, (max_distance_m, max_distance_m / 2),
                             max_iterations=_REGISTRATION_ITERATIONS, epsilon=_REGISTRATION_CONVERGED_M ** 2,
                             max_tangential_m=COVERAGE_RADIUS_M)
    T, _ = constrain_icp(icp, cloud, normals[icp.correspondences[:, 1]], _MIN_CONSTRAINT)
    lo, hi = cloud.min(axis=0), cloud.max(axis=0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    if np.max(np.linalg.norm(transform_points(T, corners) - corners, axis=1)) > max_distance_m:
        return np.eye(4)
    moved = transform_points(inv_T(T), ground_truth)
    if _mutual_misfit(moved, cloud, max_distance_m) > _mutual_misfit(ground_truth, cloud, max_distance_m):
        return np.eye(4)
    return inv_T(T)


def _mutual_misfit(ground_truth: Array, cloud: Array, max_distance_m: float) -> float:
    """How badly A (``ground_truth``) and the cloud fit each other [m]: the mean distance from each to the
    other, each distance capped at ``max_distance_m`` (A's unseen part counts the same wherever A is)."""
    to_gt, _ = cKDTree(ground_truth).query(cloud, k=1)
    to_cloud, _ = cKDTree(cloud).query(ground_truth, k=1)
    return float(np.mean(np.minimum(to_gt, max_distance_m)) + np.mean(np.minimum(to_cloud, max_distance_m)))


@dataclass(frozen=True)
class Measurement:
    """Eq. 13 as the paper measures it: after registering A to the cloud (``registered``), before it
    (``unregistered``), and the registration ``T`` (4x4, base frame) that moved A."""

    registered: Metrics
    unregistered: Metrics
    T: Array

    def as_dict(self) -> dict[str, float]:
        """result.json's ``metrics``: the registered figures (``chamfer_mm``, ``hausdorff_mm``,
        ``coverage_pct``), the unregistered ones (the same names with ``_unregistered``), and how far
        registration moved A (``registration_mm``: its translation, ``registration_deg``: its angle); the
        keys are ``METRICS_KEYS``."""
        u = self.unregistered
        return {**self.registered.as_dict(), "chamfer_unregistered_mm": u.chamfer_mm,
                "hausdorff_unregistered_mm": u.hausdorff_mm, "coverage_unregistered_pct": u.coverage_pct,
                "registration_mm": float(np.linalg.norm(self.T[:3, 3]) * 1e3),
                "registration_deg": float(np.degrees(np.linalg.norm(rotvec(self.T[:3, :3]))))}


METRICS_KEYS = ("chamfer_mm", "hausdorff_mm", "coverage_pct", "chamfer_unregistered_mm",
                "hausdorff_unregistered_mm", "coverage_unregistered_pct", "registration_mm",
                "registration_deg")


def measure(ground_truth: Array, cloud: Array, radius_m: float = COVERAGE_RADIUS_M) -> Measurement:
    """Eq. 13 of A = ``ground_truth`` and B = ``cloud`` ((N, 3) [m]) after registering A to B
    (``register_ground_truth``) and before."""
    T = register_ground_truth(ground_truth, cloud)
    return Measurement(compute_metrics(transform_points(T, ground_truth), cloud, radius_m),
                       compute_metrics(ground_truth, cloud, radius_m), T)


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


class CloudCoverage:
    """Eq. 13's coverage of the job's cloud as it stands, before A is registered to it: the figure shown
    while a scan runs (the progress line of ``cell scan``, ``servo.csv``, ``servo.png``, the operator's
    page). After the last capture it is the result's ``coverage_unregistered_pct`` exactly.

    It is not the result's ``coverage_pct``, which ``measure`` takes after registering A to the final
    cloud: that registration takes seconds (3-4 s on a 57,000-point bunny cloud), too long to repeat at
    every capture. The two differ by what registration moves A: a few points either way (bunny, VS-Local,
    seed 0: 91.3 % unregistered, 96.1 % registered; a mug 82.1 % and 80.4 %).

    The cloud is measured whole at every update, not frame by frame: the cloud is voxel-filtered and its
    centroids move as frames are averaged in, so the union of the frames' own points covers more of A than
    the cloud does (a bunny scan's union reached 95.6 % where the cloud held 91.3 %). Only the cloud
    points within the coverage radius of A's bounding box can count, and only they are searched.
    """

    def __init__(self, ground_truth: Array, radius_m: float = COVERAGE_RADIUS_M) -> None:
        self._gt = ground_truth
        self._radius = radius_m
        self._lo = ground_truth.min(axis=0) - radius_m
        self._hi = ground_truth.max(axis=0) + radius_m
        self.coverage_pct = 0.0

    def update(self, cloud: Array) -> float:
        """Measure the cloud (M, 3) [m], base frame; returns coverage [%], also kept in ``coverage_pct``."""
        near = cloud[np.all((cloud >= self._lo) & (cloud <= self._hi), axis=1)]
        if near.shape[0] == 0:
            self.coverage_pct = 0.0
        else:
            d, _ = cKDTree(near).query(self._gt, k=1, distance_upper_bound=self._radius)
            self.coverage_pct = float(100.0 * np.mean(d <= self._radius))
        return self.coverage_pct
