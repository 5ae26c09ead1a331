"""After the service or a worker died: finish the job folders and the store so that nothing stays
``running`` and nothing recorded is lost.

When the service starts it looks for its cell's jobs still marked ``running`` (the service was killed
while they ran). A worker that outlived the service has seen its input close and stopped the arm
(``cell.service.worker``); it is given time to finish its folder, then ended. A job whose folder says
``completed`` or ``no_object`` was finished safely and stays so; so does a job that ended by itself
before the restart, whose end did not reach the store (it did not answer, then the service died):
``stopped`` or ``failed`` with its own reason (:func:`own_end`), and the queue is held when that end left
the arm to a person (:func:`hold_after_end`). Any other becomes ``interrupted``, its
folder keeping every frame and log line and gaining a ``result.json`` that says so. Jobs still
``queued`` become ``cancelled``: nothing moves after a restart until someone asks again.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import os
import signal
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cell.jobs.live_cloud import LIVE_CLOUD_FILE
from cell.service.protocol import WORKER_MODULE
from cell.service.store import HoldRecord, JobRecord, Store
from cell.service.worker import SERVICE_GONE
from drivers.atomic_file import keep_aside, write_text_atomic
from drivers.errors import ARM_FAULT

RESTART_TERMINATION = "the service stopped while the job ran"
RESTART_CANCEL = "the service restarted before the job started"
TERM_GRACE_S = 5.0
"""After SIGTERM, how long a worker has to stop the arm and finish before it is killed [s]."""
START_SLACK_S = 2.0
"""How much later than its job's ``started_at`` a process may seem to have started and still be taken for
its worker [s]: the kernel's boot time is whole seconds, and the store's clock is the service's."""

log = logging.getLogger("cell.service")


def held_after(after: str) -> str:
    """The reason of a queue held after ``after`` (in words) until an operator resumes it."""
    return f"held after {after}: resume the queue to go on (cell jobs resume, or POST /api/v1/queue/resume)"


def own_end(result: dict[str, Any] | None, ended_alone: bool) -> tuple[str, str] | None:
    """The end a job's folder records (``result``, its result.json) when it is the job's own and stands
    after a restart: its status and termination. ``completed`` and ``no_object`` always stand;
    ``stopped`` and ``failed`` when the worker ended by itself (``ended_alone``: not signalled by the
    restart) and not because its service went away (``cell.service.worker.SERVICE_GONE``). None
    otherwise: the job was interrupted by the restart."""
    if result is None:
        return None
    status, termination = str(result.get("status")), str(result.get("termination"))
    if status in ("completed", "no_object"):
        return status, termination
    if status in ("stopped", "failed") and ended_alone and SERVICE_GONE not in termination:
        return status, termination
    return None


def hold_after_end(store: Store, job: JobRecord, result: dict[str, Any], termination: str) -> str | None:
    """Hold the queue of ``job``'s cell in the store after the job's own end that the service could not
    record (:func:`own_end`), when that end left the arm to a person, as the service holds it when it
    records such an end: an arm fault, or an end the service wrote for a worker it killed or lost (a stop
    not confirmed through the guard, a worker that died: its result.json keeps the worker's own under
    ``worker``, or a ``note``). Returns what was held, in words, or None."""
    if ARM_FAULT not in termination and "worker" not in result and "note" not in result:
        return None
    reason = held_after(f"job {job.id} ended ({termination}) before the service stopped; check the arm")
    store.set_hold(job.cell, HoldRecord(cell=job.cell, reason=reason, held_at=datetime.now(UTC)))
    return f"the queue is held: job {job.id} ended with {termination}"


def _frames_recorded(folder: Path) -> int:
    index = folder / "frames" / "index.csv"
    if not index.is_file():
        return 0
    with index.open(newline="") as f:
        return max(0, sum(1 for _ in csv.reader(f)) - 1)


