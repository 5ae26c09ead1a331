"""The ``Arm`` interface every arm backend implements (sim, ur5e, franka).

Frames and units: joint positions [rad], joint velocities [rad/s]; ``T_base_flange`` is the flange pose
in the robot base frame (4x4); twists are (vx, vy, vz, wx, wy, wz) [m/s, rad/s] of the flange origin,
expressed in the base frame (the convention of UR ``speedL`` and franky's Cartesian velocity motions).

Motion is gated: ``command_twist`` and ``execute_trajectory`` take the :class:`MotionToken` returned by
:meth:`Arm.claim_motion`, which the safety guard claims once when it takes the arm over. Anything else
that holds a reference to the arm (a planner, a script) cannot move it; it can only ``stop`` it, read its
state, or ``recover`` it as an explicit operator action. Backends implement the underscored methods.

Faults (protective stop, reflex, disconnect, ...) appear in ``ArmState.faults`` and ``mode`` FAULT; a
motion command while faulted raises ``RobotFault``. ``recover`` clears a fault the arm allows clearing.
"""

from __future__ import annotations

import enum
from abc import abstractmethod
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from drivers.device import Device
from drivers.errors import DriverError

Array = NDArray[np.float64]


class ArmMode(enum.Enum):
    """What the arm is doing."""

    IDLE = "idle"
    VELOCITY = "velocity"
    TRAJECTORY = "trajectory"
    STOPPING = "stopping"
    FAULT = "fault"


@dataclass(frozen=True)
class ArmState:
    """A snapshot of the arm.

    ``faults`` are short words a person understands (``"protective stop"``, ``"joint limit"``).
    """

    timestamp: float
    q: Array
    qd: Array
    T_base_flange: Array
    v_base_flange: Array
    mode: ArmMode
    faults: tuple[str, ...] = ()


@dataclass(frozen=True)
class JointTrajectory:
    """Joint positions sampled in time: ``t`` (K,) [s] from 0, strictly increasing; ``q`` (K, n) [rad]."""

    t: Array
    q: Array
    qd: Array | None = field(default=None)

    def __post_init__(self) -> None:
        if self.t.ndim != 1 or self.q.ndim != 2 or self.q.shape[0] != self.t.shape[0]:
            raise ValueError(f"trajectory shapes disagree: t {self.t.shape}, q {self.q.shape}")
        if self.t.shape[0] < 1 or np.any(np.diff(self.t) <= 0.0):
            raise ValueError("trajectory times must be non-empty and strictly increasing")
        if not (np.all(np.isfinite(self.t)) and np.all(np.isfinite(self.q))):
            raise ValueError("trajectory holds a non-finite value")

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])


class MotionToken:
    """Proof of being the one motion owner of an arm (see the module docstring). Opaque."""

    __slots__ = ()


class Arm(Device):
    """A robot arm. Use as a context manager, or call ``connect`` / ``disconnect``."""

    name: str = "arm"
    _motion_owner: MotionToken | None = None

    def claim_motion(self) -> MotionToken:
        """Become the arm's only motion owner; raises ``DriverError`` when it already has one."""
        if self._motion_owner is not None:
            raise DriverError("motion is already owned by a safety guard; only one may drive the arm",
                              device=f"arm {self.name}")
        self._motion_owner = MotionToken()
        return self._motion_owner

    def release_motion(self, token: MotionToken) -> None:
        """Give motion ownership back (the guard does this when its job ends)."""
        self._check_token(token)
        self._motion_owner = None

    def _check_token(self, token: object) -> None:
        if self._motion_owner is None or token is not self._motion_owner:
            raise DriverError("motion commands must come through the safety guard",
                              device=f"arm {self.name}")

    def command_twist(self, v_base_flange: Array, token: MotionToken) -> None:
        """Stream a flange twist in the base frame; it holds until the next command or ``stop``."""
        self._check_token(token)
        self._command_twist(v_base_flange)

    def execute_trajectory(self, trajectory: JointTrajectory, token: MotionToken) -> None:
        """Start following a joint trajectory; ``state().mode`` is TRAJECTORY until it ends."""
        self._check_token(token)
        self._execute_trajectory(trajectory)

    @property
    @abstractmethod
    def n_joints(self) -> int: ...

    @abstractmethod
    def state(self) -> ArmState:
        """Current state; raises ``DriverError`` when not connected."""

    @abstractmethod
    def _command_twist(self, v_base_flange: Array) -> None: ...

    @abstractmethod
    def _execute_trajectory(self, trajectory: JointTrajectory) -> None: ...

    @abstractmethod
    def stop(self) -> None:
        """Decelerate to rest within the arm's limits. Leaves the arm recoverable. Anyone may stop."""

    @abstractmethod
    def recover(self) -> None:
        """Operator action: clear a recoverable fault (e.g. unlock a protective stop) and return to IDLE.

        Raises ``RobotFault`` when the fault cannot be cleared from software (e.g. an emergency stop that
        is still pressed)."""
