"""Hand-eye calibration against a known shape: the mount T_flange_sensor that puts every view's measured
points on the table plane and the box (``calibration.targets``), by nonlinear least squares.

Unknowns: the mount correction p = (x, y, z, rx, ry, rz): the mount is
``T_flange_sensor = [Rot(rx, ry, rz) R0, t0 + (x, y, z)]``, a translation [m] and a small rotation vector
[rad] both in the flange frame, applied to the starting mount (R0, t0); and the nuisances: the box's pose
on the table (x, y, yaw) and the table height, which the user need not know precisely.

Residual of a point: its signed distance to the union of the table half-space and the box
(``BoxTarget.signed_distance``) after mapping it with the arm's reported flange pose and the mount. Two
rounds: a robust one (soft-L1 loss, scale ``ROBUST_SCALE_M``) from the starting mount, then plain least
squares over the points within ``INLIER_SIGMAS`` robust standard deviations of the shape, whose Jacobian
gives the covariance: sigma^2 (J^T J)^-1, sigma^2 the residuals' variance, marginalized over the
nuisances (Schur complement). The per-axis standard deviations are its diagonal's square roots (the
rotation ones about the flange axes).

Observability: the marginal information of the mount, scaled so that ``LIMIT_M`` [m] and ``LIMIT_DEG``
[deg] weigh alike, is decomposed; a direction whose standard deviation would exceed the limit is an axis
the views cannot see, and the set is refused (``CalibrationError``) naming the mount axis that dominates
it. The same test runs before the arm moves, on points predicted from the planned views
(``calibration.predict``), and after the fit, on the measured ones.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.targets import BoxTarget
from drivers.errors import CalibrationError
from drivers.transforms import make_T, transform_points

Array = NDArray[np.float64]

AXES: tuple[str, ...] = ("x", "y", "z", "rotation about x", "rotation about y", "rotation about z")
"""The mount's axes, in the order of the parameters (flange frame)."""
N_MOUNT = 6
ROBUST_SCALE_M = 0.005
INLIER_SIGMAS = 3.0
LIMIT_M = 0.02
LIMIT_DEG = 5.0
MIN_VIEWS = 4
FD_STEP = 1e-6


@dataclass(frozen=True)
class View:
    """One capture: the flange pose the arm reported (4x4, base frame) and the measured points (N, 3)
    [m, sensor frame]."""

    T_base_flange: Array
    points_sensor: Array


@dataclass(frozen=True)
class ShapeFit:
    """The fitted mount T_flange_sensor (4x4), the RMS residual of the points kept [m], the per-axis
    standard deviations (translation [m] and rotation [rad], flange axes), the box pose (x, y, yaw) and
    table height [m] found with it, and how many views and points it used."""

    T_flange_sensor: Array
    residual_m: float
    std_m: Array
    std_rad: Array
    box_pose: Array
    table_z_m: float
    n_views: int
    n_points: int

    def record(self) -> dict[str, Any]:
        """The method's own figures for the result JSON: where the box and the table were found."""
        return {"box_pose_found": {"xy_m": np.round(self.box_pose[:2], 6).tolist(),
                                   "yaw_deg": round(float(np.degrees(self.box_pose[2])), 4)},
                "table_z_found_m": round(self.table_z_m, 6)}


def mount_from_params(T0: Array, p: Array) -> Array:
    """The mount ``T0`` corrected by p[:3] [m] and the rotation vector p[3:6] [rad], flange frame."""
    R = Rotation.from_rotvec(p[3:6]).as_matrix() @ T0[:3, :3]
    return make_T(R, T0[:3, 3] + p[:3])


@dataclass(frozen=True)
class ShapeProblem:
    """The points of all views stacked (N, 3) [m, sensor frame], each with its view's flange rotation
    (N, 3, 3) and translation (N, 3) [m], the starting mount and the target; ``residuals`` of the
    parameters (the mount correction, the box pose, the table height)."""

    points: Array
    R: Array
    t: Array
    T0: Array
    target: BoxTarget

    @classmethod
    def from_views(cls, views: Sequence[View], T0: Array, target: BoxTarget) -> ShapeProblem:
        counts = [v.points_sensor.shape[0] for v in views]
        return cls(points=np.concatenate([v.points_sensor for v in views]),
                   R=np.repeat(np.stack([v.T_base_flange[:3, :3] for v in views]), counts, axis=0),
                   t=np.repeat(np.stack([v.T_base_flange[:3, 3] for v in views]), counts, axis=0),
                   T0=T0, target=target)

    def residuals(self, x: Array) -> Array:
        M = mount_from_params(self.T0, x[:N_MOUNT])
        flange = transform_points(M, self.points)
        base = np.einsum("nij,nj->ni", self.R, flange) + self.t
        return self.target.signed_distance(base, x[N_MOUNT:N_MOUNT + 3], float(x[N_MOUNT + 3]))

    def subset(self, keep: NDArray[np.bool_]) -> ShapeProblem:
        return ShapeProblem(self.points[keep], self.R[keep], self.t[keep], self.T0, self.target)


def jacobian(fun: Callable[[Array], Array], x: Array) -> Array:
    """Central-difference Jacobian (N, P) of ``fun`` at ``x``."""
    cols = []
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = FD_STEP
        cols.append((fun(x + dx) - fun(x - dx)) / (2.0 * FD_STEP))
    return np.stack(cols, axis=1)


