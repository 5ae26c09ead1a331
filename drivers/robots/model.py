"""A generic serial-arm kinematic model from Denavit-Hartenberg parameters.

Frames and units
----------------
- Lengths [m], angles [rad], joint velocities [rad/s]; twists are (vx, vy, vz, wx, wy, wz) [m/s, rad/s]
  of the flange origin, expressed in the robot base frame (the convention of :mod:`drivers.arm.base`).
- ``T_base_flange`` is the pose of the flange (tool mounting) frame in the base frame, 4x4 homogeneous.

DH conventions
--------------
Both conventions are supported, chosen by ``convention``:

- ``"standard"`` (distal, Denavit-Hartenberg 1955, used by Universal Robots): the transform from frame
  i-1 to frame i is ``Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``; joint i turns about the z axis of
  frame i-1.
- ``"modified"`` (proximal, Craig 1986, used by Franka): the transform from frame i-1 to frame i is
  ``Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i)``; joint i turns about the z axis of frame i. Here the
  arrays ``a[i]`` and ``alpha[i]`` hold the values that *precede* joint i (index i of Franka's table).

In both, ``theta_i = q_i + theta_offset_i`` (the offsets are zero for the nominal UR5e and Panda and
model encoder zero errors in :meth:`RobotModel.perturbed`).

An optional fixed ``flange`` element (a, d, alpha, no joint) follows the last joint, written in the same
convention as the chain (Panda: d = 0.107 m from link 7 to the flange). Without it the last link frame is
the flange (UR5e).

Redundancy
----------
An arm with one joint more than the six of a twist (the Panda's seven) has a self-motion that leaves the
flange still. The differential IK (:meth:`RobotModel.velocity_map`, :meth:`RobotModel.ik_velocity`) uses
it for joint-limit avoidance (Liegeois 1977; Siciliano et al., *Robotics*, eq. 3.54):
``qd = N v + |N v| c`` with ``N`` the damped least-squares map and ``c = -k P grad H(q)``, the
descent direction of the joint-limit cost ``H(q) = 1/2 sum_i x_i^2``, ``x_i = (2 q_i - q_max_i - q_min_i) /
(q_max_i - q_min_i)`` (0 mid-range, +-1 at the limits), projected by ``P`` onto the exact null space of
the Jacobian, so the flange twist is the same as without it. ``k`` is the model's
``limit_avoidance_gain`` [rad]. The null-space speed is proportional to the task's joint speed
``|N v|`` [rad/s], so that the map stays positively homogeneous (a twist scaled by s >= 0 gives joint
velocities scaled by s: speed limits that scale a twist keep their meaning, and a zero twist means rest):
the arm straightens its redundancy as it moves, not while it holds.

``fk_all`` convention
---------------------
``fk_all(q)`` returns ``n_joints + 2`` frames: index 0 is the base (identity), index i in 1..n is link
frame i (the frame after joint i), and the last entry is the flange. When the model has no flange element
(UR5e) the last link frame is the flange and appears twice (indices n and n + 1), so the shape is the same
for every model.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from drivers.errors import KinematicsError
from drivers.transforms import pose_error

Array = NDArray[np.float64]
DHConvention = Literal["standard", "modified"]
# Damping of the differential IK [m]: small against link lengths, large enough near singularities.
DLS_DAMPING_M = 0.02
# Null-space joint-limit avoidance needs exactly one redundant joint: the columns of the 6 x 6 minors of a
# 6 x 7 Jacobian (row i drops column i) and the signs of the generalised cross product.
_MINOR_COLUMNS = np.array([[j for j in range(7) if j != i] for i in range(7)])
_ALTERNATING_SIGNS = np.array([(-1.0) ** i for i in range(7)])


@dataclass(frozen=True)
class JointVelocityMap:
    """The differential IK at one configuration, without position limits (module docstring,
    "Redundancy"): ``qd = task @ v + |task @ v| * null`` [rad/s] for a flange twist ``v`` (base frame,
    [m/s, rad/s]); ``task`` (n, 6) is the damped least-squares map, ``null`` (n,) the joint-limit avoidance
    direction in the Jacobian's null space per unit of task joint speed (zero without redundancy);
    ``jacobian`` (6, n) the geometric Jacobian both were made from."""

    task: Array
    null: Array
    jacobian: Array

    def __call__(self, v: Array) -> Array:
        """Joint velocities (n,) of a twist (6,), or (k, n) of twists (k, 6)."""
        qd = v @ self.task.T
        return qd + np.linalg.norm(qd, axis=-1, keepdims=True) * self.null

    def realized(self, v: Array) -> Array:
        """The flange twist (6,) the joint velocities ``self(v)`` make: ``v`` itself away from
        singularities, short of it (and turned) along a direction the arm is near-singular in."""
        return self.jacobian @ self(v)


@dataclass(frozen=True)
class Capsule:
    """A capsule (segment ``a``-``b`` swept by a sphere of ``radius``) in the robot base frame [m]."""

    name: str
    a: Array
    b: Array
    radius: float


@dataclass(frozen=True)
class CapsuleSpec:
    """A capsule attached to frame ``frame`` of ``fk_all`` (0 = base): end points in that frame [m]."""

    name: str
    frame: int
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    radius: float


def _as_vec(x: object, n: int, what: str) -> Array:
    """``x`` as a finite float vector of length ``n``; raises ``KinematicsError`` otherwise."""
    try:
        v = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise KinematicsError(f"{what}: cannot read as numbers ({exc})") from exc
    if v.shape != (n,):
        raise KinematicsError(f"{what}: expected shape ({n},), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise KinematicsError(f"{what}: holds a non-finite value: {v}")
    return v


def _dh_standard(theta: Array, d: Array, a: Array, alpha: Array) -> Array:
    """Stacked (k, 4, 4) standard-DH link transforms Rz(theta) Tz(d) Tx(a) Rx(alpha)."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(alpha), np.sin(alpha)
    T = np.zeros((theta.shape[0], 4, 4))
    T[:, 0, 0] = ct
    T[:, 0, 1] = -st * ca
    T[:, 0, 2] = st * sa
    T[:, 0, 3] = a * ct
    T[:, 1, 0] = st
    T[:, 1, 1] = ct * ca
    T[:, 1, 2] = -ct * sa
    T[:, 1, 3] = a * st
    T[:, 2, 1] = sa
    T[:, 2, 2] = ca
    T[:, 2, 3] = d
    T[:, 3, 3] = 1.0
    return T


