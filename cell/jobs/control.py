"""Stopping a job from another thread: the handle a service (or any caller of ``run_scan``) holds.

A stop may be asked for at any time: before the job has connected its arm (it is remembered and applied
the moment the job's session exists, before the first motion), while it runs (the arm is commanded to stop
at once through the guard, from the caller's thread, and the job ends at its next control tick with
``status: stopped``), or after it ended (nothing to do).
"""

from __future__ import annotations

import threading
from typing import Protocol


class Stoppable(Protocol):
    """What a job exposes to be stopped (``cell.jobs.session.JobSession``)."""

    def request_stop(self, reason: str) -> None: ...


class JobControl:
    """A thread-safe stop switch for one job. The first reason given is the one recorded."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._session: Stoppable | None = None
        self._reason: str | None = None

    def attach(self, session: Stoppable) -> None:
        """The job's session exists (called by the runner before anything moves); a stop asked for
        earlier is applied now."""
        with self._lock:
            self._session = session
            reason = self._reason
        if reason is not None:
            session.request_stop(reason)

    def detach(self) -> None:
        """The job's motion has ended; later stops have nothing to stop."""
        with self._lock:
            self._session = None

    def request_stop(self, reason: str) -> bool:
        """Stop the job: True when a running job's arm was commanded to stop by this call; False when the
        job has not started moving yet (it stops as soon as it does) or has ended."""
        with self._lock:
            if self._reason is None:
                self._reason = reason
            session, reason = self._session, self._reason
        if session is None:
            return False
        session.request_stop(reason)
        return True
