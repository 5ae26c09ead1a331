"""What the service knows of its arm, for ``GET /cell``, without ever talking to it from the web side.

A job's worker owns the arm while the job runs; the service learns its pose from the job's progress and
its faults from how the job ended. Between jobs a simulated arm is always there (at home, or where the
last job left it); a hardware arm is connected by each job and by recovery only, so it reads as not
connected, with the last pose and faults known.

A fault the arm reported (protective stop, emergency stop, reflex, disconnect) is latched: no queued job
starts until an operator recovers the arm (``POST /arm/recover``), as on the command line, where
recovery is never automatic. The service keeps that hold in its store (:func:`fault_hold`): a restart
latches the fault again from it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from cell.config.models import CellConfig
from cell.jobs.progress import quat_of, xyz_m
from cell.service.store import HoldRecord
from drivers.errors import ARM_FAULT
from drivers.robots import get_robot_model
from drivers.transforms import inv_T, make_T

ARM_FAULTS = {"protective stop": "protective stop", "emergency stop": "emergency stop",
              "safeguard stop": "protective stop", "safety fault": "fault", "power off": "fault",
              "control script not running": "fault", "reflex": "fault", "user stop": "fault",
              "disconnect": "disconnected"}
"""Faults a job's termination can name (``arm fault: <fault>``, ``cell.safety.guard``; the UR5e's and the
Franka's words, ``drivers.arm``) and the arm state each leaves: each holds the queue until a recovery."""
_FAULT_HOLD = "the arm reported a fault: "
# between a fault hold's reason and the reason of a hold that came with it (a STOP after the fault)
_THEN = "; then "


def fault_hold(fault: str, job_id: str) -> str:
    """The reason of the queue's hold after the arm reported ``fault`` in job ``job_id``: kept in the store
    (``queue_holds``) so that a restart latches the fault again (:func:`held_fault`), and released by the
    arm's recovery."""
    return f"{_FAULT_HOLD}{fault} (job {job_id}); recover the arm first (POST /api/v1/arm/recover)"


def fault_first(fault_reason: str, other: str | None) -> str:
    """The reason of a queue hold for an arm fault (``fault_reason``, :func:`fault_hold`; a fault first
    in a hold is only the fault's part of it, as :func:`after_fault` splits it off) with the reason of
    another hold, ``other`` (a STOP, a hung worker's; None: none) after it: the fault stays what a
    restart latches, and the other hold outlives the arm's recovery."""
    fault = fault_reason.partition(_THEN)[0]
    return fault if other is None else f"{fault}{_THEN}{other}"


def after_fault(reason: str) -> str | None:
    """What else a fault hold's ``reason`` (:func:`fault_first`) holds the queue for, which the arm's
    recovery leaves to the operator's resume; None when only the fault."""
    return reason.partition(_THEN)[2] or None


def held_for_fault(cell: str, fault: str, job_id: str, held: HoldRecord | None,
                   now: datetime) -> HoldRecord | None:
    """The hold of ``cell``'s queue once job ``job_id`` ended with the arm's ``fault``, the queue held as
    ``held`` (None: not held) until then: the fault first (:func:`fault_first`), so that a restart latches
    it again, and a hold already there (a STOP) after it, since that hold's time; None when ``held`` is a
    fault's already (the arm is latched, and only its recovery releases the queue)."""
    if held is not None and held_fault(held.reason) is not None:
        return None
    other = None if held is None else held.reason
    return HoldRecord(cell=cell, reason=fault_first(fault_hold(fault, job_id), other),
                      held_at=now if held is None else held.held_at)


def fault_in(termination: str) -> str | None:
    """The arm fault (a key of :data:`ARM_FAULTS`) a job's ``termination`` names (``arm fault: <fault>``),
    or None."""
    return next((f for f in ARM_FAULTS if f"{ARM_FAULT}{f}" in termination), None)


def held_fault(reason: str) -> str | None:
    """The arm fault a queue hold's ``reason`` was made for by :func:`fault_hold`, or None (a hold of
    another kind: an operator's reason never begins so)."""
    if not reason.startswith(_FAULT_HOLD):
        return None
    fault = reason.removeprefix(_FAULT_HOLD).split(" (job ", 1)[0]
    return fault if fault in ARM_FAULTS else None


@dataclass
class ArmStatus:
    """``connected``; ``state``: ``idle``, ``moving`` (a job owns the arm), ``protective stop``,
    ``emergency stop``, ``fault`` or ``disconnected``; ``faults`` latched until recovery; ``tcp`` the
    flange pose in the base frame (``xyz_m``, ``quat_xyzw``), None before it is known."""

    connected: bool
    state: str
    faults: list[str] = field(default_factory=list)
    tcp: dict[str, Any] | None = None

    @property
    def protective_stop(self) -> bool:
        return "protective stop" in self.faults

    def as_dict(self) -> dict[str, Any]:
        return {"connected": self.connected, "state": self.state, "protective_stop": self.protective_stop,
                "faults": list(self.faults), "tcp": self.tcp}


def _pose(T: np.ndarray) -> dict[str, Any]:
    return {"xyz_m": list(xyz_m(T[:3, 3])), "quat_xyzw": list(quat_of(T))}


class ArmTracker:
    """Keeps :class:`ArmStatus` from the events of the jobs (see the module docstring)."""

    def __init__(self, config: CellConfig) -> None:
        self._simulated = config.arm.type == "sim"
        self._T_sensor_flange = inv_T(config.mount.matrix())
        home = config.arm.home_joints_rad
        model = get_robot_model(config.arm.model)
        tcp = _pose(model.fk(np.asarray(home) if home is not None else model.q_home)) if self._simulated \
            else None
        self.status = ArmStatus(connected=self._simulated, state="idle", tcp=tcp)

    @property
    def faulted(self) -> bool:
        return bool(self.status.faults)

    def job_started(self) -> None:
        self.status.connected, self.status.state = True, "moving"

    def progress(self, progress: dict[str, Any]) -> None:
        """A job's progress: the flange pose from the sensor pose and the mount."""
        T_base_sensor = make_T(Rotation.from_quat(progress["sensor_quat_xyzw"]).as_matrix(),
                               np.asarray(progress["sensor_xyz_m"]))
        self.status.tcp = _pose(T_base_sensor @ self._T_sensor_flange)

    def job_ended(self, termination: str) -> str | None:
        """Latch a fault the job's termination names, and return it; otherwise the arm is idle (None)."""
        fault = fault_in(termination)
        self.status.connected = self._simulated
        if fault is None:
            self.status.state = "idle"
            return None
        self.latch(fault)
        return fault

    def latch(self, fault: str) -> None:
        """Latch ``fault`` (a key of :data:`ARM_FAULTS`) until a recovery: a job's, or one a queue hold
        kept in the store says the arm had before a restart (:func:`held_fault`)."""
        self.status.faults = [fault]
        self.status.state = ARM_FAULTS[fault]

    def recovered(self, faults: list[str], T_base_flange: list[list[float]] | None) -> None:
        """The outcome of a recovery: the faults left (none: idle) and the pose the arm reported."""
        self.status.faults = list(faults)
        self.status.state = ARM_FAULTS.get(faults[0], "fault") if faults else "idle"
        if T_base_flange is not None:
            self.status.tcp = _pose(np.asarray(T_base_flange))
