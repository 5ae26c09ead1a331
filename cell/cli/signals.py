"""The signals that end a program stop a command that moves the arm as Ctrl-C does.

SIGTERM (systemd's and docker's stop, ``kill``) and SIGHUP (a terminal closed) end a Python process at
once by default: a scan's arm streamed on until the controller's watchdog stopped it, and the job folder
had no result.json. Inside :func:`interrupting` the first of them raises ``KeyboardInterrupt`` naming
itself, which the job's runner turns into a stop through the guard and a finished folder, as it does
Ctrl-C's. Later ones are recorded but raise nothing: the stop they ask for is under way, and an interrupt
in the middle of it (the arm's stop, the folder's writing) would leave both half done.
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from types import FrameType

TERMINATING = (signal.SIGTERM, signal.SIGHUP)
"""Signals that stop a command as Ctrl-C does."""


@contextlib.contextmanager
def interrupting() -> Iterator[list[int]]:
    """While inside, the first ``TERMINATING`` signal raises ``KeyboardInterrupt("received SIGTERM")``
    (module docstring). Yields the signals received, in order; the previous handlers come back after."""
    received: list[int] = []

    def interrupt(signum: int, _frame: FrameType | None) -> None:
        received.append(signum)
        if len(received) == 1:
            raise KeyboardInterrupt(f"received {signal.Signals(signum).name}")

    previous = {sig: signal.signal(sig, interrupt) for sig in TERMINATING}
    try:
        yield received
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
