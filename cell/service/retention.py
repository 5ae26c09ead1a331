"""Retention: which ended jobs ``service.retention`` deletes, and deleting them (folder and store row).

A plan looks at the store's ended jobs of one cell, oldest first, and at the size of the cell's job
folders on disk. It never names a running or queued job, nor one marked ``keep``: those stay even when
the size limit cannot be met without them, and the plan says so. Deleting re-reads each job first, so a
job marked ``keep`` after the plan was made is spared. The size limit governs the folders of the store's
jobs of the cell alone: anything else in the jobs folder (a folder the store does not know, another
cell's) is never deleted, so it is not counted against the limit but reported beside it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import shutil
from collections.abc import Awaitable, Callable, Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

from cell.config.models import RetentionConfig
from cell.service.store import FINISHED_STATUSES, JOB_STATUSES, JobRecord, Store
from drivers.errors import CellError

GB = 1e9
log = logging.getLogger("cell.service")


@dataclass(frozen=True)
class PrunedJob:
    """An ended job the plan deletes: its folder's size [bytes] and why it goes."""

    job_id: str
    folder: str
    ended_at: datetime
    size_bytes: int
    reason: str


@dataclass(frozen=True)
class PrunePlan:
    """What pruning deletes now: ``jobs`` (oldest first), the size of the cell's job folders before
    [bytes], what deleting frees [bytes], ``unmet``: why the size limit still is not met afterwards, or
    None; and the entries of the jobs folder that are no job of the cell's store (``unknown``: their names,
    ``unknown_bytes`` their size), which retention neither counts nor deletes."""

    jobs: tuple[PrunedJob, ...]
    total_bytes: int
    freed_bytes: int
    unmet: str | None
    unknown: tuple[str, ...] = ()
    unknown_bytes: int = 0


def folder_size(path: Path) -> int:
    """Bytes in the files under ``path`` (0 if it is gone); links are counted, not followed."""
    total = 0
    for root, _dirs, files in os.walk(path):
        for name in files:
            try:
                total += os.lstat(os.path.join(root, name)).st_size
            except FileNotFoundError:  # a file removed while walking
                continue
    return total


def _size(entry: Path) -> int:
    """Bytes under a folder, or of a file (0 once it is gone)."""
    if entry.is_dir():
        return folder_size(entry)
    try:
        return entry.lstat().st_size
    except FileNotFoundError:
        return 0


def _ended_at(job: JobRecord) -> datetime:
    return job.finished_at or job.created_at


def _inside(folder: str, jobs_dir: Path) -> bool:
    return Path(folder).resolve().parent == jobs_dir.resolve()


def listed(names: Sequence[str], most: int = 20) -> str:
    """``names`` for a log line: the first ``most`` of them, and how many more."""
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return ", ".join(names[:most]) + more


def known_folders(jobs: Iterable[JobRecord], jobs_dir: Path) -> set[str]:
    """The names in ``jobs_dir`` of the folders of ``jobs`` (a cell's jobs in the store, any status)."""
    return {Path(job.folder).name for job in jobs if _inside(job.folder, jobs_dir)}


def plan_prune(store: Store, cell: str, jobs_dir: Path, retention: RetentionConfig,
               now: datetime) -> PrunePlan:
    """The ended jobs of ``cell`` that ``retention`` deletes at ``now`` (timezone-aware)."""
    # one walk of the jobs folder gives the total, each job's share and what retention does not govern
    entries = {entry.name: _size(entry) for entry in (jobs_dir.iterdir() if jobs_dir.is_dir() else ())}
    jobs = store.jobs_in_status(cell, JOB_STATUSES)
    known = known_folders(jobs, jobs_dir)
    unknown = sorted(set(entries) - known)
    total = sum(size for name, size in entries.items() if name in known)
    ended = sorted((job for job in jobs if job.status in FINISHED_STATUSES and not job.keep),
                   key=lambda job: (_ended_at(job), job.id))
    # a job's folder is named by its id: in ``known`` when it lies inside jobs_dir (resolved once above)
    sizes = {job.id: entries.get(name, 0) if (name := Path(job.folder).name) in known else 0 for job in ended}
    chosen: list[PrunedJob] = []
    rest: list[JobRecord] = []
    if retention.days is not None:
        cutoff = now - timedelta(days=retention.days)
        for job in ended:
            if _ended_at(job) < cutoff:
                chosen.append(PrunedJob(job.id, job.folder, _ended_at(job), sizes[job.id],
                                        f"ended more than {retention.days:g} days ago"))
            else:
                rest.append(job)
    else:
        rest = ended
    freed = sum(p.size_bytes for p in chosen)
    unmet = None
    if retention.max_gb is not None:
        limit = retention.max_gb * GB
        for job in rest:
            if total - freed <= limit:
                break
            chosen.append(PrunedJob(job.id, job.folder, _ended_at(job), sizes[job.id],
                                    f"the job folders are over {retention.max_gb:g} GB"))
            freed += sizes[job.id]
        if total - freed > limit:
            unmet = (f"{(total - freed) / GB:.2f} GB of job folders remain, over the {retention.max_gb:g} GB "
                     "limit: the rest are running, queued or kept jobs")
    return PrunePlan(tuple(chosen), total, freed, unmet, tuple(unknown),
                     sum(entries[name] for name in unknown))


