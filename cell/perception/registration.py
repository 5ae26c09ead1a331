"""Frame-to-model registration (visual-servoing paper section II-A, "2) Registration").

Each new cleaned cloud is registered into the robot base frame onto the accumulated target with
point-to-plane ICP ([25] in the paper; ``point_to_plane_icp``, numpy and a compiled grid search):

- target normals estimated with a search radius of 5 mm (``normal_radius_m``; a hybrid search capped at
  ``MAX_NORMAL_NEIGHBOURS`` neighbours, as Open3D's), once per point of the target (``RegistrationTarget``);
- transformation and fitness epsilon 1e-8 (``epsilon``, with PCL's meaning, the library the paper used:
  squared motion [m^2] of the last update and change of the mean squared residual [m^2]), at most 20
  iterations (``max_iterations``);
- the arm's forward kinematics (FK) as the initial guess;
- correspondences beyond 2 mm rejected.

Choice left open by the paper, written down here: with only a 2 mm rejector, an FK error of a few
millimetres (5 mm / 1 deg displaces points by up to ~1 cm at 0.25 m) leaves too few correspondences to
converge. ICP therefore runs a coarse-to-fine schedule ``max_correspondence_m`` (default 20 mm, 8 mm,
2 mm), each stage up to ``max_iterations`` iterations and started from the previous stage's result; the
last stage is the paper's 2 mm rejector and gives the reported fitness and RMSE. ICP uses at most
``max_source_points`` of the frame (an even subset; ~16k points arrive at 2.5 mm): measured on the
bunny, 3000 points recover an injected 5 mm / 1 deg error as well as all of them, at a fifth of the cost.

Pairs beyond the target's surface are rejected in every stage (choice of this module, the pair rejection
of the paper's ICP reference [25], Rusinkiewicz and Levoy section 3.4: pairs on mesh boundaries, after
Turk and Levoy 1994): a pair is used only if the source point lies within ``normal_radius_m`` of its
target point along that point's tangent plane, the neighbourhood its normal was fitted on. Over a
sampled surface the nearest target point is within about one voxel along the plane, however far off the
surface the FK error puts the source point; only a source point beyond the edge of what the target has
seen gets a nearest point centimetres away along the plane. Such a pair says nothing about the motion,
yet its residual (p - q) . n is that tangential offset times the noise tilt of the normal (a few
degrees at 5 mm with 2.5 mm voxels), the same sign for every point of the newly seen area. Summed over
the few hundred points a new view adds at the edge of the target, it pulled the frame back onto the seen
area along directions the planes of a box and a table leave to those noise tilts: with the 20 mm first
stage, exact-pose top views of the cube slid by 5-17 mm and contaminated the target (online coverage
79.0 % against 81.9 % without registration); with the rejection they move by at most ~3 mm.

Back faces are left out of the target (choice of this module; the compatible-normals rule among the
pairings of [25], section 3.3, after Godin et al. 1994): a sensor sees a surface only from its front, so
the target a new frame is registered onto holds only the points whose normal, turned at their first
sighting towards the sensor that saw them, faces the new frame's FK sensor origin
(``RegistrationTarget.facing``). The two faces of a wall thinner than the first stages' distances are
each other's nearest points with opposite normals: a frame seeing the inside of an open cup's 4 mm wall
whose outside the target holds was pulled by the wall's thickness onto the outside, the correction grew
to 4.6 mm over an exact-pose cup scan and the wall was smeared across three voxels (VS-Local cup, seed 0,
``sim.exact``: 58.0 % coverage, 84.5 % with registration off; with back faces left out the correction
stays at 0.1-0.2 mm and coverage is 85.3 %). On a solid the points facing away from the sensor lie on
the far side of the object, which no correspondence should reach anyway.

A registration that diverges is rejected, logged with its figures (``logging`` at WARNING), and the FK pose
is used instead: fitness (share of source points with a correspondence within the last stage's distance)
below ``min_fitness``, or a correction of the sensor pose larger than ``max_correction_m`` /
``max_correction_deg``.

Degeneracy-aware acceptance (choice of this module; Zhang, Kaess and Singh, "On degeneracy of
optimization-based state estimation problems", ICRA 2016): scenes of planes (the table, the faces of a box)
leave directions of the 6-DoF pose that the point-to-plane residuals r_i = (p_i - q_i) . n_i barely
constrain, and ICP drifts along them by millimetres even from an exact FK pose. At the final pose the
correspondences of the last stage give the Jacobian rows J_i = [((p_i - c) x n_i) / L, n_i] of r_i with
respect to a twist (rotation w scaled by L, translation v) about the centroid c of the matched points,
L their RMS distance to c (so both parts are in metres); the normalised Hessian H = (1/K) sum J_i^T J_i
has eigenvalues in [0, 1]: the mean squared normal displacement per unit of motion along each
eigen-direction. The correction (as that twist) is projected onto the eigen-directions whose eigenvalue
is at least ``min_constraint``; the others keep the FK pose. The normals n_i of this test are fitted
over ``constraint_normal_radius_m`` (10 mm, twice ICP's 5 mm; choice of this module): on a plane, the
noise tilt of a 5 mm normal (2.5 mm voxels, ~12 neighbours) alone gives a slide along it an eigenvalue
of 0.0014-0.004, on both sides of ``min_constraint``, so a slide along the table could pass for a
measured direction; at 10 mm the tilt variance is ~1/7 of that (0.0001-0.0004 on exact-pose cube top
views) while the shape of a curved object at that scale stays (weakest direction of the bunny test
view 0.0049 at 5 mm, 0.0045 at 10 mm). Replayed cube vs-local scan, exact poses: mean correction
1.21 -> 0.36 mm. What was dropped is logged (INFO) and
counted in ``RegistrationResult.n_constrained``.

The correction is applied in the base frame: ``T_base_sensor_used = T_correction @ T_base_sensor_fk``.
It is measured at the sensor: the translation is the distance between the corrected and the FK sensor
origins [m], the angle that of the rotation of ``T_correction`` [deg].

For the 8x8 time-of-flight sensor (packing cell) a frame has at most 64 points: registration is off
there (``enabled: false`` in its cell file; ``min_points`` rejects such frames anyway).

Determinism: each online ICP iteration is one single-threaded compiled pass
(``_kernels.point_to_plane_system``: grid search and normal equations, summed in source order); inputs
are float64 arrays in a fixed order (the accumulated cloud from ``voxel_downsample`` is sorted by voxel
key). The offline re-processing (``cell.perception.reprocess``) uses the same ICP.
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass
from typing import Annotated, NamedTuple

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, PositiveFloat, PositiveInt, field_validator
from scipy.spatial.transform import Rotation

from cell.perception import _kernels as _k
from cell.perception.cloud import (
    VOXEL_EDGE_M,
    PerceptionDistance,
    PointGrid,
    bounds,
    cross_rows,
    in_box,
    voxel_downsample,
)
from drivers.config_base import Bounds, StrictModel
from drivers.transforms import make_T, rotvec, transform_points

Array = NDArray[np.float64]

log = logging.getLogger(__name__)

MAX_NORMAL_NEIGHBOURS = 30
"""Cap on the neighbours used for one normal (hybrid radius / k-NN search)."""

_GRID_CELL_M = 0.005
"""Cell of the correspondence search grid [m]: about four 2.5 mm target points a cell on a surface."""



class RegistrationParams(StrictModel):
    """Registration settings (paper section II-A). ``enabled`` has no default: a cell file states it
    (off for the 8x8 ToF, whose frames have too few points).

    ``normal_radius_m`` [m] target-normal search radius (5 mm), also the largest offset of an ICP pair
    along the target's tangent plane (module docstring); ``max_iterations`` per ICP stage (20);
    ``epsilon`` [m^2] the motion and the residual change that end a stage (1e-8, below);
    ``max_correspondence_m`` [m] the coarse-to-fine correspondence distances, the last one the paper's
    2 mm rejector;
    ``source_voxel_m`` [m] voxel filter of the new frame before ICP (paper: 2.5 mm; 0 = none);
    ``min_fitness`` the share of source points with a correspondence below which the result is rejected;
    ``max_correction_m`` [m] / ``max_correction_deg`` [deg] the largest accepted correction of the FK
    pose; ``min_points`` the fewest source (and target) points worth registering; ``min_constraint`` the
    smallest eigenvalue of the normalised point-to-plane Hessian (module docstring) for a direction of
    the correction to be kept (0 keeps all six; 0.003 measured: the two directions the table and the
    top face of the cube leave to the noise of the normals lie at 0.0001-0.0004 on exact-pose top views,
    the weakest direction of the bunny test view at 0.0045; the third direction of those cube views,
    held by the cube's edges and its sides seen at grazing incidence, lies at 0.0017-0.0034, around the
    threshold: when kept, it can move an exact-pose frame by up to ~5 mm);
    ``max_source_points`` the most frame points ICP uses (an even subset);
    ``constraint_normal_radius_m`` [m] the radius of the normals of the degeneracy test (module docstring).
    """

    enabled: bool
    normal_radius_m: PerceptionDistance = 0.005
    max_iterations: PositiveInt = 20
    epsilon: PositiveFloat = 1e-8
    """[m²] a stage ends when an update moves the source points by a mean squared distance of at most this, or
    changes their mean squared residual by less (PCL's transformation and Euclidean fitness epsilons)."""
    max_correspondence_m: tuple[PerceptionDistance, ...] = Field(default=(0.02, 0.008, 0.002), min_length=1)
    source_voxel_m: Annotated[float, Bounds(0.0, VOXEL_EDGE_M[1], "m", "a voxel's edge is at most a few "
                                            "centimetres (0: the frame as it is)")] = 0.0025
    min_fitness: float = Field(default=0.3, ge=0.0, le=1.0)
    """[1] the share of source points with a correspondence below which the result is rejected."""
    max_correction_m: PerceptionDistance = 0.02
    max_correction_deg: Annotated[float, Bounds(0.01, 180.0, "deg", "a correction turns the pose by less "
                                                "than half a turn")] = 3.0
    min_points: PositiveInt = 200
    min_constraint: float = Field(default=0.003, ge=0.0, le=1.0)
    """[1] the smallest eigenvalue of the normalised point-to-plane Hessian for a direction of the correction
    to be kept."""
    max_source_points: PositiveInt = 3000
    constraint_normal_radius_m: PerceptionDistance = 0.01

    @field_validator("max_correspondence_m")
    @classmethod
    def _coarse_to_fine(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if any(b > a for a, b in itertools.pairwise(v)):
            raise ValueError(f"stages must not grow (coarse to fine), got {list(v)}")
        return v


REJECTED = "rejected: "
SKIPPED_REASONS = {"disabled": "disabled in the cell file, perception.registration.enabled: false",
                   "no target yet": "no target yet: the first frame starts it",
                   "too few points": "too few points to register"}
"""The reasons ICP did not run (``RegistrationResult.reason``), in words."""


@dataclass(frozen=True)
class RegistrationResult:
    """Outcome of one registration.

    ``T_base_sensor`` the pose to use (corrected if accepted, else FK); ``T_correction`` the 4x4 base-frame
    correction found by ICP (``T_used = T_correction @ T_fk`` when accepted; identity when ICP did not
    run); ``fitness`` and ``rmse_m`` [m] of the last stage; ``correction_m`` [m] and ``correction_deg``
    [deg] its size at the sensor; ``reason`` "ok", "disabled", "no target yet", "too few points" (ICP
    skipped) or, after ICP ran and its result was refused, ``REJECTED`` followed by why;
    ``n_constrained`` how many of the 6 eigen-directions of the point-to-plane Hessian were kept
    (6 when ICP did not run) and ``min_eigenvalue`` the smallest normalised eigenvalue (NaN when ICP did
    not run).
    """

    T_base_sensor: Array
    T_correction: Array
    accepted: bool
    fitness: float
    rmse_m: float
    correction_m: float
    correction_deg: float
    reason: str
    n_constrained: int = 6
    min_eigenvalue: float = float("nan")

    @property
    def rejected(self) -> bool:
        """ICP ran and its result was refused (a skipped registration is not a rejection)."""
        return self.reason.startswith(REJECTED)

    @property
    def skipped(self) -> bool:
        """ICP did not run (``reason`` says why: the fitness, correction and constrained directions are
        placeholders then, not measurements)."""
        return not (self.accepted or self.rejected)

    def describe(self) -> str:
        """The outcome in words for a job's log: ICP's figures when it ran, else why it did not run."""
        if self.skipped:
            why = SKIPPED_REASONS.get(self.reason, self.reason)
            return f"registration skipped ({why}): the FK pose is used"
        return (f"registration {self.reason} (fitness {self.fitness:.3f}, correction "
                f"{self.correction_m * 1e3:.2f} mm / {self.correction_deg:.3f} deg, "
                f"{self.n_constrained} of 6 directions constrained)")


class IcpResult(NamedTuple):
    """Outcome of ``point_to_plane_icp``: ``T`` the 4x4 T_target_source, ``fitness`` and ``rmse_m`` [m] of
    the last stage, ``correspondences`` (K, 2) its (source index, target index) pairs at ``T``."""

    T: Array
    fitness: float
    rmse_m: float
    correspondences: NDArray[np.int32]


def estimate_normals(points: Array, cloud: Array, radius_m: float) -> Array:
    """Unit normals (M, 3) at ``points`` (M, 3) [m] of the surface sampled by ``cloud`` (N, 3) [m]: the
    eigenvector of the smallest eigenvalue of the covariance of the at most ``MAX_NORMAL_NEIGHBOURS``
    nearest cloud points within ``radius_m`` [m] (Open3D's hybrid search; a point of the cloud counts
    itself; neighbours from the exact grid search of ``PointGrid``; covariance and eigenvector in the
    compiled ``_kernels.plane_normals``, by Jacobi rotations). Their sign is arbitrary (point-to-plane
    residuals do not depend on it); fewer than 3 neighbours give (0, 0, 1), as Open3D."""
    m = points.shape[0]
    normals = np.tile(np.array([0.0, 0.0, 1.0]), (m, 1))
    if m == 0 or cloud.shape[0] == 0:
        return normals
    cloud = np.ascontiguousarray(cloud, dtype=np.float64)
    idx = PointGrid(cloud, radius_m).k_nearest_within(points, MAX_NORMAL_NEIGHBOURS, radius_m)
    _k.plane_normals(cloud, idx, normals)
    return normals


def constraint_normals(points: Array, cloud: Array, radius_m: float) -> Array:
    """Normals of the degeneracy test (module docstring) at ``points`` (M, 3) [m] of the surface sampled
    by ``cloud`` (N, 3) [m]: fitted to every cloud point within ``radius_m`` [m], without the neighbour
    cap of ``estimate_normals`` (compiled ``_kernels.radius_plane_normals``; sorting the nearest 120 of
    the ~50 points a 10 mm neighbourhood holds at 2.5 mm cost ~30 ms a frame). Sign arbitrary; fewer
    than 3 neighbours give (0, 0, 1)."""
    normals = np.empty((points.shape[0], 3))
    if points.shape[0] == 0:
        return normals
    grid = PointGrid(cloud, radius_m)
    nx, ny, nz = (int(v) for v in grid.dims)
    _k.radius_plane_normals(grid.points, grid.starts, nx, ny, nz, grid.cell_m, grid.lo,
                            np.ascontiguousarray(points, dtype=np.float64), radius_m, normals)
    return normals


def point_to_plane_icp(source: Array, target: Array, target_normals: Array, stages_m: tuple[float, ...], *,
                       max_iterations: int, epsilon: float, max_tangential_m: float) -> IcpResult:
    """Point-to-plane ICP (Chen and Medioni, 1992) of ``source`` (N, 3) [m] onto ``target`` (M, 3) [m]
    with its ``target_normals``, from the identity: one run per maximum correspondence distance in
    ``stages_m`` [m], each starting where the previous one ended.

    An iteration pairs each moved source point with its nearest target point within the stage's
    distance and solves the linearised point-to-plane least squares for a small motion (rotation vector w,
    translation t: p -> p + w x p + t); a pair whose source point lies more than ``max_tangential_m``
    [m] from its target point along the target point's tangent plane is left out (beyond the target's
    surface, module docstring). A stage stops after ``max_iterations`` or when it has converged,
    with the paper's two epsilons (PCL's ``setTransformationEpsilon`` / ``setEuclideanFitnessEpsilon``):
    the last update moved the source points by a mean squared distance of at most ``epsilon`` [m^2]
    (PCL bounds the squared translation by it but accepts any rotation under 0.26 deg, which stopped
    stages a few tenths of a degree short), or the mean squared point-to-plane residual changed by less
    than ``epsilon`` [m^2]. The returned fitness, RMSE and correspondences are evaluated at the returned
    transform with the last stage's distance. Nearest neighbours come from the exact grid search of
    ``PointGrid`` (5 mm cells: a grid is built in a few ms, a kd-tree took 5x longer); pairing and the
    6x6 normal equations of an iteration are one compiled pass over the source
    (``_kernels.point_to_plane_system``, summed in source order): nothing depends on thread counts.
    """
    grid = PointGrid(target, _GRID_CELL_M)
    src = np.ascontiguousarray(source, dtype=np.float64)
    normals = np.ascontiguousarray(target_normals[grid.order], dtype=np.float64)
    nx, ny, nz = (int(v) for v in grid.dims)
    ata, atb = np.empty((6, 6)), np.empty(6)
    centre = source.mean(axis=0)
    spread = float(np.einsum("ij,ij->", source - centre, source - centre)) / max(source.shape[0], 1)
    T = np.eye(4)
    for dist in stages_m:
        prev_mse = math.inf
        for _ in range(max_iterations):
            # pairs, residuals and the normal equations of the rows [p x n, n] in one compiled pass
            count, sse = _k.point_to_plane_system(grid.points, normals, grid.starts, nx, ny, nz, grid.cell_m,
                                                  grid.lo, src, T, dist, max_tangential_m, ata, atb)
            if count < 6:
                break
            x = np.linalg.lstsq(ata, atb, rcond=None)[0]
            T = make_T(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:]) @ T
            # mean squared motion of the source points: at their centroid, plus the turn about it
            at_centre = np.cross(x[:3], transform_points(T, centre[None])[0]) + x[3:]
            moved_sq = float(at_centre @ at_centre) + float(x[:3] @ x[:3]) * spread
            mse = sse / count
            if moved_sq <= epsilon or abs(mse - prev_mse) < epsilon:
                break
            prev_mse = mse
    j, d = grid.nearest_within(transform_points(T, source), stages_m[-1])
    matched = np.flatnonzero(j >= 0)
    fitness = matched.size / max(source.shape[0], 1)
    rmse = float(np.sqrt(np.mean(d[matched] ** 2))) if matched.size else 0.0
    return IcpResult(T, fitness, rmse, np.column_stack([matched, j[matched]]).astype(np.int32))


def constrained_correction(T_correction: Array, matched_source: Array, matched_normals: Array,
                           min_constraint: float) -> tuple[Array, Array]:
    """Project a base-frame correction onto the well-constrained directions of point-to-plane ICP (module
    docstring). ``matched_source`` (K, 3) [m] are the matched source points after the correction and
    ``matched_normals`` (K, 3) the target normals they matched. Returns (the projected 4x4 correction,
    the 6 normalised eigenvalues in ascending order)."""
    c = matched_source.mean(axis=0)
    arm = matched_source - c
    L = max(float(np.sqrt(np.einsum("ij,ij->", arm, arm) / arm.shape[0])), 1e-9)
    J = np.column_stack([cross_rows(arm, matched_normals) / L, matched_normals])
    eigval, eigvec = np.linalg.eigh(np.einsum("ki,kj->ij", J, J) / J.shape[0])
    R, t = T_correction[:3, :3], T_correction[:3, 3]
    # The correction as a twist about c: p -> R (p - c) + (R c + t); rotation scaled to metres at L.
    xi = np.concatenate([rotvec(R) * L, R @ c + t - c])
    keep = eigvec[:, eigval >= min_constraint]
    xi = keep @ (keep.T @ xi)
    R_kept = Rotation.from_rotvec(xi[:3] / L).as_matrix()
    return make_T(R_kept, c + xi[3:] - R_kept @ c), eigval


def constrain_icp(icp: IcpResult, source: Array, pair_normals: Array,
                  min_constraint: float) -> tuple[Array, Array]:
    """``icp.T`` projected onto the directions its pairs constrain (``constrained_correction``):
    ``source`` (N, 3) [m] the source points ICP started from, ``pair_normals`` (K, 3) the degeneracy-test
    normals (``constraint_normals``) of the target points of ``icp.correspondences``. Returns (the
    correction, the 6 normalised eigenvalues); ``icp.T`` and NaN eigenvalues when there is nothing to
    test (fewer than 6 pairs) or nothing to drop (``min_constraint`` 0)."""
    pairs = icp.correspondences
    if pairs.shape[0] < 6 or min_constraint <= 0.0:
        return icp.T, np.full(6, np.nan)
    matched = transform_points(icp.T, source[pairs[:, 0]])
    return constrained_correction(icp.T, matched, pair_normals, min_constraint)


def kept_directions(eigval: Array, min_constraint: float) -> int:
    """How many of the 6 directions ``constrain_icp`` kept: those whose eigenvalue is at least
    ``min_constraint``; all 6 when nothing was tested (NaN eigenvalues)."""
    return int(np.count_nonzero(eigval >= min_constraint)) if np.all(np.isfinite(eigval)) else 6


def _skipped(T_fk: Array, reason: str) -> RegistrationResult:
    return RegistrationResult(T_base_sensor=T_fk.copy(), T_correction=np.eye(4), accepted=False,
                              fitness=0.0, rmse_m=0.0, correction_m=0.0, correction_deg=0.0, reason=reason)


class RegistrationTarget:
    """The accumulated target of registration: points [m, base frame] with their normals.

    ``update`` takes the re-formed target after each accumulation (the paper concatenates and
    voxel-filters; ``CloudAccumulator.points`` is that cloud). Normals are estimated at
    ``normal_radius_m`` only for the points that are new since the previous update (``new``); the others
    keep theirs. Choice written down here: an old point whose voxel centroid moved a little with the new
    frame, or whose neighbourhood grew, keeps its normal: a 2.5 mm averaging shift or a one-sided
    neighbourhood on a smooth surface turns a normal by far less than ICP's correspondences need, and
    re-estimating the whole target every frame cost ~60 ms of the ~100 ms cycle. The new points' normals
    are turned towards the sensor of the frame that brought them (``update``'s ``viewpoint_base``); an old
    point keeps that side, a surface being seen from its front only.

    ``register`` aligns a new frame onto the part of the target that ICP can reach from the FK pose: the
    box of the frame's points widened by the first stage's distance plus the largest accepted correction
    (translation, and rotation times the frame's reach from the sensor), so the search grid is built on
    about a frame's worth of points however large the scan grows, less the points facing away from the
    frame's sensor (module docstring).
    """

    def __init__(self, params: RegistrationParams) -> None:
        self.params = params
        self._points = np.zeros((0, 3))
        self._normals = np.zeros((0, 3))
        # per point: its normal was turned towards the sensor that saw it (see ``update``)
        self._oriented = np.zeros(0, dtype=bool)

    @property
    def n_points(self) -> int:
        return self._points.shape[0]

    @property
    def points(self) -> Array:
        return self._points

    @property
    def normals(self) -> Array:
        return self._normals

    def update(self, points_base: Array, normals_base: Array | None = None, *,
               new: NDArray[np.bool_] | None = None, viewpoint_base: Array | None = None) -> None:
        """Replace the target by ``points_base`` (M, 3) [m, base frame]. Normals: ``normals_base`` (M, 3)
        if given (their sign taken as it is, unoriented); else, with ``new`` (M,), estimated for the new
        points while the others, which must be the previous target's points in the same order, keep
        theirs; else estimated for all. ``viewpoint_base`` (3,) [m]: the origin of the sensor whose frame
        brought the new points; their normals are turned towards it, so that ``register`` can tell the
        side of a surface a sensor sees (class docstring); without it they stay unoriented."""
        pts = np.ascontiguousarray(points_base, dtype=np.float64).reshape(-1, 3)
        if normals_base is not None:
            if normals_base.shape != pts.shape:
                raise ValueError(f"normals {normals_base.shape} do not match points {pts.shape}")
            self._points, self._normals = pts, np.asarray(normals_base, dtype=np.float64)
            self._oriented = np.zeros(pts.shape[0], dtype=bool)
            return
        normals = np.empty_like(pts)
        oriented = np.zeros(pts.shape[0], dtype=bool)
        if new is None:
            new = np.ones(pts.shape[0], dtype=bool)
        else:
            new = np.asarray(new, dtype=bool)
            if new.shape != (pts.shape[0],) or np.count_nonzero(~new) != self.n_points:
                raise ValueError(f"new: {np.count_nonzero(~new)} old points given, the target has "
                                 f"{self.n_points}")
            normals[~new] = self._normals
            oriented[~new] = self._oriented
        if np.any(new):
            r = self.params.normal_radius_m
            fresh = pts[new]
            # neighbours of the new points lie in their box widened by the radius
            lo, hi = bounds(fresh)
            near = in_box(pts, lo - r, hi + r)
            fitted = estimate_normals(fresh, pts[near], r)
            if viewpoint_base is not None:
                towards = np.asarray(viewpoint_base, dtype=np.float64).reshape(3) - fresh
                fitted *= np.where(np.einsum("ij,ij->i", fitted, towards) < 0.0, -1.0, 1.0)[:, None]
                oriented[new] = True
            normals[new] = fitted
        self._points, self._normals, self._oriented = pts, normals, oriented

    def facing(self, viewpoint_base: Array) -> NDArray[np.bool_]:
        """(M,) the target points a sensor at ``viewpoint_base`` (3,) [m, base frame] may see: those whose
        oriented normal points to its side of their tangent plane, and those whose normal is unoriented."""
        towards = np.asarray(viewpoint_base, dtype=np.float64).reshape(3) - self._points
        return ~self._oriented | (np.einsum("ij,ij->i", self._normals, towards) > 0.0)

    def register(self, points_sensor: Array, T_base_sensor_fk: Array) -> RegistrationResult:
        """Register ``points_sensor`` (N, 3) [m, sensor frame] captured at FK pose ``T_base_sensor_fk``
        onto the target; see the module docstring for the schedule and the acceptance checks."""
        p = self.params
        T_fk = np.asarray(T_base_sensor_fk, dtype=np.float64)
        if not p.enabled:
            return _skipped(T_fk, "disabled")
        if self.n_points == 0:
            return _skipped(T_fk, "no target yet")
        src = np.asarray(points_sensor, dtype=np.float64)
        if p.source_voxel_m > 0.0 and src.shape[0]:
            src = voxel_downsample(src, p.source_voxel_m)
        if src.shape[0] < p.min_points or self.n_points < p.min_points:
            log.warning("registration skipped: too few points (source %d, target %d, need %d)",
                        src.shape[0], self.n_points, p.min_points)
            return _skipped(T_fk, "too few points")

        if src.shape[0] > p.max_source_points:
            # an even subset in voxel-key order: spread over the whole view, the same for the same frame
            src = src[np.linspace(0, src.shape[0] - 1, p.max_source_points).round().astype(np.int64)]
        src_base = transform_points(T_fk, src)
        reach = float(np.sqrt(np.max(np.einsum("ij,ij->i", src, src))))
        margin = p.max_correspondence_m[0] + p.max_correction_m + math.radians(p.max_correction_deg) * reach
        lo, hi = bounds(src_base)
        near = np.flatnonzero(in_box(self._points, lo - margin, hi + margin) & self.facing(T_fk[:3, 3]))
        if near.size < p.min_points:
            log.warning("registration skipped: %d target points near the frame, need %d", near.size,
                        p.min_points)
            return _skipped(T_fk, "too few points")
        target, normals = self._points[near], self._normals[near]
        icp = point_to_plane_icp(src_base, target, normals, p.max_correspondence_m,
                                 max_iterations=p.max_iterations, epsilon=p.epsilon,
                                 max_tangential_m=p.normal_radius_m)
        fitness, rmse = icp.fitness, icp.rmse_m
        wide = constraint_normals(target[icp.correspondences[:, 1]], target, p.constraint_normal_radius_m)
        T, eigval = constrain_icp(icp, src_base, wide, p.min_constraint)
        n_constrained = kept_directions(eigval, p.min_constraint)
        if n_constrained < 6:
            log.info("registration: %d of 6 directions constrained (eigenvalues %s, below %g dropped); "
                     "correction %.2f mm / %.3f deg before, %.2f mm / %.3f deg after", n_constrained,
                     np.array2string(eigval, precision=4), p.min_constraint,
                     np.linalg.norm((icp.T @ T_fk)[:3, 3] - T_fk[:3, 3]) * 1e3,
                     np.degrees(np.linalg.norm(rotvec(icp.T[:3, :3]))),
                     np.linalg.norm((T @ T_fk)[:3, 3] - T_fk[:3, 3]) * 1e3,
                     np.degrees(np.linalg.norm(rotvec(T[:3, :3]))))

        T_used = T @ T_fk
        corr_m = float(np.linalg.norm(T_used[:3, 3] - T_fk[:3, 3]))
        corr_deg = float(np.degrees(np.linalg.norm(rotvec(T[:3, :3]))))
        problems = []
        if fitness < p.min_fitness:
            problems.append(f"fitness {fitness:.3f} below {p.min_fitness}")
        if corr_m > p.max_correction_m:
            problems.append(f"correction {corr_m * 1e3:.1f} mm above {p.max_correction_m * 1e3:.1f} mm")
        if corr_deg > p.max_correction_deg:
            problems.append(f"correction {corr_deg:.2f} deg above {p.max_correction_deg} deg")
        if problems:
            reason = REJECTED + "; ".join(problems)
            log.warning("registration %s (fitness %.3f, rmse %.2f mm, correction %.1f mm / %.2f deg); "
                        "using the FK pose", reason, fitness, rmse * 1e3, corr_m * 1e3, corr_deg)
            return RegistrationResult(T_base_sensor=T_fk.copy(), T_correction=T, accepted=False,
                                      fitness=fitness, rmse_m=rmse, correction_m=corr_m,
                                      correction_deg=corr_deg, reason=reason, n_constrained=n_constrained,
                                      min_eigenvalue=float(eigval[0]))
        return RegistrationResult(T_base_sensor=T_used, T_correction=T, accepted=True, fitness=fitness,
                                  rmse_m=rmse, correction_m=corr_m, correction_deg=corr_deg, reason="ok",
                                  n_constrained=n_constrained, min_eigenvalue=float(eigval[0]))


def register_frame(points_sensor: Array, T_base_sensor_fk: Array, target_base: Array,
                   params: RegistrationParams, target_normals: Array | None = None) -> RegistrationResult:
    """Register one frame onto ``target_base`` (M, 3) [m, base frame] (paper section II-A).

    One-shot form of ``RegistrationTarget``: target normals are estimated here unless given. In a scan
    loop keep a ``RegistrationTarget`` and ``update`` it after each accumulation instead.
    """
    target = RegistrationTarget(params)
    if params.enabled:
        target.update(np.asarray(target_base, dtype=np.float64).reshape(-1, 3), target_normals)
    return target.register(points_sensor, T_base_sensor_fk)
