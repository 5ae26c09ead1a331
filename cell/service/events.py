"""A job's events, numbered, for live clients: ``state``, ``progress`` and a final ``result``.

Each job keeps its events in order with increasing ids; a client that reconnects with the last id it saw
gets everything after it. The ids of a service run start above its start time in milliseconds since the
epoch, so that they are above every id an earlier run gave (a job's events are far fewer than its
milliseconds): a client that reconnects after a restart with an id of the earlier run gets the whole log
of the new one (the job's final state and result) rather than nothing.

Publishing never waits for a client: events are appended to the job's list and waiting clients are
woken; each client reads at its own pace, so a slow or vanished one costs nothing but its own connection.
Everything here runs on the service's event loop.
"""

from __future__ import annotations

import asyncio
import bisect
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

MAX_EVENTS_PER_JOB = 20_000
"""Events kept per job (a 180 s job at 5 perception updates per second makes about 900); beyond it the
oldest progress events are dropped (states and the result are always kept)."""


@dataclass(frozen=True)
class JobEvent:
    """``id`` (increasing per job), ``kind`` (``state``, ``progress``, ``result``) and its JSON data."""

    id: int
    kind: str
    data: dict[str, Any]


class JobEvents:
    """The events of one job (see the module docstring). ``closed`` once its ``result`` is published."""

    def __init__(self, first_id: int = 1) -> None:
        self._events: list[JobEvent] = []
        self._next_id = first_id
        self._changed = asyncio.Event()
        self.closed = False

    def publish(self, kind: str, data: dict[str, Any]) -> JobEvent:
        event = JobEvent(self._next_id, kind, data)
        self._next_id += 1
        self._events.append(event)
        if len(self._events) > MAX_EVENTS_PER_JOB:
            first_progress = next(i for i, e in enumerate(self._events) if e.kind == "progress")
            del self._events[first_progress]
        if kind == "result":
            self.closed = True
        changed, self._changed = self._changed, asyncio.Event()
        changed.set()
        return event

    def after(self, last_id: int) -> list[JobEvent]:
        """The events with an id above ``last_id``, in order."""
        return self._events[bisect.bisect_right(self._events, last_id, key=lambda e: e.id):]

    async def follow(self, last_id: int, idle_s: float) -> AsyncIterator[JobEvent | None]:
        """Every event after ``last_id`` as it comes, until the ``result``; None after ``idle_s`` [s]
        without one (for a keep-alive)."""
        while True:
            for event in self.after(last_id):
                last_id = event.id
                yield event
            if self.closed:
                return
            changed = self._changed
            try:
                await asyncio.wait_for(changed.wait(), idle_s)
            except TimeoutError:
                yield None


class EventHub:
    """The event logs of the jobs the service has seen since it started, the most recent ones kept."""

    def __init__(self, keep_finished: int = 50) -> None:
        self._logs: dict[str, JobEvents] = {}
        self._keep = keep_finished
        self._first_id = time.time_ns() // 1_000_000 + 1

    def log(self, job_id: str) -> JobEvents:
        """The job's log, made when first asked for."""
        log = self._logs.get(job_id)
        if log is None:
            log = self._logs[job_id] = JobEvents(self._first_id)
            finished = [k for k, v in self._logs.items() if v.closed]
            for old in finished[:max(0, len(finished) - self._keep)]:
                del self._logs[old]
        return log

    def get(self, job_id: str) -> JobEvents | None:
        return self._logs.get(job_id)
