"""After the service or a worker died: finish the job folders and the store so that nothing stays
``running`` and nothing recorded is lost.

When the service starts it looks for its cell's jobs still marked ``running`` or ``stopping`` (the service
was killed while they ran). A worker that outlived the service has seen its input close and stopped the arm
(``cell.service.worker``); it is given time to finish its folder, then ended. A job whose folder says
``completed`` or ``no_object`` was finished safely and stays so; so does a job that ended by itself
before the restart, whose end did not reach the store (it did not answer, then the service died):
``stopped`` or ``failed`` with its own reason (:func:`own_end`), and the queue is held when that end left
the arm to a person (:func:`hold_after_end`). Any other becomes ``interrupted``, its
folder keeping every frame and log line and gaining a ``result.json`` that says so. Jobs still
``queued`` become ``cancelled``: nothing moves after a restart until someone asks again.

A store restored from a backup (docs/deploy.md, section 9) is older than the job folders: a job it has
``queued`` may have run since, and jobs submitted since are not in it. A queued job whose folder holds a
result takes that result (its status, termination and times), and one whose folder shows it started but
holds none is ``interrupted``; a job folder the store does not know is imported from its ``job.json``
and ``result.json`` when it is this cell's (:func:`import_folders`), else listed in the log, and never
deleted.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import os
import shlex
import signal
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cell.jobs.live_cloud import LIVE_CLOUD_FILE
from cell.jobs.recorder import JOB_FILE, RESULT_FILE
from cell.service.arm_status import fault_in, held_for_fault
from cell.service.protocol import WORKER_MODULE
from cell.service.retention import finish_deletions, known_folders, listed
from cell.service.store import FINISHED_STATUSES, JOB_STATUSES, RUNNING_STATUSES, HoldRecord, JobRecord, Store
from cell.service.store.repository import JOB_ID
from cell.service.worker import SERVICE_GONE
from drivers.atomic_file import is_temporary, keep_aside, write_text_atomic
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
    ``worker``, or a ``note``). An arm fault is held as a fault (``fault_hold``), which the start latches
    and only the arm's recovery releases; it had been held as any other end, so the queue could be resumed
    and the next job run on the faulted arm. A queue held already keeps its hold (a fault's, or one for a
    person to look at before a resume); an arm fault goes first in any other. Returns, in words, that the
    queue is held for this end (held now or already), or None when the end holds nothing."""
    fault = fault_in(termination)
    if fault is None and ARM_FAULT not in termination and "worker" not in result and "note" not in result:
        return None
    held, now = store.get_hold(job.cell), datetime.now(UTC)
    hold: HoldRecord | None = None  # none new: already held, for a person to look at before a resume
    if fault is not None:
        # held as the service holds it when it records the end itself: first, so that the start latches
        # it again and only the arm's recovery releases it, a hold already stored (a STOP) after it
        hold = held_for_fault(job.cell, fault, job.id, held, now)
    elif held is None:
        hold = HoldRecord(cell=job.cell, reason=held_after(f"job {job.id} ended ({termination}) before the "
                                                           "service stopped; check the arm"), held_at=now)
    if hold is not None:
        store.set_hold(job.cell, hold)
    return f"the queue is held: job {job.id} ended with {termination}"


def _frames_recorded(folder: Path) -> int:
    index = folder / "frames" / "index.csv"
    if not index.is_file():
        return 0
    with index.open(newline="") as f:
        return max(0, sum(1 for _ in csv.reader(f)) - 1)


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def read_result(folder: Path) -> dict[str, Any] | None:
    """The folder's result.json, or None when it is missing or unreadable (a worker killed mid-write)."""
    return _read_json(folder / RESULT_FILE)


def _recorded_end(folder: Path) -> tuple[str, str, dict[str, Any]] | None:
    """The status, termination and result a job folder's ``result.json`` records, when it records an end
    (one of :data:`FINISHED_STATUSES`)."""
    result = read_result(folder)
    if result is None or result.get("status") not in FINISHED_STATUSES:
        return None
    return str(result["status"]), str(result.get("termination")), result


def _modified(path: Path) -> datetime | None:
    """When ``path`` was last written (UTC), or None when it is gone."""
    try:
        return datetime.fromtimestamp(path.stat().st_mtime, UTC)
    except OSError:
        return None


