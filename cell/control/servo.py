"""The dual-task visual servo law of the visual-servoing paper (section II-B, eq. 1-3).

Camera frame: z along the optical axis, x right, y down; twists v = (vx, vy, vz, wx, wy, wz) [m/s, rad/s]
of the camera, expressed in the camera frame.

Primary task (eq. 2): the features s = P_c = (X, Y, Z) [m], the object centroid in the camera frame, are
driven to s* = (0, 0, Z*): the object stays on the optical axis at the distance Z*. For a static point,
s_dot = -v - w x P_c, which is eq. 3's interaction matrix L_s = [-I_3 | [P_c]_x].

Eq. 1: v = -lambda_e L_s^+ e + lambda_g (I_6 - L_s^+ L_s) g. L_s has full row rank 3 for every P_c
(its first block is -I_3), so L_s^+ = L_s^T (L_s L_s^T)^-1 and the projector onto its null space has rank
3: the secondary task g moves the camera only in ways that leave s unchanged to first order (translating
across the view while turning to keep the centroid fixed: motion on the sphere of radius Z*, or rolling
about the optical axis).

lambda_e is ViSP's adaptive gain (``vpAdaptiveGain``): lambda(x) = (l0 - linf) exp(-l0' x / (l0 - linf))
+ linf, high near convergence and lower far from it; x is the infinity norm of e [m], as ViSP's
``vpServo`` evaluates it. The secondary task is switched on once ||e|| (Euclidean) < ``e_converged_m``
(5 mm) and stays on (paper: "from this point onward, both tasks are executed simultaneously").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def interaction_matrix(s: Array) -> Array:
    """L_s (3, 6) of eq. 3 for the centroid s = (X, Y, Z) [m] in the camera frame."""
    X, Y, Z = np.asarray(s, dtype=np.float64).reshape(3)
    return np.array([[-1.0, 0.0, 0.0, 0.0, -Z, Y],
                     [0.0, -1.0, 0.0, Z, 0.0, -X],
                     [0.0, 0.0, -1.0, -Y, X, 0.0]])


def null_space_projector(s: Array) -> Array:
    """I_6 - L_s^+ L_s (6, 6) of eq. 1 for the centroid s (3,) [m] in the camera frame: the camera motions
    that leave s unchanged to first order."""
    L = interaction_matrix(s)
    return np.eye(6) - L.T @ np.linalg.solve(L @ L.T, L)


def adaptive_gain(x: float, lambda_0: float, lambda_inf: float, lambda_0_slope: float) -> float:
    """ViSP's adaptive gain [1/s] at x >= 0: lambda_0 at 0, slope -lambda_0_slope there, lambda_inf as
    x grows: (l0 - linf) exp(-l0' x / (l0 - linf)) + linf."""
    a = lambda_0 - lambda_inf
    return float(a * np.exp(-lambda_0_slope * x / a) + lambda_inf)


def exploration_speed_mps(lambda_g: float, standoff_m: float) -> float:
    """The camera's speed [m/s] for a unit g across the view (camera x or y) with the object at s*: the
    null-space projector of eq. 1 keeps Z*^2 / (1 + Z*^2) of it as translation (Z* in metres; the rest
    is the turn that keeps the object centred), times lambda_g."""
    z2 = float(standoff_m) ** 2
    return float(lambda_g) * z2 / (1.0 + z2)


@dataclass(frozen=True)
class ServoOutput:
    """One evaluation of eq. 1: the camera twist ``v`` (6,), the primary task error ``e`` (3,) [m] and
    whether the secondary task took part (``secondary``)."""

    v: Array
    e: Array
    secondary: bool


class DualTaskServo:
    """Eq. 1-3 with the start rule of the secondary task (see the module docstring).

    ``standoff_m`` is Z* [m]; the gains are those of the paper's ViSP set-up (``ServoConfig``)."""

    def __init__(self, *, standoff_m: float, lambda_0: float, lambda_inf: float, lambda_0_slope: float,
                 lambda_g: float, e_converged_m: float) -> None:
        if not lambda_0 > lambda_inf > 0.0:
            raise ValueError(f"need lambda_0 > lambda_inf > 0, got {lambda_0}, {lambda_inf}")
        self.s_star = np.array([0.0, 0.0, float(standoff_m)])
        self._gain = (lambda_0, lambda_inf, lambda_0_slope)
        self.lambda_g = float(lambda_g)
        self.e_converged_m = float(e_converged_m)
        self.secondary_active = False

    def error(self, s: Array) -> Array:
        """e = s - s* of eq. 2 [m]."""
        return np.asarray(s, dtype=np.float64).reshape(3) - self.s_star

    def primary_converged(self, e: Array) -> bool:
        """||e|| below the convergence threshold (5 mm)."""
        return float(np.linalg.norm(e)) < self.e_converged_m

    def step(self, s: Array, g: Array) -> ServoOutput:
        """Eq. 1 for the centroid ``s`` (3,) [m] in the camera frame and the secondary task's desired
        motion ``g`` (6,) (camera frame); g is ignored until the primary task has converged once."""
        e = self.error(s)
        if not self.secondary_active and self.primary_converged(e):
            self.secondary_active = True
        L = interaction_matrix(s)
        lam = adaptive_gain(float(np.max(np.abs(e))), *self._gain)
        v = -lam * (L.T @ np.linalg.solve(L @ L.T, e))
        if self.secondary_active:
            v = v + self.lambda_g * (null_space_projector(s) @ np.asarray(g, dtype=np.float64).reshape(6))
        return ServoOutput(v=v, e=e, secondary=self.secondary_active)
