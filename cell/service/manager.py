"""The long-running cell: one arm, one sensor, jobs run one at a time from a FIFO queue.

:class:`CellService` is what the API and the packing line call; it knows nothing of HTTP. It runs on the
service's event loop: the queue, the running job and the event logs live there, the store is written
from worker threads (``asyncio.to_thread``) so that no database call holds the loop.

Each job runs in a worker process of its own (``cell.service.worker``): the control loop never shares an
interpreter lock with the web side, and a job survives nothing it should not: when the service goes away
its worker stops the arm and finishes the folder. A stop is passed to the worker, which commands the arm
to stop before it answers; a worker that does not answer in ``service.stop_confirm_timeout_s`` is killed
with its children (the arm's own connection watchdog then stops it: the UR's RTDE watchdog, the Franka's
communication reflex). With ``service.warm_worker`` the next job's worker is started ahead, between
jobs, and waits with its libraries loaded.

``stop_all`` (the operator's STOP) also holds the queue: nothing else starts until an operator resumes
it. So do a worker that died, a stop its worker did not confirm and a worker that went silent (hung:
stopped as a stop does): the arm was then left to its connection watchdog, and a person looks first. Such
a hold is kept in the store (``queue_holds``), so that a restart does not release it. A fault the arm
reported holds the queue too, until the arm is recovered (``cell.service.arm_status``; kept in the store
as well, and latched again by a restart), and so does a job
store found damaged by any call (``Store.damaged``: no job's start or end could be relied on to be
recorded), until it is restored and the service restarted. A data dir with no room for a job's recording
(:data:`JOB_DISK_MB`), or a jobs folder that takes no file, holds the next job until a job can record.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import errno
import functools
import json
import logging
import os
import secrets
import shutil
import signal
import sys
import tempfile
from collections import deque
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cell import __version__
from cell.config.models import CellConfig
from cell.jobs.control import StopEffect
from cell.line.controller import LineController
from cell.line.dio import DigitalIOHandshake, digital_io
from cell.planning.registry import PLANNERS
from cell.service.arm_clearance import ArmClearance
from cell.service.arm_status import ArmTracker, after_fault, fault_first, held_fault, held_for_fault
from cell.service.events import EventHub, JobEvents
from cell.service.instance import DataDirClaim, new_instance
from cell.service.metrics import ServiceMetrics
from cell.service.objects import ObjectLibrary
from cell.service.protocol import WORKER_BEAT_S, WORKER_MODULE, WorkerSpec, finite_json, stop_command
from cell.service.recovery import finish_folder, held_after, reconcile, worker_wrote_end
from cell.service.retention import Retention, delete_job
from cell.service.search_views import SearchViews
from cell.service.store import (
    FINISHED_STATUSES,
    RUNNING_STATUSES,
    STORE_RETRY_S,
    HoldRecord,
    JobRecord,
    Store,
)
from cell.service.store.engine import RESTORE
from cell.service.store.lease import CellLease
from cell.service.store.retry import until_stored
from cell.service.submission import JobRequest, ValidJob, validate
from drivers.arm.config import LinePinsConfig
from drivers.errors import SHUTDOWN_STOP as SERVICE_SHUTDOWN
from drivers.errors import ServiceError, StoreError, stop_cause, stop_termination

LINE_LIMIT = 1 << 24
"""Longest line a worker may send [bytes]: the ``ended`` line carries the whole result.json."""
RECOVER_TIMEOUT_S = 60.0
"""How long an arm recovery may take (connect, unlock, power on, brakes) [s]."""
LEASE_CHECK_S = 1.0
"""How often the service checks that it still holds its cell's lease (``cell.service.store.lease``) [s]:
a PostgreSQL lease lost with its connection in an outage is taken again this soon after the store
answers, the window in which a second service of the cell could start."""
SPAWN_RETRY_S = 1.0
"""How soon a worker process that could not be started (the service out of file descriptors, processes or
memory) is tried again [s]: a job waits in the queue for it, the warm spare is started again, and the
service takes jobs again by itself once the resources are back."""
WORKER_SILENT_S = 10 * WORKER_BEAT_S
"""How long a running job's worker may send nothing (no progress, no beat) before it is taken for hung and
stopped [s]: ten of its beats (``cell.service.protocol.WORKER_BEAT_S``). Its beat thread needs the
interpreter lock, which one long library call of the job can hold (an import, a mesh's ray cast): the
longest gap between two lines of a 60 s sim job of each shipped sim cell, beside another job and a test
run on a 2-core machine, was 1.1 s: five seconds of silence is no slow job."""
NO_VERDICT = frozenset({errno.EMFILE, errno.ENFILE, errno.ENOMEM, errno.EINTR})
"""The errors of a file made in the jobs folder that are no verdict on the folder (this process out of
descriptors or memory, a signal): every other one says it takes no job's recording (a permission, a
read-only or full file system, a folder gone, a failing disk (EIO), a stale or lost network mount
(ESTALE, ENOTCONN)), and jobs wait rather than each start and fail."""
JOB_DISK_MB = 200.0
"""Free space a job needs in the data dir to record [MB]. The largest recording a shipped cell makes is the
RGB-D one's: a 640 x 480 depth and colour frame is ~0.9 MB compressed in ``frames/`` (a 20 s sim-franka-rgbd
job left 18 in 16 MB), one per second of job time (``perception.rate_hz``), so its 180 s budget
(``scan.max_time_s``) records ~165 MB, plus its cloud, map and plots (~2 MB). Below it the next job waits
(the queue says why) rather than fail on a full disk, and the service warns at start."""
SHUTDOWN_CANCEL = "the service shut down before the job started"
SHUTDOWN_STOP = "the service is shutting down"
STOP_EFFECTS = {StopEffect.COMMANDED: "the arm was commanded to stop",
                StopEffect.BEFORE_MOTION: "the job had not moved yet: it stops before its first motion",
                StopEffect.AFTER_MOTION: "the job's motion had already ended: it was finishing its result"}
"""A running job's stop, in words, by what it did to the job's motion."""

log = logging.getLogger("cell.service")


@dataclass
class _Queued:
    """A job waiting: its record, what its worker loads, and who asked (``api`` or ``line``)."""

    job: JobRecord
    source: str
    origin: str


@dataclass
class _Running:
    """The job on the arm: its worker (None while it is being started), whether the worker said it
    started (it says so before it touches the arm), whether the first stop passed on to it, the one its
    job ends with, was one someone asked for (``requested``: an operator, the line, the shutdown; False:
    the service's own stop of a hung worker or after its own failure; None: no stop was passed on), a
    stop asked for while it was being started (``pending_stop``: its reason and whether it was requested,
    the pair ``JobControl`` keeps; until it is passed on once the worker has the job), the stop
    confirmations the worker owes, the stop its worker was killed for (it did not confirm in time, or had
    not started: its cause as the termination begins, ``operator stop: `` for a request but the
    shutdown's, ``shutdown stop: ``), its newest
    progress, its worker's last word, whether its end is recorded (the worker may still be exiting) and
    in the store (``stored``), whether it is ``stopping`` (its worker took a stop) and the write of that
    to its record (``stopping_write``), whether its ``running`` was published (``announced``), the stop
    of a worker taken for hung (``hung_stop``) and ``gone``, set once the worker has exited."""

    job: JobRecord
    origin: str
    proc: asyncio.subprocess.Process | None = None
    started: bool = False
    requested: bool | None = None
    pending_stop: tuple[str, bool] | None = None
    acks: deque[asyncio.Future[StopEffect]] = field(default_factory=deque)
    killed_for: str | None = None
    progress: dict[str, Any] | None = None
    ended: dict[str, Any] | None = None
    recorded: bool = False
    stored: bool = False
    stopping: bool = False
    announced: bool = False
    stopping_write: asyncio.Task[None] | None = None
    hung_stop: asyncio.Task[StopOutcome] | None = None
    gone: asyncio.Event = field(default_factory=asyncio.Event)

    @property
    def status(self) -> str:
        """The job's status as the service knows it: ``stopping`` once its worker took a stop, before its
        record may say so."""
        return "stopping" if self.stopping else "running"


@dataclass(frozen=True)
class StopOutcome:
    """What a stop did: the job it reached (None: nothing ran), whether that job's arm was commanded to
    stop before the answer (False: it had not moved yet, or its motion had ended), and in words."""

    job_id: str | None
    arm_commanded: bool
    message: str


def _now() -> datetime:
    return datetime.now(UTC)


def _exit_text(code: int) -> str:
    if code < 0:
        return f"killed by {signal.Signals(-code).name}"
    return f"exit code {code}"


def _drop_empty_logs(logs_dir: Path) -> None:
    """Delete the empty worker logs a previous run left (its service killed before it could, or a spare
    that never had a job): a log is kept only when its worker printed something (:func:`_drop_if_empty`)."""
    for log_path in logs_dir.glob("worker-*.log"):
        _drop_if_empty(log_path)


def _drop_if_empty(log_path: Path) -> None:
    """Delete the log of an ended worker process when it wrote nothing there. A job logs into its folder
    (``log.txt``); the worker's log (its standard error) holds only what the process printed besides, a
    crash's traceback or a library's messages, and is kept when there is any."""
    with contextlib.suppress(OSError):
        if log_path.stat().st_size == 0:
            log_path.unlink()


class CellService:
    """The service of one cell (see the module docstring). ``config_data`` is the cell file's parsed
    YAML, handed to each job's worker so that every job runs the file as it was when the service
    started."""

    def __init__(self, *, config: CellConfig, config_data: dict[str, Any], config_file: str, data_dir: Path,
                 store: Store, lease: CellLease | None = None,
                 data_dir_claim: DataDirClaim | None = None) -> None:
        self.config = config
        self.name = config.name
        self.instance = ""
        """The id of this start (``cell.service.instance``), drawn when it starts."""
        self._config_data = config_data
        self._config_file = config_file
        self.data_dir = data_dir
        self.jobs_dir = data_dir / "jobs"
        self._logs_dir = data_dir / "logs"
        self.store = store
        self._lease = lease
        self._data_dir_claim = data_dir_claim  # released last, in close
        self._lease_lost: str | None = None
        self._lease_keeper: asyncio.Task[None] | None = None
        self._arm_clearance = ArmClearance(config)
        self._search_views = SearchViews(config)
        self.objects = ObjectLibrary(data_dir / "objects", config, self._arm_clearance)
        self.retention = Retention(store, self.name, self.jobs_dir, config.service.retention)
        self._pruner: asyncio.Task[None] | None = None
        self.events = EventHub()
        self.arm = ArmTracker(config)
        self.metrics = ServiceMetrics(lambda: self.store.count_by_status(self.name),
                                      lambda: len(self._queued), lambda: self.hold_reason() is not None,
                                      lambda: self.store.damaged)
        self._queued: dict[str, _Queued] = {}
        self._running: _Running | None = None
        self._held: HoldRecord | None = None
        self._hold_writer: asyncio.Task[None] | None = None
        self._unrecordable: str | None = None  # why the next job waits: it could not record (_no_room)
        self._busy_with_arm = False
        self._closing = False
        self._submit_lock = asyncio.Lock()
        self._wake = asyncio.Event()
        self._dispatcher: asyncio.Task[None] | None = None
        self.line = LineController(self, config.line, store) if config.line is not None else None
        self.dio: DigitalIOHandshake | None = None  # the line's digital-I/O handshake (line.dio)
        self._spare: asyncio.subprocess.Process | None = None
        self._spare_log = self._logs_dir / "worker-spare.log"
        self._spare_watch: asyncio.Task[None] | None = None
        self._spare_loaded = False
        self._checks_loaded = False  # the dispatcher has loaded the placement checks: it starts jobs
        self._warming = False
        self._rewarm: asyncio.Task[None] | None = None
        self._warmer: asyncio.Task[None] | None = None
        self._spawn_failure: str | None = None
        self._broken: str | None = None
        # the next worker may load beside a running job only where no arm moves on the wall clock
        self._warm_beside_jobs = config.mode in ("sim", "replay")

    # ------------------------------------------------------------------ life

    async def start(self) -> list[str]:
        """Settle what a previous run left (``cell.service.recovery``), then take jobs. Returns what was
        settled, in words."""
        for folder in (self.jobs_dir, self._logs_dir):
            folder.mkdir(parents=True, exist_ok=True)
        self.instance = await asyncio.to_thread(new_instance, self.data_dir)
        settled = await asyncio.to_thread(reconcile, self.store, self.name,
                                          self.config.service.shutdown_timeout_s)
        # after the reconcile, which ended the workers of the previous run: none of them writes there now
        await asyncio.to_thread(_drop_empty_logs, self._logs_dir)
        self._held = await asyncio.to_thread(self.store.get_hold, self.name)
        if self._held is not None:
            log.warning("the queue is held since %s: %s", self._held.held_at.isoformat(), self._held.reason)
            if (fault := held_fault(self._held.reason)) is not None:  # held until the arm is recovered
                self.arm.latch(fault)
        if (short := await asyncio.to_thread(self._cannot_record)) is not None:
            log.warning("%s", short)
        if self.line is not None:
            await self.line.start()
            line_cfg, arm_cfg = self.config.line, self.config.arm
            assert line_cfg is not None
            if line_cfg.dio is not None and isinstance(arm_cfg, LinePinsConfig):  # a real or simulated UR5e
                self.dio = DigitalIOHandshake(self.line, arm_cfg, line_cfg.dio, digital_io(arm_cfg))
                self.dio.start()
        self._dispatcher = asyncio.create_task(self._dispatch(), name="dispatcher")
        if self.retention.active:
            self._pruner = asyncio.create_task(self.retention.run(), name="retention")
        if self._lease is not None:
            self._lease_keeper = asyncio.create_task(self._keep_lease(self._lease), name="lease")
        await self._warm()
        return settled

    def _load_checks(self) -> None:
        """Load what a submission's placement checks need (``validate``): the cell's collision world and
        the default planner's search views, with FCL, Open3D and the planner's modules (about a second).
        The dispatcher does so before it starts any job: importing them holds the GIL for up to 0.1 s at a
        time, which at a first submission could fall while a job runs and delay a STOP on the event loop;
        the line's first part then finds them loaded. The service answers meanwhile (``/healthz``), as it
        did before it loaded them."""
        self._arm_clearance.world()
        self._search_views.of(self.config.scan.planner)

    async def _keep_lease(self, lease: CellLease) -> None:
        """Check the cell's lease every ``LEASE_CHECK_S``; while it is lost, no queued job starts."""
        while True:
            await asyncio.sleep(LEASE_CHECK_S)
            lost = await asyncio.to_thread(lease.keep)
            if lease.taken and self._queued:
                # the service that took the cell settled its jobs (the queued ones cancelled): not ours now
                log.error("%d queued jobs left to the service that took the cell", len(self._queued))
                self._queued.clear()
            if lost != self._lease_lost:
                if lost is None:
                    log.warning("the cell's lease is held again: queued jobs may start")
                else:
                    log.error("%s", lost)
                self._lease_lost = lost
                self._wake.set()

    async def stop_for_shutdown(self) -> None:
        """The start of a shutdown, the arm first: no job starts from now and the running one is stopped
        (its arm commanded to stop before this returns). ``close`` begins with it; ``cell serve`` calls it
        as soon as a shutdown begins, before it waits for open requests (an event stream kept the arm
        moving 2 s longer). Once: later calls return at once."""
        if self._closing:
            return
        self._closing = True
        if self.line is not None:
            self.line.service_stopping(SHUTDOWN_STOP)
        running = self._running
        if running is not None:
            # its termination says the service was shut down (an operator's stop it is not); the arm
            # stops through the guard as for any requested stop
            stopped = await self._stop_running(running, f"{SERVICE_SHUTDOWN}{SHUTDOWN_STOP}")
            self._logged(stopped, SHUTDOWN_STOP)

    @property
    def closing(self) -> bool:
        """Whether the service has begun to shut down."""
        return self._closing

    async def close(self) -> None:
        """Shut down: queued jobs are cancelled, the running one is stopped and its folder finished."""
        await self.stop_for_shutdown()  # the arm first: nothing below may delay its stop
        for task in (self._pruner, self._lease_keeper):
            if task is not None:
                task.cancel()
        running = self._running
        if running is not None:
            proc = running.proc
            if proc is not None:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(proc.wait(), self.config.service.shutdown_timeout_s)
                if proc.returncode is None:
                    self._kill(proc)
        for job_id in list(self._queued):
            try:
                await self._cancel_queued(job_id, SHUTDOWN_CANCEL)
            except StoreError as exc:  # the next start cancels what the store still has queued
                log.warning("job left queued in the store, the service shutting down: %s", exc,
                            extra={"job_id": job_id})
        if self._dispatcher is not None:
            self._wake.set()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(self._dispatcher),
                                       self.config.service.shutdown_timeout_s)
            self._dispatcher.cancel()
        if self._warmer is not None:  # not cancelled: a spare it spawns as the service closes is closed
            try:
                await self._warmer
            except Exception:  # a spare that failed to start leaves the rest of the close to do
                log.exception("the next job's worker failed to start")
        if self._rewarm is not None:
            self._rewarm.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._rewarm
        await self._close_spare()
        if self._hold_writer is not None:  # a hold written a moment ago outlives this run
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(self._hold_writer),
                                       self.config.service.shutdown_timeout_s)
        if self.dio is not None:
            await self.dio.close()
        if self.line is not None:
            await self.line.close()
        if self._lease is not None:
            self._lease.release()
        if self._data_dir_claim is not None:
            self._data_dir_claim.release()

    @property
    def ready(self) -> bool:
        """Taking jobs: started, its job dispatcher running and not shutting down."""
        return self._dispatcher is not None and not self._dispatcher.done() and not self._closing

    @property
    def warm_worker(self) -> str:
        """The next job's warm worker (``service.warm_worker``), for ``/readyz``: ``off`` (not configured),
        ``none`` (not started: a job runs on a cell that warms none beside it, or it could not be started),
        ``loading`` (importing its libraries: a job given it now waits for them), ``loaded`` (waiting for
        a job, which then starts without the imports)."""
        if not self.config.service.warm_worker:
            return "off"
        if self._spare is None:
            return "none"
        return "loaded" if self._spare_loaded else "loading"

    @property
    def placement_checks(self) -> str:
        """Whether the dispatcher has loaded the placement checks (:meth:`_load_checks`), for ``/readyz``:
        ``loading`` (a job submitted now starts once they are loaded, about a second after the start) or
        ``loaded`` (it waits for queued jobs)."""
        return "loaded" if self._checks_loaded else "loading"

    @property
    def broken(self) -> str | None:
        """Why the service can run no job until it is restarted (its job dispatcher ended on an error), in
        words, or None. The systemd watchdog's pings stop then (``cell.api.server``)."""
        return self._broken

    # ------------------------------------------------------------------ reading

    def status(self) -> dict[str, Any]:
        """The cell now (no database, no device: safe to poll). A job whose end is recorded is no longer
        the running one, though its worker may still be exiting."""
        # shown until its end is in the store: the job's record says `running` until then
        running = self._running if self._running is not None and not self._running.stored else None
        cfg = self.config
        # a hardware sensor is connected by each job: it is known to deliver once a job has a frame
        sensor_up = cfg.sensor.type.startswith("sim-") or (running is not None
                                                           and running.progress is not None)
        return {
            "name": self.name, "mode": cfg.mode, "version": __version__, "max_time_s": cfg.scan.max_time_s,
            "arm": {"type": cfg.arm.type, "model": cfg.arm.model, **self.arm.status.as_dict()},
            "sensor": {"type": cfg.sensor.type, "connected": sensor_up},
            "job": None if running is None else {
                "id": running.job.id, "status": running.status,
                "planner": running.job.planner, "part_id": running.job.part_id, "progress": running.progress},
            "queue": {"length": len(self._queued), "max": self.config.service.queue_max,
                      "held": self.hold_reason() or self._waiting_for_resources(),
                      "held_at": None if self._held is None else self._held.held_at},
            "line": None if self.line is None else self.line.snapshot().as_dict(),
        }

    def hold_reason(self) -> str | None:
        """Why queued jobs do not start, or None."""
        if self.store.damaged:  # first: neither a resume nor an arm recovery helps
            return RESTORE
        if self.store.lost is not None:  # nor here: what a job records now would be lost
            return self.store.lost
        if self.arm.faulted:
            return f"arm {self.arm.status.state}: recover the arm first (POST /api/v1/arm/recover)"
        return self._broken or self._lease_lost or (None if self._held is None else self._held.reason)

    def _waiting_for_resources(self) -> str | None:
        """Why the next job waits though nothing holds the queue: no worker process could be started for
        it, or it could not record in the jobs folder (:meth:`_cannot_record`; both tried again every
        ``SPAWN_RETRY_S``), or None."""
        return self._spawn_failure or self._unrecordable if self._queued and self._running is None else None

    def not_ready(self) -> str | None:
        """Why a job submitted now would not run, in words (for ``/readyz``), or None: starting or shutting
        down, the queue held, no worker process can be started, the jobs folder not writable or without
        room for a job. Reads no database and no device: the route checks the store first, also whether
        its file is still the one opened (``Store.check_file``, which latches a deleted one, holding the
        queue)."""
        if not self.ready:
            return "not taking jobs (starting or shutting down)"
        if (held := self.hold_reason()) is not None:
            return f"the queue is held: {held}"
        if self._spawn_failure is not None:
            return self._spawn_failure
        return self._cannot_record()

    def _cannot_record(self) -> str | None:
        """Why a job could not record in the jobs folder now, or None: the folder takes no file (one made
        and dropped there says so, also for root, whom permissions do not stop, and on a file system
        mounted read-only), or the data dir has not the room a job needs (:meth:`_disk_short`)."""
        try:
            tempfile.TemporaryFile(dir=self.jobs_dir).close()  # no name on Linux: retention never sees it
        except OSError as exc:
            if exc.errno not in NO_VERDICT:  # out of descriptors or memory: the job's own start says
                return (f"the jobs folder {self.jobs_dir} is not writable ({exc.strerror or exc}): no job "
                        "could record; make it writable: jobs start again once it is")
        return self._disk_short()

    def _disk_short(self) -> str | None:
        """``disk full under <data dir>: N MB free`` when the data dir has less room than a job needs
        (:data:`JOB_DISK_MB`), else None (also when its free space cannot be read: the job then says)."""
        try:
            free_mb = shutil.disk_usage(self.jobs_dir).free / 1e6
        except OSError:
            return None
        if free_mb >= JOB_DISK_MB:
            return None
        return (f"disk full under {self.data_dir}: {free_mb:.0f} MB free, a job needs {JOB_DISK_MB:.0f} MB "
                "to record; free space or set service.retention: jobs start again once there is room")

    def planners(self) -> list[dict[str, str | bool]]:
        return [{"name": name, "description": entry.description, "default": name == self.config.scan.planner}
                for name, entry in sorted(PLANNERS.items())]

    async def job(self, job_id: str) -> JobRecord:
        """A job of this cell, with the running job's newest progress and its ``stopping`` before its record
        has it; ``ServiceError`` (not found)."""
        job = await asyncio.to_thread(self.store.get_job, job_id)
        if job is None or job.cell != self.name:
            raise ServiceError(f"no job {job_id!r} on cell {self.name!r}", reason="not found")
        running = self._running
        job = self.as_now(job)
        if running is None or running.job.id != job_id or running.progress is None:
            return job
        return dataclasses.replace(job, progress=running.progress)

    def as_now(self, job: JobRecord) -> JobRecord:
        """``job`` read from the store, ``stopping`` when it is the running job and its worker has taken a
        stop whose write to its record may still be under way (:meth:`_mark_stopping`); safe to call from
        a worker thread (it only reads the running job)."""
        running = self._running
        if running is None or running.job.id != job.id or job.status != "running":
            return job
        return dataclasses.replace(job, status=running.status)

    async def job_events(self, job_id: str) -> JobEvents:
        """The job's event log; for a job this run of the service has not seen (it ended before a
        restart), one made of its final state and result."""
        log = self.events.get(job_id)
        if log is not None:
            return log
        job = await self.job(job_id)
        log = self.events.log(job_id)
        log.publish("state", {"status": job.status, "termination": job.termination})
        if job.status in FINISHED_STATUSES:
            log.publish("result", {"status": job.status, "result": job.result})
        return log

    # ------------------------------------------------------------------ submitting and cancelling

    async def submit(self, request: JobRequest, submitted_by: str | None, origin: str = "api") -> JobRecord:
        """Validate and queue a job from ``origin`` (``api``: an operator; ``line``: the packing line's
        Start); ``ServiceError`` when invalid (naming the field), when the queue is full, while shutting
        down, for an operator's job while the line owns the cell (Production mode), and (``unavailable``)
        when the store's file was deleted (``Store.check_file``)."""
        if origin == "api" and self.line is not None and self.line.owns_cell:
            raise ServiceError(f"the packing line owns the cell (PackML {self.line.mode.label} mode, "
                               f"{self.line.state.label}): operator jobs run in Manual mode (POST "
                               "/api/v1/line/mode)", reason="conflict")
        valid: ValidJob = await asyncio.to_thread(validate, self.config, self.objects, self._arm_clearance,
                                                  self._search_views, request)
        if (lost := await asyncio.to_thread(self.store.check_file)) is not None:
            raise ServiceError(lost, reason="unavailable")
        async with self._submit_lock:
            if self._closing:
                raise ServiceError("the service is shutting down", reason="conflict")
            limit = self.config.service.queue_max
            if len(self._queued) >= limit:
                # while the queue is held nothing starts by itself: waiting would not help
                held = self.hold_reason()
                advice = ("; try again when one has started" if held is None
                          else f" and held, so none starts by itself: {held}")
                raise ServiceError(f"the queue is full: {len(self._queued)} jobs wait (service.queue_max "
                                   f"{limit}){advice}", reason="queue full")
            job_id = secrets.token_hex(8)
            job = JobRecord(id=job_id, cell=self.name, status="queued", planner=valid.planner,
                            object=valid.object, object_pose=valid.object_pose, seed=valid.seed,
                            max_time_s=valid.max_time_s, part_id=valid.part_id,
                            folder=str((self.jobs_dir / job_id).resolve()), submitted_by=submitted_by,
                            created_at=_now())
            await asyncio.to_thread(self.store.add_job, job)
            self._queued[job_id] = _Queued(job, valid.object_source, origin)
        log.info("job queued: %s, planner %s, seed %d, from %s", job.object or "unknown object", job.planner,
                 job.seed, submitted_by or origin, extra={"job_id": job_id, "part_id": job.part_id})
        self.events.log(job_id).publish("state", {"status": "queued", "termination": None})
        self._wake.set()
        return job

    async def cancel(self, job_id: str, reason: str) -> JobRecord:
        """Cancel a queued job; ``ServiceError`` (conflict) for a job that is not queued."""
        if job_id not in self._queued:
            job = await self.job(job_id)
            raise ServiceError(f"job {job_id} is {job.status}, not queued: "
                               + ("stop it instead" if job.status in RUNNING_STATUSES else "it has ended"),
                               reason="conflict")
        return await self._cancel_queued(job_id, reason)

    async def _cancel_queued(self, job_id: str, reason: str) -> JobRecord:
        """Cancel a queued job; ``StoreError`` when the store does not take it (the job stays queued, where
        it was)."""
        order = list(self._queued)
        queued = self._queued.pop(job_id)  # out of the dispatcher's reach while the store is written
        try:
            job = await asyncio.to_thread(self.store.update_job, job_id, status="cancelled",
                                          termination=reason, finished_at=_now())
        except StoreError:
            self._queued[job_id] = queued
            self._queued = {k: self._queued[k] for k in order if k in self._queued} | self._queued
            raise
        log.info("job cancelled: %s", reason, extra={"job_id": job_id, "status": "cancelled"})
        events = self.events.log(job_id)
        events.publish("state", {"status": "cancelled", "termination": reason})
        events.publish("result", {"status": "cancelled", "result": None})
        if self.line is not None:
            self.line.job_ended(job_id, "cancelled", reason, None)
        return job

    async def purge(self, job_id: str) -> None:
        """Delete an ended job: its folder and its record (admin)."""
        job = await self.job(job_id)
        if job.status not in FINISHED_STATUSES:
            raise ServiceError(f"job {job_id} is {job.status}: cancel or stop it first", reason="conflict")
        await asyncio.to_thread(delete_job, self.store, job, self.jobs_dir)
        log.info("job deleted with its folder", extra={"job_id": job_id})

    async def set_keep(self, job_id: str, keep: bool) -> JobRecord:
        """Mark a job kept (retention never deletes it) or not; ``ServiceError`` (not found)."""
        await self.job(job_id)
        job = await asyncio.to_thread(self.store.update_job, job_id, keep=keep)
        log.info("job %s", "kept" if keep else "no longer kept", extra={"job_id": job_id})
        return job

    # ------------------------------------------------------------------ stopping

    async def stop_job(self, job_id: str, reason: str, *, may_cancel: bool = True) -> StopOutcome:
        """Stop one job: a running one through its worker (the arm is commanded to stop before this
        returns), a queued one is cancelled, when ``may_cancel`` (a caller whose key may stop but not
        cancel: ``ServiceError``, forbidden)."""
        if job_id in self._queued:
            if not may_cancel:
                raise ServiceError(f"job {job_id} has not started: its stop would cancel it, which needs a "
                                   "key that may cancel (every key may stop a running job)",
                                   reason="forbidden")
            await self._cancel_queued(job_id, f"cancelled before it started: {reason}")
            return StopOutcome(job_id, False, "the job had not started: cancelled")
        running = self._running
        if running is None or running.job.id != job_id or running.stored:
            # a job whose end is in the store is answered as its record says, also while its worker exits;
            # before, its stop is answered "had already ended" (the line moves on at the job's end)
            job = await self.job(job_id)
            raise ServiceError(f"job {job_id} is {job.status}: nothing to stop", reason="conflict")
        return self._logged(await self._stop_running(running, reason), reason)

    async def stop_all(self, reason: str) -> StopOutcome:
        """The operator's STOP: hold the queue and stop the running job, if any; the line, if wired, is
        stopped too (Stopping, then Stopped)."""
        if self.line is not None:
            self.line.operator_stop(reason)
        self._hold(f"a stop ({reason})")
        running = self._running
        if running is None:
            return self._logged(StopOutcome(None, False, "nothing was moving; the queue is held"), reason)
        return self._logged(await self._stop_running(running, reason), reason)

    def _hold(self, after: str) -> None:
        """Hold the queue until an operator resumes it (never the line's Reset: a person looks first), also
        across restarts: the hold is written to the store beside (:meth:`_write_hold`), never before a
        stop. A hold for an arm fault still latched keeps its reason first (:func:`fault_first`), the new
        one after it: a STOP pressed after the fault does not free the arm from its recovery, nor the
        recovery the queue from the STOP."""
        reason, since = held_after(after), _now()
        if self._held is not None and held_fault(self._held.reason) is not None and self.arm.faulted:
            # the arm's fault stays what the hold is for, also across a restart (it is latched again then)
            reason, since = fault_first(self._held.reason, reason), self._held.held_at
        self._held = HoldRecord(cell=self.name, reason=reason, held_at=since)
        self._write_hold()

    def _write_hold(self) -> None:
        """Have the queue's hold as it is now written to the store, by one task at a time so that the
        writes land in order (a change meanwhile is written after the one under way)."""
        if self._hold_writer is None or self._hold_writer.done():
            self._hold_writer = asyncio.create_task(self._hold_written(), name="queue hold")

    async def _hold_written(self) -> None:
        while True:
            wanted = self._held
            if not await until_stored(functools.partial(self.store.set_hold, self.name, wanted),
                                      "the queue's hold", lambda: self._closing, log):
                return
            if self._held is wanted:
                return

    @staticmethod
    def _logged(outcome: StopOutcome, reason: str) -> StopOutcome:
        """``outcome``, logged once the stop was passed on (the log never delays a stop)."""
        log.warning("stop (%s): %s", reason, outcome.message, extra={"job_id": outcome.job_id})
        return outcome

    def resume(self) -> None:
        """Let queued jobs start again after a STOP; ``ServiceError`` (conflict) while the arm is faulted or
        the store damaged or its file lost."""
        if self.arm.faulted or self.store.damaged or self.store.lost is not None:
            raise ServiceError(self.hold_reason() or "the arm is faulted", reason="conflict")
        if self._held is not None:
            log.warning("the queue is resumed (it was %s)", self._held.reason)
            self._held = None
            self._write_hold()
        self._wake.set()

    def operator_jobs(self) -> bool:
        """Whether an operator's job waits or runs."""
        running = self._running
        return any(q.origin == "api" for q in self._queued.values()) or (
            running is not None and running.origin == "api")

    async def _stop_running(self, running: _Running, reason: str, *, requested: bool = True) -> StopOutcome:
        """Stop the running job through its worker, whose guard stops the arm and ends the job ``operator
        stop: <reason>`` when someone asked for the stop (``requested``: an operator, the line; the
        shutdown's reason says ``shutdown stop:`` itself and stays so), else ``safety stop: <reason>``
        (the service stops the job itself: a hung worker that answers after all, its own failure; the line
        reads StopReason 4, not 2). A worker that cannot confirm is killed, and its job ends as the stop's
        cause says, the kill added: an operator's stop read as a safety stop when its worker was killed."""
        self.metrics.stop_requests.inc()
        job_id, proc = running.job.id, running.proc
        if proc is None:
            if running.pending_stop is None:
                running.pending_stop = (reason, requested)
            return StopOutcome(job_id, False, "the job was starting: it stops before its first motion")
        # first, a "started" the worker sent is read, and a stop in flight beside this one (the line's,
        # behind an operator's) goes on to its kill, if any
        await asyncio.sleep(0)
        if running.ended is not None or proc.returncode is not None or running.killed_for is not None:
            # a worker killed for an earlier stop keeps that stop's cause, as JobControl keeps the first
            return StopOutcome(job_id, False, "the job had already ended")
        if running.requested is None:  # the worker's JobControl keeps the first stop it is given
            running.requested = requested
        cause = stop_cause(reason, requested)
        if not running.started:
            # still loading its libraries, it cannot answer for seconds, and it has not touched the arm:
            # ended now, the stop takes milliseconds rather than the confirmation's timeout and a kill
            running.killed_for = f"{cause} (ended while its worker was starting, before any motion)"
            self._kill(proc)
            self._mark_stopping(running)
            return StopOutcome(job_id, False, "the job's worker was still starting: it was ended before "
                                              "any motion")
        ack: asyncio.Future[StopEffect] = asyncio.get_running_loop().create_future()
        running.acks.append(ack)
        try:
            assert proc.stdin is not None
            proc.stdin.write(stop_command(reason, operator=requested))
            await proc.stdin.drain()
            effect = await asyncio.wait_for(asyncio.shield(ack), self.config.service.stop_confirm_timeout_s)
        except (BrokenPipeError, ConnectionResetError):
            return StopOutcome(job_id, False, "the job's worker had already ended")
        except TimeoutError:
            if running.killed_for is None:  # the first stop that timed out names the kill
                running.killed_for = (f"{cause} (the job's worker did not confirm the stop in "
                                      f"{self.config.service.stop_confirm_timeout_s:g} s and was killed)")
                # the arm was not stopped through the guard but by its connection watchdog: a person looks
                # before the next job moves it, as after a worker that died
                self._hold(f"a stop its job's worker did not confirm ({running.killed_for}); check the arm")
            self._kill(proc)
            self._mark_stopping(running)
            return StopOutcome(job_id, False, "the job's worker did not confirm the stop in "
                               f"{self.config.service.stop_confirm_timeout_s:g} s and was killed; the arm's "
                               "connection watchdog stops the arm")
        if effect is not StopEffect.AFTER_MOTION:  # a job whose motion had ended may still complete
            self._mark_stopping(running)
        return StopOutcome(job_id, effect is StopEffect.COMMANDED, STOP_EFFECTS[effect])

    def _mark_stopping(self, running: _Running) -> None:
        """Say that the running job is ``stopping`` (its worker has taken the stop, the arm commanded to
        stop or not moved yet, or it was killed) until its worker has written how it ended, so that nothing
        read after the stop's answer shows it ``running``: at once in the cell's state, :meth:`job` and its
        events (after its ``running``), and in its record by a write beside, which the stop's answer does
        not wait for (a store that is slow or does not answer would have held it for its timeout; one that
        does not take the write leaves the record ``running``, logged; the arm was stopped before either
        way)."""
        if running.stopping or running.recorded:
            return
        running.stopping = True
        if running.announced:
            self._publish_stopping(running)
        running.stopping_write = asyncio.create_task(self._write_stopping(running.job.id), name="stopping")

    def _publish_stopping(self, running: _Running) -> None:
        self.events.log(running.job.id).publish("state", {"status": "stopping", "termination": None})

    async def _write_stopping(self, job_id: str) -> None:
        """The record's ``stopping`` (:meth:`_mark_stopping`); a record whose end was stored first stays as
        it is (``Store.mark_stopping`` changes only a ``running`` one)."""
        try:
            await asyncio.to_thread(self.store.mark_stopping, job_id)
        except StoreError as exc:
            log.warning("the job's record still says running: %s", exc, extra={"job_id": job_id})

    @staticmethod
    def _kill(proc: asyncio.subprocess.Process) -> None:
        """End a worker and its children (an arm driver's own process) at once."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)

    async def _reap(self, proc: asyncio.subprocess.Process) -> None:
        """Let a worker that nobody else reads end: its input is closed, its output read to the end and
        its exit awaited; after ``service.stop_confirm_timeout_s`` it is killed. Its pipes are then closed
        while the event loop runs: a pipe left open is closed by the garbage collector, on a loop that
        may have ended (``wait`` alone returns at the exit, often before the loop has read the output's
        end)."""
        try:
            await asyncio.wait_for(proc.communicate(), self.config.service.stop_confirm_timeout_s)
        except TimeoutError:
            self._kill(proc)
            await proc.communicate()

    # ------------------------------------------------------------------ the arm

    async def recover_arm(self) -> dict[str, Any]:
        """Operator action after a fault: a hardware arm is connected by a worker, recovered and
        disconnected; a simulated arm has only its latched fault cleared (each job gets a fresh one).
        ``ServiceError`` (conflict) while a job owns the arm."""
        running = self._running
        if running is not None and running.recorded:  # the job has ended: its worker is letting go
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(running.gone.wait(), self.config.service.shutdown_timeout_s)
        if self._running is not None or self._busy_with_arm:
            raise ServiceError("a job owns the arm: stop it first", reason="conflict")
        if self.config.arm.type == "sim":
            self.arm.recovered([], None)
            self._release_fault_hold()
            return {"ok": True, "message": "recovered (simulated arm)", "arm": self.arm.status.as_dict()}
        self._busy_with_arm = True
        try:
            report = await self._recover_in_worker()
        finally:
            self._busy_with_arm = False
        if report.get("arm") is not None:
            self.arm.recovered(report["arm"]["faults"], report["arm"]["T_base_flange"])
        self._release_fault_hold()
        return {"ok": bool(report.get("ok")), "message": str(report.get("message")),
                "arm": self.arm.status.as_dict()}

    def _release_fault_hold(self) -> None:
        """After a recovery: release the queue's hold for an arm fault (``fault_hold``) once the arm has
        none, in the store too; a hold of another kind (a STOP), also one that came after the fault
        (:func:`after_fault`), waits for the operator's resume."""
        if not self.arm.faulted and self._held is not None and held_fault(self._held.reason) is not None:
            rest = after_fault(self._held.reason)
            if rest is None:
                log.warning("the queue is released: the arm was recovered (%s)", self._held.reason)
                self._held = None
            else:
                log.warning("the arm was recovered (%s); the queue stays held until resumed: %s",
                            self._held.reason, rest)
                self._held = HoldRecord(cell=self.name, reason=rest, held_at=self._held.held_at)
            self._write_hold()
        self._wake.set()

    async def _recover_in_worker(self) -> dict[str, Any]:
        spec = WorkerSpec(op="recover", job_id="recover", config=self._config_data,
                          config_file=self._config_file)
        log_path = self._logs_dir / "worker-recover.log"
        proc = await self._worker(log_path, spec.job_id)
        if proc is None:
            return {"ok": False, "message": f"the arm was not recovered: {self._spawn_failure}"}
        await self._hand(proc, spec)
        assert proc.stdout is not None
        report: dict[str, Any] = {"ok": False, "message": "the recovery worker ended without an answer"}
        try:
            async with asyncio.timeout(RECOVER_TIMEOUT_S):
                while line := await proc.stdout.readline():
                    message = json.loads(line)
                    if message.get("type") == "recovered":
                        report = message
        except TimeoutError:
            report = {"ok": False, "message": f"the arm did not recover within {RECOVER_TIMEOUT_S:g} s"}
            self._kill(proc)
        await self._reap(proc)
        _drop_if_empty(log_path)
        return report

    # ------------------------------------------------------------------ running jobs

    async def _start_worker(self, log_path: Path, label: str) -> asyncio.subprocess.Process:
        with log_path.open("ab") as log:
            return await asyncio.create_subprocess_exec(
                sys.executable, "-m", WORKER_MODULE, "--job", label,
                stdin=asyncio.subprocess.PIPE,
                stdout=asyncio.subprocess.PIPE, stderr=log, start_new_session=True, limit=LINE_LIMIT)

    async def _spawn(self, log_path: Path, label: str) -> asyncio.subprocess.Process | None:
        """A new worker process for ``label``, or None when it could not be started (its log file or the
        process itself: out of file descriptors, processes or memory). A failure is logged in one line
        when it begins or changes, and once workers start again; the caller tries again in
        ``SPAWN_RETRY_S``."""
        try:
            proc = await self._start_worker(log_path, label)
        except OSError as exc:
            # the reason without the file it names (a new log file each try): the same failure, one line
            failure = (f"a worker process could not be started ({type(exc).__name__}: "
                       f"{exc.strerror or exc}); trying again every {SPAWN_RETRY_S:g} s")
            if failure != self._spawn_failure:
                log.error("%s", failure, extra={"job_id": None if label in ("spare", "recover") else label})
            self._spawn_failure = failure
            return None
        if self._spawn_failure is not None:
            log.warning("worker processes start again")
            self._spawn_failure = None
        return proc

    async def _worker(self, log_path: Path, label: str, *,
                      warm: bool = False) -> asyncio.subprocess.Process | None:
        """A worker for a job (``label``): the warm spare when ``warm`` and one is ready (its log renamed
        to ``log_path``), else a new process, or None when none could be started (:meth:`_spawn`). It
        waits for its spec (:meth:`_hand`)."""
        proc, self._spare = (self._spare, None) if warm else (None, self._spare)
        spare_log = self._spare_log  # a next spare may start while this one's watch ends
        if proc is not None:
            await self._stop_watching_spare()  # the job's follower reads its output from here on
        if proc is not None and proc.returncode is None:
            os.replace(spare_log, log_path)
            return proc
        if proc is not None:  # the spare died waiting (its log says why)
            await self._reap(proc)
        return await self._spawn(log_path, label)

    @staticmethod
    async def _hand(proc: asyncio.subprocess.Process, spec: WorkerSpec) -> None:
        """Give a worker its job: it starts at once."""
        assert proc.stdin is not None
        proc.stdin.write(spec.line())
        await proc.stdin.drain()

    def _wants_spare(self) -> bool:
        """Whether the next job's worker should be started now (``service.warm_worker``): none is ready,
        and no job runs or the cell warms it beside a running job (sim and replay)."""
        return (self.config.service.warm_worker and not self._closing and self._spare is None
                and (self._running is None or self._warm_beside_jobs))

    async def _warm(self) -> None:
        """Start the next job's worker now, if it should be (:meth:`_wants_spare`): it loads its libraries
        and waits. Never raises: a worker that could not be started is tried again every
        ``SPAWN_RETRY_S`` by a task of its own while one is wanted (a job's end wants one again)."""
        if await self._spawn_spare():
            return
        if self._rewarm is None or self._rewarm.done():
            self._rewarm = asyncio.create_task(self._warm_again(), name="warm worker")

    def _warm_beside(self) -> None:
        """:meth:`_warm` beside a job that has just been announced, by a task of its own (awaited at the
        shutdown): the spare's spawn (a fork and exec, milliseconds to a loaded machine's tenths of a
        second) never stands between a job's worker having its job and the service reading that it
        started, and a stop waits for no worker's start."""
        if self._warmer is None or self._warmer.done():
            self._warmer = asyncio.create_task(self._warm(), name="warm worker beside a job")

    async def _warm_again(self) -> None:
        while self._wants_spare():
            await asyncio.sleep(SPAWN_RETRY_S)
            if await self._spawn_spare():
                return

    async def _spawn_spare(self) -> bool:
        """Start the spare if one is wanted; False when it could not be started."""
        if self._warming or not self._wants_spare():
            return True
        self._warming = True  # one start at a time: the dispatcher's and the retrying task's
        try:
            log_path = self._logs_dir / f"worker-spare-{secrets.token_hex(4)}.log"
            spare = await self._spawn(log_path, "spare")
        finally:
            self._warming = False
        if spare is not None:
            self._spare_log, self._spare = log_path, spare
            self._spare_watch = asyncio.create_task(self._watch_spare(spare), name="warm worker loading")
            if self._closing:  # the service began to shut down meanwhile
                await self._close_spare()
        return spare is not None

    async def _watch_spare(self, spare: asyncio.subprocess.Process) -> None:
        """Read the spare's first line: its ``loaded`` notice (``cell.service.protocol``) makes
        :attr:`warm_worker` ``loaded``. Cancelled when a job takes the spare or it is closed."""
        assert spare.stdout is not None
        with contextlib.suppress(ValueError):  # an end of file, or a line too long or not JSON
            message = json.loads(await spare.stdout.readline())
            self._spare_loaded = isinstance(message, dict) and message.get("type") == "loaded" \
                and self._spare is spare

    async def _stop_watching_spare(self) -> None:
        """End :meth:`_watch_spare` (a line it has not read stays for the next reader)."""
        watch, self._spare_watch, self._spare_loaded = self._spare_watch, None, False
        if watch is not None and not watch.done():
            watch.cancel()
            await asyncio.wait({watch})

    async def _close_spare(self) -> None:
        """End the warm spare at once: it holds no job and no arm, and it would read the end of its input
        only once its libraries are loaded (seconds). Its pipes are then closed as :meth:`_reap` does."""
        spare, self._spare = self._spare, None
        if spare is None:
            return
        await self._stop_watching_spare()
        self._kill(spare)
        await spare.communicate()
        _drop_if_empty(self._spare_log)

    def _may_start(self) -> bool:
        return bool(self._queued) and self._running is None and self.hold_reason() is None \
            and not self._busy_with_arm and not self._closing

    async def _dispatch(self) -> None:
        """Start queued jobs one at a time, until the service shuts down. An error it did not expect ends
        it: logged, the service then not ready (``/readyz`` 503), its queue held saying so, and the systemd
        watchdog's pings stopped (:attr:`broken`), rather than jobs queued for ever in silence. No job
        starts before the placement checks are loaded (:meth:`_load_checks`)."""
        try:
            await asyncio.to_thread(self._load_checks)
            self._checks_loaded = True
            await self._dispatch_jobs()
        except Exception as exc:
            self._broken = (f"the job dispatcher stopped on an error ({type(exc).__name__}: {exc}): no job "
                            "starts until the service is restarted")
            log.critical("%s", self._broken, exc_info=True)

    async def _dispatch_jobs(self) -> None:
        while not self._closing:
            await self._wake.wait()
            self._wake.clear()
            while self._may_start():
                if await self._no_room():
                    asyncio.get_running_loop().call_later(SPAWN_RETRY_S, self._wake.set)
                    break
                if not self._may_start():  # the queue changed while the jobs folder was looked at
                    break
                job_id = next(iter(self._queued))
                queued = self._queued.pop(job_id)
                running = self._running = _Running(queued.job, queued.origin)
                try:
                    retry_s = await self._run(running, queued.source)
                except Exception as exc:  # the job fails, the service goes on with the next
                    log.exception("job %s could not be run", job_id)
                    proc = running.proc
                    if proc is not None and proc.returncode is None:  # not left moving on its own
                        self._kill(proc)
                        await self._reap(proc)
                    await self._finish(running, None, f"the service could not run the job: "
                                                      f"{type(exc).__name__}: {exc}")
                    continue
                if retry_s is not None:  # the job waits, first in the queue, and is tried again
                    self._running = None
                    running.gone.set()
                    self._queued = {job_id: queued, **self._queued}
                    if running.pending_stop is not None:  # and a stop of it came meanwhile
                        self._hold(f"a stop ({running.pending_stop[0]})")
                    asyncio.get_running_loop().call_later(retry_s, self._wake.set)
                    break

    async def _no_room(self) -> bool:
        """Whether a job could not record now (:meth:`_cannot_record`, on a thread: a file made in the jobs
        folder, which a hung network mount would make the event loop wait for: the jobs folder not
        writable, or the data dir without the room a job needs); logged in one line when that begins or
        changes, and once a job can record again."""
        short = await asyncio.to_thread(self._cannot_record)
        if short != self._unrecordable:
            if short is not None:
                log.error("%s", short)
            else:
                log.warning("the jobs folder takes a job's recording again")
            self._unrecordable = short
        return short is not None

    async def _run(self, running: _Running, source: str) -> float | None:
        """Run the job to its end (None). When it did not start, how soon to try again [s]: its worker
        could not be started, or the store did not record its start (its worker is then ended before it
        had the job: nothing moved). Once its worker has the job, the job is followed to its end: an
        error of the service meanwhile stops it through its worker (:meth:`_follow`)."""
        job = running.job
        spec = WorkerSpec(op="scan", job_id=job.id, config=self._config_data, config_file=self._config_file,
                          object=source, object_pose=job.object_pose or (0.0, 0.0, 0.0),
                          planner=job.planner, seed=job.seed, max_time_s=job.max_time_s, folder=job.folder,
                          part_id=job.part_id, submitted_by=job.submitted_by)
        log_path = self._logs_dir / f"worker-{job.id}.log"
        proc = await self._worker(log_path, job.id, warm=True)
        if proc is None:
            return SPAWN_RETRY_S
        try:
            # recorded before the worker has its job: a job that moves the arm is always `running` in
            # the store, with the worker a restart settles
            running.job = await asyncio.to_thread(self.store.update_job, job.id, status="running",
                                                  started_at=_now(), worker_pid=proc.pid)
        except StoreError as exc:
            log.warning("job not started: %s", exc, extra={"job_id": job.id})
            self._kill(proc)
            await self._reap(proc)
            _drop_if_empty(log_path)
            return STORE_RETRY_S
        await self._hand(proc, spec)
        running.proc = proc  # a stop that came before is carried out below, after the spec
        try:
            code = await self._follow(running)
        except Exception as exc:
            failure = f"the service failed while it ran the job ({type(exc).__name__}: {exc})"
            log.exception("job %s: %s; it is stopped through its worker", job.id, failure)
            # an error before the job was announced or its pending stop passed on: both first, so that
            # the job reads running, then stopping, and a stop someone asked for stays the first one
            try:
                await self._announce(running)
            except Exception:  # the same error again: the job is stopped all the same, below
                log.exception("job %s: the announce failed again", job.id)
            reason, requested = running.pending_stop or (failure, False)
            running.pending_stop = None
            follower = asyncio.create_task(self._follow(running))
            await self._stop_running(running, reason, requested=requested)
            code = await follower
        await self._finish(running, code)
        _drop_if_empty(log_path)
        return None

    async def _follow(self, running: _Running) -> int:
        """Follow a job whose worker has it to its end (its worker's exit code), taking each line the
        worker sends, once the job is announced (:meth:`_announce`; a second follower follows after an
        error of the first, :meth:`_run`)."""
        job, proc = running.job, running.proc
        assert proc is not None and proc.stdout is not None
        await self._announce(running)
        while line := await self._next_line(running, proc.stdout):
            try:
                message = finite_json(json.loads(line))
            except ValueError:
                log.warning("job %s: a malformed line from its worker: %r", job.id, line[:200])
                continue
            self._take(running, message)
            if running.ended is not None and not running.recorded:
                await self._record_end(running)
        return await proc.wait()

    async def _announce(self, running: _Running) -> None:
        """Say that the job runs, as soon as its worker has it and before anything is awaited (the worker
        may move the arm within milliseconds, and a stop in between must reach it through its guard, read
        as a stop of a running job), then pass on a stop asked for while it was being started
        (``pending_stop``: its worker had not had the job, so it cannot have moved; ended at once).
        Each once, by the job's first follower or, after an error of the follower before it got there, by
        :meth:`_run`. The next job's worker is then started beside, by a task (:meth:`_warm_beside`): its
        spawn comes after the announce, and holds the loop only for its fork and exec (5-15 ms measured on
        a loaded machine), not for the worker's start."""
        job, proc = running.job, running.proc
        assert proc is not None
        if not running.announced:
            self.arm.job_started()
            log.info("job started (worker %d)", proc.pid, extra={"job_id": job.id, "part_id": job.part_id})
            # before a stop passed on below: its `stopping` follows `running`
            self.events.log(job.id).publish("state", {"status": "running", "termination": None})
            running.announced = True
            self._warm_beside()
        if running.pending_stop is not None:
            (reason, requested), running.pending_stop = running.pending_stop, None
            await self._stop_running(running, reason, requested=requested)

    async def _next_line(self, running: _Running, stdout: asyncio.StreamReader) -> bytes:
        """The worker's next line. Once it started its job it sends one every ``WORKER_BEAT_S`` at least:
        silent for ``WORKER_SILENT_S`` it is taken for hung, and its job is stopped as a stop does (the
        arm through the guard if the worker still answers, else the worker is killed and the arm's
        connection watchdog stops it), the queue held and the reason logged."""
        while running.started and running.hung_stop is None and running.ended is None:
            try:
                return await asyncio.wait_for(stdout.readline(), WORKER_SILENT_S)
            except TimeoutError:
                reason = (f"the job's worker sent nothing for {WORKER_SILENT_S:g} s (it beats every "
                          f"{WORKER_BEAT_S:g} s): hung")
                log.error("job %s: %s; stopping it", running.job.id, reason, extra={"job_id": running.job.id})
                self._hold(f"{reason}; check the arm")
                running.hung_stop = asyncio.create_task(self._stop_running(running, reason, requested=False),
                                                        name="hung stop")
        return await stdout.readline()

    def _take(self, running: _Running, message: dict[str, Any]) -> None:
        """One line from the job's worker."""
        kind = message.get("type")
        if kind == "progress":
            progress = message["progress"]
            self.metrics.ticks.running = progress.pop("ticks", None)
            running.progress = progress
            self.arm.progress(progress)
            if progress.get("perception_cycle_s") is not None:
                self.metrics.perception_cycle.observe(progress["perception_cycle_s"])
            self.events.log(running.job.id).publish("progress", progress)
        elif kind == "stop" and running.acks:
            ack = running.acks.popleft()
            if not ack.done():
                ack.set_result(StopEffect(message["effect"]))
        elif kind == "started":
            running.started = True
        elif kind == "ended":
            running.ended = message

    async def _record_end(self, running: _Running, code: int | None = None,
                          failure: str | None = None) -> None:
        """Record how the job ended, as soon as it is known: from its worker's last word (while the worker
        process still exits), or ``failure`` / the worker's exit ``code`` when it had none (the folder is
        then finished here)."""
        running.recorded = True
        job, ended = running.job, running.ended
        for ack in running.acks:
            if not ack.done():
                ack.set_result(StopEffect.AFTER_MOTION)
        if ended is None:
            if running.killed_for is not None:
                # a stop carried out by killing a worker that did not answer (busy starting, or hung)
                status, termination = "stopped", stop_termination(running.killed_for)
                result = await self._finish_folder(job, status, termination)
            else:
                exit_text = _exit_text(code or 0)
                # killed after it wrote its result.json (its last output, once the arm was at rest through
                # the guard) but before its last line: the folder holds the job's whole end, which stands
                wrote = None if failure is not None else await self._worker_wrote_end(job, exit_text)
                if wrote is not None:
                    status, termination, result = wrote[0], wrote[1], finite_json(wrote[2])
                    log.warning("the job's worker ended unexpectedly (%s) after it wrote its result: %s "
                                "stands", exit_text, status, extra={"job_id": job.id})
                else:
                    status = "failed"
                    termination = failure or f"the job's worker process ended unexpectedly ({exit_text})"
                    if failure is None:
                        # no one stopped the arm through the guard, only the controller's watchdog: a
                        # person looks before the next job moves it
                        self._hold(f"the job's worker ended unexpectedly ({exit_text}); check the arm")
                    result = await self._finish_folder(job, status, termination)
        else:
            status, termination = ended["status"], ended["termination"]
            result = finite_json(ended.get("result")) or await self._finish_folder(job, status, termination)
        self.metrics.ticks.job_ended(None if ended is None else ended.get("ticks"))
        if status == "completed" and result is not None and result.get("sim_time_s") is not None:
            self.metrics.scan_duration.labels(job.planner).observe(result["sim_time_s"])
        if (fault := self.arm.job_ended(termination)) is not None and (
                held := held_for_fault(self.name, fault, job.id, self._held, _now())) is not None:
            # kept in the store as the other holds are, first in a hold that came during the job (a STOP,
            # a hung worker's): the latch alone was lost with a restart
            self._held = held
            self._write_hold()
        log.log(logging.INFO if status == "completed" else logging.WARNING, "job ended %s: %s", status,
                termination, extra={"job_id": job.id, "part_id": job.part_id, "status": status})
        # a job's end is never dropped (it stayed `running` until a restart)
        changes = {"status": status, "termination": termination, "result": result, "finished_at": _now(),
                   "worker_pid": None, "progress": running.progress}
        await until_stored(lambda: self.store.update_job(job.id, **changes), "job's end",
                           lambda: self._closing, log, {"job_id": job.id})
        running.stored = True
        # the line hears once the store has the outcome: a line that reads the job finds it ended
        if self.line is not None:
            self.line.job_ended(job.id, status, termination, result, requested=bool(running.requested))
        events = self.events.log(job.id)
        events.publish("state", {"status": status, "termination": termination})
        events.publish("result", {"status": status, "result": result})

    @staticmethod
    async def _worker_wrote_end(job: JobRecord, exit_text: str) -> tuple[str, str, dict[str, Any]] | None:
        """``worker_wrote_end`` of the job's folder, on a thread; None when it wrote none (or the folder
        cannot be read)."""
        try:
            return await asyncio.to_thread(worker_wrote_end, Path(job.folder), exit_text)
        except OSError:
            return None

    @staticmethod
    async def _finish_folder(job: JobRecord, status: str, termination: str) -> dict[str, Any] | None:
        """``finish_folder`` on a thread; None when the folder could not be written (out of file
        descriptors, a full disk): the job's end is recorded in the store all the same."""
        try:
            return await asyncio.to_thread(finish_folder, Path(job.folder), job, status, termination)
        except OSError as exc:
            log.error("the job's folder could not be finished: %s: %s", type(exc).__name__, exc,
                      extra={"job_id": job.id})
            return None

    async def _finish(self, running: _Running, code: int | None, failure: str | None = None) -> None:
        """The job's worker has exited: the arm is free for the next job."""
        if not running.recorded:
            await self._record_end(running, code, failure)
        self._running = None
        running.gone.set()
        self._wake.set()
        await self._warm()