def folder_files(root: Path) -> list[Path]:
    """The files a job folder ``root`` (resolved) shows its viewers, sorted: every file in it, its
    subfolders' too, but the temporary files of writes under way or left half done by a killed worker
    (``drivers.atomic_file.is_temporary``) and anything a link leads out of it to."""
    return [p for p in sorted(root.rglob("*"))
            if p.is_file() and not is_temporary(p) and p.resolve().is_relative_to(root)]


def finish_folder(folder: Path, job: JobRecord, status: str, termination: str) -> dict[str, Any]:
    """Give the job folder a ``result.json`` with ``status`` and ``termination`` and return it: the
    worker's own result with those two replaced (its own kept under ``worker``) when there is one, else
    what the folder shows (captures recorded, files kept). A ``result.json`` that cannot be read is kept
    as ``result.json.unreadable`` (``drivers.atomic_file.keep_aside``), and the new one is written whole; the
    live cloud snapshot a watched job keeps while it runs (``cloud_live.npy``) and the temporary files of
    writes its killed worker left half done (``drivers.atomic_file.is_temporary``, a frame's
    ``frames/.NNNNNN.PID.tmp.npz``) are removed: the job has ended. A folder with frames and no
    ``cloud.ply`` says under ``rebuild`` how to make a cloud (``cell reprocess``: ``cloud_hires.ply``). A
    line goes to ``log.txt``.
    Only the job's own folder is made when missing, never its parents: a folder recorded elsewhere
    (another data dir's) is not recreated (``OSError``)."""
    folder.mkdir(exist_ok=True)
    _remove_temporary(folder)
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
    if not (folder / "cloud.ply").exists() and (n_frames := _frames_recorded(folder)) > 0:
        result["rebuild"] = (f"no cloud.ply: `cell reprocess {shlex.quote(str(folder))}` makes a cloud from "
                             f"the {n_frames} frames (cloud_hires.ply, result_hires.json)")
    write_text_atomic(folder / "result.json", json.dumps(result, indent=2) + "\n", durable=True)
    with contextlib.suppress(OSError):
        (folder / LIVE_CLOUD_FILE).unlink(missing_ok=True)
    _log_line(folder, f"{status}: {termination}", result.get("rebuild"))
    return result


def _remove_temporary(folder: Path) -> None:
    """Remove the temporary files of writes a killed worker left half done in ``folder`` and its
    subfolders (``drivers.atomic_file.is_temporary``): never a file of the job's own."""
    for path in list(folder.rglob(".*")):
        if is_temporary(path):
            with contextlib.suppress(OSError):
                path.unlink()


def _log_line(folder: Path, *lines: str | None) -> None:
    """Append ``lines`` (None skipped) to the job's ``log.txt`` as the service's, when it has one."""
    if (folder / "log.txt").is_file():
        with (folder / "log.txt").open("a") as log:
            log.writelines(f"[service] {line}\n" for line in lines if line is not None)


def worker_wrote_end(folder: Path, exit_text: str) -> tuple[str, str, dict[str, Any]] | None:
    """The end a job's worker wrote into ``folder`` before it died without telling the service (killed
    between its ``result.json`` and its last line, ``exit_text`` saying how it ended): the status,
    termination and result of its ``result.json`` when :func:`own_end` lets that stand (``completed``
    and ``no_object``; ``stopped`` and ``failed`` for reasons of the job's own), else None. The worker
    writes ``result.json`` last, after every other output and after the arm was brought to rest through
    the guard and disconnected (``cell.jobs.runner``), so such a folder is whole: the record takes that
    end, not "ended unexpectedly", and ``result.json`` is left as the worker wrote it. Half-written
    temporary files and the live cloud are removed, as :func:`finish_folder` does, and a line goes to
    ``log.txt``."""
    result = read_result(folder)
    own = own_end(result, ended_alone=True)
    if result is None or own is None:
        return None
    _remove_temporary(folder)
    with contextlib.suppress(OSError):
        (folder / LIVE_CLOUD_FILE).unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        _log_line(folder, f"the job's worker ended unexpectedly ({exit_text}) after it wrote its result: "
                          f"{own[0]} stands")
    return own[0], own[1], result


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
    for job in store.jobs_in_status(cell, RUNNING_STATUSES):
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
        done.append(f"job {job.id} was {job.status} when the service stopped: now {status}")
    done += settle_queued(store, cell, now)
    if store.jobs_dir is not None:
        # a deletion cut short first: its job is gone, never imported again from what is left of its folder
        done += finish_deletions(store, store.jobs_dir)
        done += import_folders(store, cell, store.jobs_dir)
    return done