def _dh_modified(theta: Array, d: Array, a: Array, alpha: Array) -> Array:
    """Stacked (k, 4, 4) modified-DH link transforms Rx(alpha) Tx(a) Rz(theta) Tz(d)."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(alpha), np.sin(alpha)
    T = np.zeros((theta.shape[0], 4, 4))
    T[:, 0, 0] = ct
    T[:, 0, 1] = -st
    T[:, 0, 3] = a
    T[:, 1, 0] = st * ca
    T[:, 1, 1] = ct * ca
    T[:, 1, 2] = -sa
    T[:, 1, 3] = -sa * d
    T[:, 2, 0] = st * sa
    T[:, 2, 1] = ct * sa
    T[:, 2, 2] = ca
    T[:, 2, 3] = ca * d
    T[:, 3, 3] = 1.0
    return T


@dataclass(frozen=True, eq=False)
class RobotModel:
    """Kinematics, limits and a capsule collision model of one serial arm.

    Arrays are per joint (length ``n_joints``): DH parameters ``a``, ``d``, ``alpha`` [m, m, rad] in the
    model's ``convention``, ``theta_offset`` [rad] (joint zero offsets), limits ``q_min``, ``q_max``
    [rad], ``qd_max`` [rad/s], ``qdd_max`` [rad/s^2], ``qddd_max`` [rad/s^3], and the ready pose
    ``q_home`` [rad]. ``flange`` is (a, d, alpha) of the fixed flange element or ``None``.
    Cartesian ceilings of the flange: ``tcp_max_linear_mps`` [m/s], ``tcp_max_angular_rps`` [rad/s],
    ``tcp_max_linear_acc`` [m/s^2], ``tcp_max_angular_acc`` [rad/s^2], ``tcp_max_linear_jerk`` [m/s^3],
    ``tcp_max_angular_jerk`` [rad/s^3]. ``limit_avoidance_gain`` [rad]: the gain k of the null-space
    joint-limit avoidance (module docstring, "Redundancy"); non-zero only for a 7-joint arm.

    The instance is immutable; :meth:`perturbed` returns a modified copy.
    """

    name: str
    convention: DHConvention
    a: Array
    d: Array
    alpha: Array
    q_min: Array
    q_max: Array
    qd_max: Array
    qdd_max: Array
    qddd_max: Array
    q_home: Array
    tcp_max_linear_mps: float
    tcp_max_angular_rps: float
    tcp_max_linear_acc: float
    tcp_max_angular_acc: float
    tcp_max_linear_jerk: float
    tcp_max_angular_jerk: float
    capsule_specs: tuple[CapsuleSpec, ...] = ()
    extra_adjacent_pairs: tuple[tuple[str, str], ...] = ()
    flange: tuple[float, float, float] | None = None
    theta_offset: Array | None = None
    limit_avoidance_gain: float = 0.0
    n_joints: int = field(init=False)
    adjacent_capsule_pairs: frozenset[frozenset[str]] = field(init=False)
    _fixed_links: Array = field(init=False, repr=False)
    _flange_link: Array = field(init=False, repr=False)

    def __post_init__(self) -> None:
        n = int(np.asarray(self.a).shape[0])
        set_ = object.__setattr__
        set_(self, "n_joints", n)
        if self.convention not in ("standard", "modified"):
            raise ValueError(f"{self.name}: unknown DH convention {self.convention!r} "
                             "(allowed: 'standard', 'modified')")
        for attr in ("a", "d", "alpha", "q_min", "q_max", "qd_max", "qdd_max", "qddd_max", "q_home"):
            v = np.array(getattr(self, attr), dtype=float)
            if v.shape != (n,) or not np.all(np.isfinite(v)):
                raise ValueError(f"{self.name}: {attr} must be {n} finite numbers, got {v}")
            v.setflags(write=False)
            set_(self, attr, v)
        off = np.zeros(n) if self.theta_offset is None else np.array(self.theta_offset, dtype=float)
        if off.shape != (n,):
            raise ValueError(f"{self.name}: theta_offset must have {n} entries")
        off.setflags(write=False)
        set_(self, "theta_offset", off)
        # The parts of the DH transforms no joint changes, computed once (fk_all, _links).
        dh = _dh_standard if self.convention == "standard" else _dh_modified
        set_(self, "_fixed_links", dh(np.zeros(n), self.d, self.a, self.alpha))
        fa, fd, falpha = self.flange if self.flange is not None else (0.0, 0.0, 0.0)
        set_(self, "_flange_link", dh(np.zeros(1), np.array([fd]), np.array([fa]), np.array([falpha]))[0])
        if np.any(self.q_min >= self.q_max):
            raise ValueError(f"{self.name}: q_min must be below q_max")
        if np.any(self.qd_max <= 0) or np.any(self.qdd_max <= 0) or np.any(self.qddd_max <= 0):
            raise ValueError(f"{self.name}: velocity, acceleration and jerk limits must be positive")
        if not (np.isfinite(self.limit_avoidance_gain) and self.limit_avoidance_gain >= 0.0):
            raise ValueError(f"{self.name}: limit_avoidance_gain must be >= 0, got "
                             f"{self.limit_avoidance_gain}")
        if self.limit_avoidance_gain > 0.0 and n != 7:
            raise ValueError(f"{self.name}: null-space joint-limit avoidance (limit_avoidance_gain) needs a "
                             f"7-joint arm (one redundant joint), this one has {n}")
        if np.any(self.q_home < self.q_min) or np.any(self.q_home > self.q_max):
            raise ValueError(f"{self.name}: q_home {self.q_home} is outside the joint limits")
        names = [c.name for c in self.capsule_specs]
        if len(set(names)) != len(names):
            raise ValueError(f"{self.name}: capsule names must be unique: {names}")
        for c in self.capsule_specs:
            if not 0 <= c.frame <= n + 1:
                raise ValueError(f"{self.name}: capsule {c.name} attached to unknown frame {c.frame}")
        # Adjacent pairs: capsules on the same or on consecutive frames touch by construction (they
        # share a joint), plus the model's extra pairs; self-collision checks skip them.
        pairs: set[frozenset[str]] = set()
        for i, ci in enumerate(self.capsule_specs):
            for cj in self.capsule_specs[i + 1:]:
                if abs(ci.frame - cj.frame) <= 1:
                    pairs.add(frozenset((ci.name, cj.name)))
        for p, r in self.extra_adjacent_pairs:
            if p not in names or r not in names:
                raise ValueError(f"{self.name}: extra adjacent pair ({p}, {r}) names an unknown capsule")
            pairs.add(frozenset((p, r)))
        set_(self, "adjacent_capsule_pairs", frozenset(pairs))

    # ------------------------------------------------------------------ kinematics

    def _links(self, theta: Array) -> Array:
        """The link transforms (n, 4, 4) at joint angles ``theta`` (n,) [rad] (offsets included): the
        joint's turn about z times the link's fixed part (standard DH, Rz(theta) Tz(d) Tx(a) Rx(alpha)), or
        the fixed part times the turn (modified DH, Rx(alpha) Tx(a) Tz(d) Rz(theta), as Rz and Tz commute).
        Only the two rows or columns the turn mixes are computed."""
        ct, st = np.cos(theta)[:, None], np.sin(theta)[:, None]
        fixed = self._fixed_links
        A = fixed.copy()
        if self.convention == "standard":
            A[:, 0, :] = ct * fixed[:, 0, :] - st * fixed[:, 1, :]
            A[:, 1, :] = st * fixed[:, 0, :] + ct * fixed[:, 1, :]
        else:
            A[:, :, 0] = ct * fixed[:, :, 0] + st * fixed[:, :, 1]
            A[:, :, 1] = ct * fixed[:, :, 1] - st * fixed[:, :, 0]
        return A

    def check_q(self, q: object, what: str = "q") -> Array:
        """``q`` as a float array of length ``n_joints``; raises ``KinematicsError`` when it is not."""
        return _as_vec(q, self.n_joints, f"{self.name} {what}")

    def fk_all(self, q: object) -> Array:
        """All frames in the base frame, shape (n_joints + 2, 4, 4): base, link 1..n, flange.

        See the module docstring for the convention when the model has no separate flange element.
        """
        qv = self.check_q(q)
        assert self.theta_offset is not None
        A = self._links(qv + self.theta_offset)
        n = self.n_joints
        out = np.empty((n + 2, 4, 4))
        out[0] = np.eye(4)
        for i in range(n):
            np.matmul(out[i], A[i], out=out[i + 1])
        np.matmul(out[n], self._flange_link, out=out[n + 1])
        return out

    def fk(self, q: object) -> Array:
        """T_base_flange (4, 4) at joint positions ``q`` [rad]."""
        return self.fk_all(q)[-1]

    def home(self, configured: list[float] | None) -> Array:
        """The home joints [rad]: a cell's ``arm.home_joints_rad`` when it sets them, else ``q_home``."""
        return np.asarray(configured, dtype=float) if configured is not None else self.q_home

    @property
    def axis_frames(self) -> NDArray[np.intp]:
        """For each joint i (0-based), the ``fk_all`` frame whose z axis it turns about, through that frame's
        origin: frame i (standard DH) or i + 1 (modified DH). The joint moves the frames after i."""
        return np.arange(self.n_joints) + (0 if self.convention == "standard" else 1)

    def jacobian_from_frames(self, F: Array) -> Array:
        """The geometric Jacobian (see :meth:`jacobian`) from frames ``F`` already computed by ``fk_all``."""
        n = self.n_joints
        # Joint i (0-based) turns about z of frame i (standard) or frame i + 1 (modified) of fk_all.
        axes_frames = F[0:n] if self.convention == "standard" else F[1:n + 1]
        z = axes_frames[:, :3, 2]
        o = axes_frames[:, :3, 3]
        p = F[-1, :3, 3]
        r = p - o
        J = np.empty((6, n))
        # z x r written out: np.cross costs more than the rest of the Jacobian for a handful of rows.
        J[0] = z[:, 1] * r[:, 2] - z[:, 2] * r[:, 1]
        J[1] = z[:, 2] * r[:, 0] - z[:, 0] * r[:, 2]
        J[2] = z[:, 0] * r[:, 1] - z[:, 1] * r[:, 0]
        J[3:] = z.T
        return J

    def jacobian(self, q: object) -> Array:
        """Geometric Jacobian (6, n) of the flange origin in the base frame, rows (vx, vy, vz, wx, wy, wz)."""
        return self.jacobian_from_frames(self.fk_all(q))

    def min_singular_value(self, q: object) -> float:
        """The smallest singular value of :meth:`jacobian` at ``q`` (translational rows in m/rad,
        rotational in rad/rad): zero at a singularity. The damped least-squares IK realizes a twist along
        the corresponding direction at s^2 / (s^2 + damping^2) of its size (0.9 at s = 3 ``DLS_DAMPING_M``,
        0.5 at s = ``DLS_DAMPING_M``)."""
        return float(np.linalg.svd(self.jacobian(q), compute_uv=False)[-1])

    def min_singular_value_gradient(self, q: object, step_rad: float = 1e-6) -> Array:
        """d :meth:`min_singular_value` / dq (n,) by central differences of ``step_rad`` [rad] (where the
        two smallest singular values cross, the derivative of the smaller one)."""
        qv = self.check_q(q)
        grad = np.empty(self.n_joints)
        for i in range(self.n_joints):
            dq = np.zeros(self.n_joints)
            dq[i] = step_rad
            grad[i] = (self.min_singular_value(qv + dq) - self.min_singular_value(qv - dq)) / (2.0 * step_rad)
        return grad

    def velocity_map(self, q: object, damping: float = DLS_DAMPING_M) -> JointVelocityMap:
        """The differential IK at ``q`` without the position limits :meth:`ik_velocity` applies (e.g. to
        predict motion): the damped least-squares map ``J^T (J J^T + damping^2 I)^-1`` (n, 6) and the
        null-space joint-limit avoidance (module docstring, "Redundancy")."""
        qv = self.check_q(q)
        return self._velocity_map_J(qv, self.jacobian(qv), damping)

    def _velocity_map_J(self, q: Array, J: Array, damping: float) -> JointVelocityMap:
        task = J.T @ np.linalg.inv(J @ J.T + damping * damping * np.eye(6))
        if self.limit_avoidance_gain == 0.0:
            return JointVelocityMap(task, np.zeros(self.n_joints), J)
        # The null space of a full-rank 6 x 7 Jacobian is spanned by its generalised cross product,
        # n_i = (-1)^i det(J without column i) (zero at a singularity, where the avoidance pauses).
        n = _ALTERNATING_SIGNS * np.linalg.det(J[:, _MINOR_COLUMNS].transpose(1, 0, 2))
        nn = float(n @ n)
        if nn < 1e-24:
            return JointVelocityMap(task, np.zeros(self.n_joints), J)
        span = self.q_max - self.q_min
        grad_h = 2.0 * (2.0 * q - self.q_max - self.q_min) / (span * span)  # dH/dq [1/rad]
        return JointVelocityMap(task, -self.limit_avoidance_gain * float(n @ grad_h) / nn * n, J)

    def ik_velocity(self, q: object, v_base_flange: object, dt: float,
                    damping: float = DLS_DAMPING_M) -> Array:
        """Joint velocities [rad/s] that best produce the flange twist ``v_base_flange`` [m/s, rad/s].

        Damped least squares ``qd = J^T (J J^T + damping^2 I)^-1 v`` (``damping`` in the units of J,
        i.e. metres for the linear rows) with the null-space joint-limit avoidance of
        :meth:`velocity_map` (module docstring, "Redundancy"). Limits:

        - position: a joint whose ``q + qd * dt`` [dt in s] would leave ``[q_min, q_max]`` is fixed at the
          velocity that brings it exactly to the limit, its contribution is removed from the twist and the
          other joints are re-solved without the null-space term (repeated until no joint leaves, at most
          ``n_joints`` rounds);
        - velocity: the whole ``qd`` is then scaled down uniformly so that ``|qd_i| <= qd_max_i``, which
          keeps the direction of motion and, because ``q`` lies inside the limits, the position limits.
        """
        qv = self.check_q(q)
        v = _as_vec(v_base_flange, 6, f"{self.name} twist")
        if not (np.isfinite(dt) and dt > 0.0):
            raise KinematicsError(f"{self.name} ik_velocity: dt must be positive, got {dt}")
        J = self.jacobian(qv)
        return self._ik_velocity_J(qv, J, v, dt, damping, self._velocity_map_J(qv, J, damping))

    def _ik_velocity_J(self, q: Array, J: Array, v: Array, dt: float, damping: float,
                       unlimited: JointVelocityMap | None = None,
                       bounds: tuple[Array, Array] | None = None) -> Array:
        """The limited IK step; ``unlimited`` (the map at ``q``, null-space term included) gives the
        first round, before any joint is fixed at its limit; ``bounds`` (lower, upper) [rad] stand for the
        joint limits when given."""
        n = self.n_joints
        lam2 = damping * damping
        q_lo, q_hi = bounds if bounds is not None else (self.q_min, self.q_max)
        hi = np.maximum((q_hi - q) / dt, 0.0)  # largest allowed qd per joint over dt
        lo = np.minimum((q_lo - q) / dt, 0.0)
        free = np.ones(n, dtype=bool)
        qd = np.zeros(n)
        for _ in range(n + 1):
            if unlimited is not None and free.all():
                qd = unlimited(v)
            else:
                Jf = J[:, free]
                v_rest = v - J[:, ~free] @ qd[~free]
                qd[free] = Jf.T @ np.linalg.solve(Jf @ Jf.T + lam2 * np.eye(6), v_rest)
            over = free & ((qd > hi) | (qd < lo))
            if not np.any(over):
                break
            qd[over] = np.clip(qd[over], lo[over], hi[over])
            free &= ~over
            if not np.any(free):
                break
        ratio = float(np.max(np.abs(qd) / self.qd_max))
        if ratio > 1.0:
            qd = qd / ratio
        return qd

    def ik_pose(self, T_base_flange_goal: Array, q_seed: object, *, tol_m: float = 1e-4,
                tol_rad: float = 1e-3, max_iter: int = 200,
                q_bounds: tuple[Array, Array] | None = None) -> Array:
        """Joint positions [rad] reaching ``T_base_flange_goal``, iterating DLS steps from ``q_seed``.

        Each iteration takes the pose error (position [m], axis-angle [rad], base frame), caps it at
        0.1 m / 0.5 rad so that one step stays in the region where the linearisation holds, and applies
        the :meth:`ik_velocity` step with ``dt = 1`` (so the position limits hold at every iterate; its
        null-space term steers a redundant arm towards a solution away from its joint limits).

        ``q_bounds`` (lower, upper) [rad], inside the joint limits: where a safety layer keeps the joints
        (its limits less its margin). A solution within the limits that ends outside them, in the margin
        the layer refuses, is solved again from the seed with every iterate kept within them, and that
        solution is returned when it converges (on a Panda's LR-NBV scan of the camera cell, 21 of 168
        solutions lay in a 0.05 rad margin); else the first, for the caller to refuse. Iterating within
        the bounds from the start misses solutions that the limits' wider room lets the iteration reach
        (on the camera cell's packing grid, a tenth more views came out unreachable).
        Raises ``KinematicsError`` with the remaining residual when ``tol_m`` and ``tol_rad`` are not met
        within ``max_iter`` iterations.
        """
        T_goal = np.asarray(T_base_flange_goal, dtype=float)
        if T_goal.shape != (4, 4) or not np.all(np.isfinite(T_goal)):
            raise KinematicsError(f"{self.name} ik_pose: goal must be a finite 4x4 transform")
        seed = self.check_q(q_seed, "q_seed")
        q = self._ik_iterate(T_goal, seed, tol_m, tol_rad, max_iter, (self.q_min, self.q_max))
        if q_bounds is None or np.all((q >= q_bounds[0]) & (q <= q_bounds[1])):
            return q
        try:
            return self._ik_iterate(T_goal, seed, tol_m, tol_rad, max_iter, q_bounds)
        except KinematicsError:
            return q

    def _ik_iterate(self, T_goal: Array, q_seed: Array, tol_m: float, tol_rad: float, max_iter: int,
                    bounds: tuple[Array, Array]) -> Array:
        """:meth:`ik_pose`'s iteration from ``q_seed`` with every iterate within ``bounds`` (lower, upper)
        [rad]."""
        q_lo, q_hi = bounds
        q = np.clip(q_seed, q_lo, q_hi)
        e = np.zeros(6)
        for _ in range(max_iter):
            F = self.fk_all(q)
            e = pose_error(F[-1], T_goal)
            ep, er = float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:]))
            if ep <= tol_m and er <= tol_rad:
                return q
            step = e.copy()
            if ep > 0.1:
                step[:3] *= 0.1 / ep
            if er > 0.5:
                step[3:] *= 0.5 / er
            J = self.jacobian_from_frames(F)
            dq = self._ik_velocity_J(q, J, step, 1.0, 0.02, self._velocity_map_J(q, J, 0.02), bounds)
            q = np.clip(q + dq, q_lo, q_hi)
        e = pose_error(self.fk(q), T_goal)
        raise KinematicsError(
            f"{self.name} ik_pose did not converge in {max_iter} iterations: residual "
            f"{np.linalg.norm(e[:3]) * 1000:.3f} mm, {np.linalg.norm(e[3:]):.5f} rad "
            f"(tolerance {tol_m * 1000:.3f} mm, {tol_rad:.5f} rad)")

    def within_limits(self, q: object) -> bool:
        """True when every joint of ``q`` lies inside ``[q_min, q_max]``."""
        qv = self.check_q(q)
        return bool(np.all(qv >= self.q_min) and np.all(qv <= self.q_max))

    # ------------------------------------------------------------------ collision geometry

    def capsules(self, q: object) -> list[Capsule]:
        """The capsule collision model at ``q``, in the base frame (see the robot module for figures)."""
        F = self.fk_all(q)
        out = []
        for c in self.capsule_specs:
            T = F[c.frame]
            a = T[:3, :3] @ np.asarray(c.a) + T[:3, 3]
            b = T[:3, :3] @ np.asarray(c.b) + T[:3, 3]
            out.append(Capsule(c.name, a, b, float(c.radius)))
        return out

    def are_adjacent(self, name_a: str, name_b: str) -> bool:
        """True when the two capsules touch by construction and self-collision checks skip the pair."""
        return frozenset((name_a, name_b)) in self.adjacent_capsule_pairs

    # ------------------------------------------------------------------ calibration error

    def perturbed(self, rng: np.random.Generator, joint_offset_std_rad: float,
                  link_std_m: float) -> RobotModel:
        """A copy with random joint zero offsets and DH length errors (simulated calibration error).

        Draws, in this order, ``n_joints`` offsets N(0, joint_offset_std_rad) [rad] added to
        ``theta_offset`` (skipped when that std is 0), then ``n_joints`` errors N(0, link_std_m) [m] on
        ``a``, ``n_joints`` on ``d`` and two for the flange element's ``a`` and ``d`` (always drawn, used
        only when there is a flange element; all skipped when ``link_std_m`` is 0). With both standard
        deviations zero the copy has exactly the same kinematics and ``rng`` is not consumed. Limits and
        capsules are unchanged (the capsules follow the perturbed frames).
        """
        if joint_offset_std_rad < 0.0 or link_std_m < 0.0:
            raise ValueError("perturbed: standard deviations must be >= 0")
        n = self.n_joints
        d_off = rng.normal(0.0, joint_offset_std_rad, n) if joint_offset_std_rad > 0 else np.zeros(n)
        if link_std_m > 0:
            da = rng.normal(0.0, link_std_m, n)
            dd = rng.normal(0.0, link_std_m, n)
            df = rng.normal(0.0, link_std_m, 2)
        else:
            da, dd, df = np.zeros(n), np.zeros(n), np.zeros(2)
        flange = self.flange
        if flange is not None:
            flange = (flange[0] + float(df[0]), flange[1] + float(df[1]), flange[2])
        assert self.theta_offset is not None
        return dataclasses.replace(
            self, a=self.a + da, d=self.d + dd, theta_offset=self.theta_offset + d_off, flange=flange)
