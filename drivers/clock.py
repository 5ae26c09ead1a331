"""Clocks: a deterministic simulated clock and the wall clock, behind one small protocol.

Sim mode steps every simulated device from the clock, so that ``sleep(dt)`` in the job loop advances the
whole simulated cell by ``dt`` seconds; real mode sleeps on the monotonic wall clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol


class Clock(Protocol):
    """Time source of a job, in seconds."""

    def now(self) -> float:
        """Current time [s]."""
        ...

    def sleep(self, dt: float) -> None:
        """Let ``dt`` seconds pass."""
        ...


class SimClock:
    """Simulated time [s]; ``sleep`` advances it and steps every registered device by ``dt``.

    Devices are stepped in registration order so that a run is reproducible.
    """

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)
        self._steppers: list[Callable[[float], None]] = []
        self._overrun = 0.0

    def now(self) -> float:
        return self._t

    def add_stepper(self, step: Callable[[float], None]) -> None:
        """Register ``step(dt)``, called on every ``sleep`` before time moves on."""
        self._steppers.append(step)

    def set_overrun(self, extra_s: float) -> None:
        """Make every ``sleep`` last ``extra_s`` seconds longer (0 ends it): a simulated control loop
        that runs late, while the devices keep moving."""
        if extra_s < 0.0:
            raise ValueError(f"overrun must be >= 0, got {extra_s} s")
        self._overrun = float(extra_s)

    def sleep(self, dt: float) -> None:
        if dt < 0.0:
            raise ValueError(f"cannot sleep a negative time ({dt} s)")
        dt += self._overrun
        for step in self._steppers:
            step(dt)
        self._t += dt


class WallClock:
    """Monotonic wall-clock time [s] since construction."""

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def now(self) -> float:
        return time.monotonic() - self._t0

    def sleep(self, dt: float) -> None:
        if dt > 0.0:
            time.sleep(dt)