def settle_queued(store: Store, cell: str, now: datetime) -> list[str]:
    """End ``cell``'s jobs still ``queued``: one whose folder records its end (it ran after the backup the
    store was restored from) takes it; one whose folder shows it started is ``interrupted``, the folder
    finished (:func:`finish_folder`); any other is ``cancelled``. Returns what was done, in words."""
    done: list[str] = []
    for job in store.jobs_in_status(cell, ["queued"]):
        folder = Path(job.folder)
        ended = _recorded_end(folder)
        if ended is not None:
            status, termination, result = ended
            store.update_job(job.id, status=status, termination=termination, result=result,
                             started_at=_modified(folder / JOB_FILE),
                             finished_at=_modified(folder / RESULT_FILE) or now)
            done.append(f"job {job.id} was queued in the store, but its folder records its end: now {status}")
        elif (folder / JOB_FILE).is_file():
            result = finish_folder(folder, job, "interrupted", RESTART_TERMINATION)
            store.update_job(job.id, status="interrupted", termination=RESTART_TERMINATION, result=result,
                             started_at=_modified(folder / JOB_FILE), finished_at=now)
            done.append(f"job {job.id} was queued in the store, but its folder shows it ran: now interrupted")
        else:
            store.update_job(job.id, status="cancelled", termination=RESTART_CANCEL, finished_at=now)
            done.append(f"job {job.id} was queued when the service stopped: now cancelled")
    return done


def import_folders(store: Store, cell: str, jobs_dir: Path) -> list[str]:
    """Add to the store the job folders of ``jobs_dir`` it does not know that are ``cell``'s: a folder
    named as a job id, with a readable ``job.json`` (of ``cell``, or naming no cell: written before jobs
    named theirs), and no job of that id in the store. It takes the status, termination and result of
    its ``result.json`` (``interrupted`` without one: the job did not end), its part id and the key that
    submitted it from its ``job.json`` (where a service wrote them), its times from the files'.
    Every other entry is listed, and left as it is. Returns what was done, in words."""
    done: list[str] = []
    skipped: list[str] = []
    known = known_folders(store.jobs_in_status(cell, JOB_STATUSES), jobs_dir)
    for folder in sorted(jobs_dir.iterdir() if jobs_dir.is_dir() else ()):
        if folder.name in known:
            continue
        job = _found_job(folder, cell)
        if job is None or store.get_job(job.id) is not None:  # not a job, or another cell's
            skipped.append(folder.name)
            continue
        try:
            store.add_job(job)
        except ValueError:  # a job.json with values no job has (a negative seed, a pose of text)
            skipped.append(folder.name)
            continue
        done.append(f"job {job.id} was not in the store (restored from an older backup?): imported from "
                    f"its folder, now {job.status}")
    if skipped:
        done.append(f"{len(skipped)} entries of {jobs_dir} are no job of this cell's store and were left as "
                    f"they are: {listed(skipped)} (GET /api/v1/retention counts them)")
    return done


def _text(value: Any) -> str | None:
    """A job.json's optional text (a part id, a key's name): None when absent or not text."""
    return value if isinstance(value, str) else None


def _found_job(folder: Path, cell: str) -> JobRecord | None:
    """The job of ``cell`` that ``folder`` holds, as :func:`import_folders` adds it; None when it holds
    none (not named as a job id, no readable ``job.json``, another cell's, values of the wrong kind)."""
    asked = _read_json(folder / JOB_FILE) if JOB_ID.fullmatch(folder.name) and folder.is_dir() else None
    if asked is None or asked.get("cell", cell) != cell:
        return None
    status, termination, result = _recorded_end(folder) or ("interrupted", RESTART_TERMINATION, None)
    created = _modified(folder / JOB_FILE) or datetime.now(UTC)
    placement = asked.get("object_placement")
    try:
        pose = (float(placement[0]), float(placement[1]), float(placement[2])) \
            if isinstance(placement, list) and len(placement) == 3 else None
        max_time = asked.get("max_time_s")
        return JobRecord(id=folder.name, cell=cell, status=status, planner=str(asked["planner"]),
                         object=None if asked.get("object") is None else str(asked["object"]),
                         object_pose=pose, seed=int(asked["seed"]),
                         max_time_s=None if max_time is None else float(max_time),
                         part_id=_text(asked.get("part_id")), folder=str(folder),
                         submitted_by=_text(asked.get("submitted_by")), created_at=created,
                         started_at=created,
                         finished_at=_modified(folder / RESULT_FILE) or created, termination=termination,
                         result=result)
    except (KeyError, TypeError, ValueError):
        return None