def read_result(folder: Path) -> dict[str, Any] | None:
    """The folder's result.json, or None when it is missing or unreadable (a worker killed mid-write)."""
    try:
        data = json.loads((folder / "result.json").read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def finish_folder(folder: Path, job: JobRecord, status: str, termination: str) -> dict[str, Any]:
    """Give the job folder a ``result.json`` with ``status`` and ``termination`` and return it: the
    worker's own result with those two replaced (its own kept under ``worker``) when there is one, else
    what the folder shows (captures recorded, files kept). A ``result.json`` that cannot be read is kept
    as ``result.json.unreadable`` (``drivers.atomic_file.keep_aside``), and the new one is written whole; the
    live cloud snapshot a watched job keeps while it runs (``cloud_live.npy``) is removed: the job has
    ended. A line goes to ``log.txt``."""
    folder.mkdir(parents=True, exist_ok=True)
    previous = read_result(folder)
    if previous is None and (folder / "result.json").exists():
        keep_aside(folder / "result.json")
    if previous is not None:
        result = {**previous, "status": status, "termination": termination,
                  "worker": {"status": previous.get("status"), "termination": previous.get("termination")}}
    else:
        result = {"planner": job.planner, "object": job.object, "seed": job.seed, "status": status,
                  "termination": termination, "n_captures": _frames_recorded(folder),
                  "files": sorted(str(p.relative_to(folder)) for p in folder.iterdir()),
                  "note": "the job's worker ended before it wrote its result; its frames, trajectory and "
                          "log are kept, and `cell reprocess` rebuilds a cloud from the frames"}
    write_text_atomic(folder / "result.json", json.dumps(result, indent=2) + "\n", durable=True)
    with contextlib.suppress(OSError):
        (folder / LIVE_CLOUD_FILE).unlink(missing_ok=True)
    if (folder / "log.txt").is_file():
        with (folder / "log.txt").open("a") as log:
            log.write(f"[service] {status}: {termination}\n")
    return result


def _started(pid: int) -> float:
    """When process ``pid`` started, on the wall clock [s since the epoch] (``/proc/<pid>/stat`` field 22,
    in clock ticks since boot, plus the boot time of ``/proc/stat``)."""
    stat = Path(f"/proc/{pid}/stat").read_text()
    ticks = int(stat.rsplit(")", 1)[1].split()[19])  # field 22; the name in brackets may hold spaces
    boot = next(int(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                if line.startswith("btime "))
    return boot + ticks / os.sysconf("SC_CLK_TCK")


def _is_worker(pid: int, started_at: datetime | None) -> bool:
    """Whether ``pid`` is alive and is the worker of a job that started at ``started_at``: a process of
    the worker module that was already running then. Its command line cannot name the job: the service
    starts the next job's worker before the job (``service.warm_worker``). A process that reused the pid
    of a worker that ended started after it."""
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        started = _started(pid)
    except (OSError, ValueError, IndexError):
        return False
    if WORKER_MODULE.encode() not in cmdline:
        return False
    return started_at is None or started <= started_at.timestamp() + START_SLACK_S


def end_worker(pid: int | None, started_at: datetime | None, wait_s: float) -> bool:
    """Wait up to ``wait_s`` [s] for the worker of a job that started at ``started_at`` to end by itself,
    then SIGTERM it (it stops the arm and finishes), then SIGKILL it after ``TERM_GRACE_S``. Returns
    whether it ended without a signal (or was gone already). A wait is logged first: the service's start
    waits on it, silent otherwise."""
    if pid is None or not _is_worker(pid, started_at):
        return True
    log.warning("waiting for worker pid %d of a job the previous run left running: up to %g s "
                "(service.shutdown_timeout_s) for it to stop the arm and finish the job's folder, then "
                "SIGTERM and up to %g s, then SIGKILL", pid, wait_s, TERM_GRACE_S)
    for sig, wait in ((None, wait_s), (signal.SIGTERM, TERM_GRACE_S), (signal.SIGKILL, TERM_GRACE_S)):
        if sig is not None and _is_worker(pid, started_at):
            log.warning("worker pid %d still runs: %s", pid, sig.name)
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)
        deadline = time.monotonic() + wait
        while _is_worker(pid, started_at) and time.monotonic() < deadline:
            time.sleep(0.05)
        if not _is_worker(pid, started_at):
            return sig is None
    return False


def reconcile(store: Store, cell: str, worker_wait_s: float) -> list[str]:
    """Settle the jobs a previous run of the service left (module docstring); returns what was done, in
    words, for the service's log."""
    done: list[str] = []
    now = datetime.now(UTC)
    for job in store.jobs_in_status(cell, ["running"]):
        ended_alone = end_worker(job.worker_pid, job.started_at, worker_wait_s)
        folder = Path(job.folder)
        result = read_result(folder)
        if result is not None and (own := own_end(result, ended_alone)) is not None:
            status, termination = own
            if (held := hold_after_end(store, job, result, termination)) is not None:
                done.append(held)
        else:
            status, termination = "interrupted", RESTART_TERMINATION
            result = finish_folder(folder, job, status, termination)
        store.update_job(job.id, status=status, termination=termination, result=result,
                         finished_at=now, worker_pid=None)
        done.append(f"job {job.id} was running when the service stopped: now {status}")
    for job in store.jobs_in_status(cell, ["queued"]):
        store.update_job(job.id, status="cancelled", termination=RESTART_CANCEL, finished_at=now)
        done.append(f"job {job.id} was queued when the service stopped: now cancelled")
    return done
