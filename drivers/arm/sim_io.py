"""The standard digital I/O of a simulated UR5e, for a packing line's handshake in a sim cell.

A real UR5e's inputs are wires from the PLC and its outputs wires to it
(:class:`drivers.arm.ur_io.URDigitalIO` reads and sets them over RTDE). A sim cell has no PLC:
:class:`SimDigitalIO` holds the eight inputs and the eight outputs in the service's memory, the handshake
reads and writes them as it does a UR5e's, and an integrator sets the inputs and reads the outputs over
REST (``cell line dio``), to try the handshake before the robot arrives.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol

from drivers.arm.config import DIGITAL_PINS


class DigitalIO(Protocol):
    """A robot's standard digital inputs and outputs (``DIGITAL_PINS`` of each), as the line's handshake
    uses them; every method may raise ``DriverError`` for a link that failed."""

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def inputs(self) -> tuple[tuple[bool, ...], float]:
        """The inputs' levels, DI0 first, and when the device sampled them [s, on the device's own clock]:
        a debounce filter measures how long a level held on that clock, so that a sample read late, or
        read again, does not stretch a short pulse into a level."""
        ...

    def set_outputs(self, outputs: list[tuple[int, bool]]) -> None:
        """Set outputs ``[(index, level), ...]``."""
        ...


class SimDigitalIO:
    """The digital inputs and outputs of a simulated UR5e: all low at first; ``set_input`` is the
    simulated PLC's wire, ``outputs`` what a PLC would read. Safe to use from any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._inputs = [False] * DIGITAL_PINS
        self._outputs = [False] * DIGITAL_PINS

    def connect(self) -> None:
        """Nothing to connect to: the levels live in this object (they outlive a reconnection, as a
        controller's do)."""

    def close(self) -> None:
        """Nothing to close (see :meth:`connect`)."""

    def inputs(self) -> tuple[tuple[bool, ...], float]:
        """The levels and the time they are read at (``time.monotonic``: they live here, read now)."""
        with self._lock:
            return tuple(self._inputs), time.monotonic()

    def set_outputs(self, outputs: list[tuple[int, bool]]) -> None:
        with self._lock:
            for index, level in outputs:
                self._outputs[index] = level

    def set_input(self, index: int, level: bool) -> None:
        """Drive input ``index`` to ``level``, as the PLC's wire would."""
        with self._lock:
            self._inputs[index] = level

    def outputs(self) -> tuple[bool, ...]:
        """The outputs' levels, DO0 first."""
        with self._lock:
            return tuple(self._outputs)
