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

    def request_stop(self, reason: str) -> None: ...


class JobControl:
    """A thread-safe stop switch for one job. The first reason given is the one recorded."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._session: Stoppable | None = None
        self._moved = False
        self._reason: str | None = None

    def attach(self, session: Stoppable) -> None:
        """The job's session exists (called by the runner before anything moves); a stop asked for
        earlier is applied now."""
        with self._lock:
            self._session = session
            self._moved = True
            reason = self._reason
        if reason is not None:
            session.request_stop(reason)

    def detach(self) -> None:
        """The job's motion has ended; later stops have nothing to stop."""
        with self._lock:
            self._session = None

    def request_stop(self, reason: str) -> StopEffect:
        """Stop the job; what this call did to its motion."""
        with self._lock:
            if self._reason is None:
                self._reason = reason
            session, reason, moved = self._session, self._reason, self._moved
        if session is None:
            return StopEffect.AFTER_MOTION if moved else StopEffect.BEFORE_MOTION
        session.request_stop(reason)
        return StopEffect.COMMANDED
