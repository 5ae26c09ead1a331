"""Virtual barrier planes (visual-servoing paper section III-A, Fig. 3) and the projection of a desired
velocity into the set they allow.

A plane is a point and a unit normal in the robot base frame; the normal points into the allowed side, and
a point's signed distance ``d = n . (p - p0)`` is positive there. Guarded points (the TCP and the sensor
origin) must keep ``d >= margin``.

The feasible set of a velocity is a polyhedral cone shifted by the allowed approach speeds: for each plane
``i`` and guarded point ``k`` moving at ``v_k``, ``n_i . v_k >= -s(d_ik - margin)``, where ``s`` is the
fastest approach from which the motion can still come to rest before the plane (see :func:`approach_speed`).
The projection is the closest feasible velocity in a weighted Euclidean norm: the component that would
push through an active plane is removed and the motion slides along it, with several planes at once (an
exact active-set solution of the small quadratic program).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

_FEAS_TOL = 1e-12


@dataclass(frozen=True)
class BarrierPlane:
    """A plane through ``point`` [m] with unit ``normal`` into the allowed side, base frame."""

    name: str
    point: Array
    normal: Array

    @staticmethod
    def make(name: str, point: Sequence[float], normal: Sequence[float]) -> BarrierPlane:
        n = np.asarray(normal, dtype=float)
        return BarrierPlane(name, np.asarray(point, dtype=float), n / np.linalg.norm(n))

    def distance(self, p: Array) -> Array:
        """Signed distance [m] of points ``p`` (..., 3) to the plane, positive on the allowed side."""
        return (np.asarray(p) - self.point) @ self.normal


def workspace_planes(min_m: Sequence[float], max_m: Sequence[float]) -> list[BarrierPlane]:
    """The six faces of an axis-aligned workspace box as inward-facing barrier planes."""
    planes = []
    for axis, name in enumerate("xyz"):
        e = np.eye(3)[axis]
        planes.append(BarrierPlane(f"workspace {name} min", e * min_m[axis], e.copy()))
        planes.append(BarrierPlane(f"workspace {name} max", e * max_m[axis], -e))
    return planes


def approach_speed(distance_m: Array, *, acc: float | Array, jerk: float | Array, latency_s: float,
                   time_constant_s: float) -> Array:
    """Fastest allowed approach speed [m/s] towards a plane ``distance_m`` away (0 at or beyond it);
    ``acc`` / ``jerk`` are scalars or per-element arrays that broadcast against ``distance_m``.

    Two bounds, the smaller wins: an exponential approach ``d / time_constant_s`` (a barrier function that
    never reaches the plane in continuous time), and the stopping bound: a motion that keeps its speed
    ``v`` for ``latency_s + acc / jerk`` (a control period, then the jerk-limited ramp to full braking)
    and then brakes at ``acc`` covers ``v (latency + acc/jerk) + v^2 / (2 acc)``, which must not exceed
    ``d``. Solving for ``v`` gives ``acc (-t + sqrt(t^2 + 2 d / acc))`` with ``t = latency + acc/jerk``.
    """
    d = np.maximum(np.asarray(distance_m, dtype=float), 0.0)
    t = latency_s + acc / jerk
    stopping = acc * (-t + np.sqrt(t * t + 2.0 * d / acc))
    return np.minimum(d / time_constant_s, stopping)


def project_onto_halfspaces(x_desired: Array, A: Array, b: Array, weights: Array) -> tuple[Array, Array]:
    """Closest ``x`` to ``x_desired`` with ``A x >= b``, in the norm ``sum(weights * dx^2)``.

    Exact active-set method for the handful of constraints a tick produces: add the most violated
    constraint, solve the equality-constrained projection onto the active ones, drop any whose multiplier
    turns negative, repeat. Returns ``x`` and the indices of the active constraints. When the constraints
    have no common solution (cannot happen for planes a point is inside of), the least-squares compromise
    of the active set is returned.
    """
    x_d = np.asarray(x_desired, dtype=float)
    m = A.shape[0]
    if m == 0:
        return x_d.copy(), np.zeros(0, dtype=int)
    w_inv = 1.0 / weights
    active: list[int] = []
    x = x_d.copy()
    for _ in range(4 * m + 4):
        slack = A @ x - b
        slack[active] = 0.0
        worst = int(np.argmin(slack))
        if slack[worst] >= -_FEAS_TOL:
            break
        active.append(worst)
        while True:
            As = A[active]
            M = (As * w_inv) @ As.T
            lam = np.linalg.lstsq(M, b[active] - As @ x_d, rcond=None)[0]
            if np.all(lam >= -_FEAS_TOL) or len(active) == 1:
                break
            active.pop(int(np.argmin(lam)))
        x = x_d + w_inv * (As.T @ np.maximum(lam, 0.0))
    return x, np.asarray(active, dtype=int)


class Barriers:
    """A set of barrier planes with the margin and braking figures the projection uses.

    ``margin_m``: guarded points keep this distance from every plane. ``acc``, ``jerk``: the linear braking
    acceleration [m/s^2] and jerk [m/s^3] of the motion (the cell's TCP limits); ``latency_s``: one control
    period; ``time_constant_s``: the exponential approach rate (the guard's lookahead).
    """

    def __init__(self, planes: Sequence[BarrierPlane], *, margin_m: float, acc: float, jerk: float,
                 latency_s: float, time_constant_s: float) -> None:
        self.planes = tuple(planes)
        self.margin_m = margin_m
        self._acc = acc
        self._jerk = jerk
        self._latency = latency_s
        self._tau = time_constant_s
        self._P = np.array([p.point for p in self.planes]).reshape(-1, 3)
        self._N = np.array([p.normal for p in self.planes]).reshape(-1, 3)

    def clearances(self, points: Array) -> Array:
        """Distance [m] beyond the margin of each point (k, 3) to each plane: (k, planes)."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        return np.einsum("kpj,pj->kp", p[:, None, :] - self._P[None], self._N) - self.margin_m

    def first_violation(self, points: Array, names: Sequence[str], floor: Array | float = 0.0) -> str | None:
        """A sentence naming the first guarded point inside a plane's margin, or None. ``floor``: the
        clearance [m] (scalar, or per point and plane as ``clearances`` gives) a point may go down to; 0
        keeps every point out of the margin."""
        c = self.clearances(points)
        bad = np.argwhere(c < floor)
        if bad.size == 0:
            return None
        k, i = bad[0]
        return (f"the {names[k]} would be {-c[k, i] * 1e3:.1f} mm past barrier '{self.planes[i].name}' "
                f"(margin {self.margin_m * 1e3:.1f} mm)")

    def allowed_approach(self, points: Array) -> Array:
        """Fastest approach speed [m/s] of each point (k, 3) towards each plane: (k, planes)."""
        return approach_speed(self.clearances(points), acc=self._acc, jerk=self._jerk,
                              latency_s=self._latency, time_constant_s=self._tau)

    def project_twist(self, twist: Array, origin: Array, points: Array,
                      max_point_speed: float) -> tuple[Array, list[str]]:
        """Project a twist (v, w) of a body at ``origin`` (base frame) into the feasible set of its guarded
        ``points`` (k, 3), changing only its linear part: the rotation a planner asks for is kept, and the
        body slides along the planes. A point at ``r`` from the origin moves at ``v + w x r``, so each
        constraint reads ``n . v >= -s - n . (w x r)``. Constraints whose allowed approach exceeds
        ``max_point_speed`` cannot bind and are left out. Returns the twist and the names of the planes
        that bound it.
        """
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        s = self.allowed_approach(pts)
        ks, iis = np.nonzero(s < max_point_speed)
        out = np.asarray(twist, dtype=float).copy()
        if ks.size == 0:
            return out, []
        n = self._N[iis]
        swirl = np.einsum("kj,kj->k", n, np.cross(out[3:], pts[ks] - origin))
        out[:3], active = project_onto_halfspaces(out[:3], n, -s[ks, iis] - swirl, np.ones(3))
        return out, sorted({self.planes[iis[j]].name for j in active})

    def project_velocity(self, point: Array, velocity: Array, activation_m: float) -> Array:
        """Project a desired velocity (3,) of ``point`` (base frame) so that it does not push through any
        plane within ``activation_m`` beyond the margin: the normal component into such a plane is removed
        and the motion slides along it (the planners' exploration direction, paper Fig. 3)."""
        c = self.clearances(point)[0]
        near = np.nonzero(c < activation_m)[0]
        x, _ = project_onto_halfspaces(np.asarray(velocity, dtype=float), self._N[near],
                                       np.zeros(near.size), np.ones(3))
        return x