DELETING = ".deleting-"
"""The name a job folder being deleted takes first in the jobs folder (``.deleting-<folder name>``)."""


def delete_job(store: Store, job: JobRecord, jobs_dir: Path) -> None:
    """Delete an ended job so that it is, at every moment, listed with its folder whole or gone: its
    folder, when it is one of ``jobs_dir``'s (a folder elsewhere is never touched), is first renamed
    ``.deleting-<name>`` (one atomic rename), then its row is deleted, then the renamed folder. A prune
    killed anywhere in between leaves a ``.deleting-`` folder that the next start finishes
    (:func:`finish_deletions`): a job listed over a folder cut in half had stayed so."""
    if _inside(job.folder, jobs_dir):
        folder = Path(job.folder)
        doomed = jobs_dir / f"{DELETING}{folder.name}"
        with contextlib.suppress(FileNotFoundError):  # no folder: only its row is left
            folder.rename(doomed)
        store.delete_job(job.id)
        shutil.rmtree(doomed, ignore_errors=True)
        return
    store.delete_job(job.id)


def finish_deletions(store: Store, jobs_dir: Path) -> list[str]:
    """Finish the deletions a killed prune or purge left in ``jobs_dir`` (:func:`delete_job`): the row of
    each ``.deleting-<id>`` folder's job, when still there, then the folder. Returns what was done, in
    words: a folder that could not be removed all is named with the error and left (the job is gone from
    the store; the plan of a prune lists the folder as an entry it does not count, ``unknown``)."""
    done = []
    for doomed in sorted(jobs_dir.glob(f"{DELETING}*") if jobs_dir.is_dir() else ()):
        job_id = doomed.name.removeprefix(DELETING)
        job = store.get_job(job_id)
        if job is not None and Path(job.folder).name == job_id and _inside(job.folder, jobs_dir):
            store.delete_job(job_id)
        try:
            shutil.rmtree(doomed)
        except OSError as exc:
            done.append(f"job {job_id}: deleted, but its folder {doomed} could not be removed "
                        f"({exc.strerror or exc}: {exc.filename}); remove it by hand")
            continue
        done.append(f"job {job_id}: its deletion, cut short when the service stopped, is finished")
    return done


def prune(store: Store, plan: PrunePlan, jobs_dir: Path) -> list[PrunedJob]:
    """Delete the plan's jobs (:func:`delete_job`). Returns the jobs deleted; a job gone, marked ``keep``
    or no longer ended meanwhile is left."""
    done = []
    for item in plan.jobs:
        job = store.get_job(item.job_id)
        if job is None or job.keep or job.status not in FINISHED_STATUSES:
            continue
        delete_job(store, job, jobs_dir)
        done.append(item)
    return done


class Retention:
    """A cell's retention in the service: plans and prunes off the event loop, one prune at a time, and
    prunes by itself every ``interval_h`` hours (``run``) when any limit is set."""

    def __init__(self, store: Store, cell: str, jobs_dir: Path, config: RetentionConfig) -> None:
        self.config = config
        self._store, self._cell, self._jobs_dir = store, cell, jobs_dir
        self._lock = asyncio.Lock()
        self.on_thread: Callable[[Callable[[], PrunePlan]], Awaitable[PrunePlan]] = asyncio.to_thread
        """How a plan is made on a worker thread: in the API's bulk turn once ``cell serve`` runs
        (``cell.api.bulk``), as it reads every job of the store and walks the jobs folder."""

    @property
    def active(self) -> bool:
        """Whether any limit is set (else nothing is ever deleted by retention)."""
        return self.config.days is not None or self.config.max_gb is not None

    def plan_now(self) -> PrunePlan:
        """What pruning would delete now; it blocks: on a worker thread (``plan``)."""
        return plan_prune(self._store, self._cell, self._jobs_dir, self.config, datetime.now(UTC))

    async def plan(self) -> PrunePlan:
        """What pruning would delete now, planned by ``on_thread``."""
        return await self.on_thread(self.plan_now)

    async def prune(self) -> tuple[PrunePlan, list[PrunedJob]]:
        """Prune now; returns the plan and the jobs deleted, each logged."""
        async with self._lock:
            plan = await self.plan()
            done = await asyncio.to_thread(prune, self._store, plan, self._jobs_dir)
        for item in done:
            log.info("job deleted by retention: %s (%.1f MB)", item.reason, item.size_bytes / 1e6,
                     extra={"job_id": item.job_id})
        if plan.unmet:
            log.warning("retention: %s", plan.unmet)
        if plan.unknown:
            log.warning("retention: %d entries of %s (%.2f GB) are no job of this cell's store, neither "
                        "counted nor deleted: %s", len(plan.unknown), self._jobs_dir, plan.unknown_bytes / GB,
                        listed(plan.unknown))
        return plan, done

    async def run(self) -> None:
        """Prune now and then every ``interval_h`` hours, until cancelled; a failure is logged, not fatal."""
        while True:
            try:
                await self.prune()
            except (CellError, OSError) as exc:
                log.error("retention could not prune: %s", exc)
            await asyncio.sleep(self.config.interval_h * 3600.0)
