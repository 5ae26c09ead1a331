"""The job store's domain records: plain frozen dataclasses that the service passes around, free of the
database layer (:mod:`cell.service.store.models` maps them onto tables)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any

# Every status a job can be in, in the order of its life: waiting, on the arm (``stopping``: its worker
# has taken a stop, the arm is commanded to stop, and the worker has not yet written how the job ended),
# then one way of ending.
JOB_STATUSES = ("queued", "running", "stopping", "completed", "no_object", "failed", "stopped", "cancelled",
                "interrupted")
# The statuses of a job whose worker holds the arm.
RUNNING_STATUSES = ("running", "stopping")
# The statuses a job never leaves: ``completed``, ``no_object`` (the scan found nothing on the table),
# ``failed`` and ``stopped`` are the scan's own outcomes (``result.json``), ``cancelled`` a job removed
# from the queue before it ran, ``interrupted`` a job whose worker died or whose service went down while
# it ran.
FINISHED_STATUSES = frozenset({"completed", "no_object", "failed", "stopped", "cancelled", "interrupted"})
STORE_RETRY_S = 1.0
"""How often the service tries again a write the store refused (it does not answer) [s]: a job's start
or end, the line's state and transitions."""


@dataclass(frozen=True)
class JobRecord:
    """One scan job as the service keeps it.

    ``id`` is 16 lowercase hex characters chosen by the caller; ``cell`` the name of the cell that runs it
    (several cells may share one PostgreSQL store); ``status`` one of :data:`JOB_STATUSES`.
    ``object`` is a shipped object's name or mesh file, or None (a real cell scans an unknown object);
    ``object_pose`` is (x [m], y [m], yaw [deg]) on the table from the cell's station; ``max_time_s`` the
    time budget [s] (None: the cell file's); ``part_id`` the line's identifier of the part, if any;
    ``folder`` the path of the job folder: the store keeps one in its cell's job folders by its name
    there and gives it back in the serving data dir's (:class:`cell.service.store.Store`), so that a data
    dir may move; ``submitted_by`` the name of the API key that submitted it. Every time is
    timezone-aware UTC. ``result`` is the job's ``result.json`` once it ended, ``progress`` the last
    progress snapshot, ``worker_pid`` the process id of the worker that runs it; ``keep``: retention never
    deletes the job.
    """

    id: str
    cell: str
    status: str
    planner: str
    object: str | None
    object_pose: tuple[float, float, float] | None
    seed: int
    max_time_s: float | None
    part_id: str | None
    folder: str
    submitted_by: str | None
    created_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    termination: str | None = None
    result: dict[str, Any] | None = None
    progress: dict[str, Any] | None = None
    worker_pid: int | None = None
    keep: bool = False


@dataclass(frozen=True)
class KeyRecord:
    """An API key as stored: its ``name``, its ``role`` (see :class:`cell.service.keys.Role`), the hex
    SHA-256 of the key (the key itself is never stored), when it was created and, once revoked, when
    (timezone-aware UTC)."""

    name: str
    role: str
    key_hash: str
    created_at: datetime
    revoked_at: datetime | None = None

    @property
    def active(self) -> bool:
        """Whether the key still authenticates (it has not been revoked)."""
        return self.revoked_at is None


@dataclass(frozen=True)
class LineTransition:
    """One transition of a cell's PackML state machine: when (timezone-aware UTC), the states before and
    after (their PackML numbers, :class:`cell.line.packml.State`), the unit mode after, and the cause in
    words (the command and who sent it, or the event)."""

    cell: str
    at: datetime
    from_state: int
    to_state: int
    mode: int
    cause: str


@dataclass(frozen=True)
class LineRecord:
    """What a cell's line keeps across restarts: the unit mode, the PackML counters (parts processed,
    defective), the last stop reason (ID and text) and the last result the line read (JSON)."""

    cell: str
    mode: int
    processed: int = 0
    defective: int = 0
    stop_reason_id: int = 0
    stop_reason: str = ""
    last_result: dict[str, Any] | None = None


@dataclass(frozen=True)
class HoldRecord:
    """A cell's held queue, kept across restarts until an operator resumes it: why, in words (what held
    it and what to do), and since when (timezone-aware UTC)."""

    cell: str
    reason: str
    held_at: datetime
