"""The simulated arm: integrates commanded motion on the simulated clock through a robot model.

It is a real backend (the embedded default), not a test double. Every ``clock.sleep(dt)`` calls
:meth:`SimArm._step`, which advances the joints by ``dt`` seconds according to the current mode:

- VELOCITY (``command_twist``): the held flange twist (base frame) is turned into joint velocities by the
  nominal model's damped-least-squares ``ik_velocity`` (joint velocity and position limits), the change
  of joint velocity per step is limited to ``qdd_max * dt`` (scaled uniformly, so the joint-space
  direction is kept), and ``q += qd * dt``.
- TRAJECTORY (``execute_trajectory``): q is interpolated linearly between samples at the time elapsed
  since the call; qd is the finite difference over the step. At the end the arm holds the last sample and
  becomes IDLE.
- STOPPING (``stop``): qd is scaled down towards zero so that no joint decelerates faster than its
  ``qdd_max``; IDLE once at rest.
- FAULT (:meth:`SimArm.inject_fault`, for scenario tests, the ``sim.faults`` schedule and contact with the
  object or the table, :mod:`drivers.sim.contact`): the arm brakes like STOPPING and stays in FAULT,
  refusing motion with ``RobotFault``, until ``recover``. A ``"disconnect"`` fault makes ``state`` raise
  ``RobotFault`` too, as a vanished controller would.

Joint positions are always clamped to the model's limits (a clamped joint's velocity is set to zero).

Calibration error: given a ``true_model`` (a perturbed copy of the nominal model, drawn per job by
``drivers.sim.errors``), the joints "really" move that arm: :meth:`true_flange_pose` (what the simulated
sensors use) is its FK at the current q, while :meth:`state` reports the nominal FK, like a real arm whose
kinematic calibration is a little off.
"""

from __future__ import annotations

import numpy as np

from drivers.arm.base import Arm, ArmMode, ArmState, JointTrajectory
from drivers.arm.config import SimArmConfig
from drivers.clock import SimClock
from drivers.errors import DriverError, RobotFault
from drivers.robots.model import RobotModel

Array = np.ndarray

_DEVICE = "arm sim"
_TRAJ_START_TOL_RAD = 1e-3


