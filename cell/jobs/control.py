"""Stopping a job from another thread: the handle a service (or any caller of ``run_scan``) holds.

A stop may be asked for at any time: before the job has connected its arm (it is remembered and applied
the moment the job's session exists, before the first motion), while it runs (the arm is commanded to stop
at once through the guard, from the caller's thread, and the job ends at its next control tick with
``status: stopped``), or after its motion ended (nothing to do). ``request_stop`` says which.
"""

from __future__ import annotations

import enum
import threading
from typing import Protocol


class StopEffect(enum.Enum):
    """What a stop did to a job's motion."""

    COMMANDED = "commanded"  # the arm was commanded to stop by this stop
    BEFORE_MOTION = "before motion"  # the job has not moved yet: it stops before its first motion
    AFTER_MOTION = "after motion"  # the job's motion had ended: it was finishing its result


class Stoppable(Protocol):
    """What a job exposes to be stopped (``cell.jobs.session.JobSession``)."""

    def request_stop(self, reason: str, *, operator: bool = True) -> None: ...


class JobControl:
    """A thread-safe stop switch for one job. The first stop given is the one recorded: its reason, and
    whether someone asked for it (``operator``, the default) or the service stops the job itself."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._session: Stoppable | None = None
        self._moved = False
        self._stop: tuple[str, bool] | None = None

    def attach(self, session: Stoppable) -> None:
        """The job's session exists (called by the runner before anything moves); a stop asked for
        earlier is applied now."""
        with self._lock:
            self._session = session
            self._moved = True
            stop = self._stop
        if stop is not None:
            session.request_stop(stop[0], operator=stop[1])

    def detach(self) -> None:
        """The job's motion has ended; later stops have nothing to stop."""
        with self._lock:
            self._session = None

    def request_stop(self, reason: str, *, operator: bool = True) -> StopEffect:
        """Stop the job (``operator``: someone asked for it, ``Stoppable.request_stop``); what this call
        did to its motion."""
        with self._lock:
            if self._stop is None:
                self._stop = (reason, operator)
            session, stop, moved = self._session, self._stop, self._moved
        if session is None:
            return StopEffect.AFTER_MOTION if moved else StopEffect.BEFORE_MOTION
        session.request_stop(stop[0], operator=stop[1])
        return StopEffect.COMMANDED