def mount_covariance(J: Array, sigma_m: float) -> Array:
    """The mount's (6, 6) covariance from the Jacobian (N, 6 + nuisances) of the residuals and their
    standard deviation [m], marginalized over the nuisance parameters (Schur complement; pseudo-inverses,
    so an unseen nuisance or an unobservable direction gives a huge variance rather than an error)."""
    info = J.T @ J
    A, B, C = info[:N_MOUNT, :N_MOUNT], info[:N_MOUNT, N_MOUNT:], info[N_MOUNT:, N_MOUNT:]
    marginal = A - B @ np.linalg.pinv(C, rcond=1e-12) @ B.T
    return np.asarray(sigma_m ** 2 * np.linalg.pinv(marginal, rcond=1e-14), dtype=np.float64)


def check_observable(J: Array, sigma_m: float) -> None:
    """Raise ``CalibrationError`` naming the mount axis the views cannot observe: the direction of the
    scaled marginal covariance whose standard deviation exceeds ``LIMIT_M`` / ``LIMIT_DEG``."""
    cov = mount_covariance(J, sigma_m)
    scale = np.array([LIMIT_M] * 3 + [np.deg2rad(LIMIT_DEG)] * 3)
    scaled = cov / np.outer(scale, scale)
    eigval, eigvec = np.linalg.eigh(scaled)
    if eigval[-1] <= 1.0:
        return
    direction = eigvec[:, -1]
    axis = AXES[int(np.argmax(np.abs(direction)))]
    std = float(np.sqrt(eigval[-1]))
    raise CalibrationError(
        f"the views cannot observe the mount's {axis} (standard deviation {std:.3g} times the limit of "
        f"{LIMIT_M * 1e3:g} mm / {LIMIT_DEG:g} deg along it): add views that look at the target from "
        "other directions and with other rotations of the flange")


def mount_std(fun: Callable[[Array], Array], x: Array, r: Array) -> Array:
    """The mount's per-axis standard deviations (6,) at ``x``, the least-squares solution of ``fun``
    whose residuals there are ``r``: sigma from ``r`` and its degrees of freedom, the covariance of
    :func:`mount_covariance`; raises ``CalibrationError`` first when an axis is unobservable
    (:func:`check_observable`)."""
    sigma = float(np.sqrt(np.sum(r ** 2) / max(r.size - x.size, 1)))
    J = jacobian(fun, x)
    check_observable(J, sigma)
    return np.sqrt(np.diag(mount_covariance(J, sigma)))


def robust_std(values: Array) -> float:
    """The standard deviation of ``values`` (K >= 1,) that their median absolute deviation gives."""
    return 1.4826 * float(np.median(np.abs(values - np.median(values))))


def _subsample(views: Sequence[View], max_points: int, rng: np.random.Generator) -> list[View]:
    out = []
    for v in views:
        pts = v.points_sensor
        if pts.shape[0] > max_points:
            pts = pts[np.sort(rng.choice(pts.shape[0], max_points, replace=False))]
        out.append(View(v.T_base_flange, pts))
    return out


def _near_target(views: Sequence[View], T0: Array, target: BoxTarget, box_pose: Array,
                 margin_m: float) -> list[View]:
    """Each view's points within ``margin_m`` [m] (horizontally) of the box's footprint at the start,
    so that whatever else the sensor sees far from the target stays out of the fit."""
    radius = 0.5 * float(np.linalg.norm(target.size_m[:2])) + margin_m
    out = []
    for v in views:
        base = transform_points(v.T_base_flange @ T0, v.points_sensor)
        near = np.linalg.norm(base[:, :2] - box_pose[:2], axis=1) <= radius
        out.append(View(v.T_base_flange, v.points_sensor[near]))
    return out


def fit_mount_to_shape(views: Sequence[View], T_mount0: Array, target: BoxTarget, box_pose0: Array,
                       table_z0: float, *, max_points_per_view: int = 1500, margin_m: float = 0.2,
                       seed: int = 0) -> ShapeFit:
    """Fit the mount (see the module docstring) from ``views``, starting at ``T_mount0`` with the box at
    ``box_pose0`` (x, y, yaw) [m, m, rad] and the table at ``table_z0`` [m]. Points further than
    ``margin_m`` from the box's footprint are left out; at most ``max_points_per_view`` are drawn from
    each view (seeded by ``seed``). Raises ``CalibrationError`` for too few views with points or an axis
    the views cannot observe."""
    views = _near_target(views, T_mount0, target, np.asarray(box_pose0, dtype=float), margin_m)
    views = [v for v in _subsample(views, max_points_per_view, np.random.default_rng(seed))
             if v.points_sensor.shape[0] >= 3]
    if len(views) < MIN_VIEWS:
        raise CalibrationError(f"only {len(views)} views saw the target; at least {MIN_VIEWS} are needed")
    problem = ShapeProblem.from_views(views, T_mount0, target)
    x0 = np.concatenate([np.zeros(N_MOUNT), np.asarray(box_pose0, dtype=float), [table_z0]])
    robust = least_squares(problem.residuals, x0, loss="soft_l1", f_scale=ROBUST_SCALE_M, x_scale="jac")
    r = problem.residuals(robust.x)
    keep = np.abs(r) <= max(INLIER_SIGMAS * robust_std(r), 1e-4)
    inliers = problem.subset(keep)
    final = least_squares(inliers.residuals, robust.x, x_scale="jac")
    r = inliers.residuals(final.x)
    std = mount_std(inliers.residuals, final.x, r)
    return ShapeFit(T_flange_sensor=mount_from_params(T_mount0, final.x[:N_MOUNT]),
                    residual_m=float(np.sqrt(np.mean(r ** 2))), std_m=std[:3], std_rad=std[3:],
                    box_pose=final.x[N_MOUNT:N_MOUNT + 3].copy(), table_z_m=float(final.x[N_MOUNT + 3]),
                    n_views=len(views), n_points=r.size)