class SimArm(Arm):
    """A simulated arm stepped by a :class:`SimClock` (see the module docstring for the motion model)."""

    name = "sim"

    def __init__(self, config: SimArmConfig, model: RobotModel, clock: SimClock,
                 true_model: RobotModel | None = None) -> None:
        if config.model != model.name:
            raise ValueError(f"arm sim: config names model {config.model!r} but the model given is "
                             f"{model.name!r}")
        self._config = config
        self._model = model
        self._clock = clock
        n = model.n_joints
        if config.home_joints_rad is not None:
            q0 = np.asarray(config.home_joints_rad, dtype=float)
            if q0.shape != (n,) or not np.all(np.isfinite(q0)):
                raise ValueError(f"arm sim: home_joints_rad must hold {n} finite values for {model.name}, "
                                 f"got {config.home_joints_rad}")
            outside = np.flatnonzero((q0 < model.q_min) | (q0 > model.q_max))
            if outside.size:
                j = int(outside[0])
                raise ValueError(
                    f"arm sim: home_joints_rad[{j}] = {q0[j]:.4f} rad is outside the {model.name} limits "
                    f"[{model.q_min[j]:.4f}, {model.q_max[j]:.4f}]")
        else:
            q0 = model.q_home.copy()
        self._q: Array = q0.astype(float).copy()
        self._qd: Array = np.zeros(n)
        self._mode = ArmMode.IDLE
        self._twist: Array = np.zeros(6)
        self._traj: JointTrajectory | None = None
        self._traj_t0 = 0.0
        self._connected = False
        self._fault: str | None = None
        self._fault_detail: str | None = None
        self._fault_recoverable = True
        self._true_model = true_model if true_model is not None else model
        clock.add_stepper(self._step)

    # ------------------------------------------------------------------ connection

    def connect(self) -> None:
        self._connected = True

    def disconnect(self) -> None:
        """Stop at once (simulated brakes) and close. Safe to call twice."""
        self._qd = np.zeros(self._model.n_joints)
        self._twist = np.zeros(6)
        self._traj = None
        self._mode = ArmMode.IDLE
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    @property
    def n_joints(self) -> int:
        return self._model.n_joints

    @property
    def model(self) -> RobotModel:
        """The nominal model the arm reports with."""
        return self._model

    def _require_connected(self, what: str) -> None:
        if not self._connected:
            raise DriverError(f"{what} while not connected (call connect() first)", device=_DEVICE)

    # ------------------------------------------------------------------ interface

    def _require_unfaulted(self, what: str) -> None:
        self._require_connected(what)
        if self._fault is not None:
            raise RobotFault(f"{what} refused: the arm is in {self._described_fault()}", device=_DEVICE,
                             fault=self._fault)

    def _described_fault(self) -> str:
        """The latched fault for people: its kind, and what caused it when known (``kind: detail``, as
        the Franka driver describes a reflex)."""
        assert self._fault is not None
        return self._fault if self._fault_detail is None else f"{self._fault}: {self._fault_detail}"

    def state(self) -> ArmState:
        self._require_connected("state()")
        if self._fault == "disconnect":
            raise RobotFault("no reply from the arm (disconnected)", device=_DEVICE, fault="disconnect")
        F = self._model.fk_all(self._q)
        J = self._model.jacobian_from_frames(F)
        return ArmState(
            timestamp=self._clock.now(),
            q=self._q.copy(),
            qd=self._qd.copy(),
            T_base_flange=F[-1].copy(),
            v_base_flange=J @ self._qd,
            mode=self._mode,
            faults=(self._described_fault(),) if self._fault is not None else (),
        )

    def true_flange_pose(self) -> Array:
        """Where the flange really is (4x4, base frame): the perturbed model's FK at the current q.

        Equal to ``state().T_base_flange`` without a ``true_model``. Works while
        disconnected (the arm is still somewhere).
        """
        return self._true_model.fk(self._q)

    def true_frames(self) -> Array:
        """Where all the arm's frames really are: the perturbed model's ``fk_all`` at the current q
        ((n + 2, 4, 4), base frame [m]). Works while disconnected."""
        return self._true_model.fk_all(self._q)

    @property
    def joints(self) -> Array:
        """The joint positions (n,) [rad] the arm is at (a copy); read while disconnected or faulted too,
        as the simulation's own view."""
        return self._q.copy()

    @property
    def fault(self) -> str | None:
        """The kind of the latched fault (``"protective stop"``, ...), or None."""
        return self._fault

    def _command_twist(self, v_base_flange: Array) -> None:
        self._require_unfaulted("command_twist()")
        v = np.asarray(v_base_flange, dtype=float)
        if v.shape != (6,):
            raise ValueError(f"arm sim: twist must have shape (6,), got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"arm sim: twist holds a non-finite value: {v}")
        self._twist = v.copy()
        self._traj = None
        self._mode = ArmMode.VELOCITY

    def _execute_trajectory(self, trajectory: JointTrajectory) -> None:
        self._require_unfaulted("execute_trajectory()")
        n = self._model.n_joints
        if trajectory.q.shape[1] != n:
            raise ValueError(f"arm sim: trajectory has {trajectory.q.shape[1]} joints, the arm has {n}")
        dev = float(np.max(np.abs(trajectory.q[0] - self._q)))
        if dev > _TRAJ_START_TOL_RAD:
            raise ValueError(f"arm sim: trajectory starts {dev:.5f} rad away from the current joints "
                             f"(tolerance {_TRAJ_START_TOL_RAD} rad)")
        m = self._model
        if np.any(trajectory.q < m.q_min - 1e-9) or np.any(trajectory.q > m.q_max + 1e-9):
            raise ValueError(f"arm sim: trajectory leaves the {m.name} joint limits")
        self._traj = trajectory
        self._traj_t0 = self._clock.now()
        self._twist = np.zeros(6)
        self._mode = ArmMode.TRAJECTORY

    def stop(self) -> None:
        self._require_connected("stop()")
        self._traj = None
        self._twist = np.zeros(6)
        if self._fault is None:
            self._mode = ArmMode.STOPPING if np.any(self._qd != 0.0) else ArmMode.IDLE

    def recover(self) -> None:
        self._require_connected("recover()")
        if self._fault is None:
            return
        if not self._fault_recoverable:
            raise RobotFault(f"{self._fault} cannot be cleared from software", device=_DEVICE,
                             fault=self._fault)
        if np.any(self._qd != 0.0):
            raise RobotFault(f"{self._fault}: wait until the arm is at rest before recovering",
                             device=_DEVICE, fault=self._fault)
        self._fault = self._fault_detail = None
        self._mode = ArmMode.IDLE

    def inject_fault(self, fault: str, *, recoverable: bool = True, detail: str | None = None) -> None:
        """Simulate a controller fault (``"protective stop"``, ``"reflex"``, ``"disconnect"``, ...): the
        arm brakes within its deceleration limits and refuses motion until ``recover``. ``detail`` says
        what caused it (``state().faults`` reads ``"fault: detail"``)."""
        self._fault = fault
        self._fault_detail = detail
        self._fault_recoverable = recoverable
        self._traj = None
        self._twist = np.zeros(6)
        self._mode = ArmMode.FAULT

    def release_fault(self) -> None:
        """The cause of a non-recoverable fault went away (an emergency stop button released)."""
        self._fault_recoverable = True

    # ------------------------------------------------------------------ simulation

    def _step(self, dt: float) -> None:
        """Advance the joints by ``dt`` seconds (called by the clock before time moves on)."""
        if dt <= 0.0:
            return
        m = self._model
        if self._mode is ArmMode.VELOCITY:
            qd_cmd = m.ik_velocity(self._q, self._twist, dt)
            dqd = qd_cmd - self._qd
            ratio = float(np.max(np.abs(dqd) / (m.qdd_max * dt)))
            qd = self._qd + (dqd / ratio if ratio > 1.0 else dqd)
            self._integrate(qd, dt)
        elif self._mode is ArmMode.TRAJECTORY and self._traj is not None:
            traj = self._traj
            t = traj.t[0] + (self._clock.now() + dt - self._traj_t0)
            if t >= traj.t[-1]:
                q_new = traj.q[-1].copy()
                self._qd = np.zeros(m.n_joints)
                self._q = np.clip(q_new, m.q_min, m.q_max)
                self._traj = None
                self._mode = ArmMode.IDLE
            else:
                q_new = np.array([np.interp(t, traj.t, traj.q[:, j]) for j in range(m.n_joints)])
                q_new = np.clip(q_new, m.q_min, m.q_max)
                self._qd = (q_new - self._q) / dt
                self._q = q_new
        elif self._mode in (ArmMode.STOPPING, ArmMode.FAULT):
            speed = np.abs(self._qd)
            # Joints slower than qdd_max * dt could stop within this step; only the others bound it (and
            # dividing by them alone keeps a vanishing speed from overflowing the ratio).
            too_fast = speed > m.qdd_max * dt
            if np.any(too_fast):
                # largest uniform scale-down allowed: no joint may lose more than qdd_max * dt of speed
                shrink = float(np.min(m.qdd_max[too_fast] * dt / speed[too_fast]))
                self._integrate(self._qd * (1.0 - shrink), dt)
            else:
                self._qd = np.zeros(m.n_joints)
            if self._mode is ArmMode.STOPPING and not np.any(self._qd != 0.0):
                self._mode = ArmMode.IDLE
        else:
            self._qd = np.zeros(m.n_joints)

    def _integrate(self, qd: Array, dt: float) -> None:
        m = self._model
        q_new = self._q + qd * dt
        clamped = (q_new < m.q_min) | (q_new > m.q_max)
        self._q = np.clip(q_new, m.q_min, m.q_max)
        self._qd = np.where(clamped, 0.0, qd)
