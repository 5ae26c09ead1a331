"""After the service or a worker died: finish the job folders and the store so that nothing stays
``running`` and nothing recorded is lost.

When the service starts it looks for its cell's jobs still marked ``running`` (the service was killed
while they ran). A worker that outlived the service has seen its input close and stopped the arm
(``cell.service.worker``); it is given time to finish its folder, then ended. A job whose folder says
``completed`` or ``no_object`` was finished safely and stays so; any other becomes ``interrupted``, its
folder keeping every frame and log line and gaining a ``result.json`` that says so. Jobs still
``queued`` become ``cancelled``: nothing moves after a restart until someone asks again.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import signal
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cell.jobs.live_cloud import LIVE_CLOUD_FILE
from cell.service.protocol import WORKER_MODULE
from cell.service.store import JobRecord, Store
from drivers.atomic_file import keep_aside, write_text_atomic

RESTART_TERMINATION = "the service stopped while the job ran"
RESTART_CANCEL = "the service restarted before the job started"
TERM_GRACE_S = 5.0
"""After SIGTERM, how long a worker has to stop the arm and finish before it is killed [s]."""
START_SLACK_S = 2.0
"""How much later than its job's ``started_at`` a process may seem to have started and still be taken for
its worker [s]: the kernel's boot time is whole seconds, and the store's clock is the service's."""


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


def end_worker(pid: int | None, started_at: datetime | None, wait_s: float) -> None:
    """Wait up to ``wait_s`` [s] for the worker of a job that started at ``started_at`` to end by itself,
    then SIGTERM it (it stops the arm and finishes), then SIGKILL it after ``TERM_GRACE_S``."""
    if pid is None:
        return
    for sig, wait in ((None, wait_s), (signal.SIGTERM, TERM_GRACE_S), (signal.SIGKILL, TERM_GRACE_S)):
        if sig is not None and _is_worker(pid, started_at):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)
        deadline = time.monotonic() + wait
        while _is_worker(pid, started_at) and time.monotonic() < deadline:
            time.sleep(0.05)
        if not _is_worker(pid, started_at):
            return


def reconcile(store: Store, cell: str, worker_wait_s: float) -> list[str]:
    """Settle the jobs a previous run of the service left (module docstring); returns what was done, in
    words, for the service's log."""
    done: list[str] = []
    now = datetime.now(UTC)
    for job in store.jobs_in_status(cell, ["running"]):
        end_worker(job.worker_pid, job.started_at, worker_wait_s)
        folder = Path(job.folder)
        result = read_result(folder)
        if result is not None and result.get("status") in ("completed", "no_object"):
            status, termination = str(result["status"]), str(result.get("termination"))
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
