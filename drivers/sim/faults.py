"""Faults injected into a simulated cell on a schedule (``sim.faults`` in a cell file).

They exercise the safety layer's reactions the way hardware would trigger them: the arm reports a
protective stop, a reflex or an emergency stop, or stops answering (disconnect); the control loop runs
late (loop overrun: every control period lasts ``overrun_s`` longer while the arm keeps moving); the
sensor delivers no frames (sensor stall). Times are sim time [s].

Not scheduled but always on: the arm faults when one of its bodies touches the object or the table, with
the kind the real arm would report (a UR5e's protective stop, a Franka's reflex) and what touched what
where (:mod:`drivers.sim.contact`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal, get_args

from pydantic import Field, PositiveFloat, model_validator

from drivers.config_base import StrictModel

if TYPE_CHECKING:  # the injector's devices: the cell file's models import this module, not the sim
    from drivers.arm.sim import SimArm
    from drivers.clock import SimClock
    from drivers.depth.sim_base import SimDepthSensor

ArmFaultKind = Literal["protective stop", "reflex", "emergency stop", "disconnect"]
FaultKind = ArmFaultKind | Literal["loop overrun", "sensor stall"]
ARM_FAULTS: tuple[str, ...] = get_args(ArmFaultKind)


class SimFault(StrictModel):
    """One scheduled fault: ``kind`` at ``at_s``; ``duration_s`` for a loop overrun or a sensor stall,
    ``overrun_s`` [s] the extra length of each control period during a loop overrun."""

    at_s: float = Field(ge=0.0)
    kind: FaultKind
    duration_s: PositiveFloat | None = None
    overrun_s: PositiveFloat | None = None

    @model_validator(mode="after")
    def _complete(self) -> SimFault:
        if self.kind in ("loop overrun", "sensor stall") and self.duration_s is None:
            raise ValueError(f"a {self.kind} needs duration_s")
        if self.kind == "loop overrun" and self.overrun_s is None:
            raise ValueError("a loop overrun needs overrun_s")
        return self


class SimFaultInjector:
    """Applies a schedule of faults as the sim clock passes their times (registered as a clock stepper
    after the devices, so a fault takes effect from the next period on)."""

    def __init__(self, faults: list[SimFault], clock: SimClock, arm: SimArm, sensor: SimDepthSensor) -> None:
        self._pending = sorted(faults, key=lambda f: f.at_s)
        self._clock = clock
        self._arm = arm
        self._sensor = sensor
        self._overrun_until: float | None = None
        clock.add_stepper(self._step)

    def _step(self, dt: float) -> None:
        now = self._clock.now() + dt
        if self._overrun_until is not None and now >= self._overrun_until:
            self._clock.set_overrun(0.0)
            self._overrun_until = None
        while self._pending and self._pending[0].at_s <= now:
            self._apply(self._pending.pop(0), now)

    def _apply(self, fault: SimFault, now: float) -> None:
        if fault.kind in ARM_FAULTS:
            self._arm.inject_fault(fault.kind, recoverable=fault.kind != "emergency stop")
        elif fault.kind == "loop overrun":
            assert fault.overrun_s is not None and fault.duration_s is not None
            self._clock.set_overrun(fault.overrun_s)
            self._overrun_until = now + fault.duration_s
        else:
            assert fault.duration_s is not None
            self._sensor.stall(fault.duration_s + (now - self._clock.now()))
