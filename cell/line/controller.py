"""The cell's PackML state machine, owned by the service: what the line's commands do to the cell.

One :class:`LineController` per cell. The three ways in (OPC UA, the robot's digital I/O, REST) call
:meth:`LineController.command` and :meth:`LineController.set_mode`; they learn of every change through
:meth:`LineController.subscribe`. Everything runs on the service's event loop.

What each state does (TR88.00.02's model, :mod:`cell.line.packml`):

- Starting: the part id (``Command/Parameter/PartId``) becomes a scan job, which Execute runs. In sim
  and dry-run cells the part id names the feeder's part (:mod:`cell.line.result`); a part the cell does
  not know, or cannot place on its table, ends the cycle as a defective part with the reason, not as a
  fault.
- Completing writes the result (:class:`cell.line.result.CycleResult`) and the counters; Complete holds
  them until Reset. A scan that found nothing on the table (job ``no_object``) completes the cycle too,
  with a no-part result (``Result/Status`` ``no_object``, ``Fits`` false: counted defective), not a
  fault: the line decides what an empty station means.
- Stopping stops the scan's arm through the guard (the job ends ``stopped``), then Stopped. An operator's
  STOP (API, web page) is a Stop too, and so is the scan's job stopped through the API or by the
  service's shutdown during Execute.
- Aborting is the fault path: a safety stop (a guard refusal, a watchdog), an arm fault or a failed job
  during Execute, or the Abort command, stop the scan and end in Aborted with the stop reason. Clearing
  recovers a faulted arm (as ``POST /arm/recover`` does), then Stopped; Resetting goes to Idle. A queue
  the service holds (an operator's STOP, a job's worker that died) is resumed by an operator alone: till
  then Reset is refused (the line may not release what a person is to look at).
- Holding and Suspending stop the scan (a scan cannot be paused half-way: its maps and its path are those
  of one continuous run); Unholding and Unsuspending scan the same part again from the start. A scan
  that completed before the hold took effect is not repeated: its result is written on Unhold.

Production mode lets the line start scans and refuses operator jobs; Manual mode is the operator's and
refuses Start. The mode changes only in Stopped, Idle or Aborted, and not to Production while operator
jobs wait or run.

Every transition is recorded (time, from, to, cause) in the job store, and the mode, counters and last
result are kept there across restarts; the state starts at Stopped, as a machine's does after power-up
(its transition from the state recorded last), with the service's start (7) as the stop reason. Store
writes are queued to a task of their own, so that no transition waits for the database.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

from cell.line import packml
from cell.line.config import LineConfig
from cell.line.packml import Command, State, StopReason, UnitMode
from cell.line.result import CycleResult, check_part_id, cycle_result, feeder_part, rejected
from cell.service.store import LineRecord, LineTransition, Store
from cell.service.store.retry import until_stored
from cell.service.submission import JobRequest
from drivers.errors import OPERATOR_STOP, SAFETY_STOP, SHUTDOWN_STOP, ServiceError

if TYPE_CHECKING:
    from cell.service.manager import CellService

log = logging.getLogger("cell.line")

MODE_NAMES = {"production": UnitMode.PRODUCTION, "manual": UnitMode.MANUAL}


@dataclass(frozen=True)
class LineSnapshot:
    """The line now: PackML state and unit mode, the part id parameter, the cycle's scan job (the last one
    the cycle submitted, running or ended, until Reset: in Complete the job whose result the line holds, in
    Stopped or Aborted the one that stopped or failed; None from Reset until the next cycle's scan is
    submitted, and for a part rejected before a scan), the counters, the last stop reason, the last result
    (None before the first), and the outcome of the last command or mode change, or of a request a way in
    refused by itself, in words."""

    state: State
    mode: UnitMode
    part_id: str
    job_id: str | None
    processed: int
    defective: int
    stop_reason_id: StopReason
    stop_reason: str
    result: CycleResult | None
    message: str

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready, with the state's and mode's names beside their numbers."""
        return {"state": int(self.state), "state_name": self.state.label, "mode": int(self.mode),
                "mode_name": self.mode.label, "part_id": self.part_id, "job_id": self.job_id,
                "processed": self.processed, "defective": self.defective,
                "stop_reason": {"id": int(self.stop_reason_id), "message": self.stop_reason},
                "result": None if self.result is None else self.result.as_dict(), "message": self.message}


Listener = Callable[[LineSnapshot], None]


class LineController:
    """The PackML state machine of one cell (see the module docstring)."""

    def __init__(self, service: CellService, config: LineConfig, store: Store) -> None:
        self._service = service
        self._config = config
        self._store = store
        self._cell = service.name
        self.state = State.STOPPED
        self.mode = MODE_NAMES[config.initial_mode]
        self.part_id = ""
        self._part_id_pending = False  # part_id was set for the coming part: no Start has taken it yet
        self._job_id: str | None = None  # the cycle's scan job while it runs: the one the line stops
        self._cycle_job_id: str | None = None  # the cycle's last scan job, ended or not, until Reset
        self._cycle_part = ""
        self._done: CycleResult | None = None  # a scan that completed while the line held or suspended
        self._record = LineRecord(cell=self._cell, mode=int(self.mode))
        self._message = ""
        self._source = ""
        self._cause = ""  # why the line entered its state now (the newest transition's cause)
        self._listeners: list[Listener] = []
        # store writes in order: a write, a reader's marker (set once the writes before it are done), or
        # None (close)
        self._writes: asyncio.Queue[Callable[[], None] | asyncio.Event | None] = asyncio.Queue()
        self._writer: asyncio.Task[None] | None = None
        self._closing = False
        self._tasks: set[asyncio.Task[None]] = set()
        # what each acting state does before its state-complete transition
        self._acting_work: dict[State, Callable[[], Awaitable[None]]] = {
            State.STARTING: self._starting, State.UNHOLDING: self._restarting,
            State.UNSUSPENDING: self._restarting, State.STOPPING: self._stop_scan,
            State.HOLDING: self._stop_scan, State.SUSPENDING: self._stop_scan,
            State.ABORTING: self._stop_scan,
            State.CLEARING: self._clearing, State.RESETTING: self._resetting,
        }

    # ------------------------------------------------------------------ life

    async def start(self) -> None:
        """Load what the store kept (mode, counters, last result) and begin in Stopped; on a restart, from
        the state the line was last in, with the service's start as the stop reason."""
        kept = await asyncio.to_thread(self._store.get_line, self._cell)
        if kept is not None:
            self._record = kept
            self.mode = UnitMode(kept.mode)
            last = await asyncio.to_thread(self._store.line_transitions, self._cell, limit=1)
            # the start's transition is from the state the line was in when the service last ended
            self.state = State(last[0][1].to_state) if last else State.STOPPED
            self._set_stop_reason(StopReason.SHUTDOWN,
                                  f"the service started (the line was {self.state.label})")
        self._writer = asyncio.create_task(self._write_all(), name="line store writer")
        self._record_transition(State.STOPPED, "the service started")

    async def close(self) -> None:
        """Finish the queued store writes."""
        for task in list(self._tasks):
            task.cancel()
        self._closing = True
        if self._writer is not None:
            self._writes.put_nowait(None)
            with contextlib.suppress(asyncio.CancelledError):
                await self._writer

    async def settle(self) -> None:
        """Wait until the acting states entered so far have done their work (Resetting has reached Idle,
        Clearing Stopped, Starting Execute): a command after it meets the state they led to."""
        while pending := [task for task in self._tasks if not task.done()]:
            await asyncio.wait(pending)

    def subscribe(self, listener: Listener) -> None:
        """Call ``listener`` (on the event loop; it must not block) with the snapshot after every change."""
        self._listeners.append(listener)

    # ------------------------------------------------------------------ reading

    @property
    def owns_cell(self) -> bool:
        """Production mode: the line starts scans and operator jobs are refused."""
        return self.mode is UnitMode.PRODUCTION

    @property
    def job_id(self) -> str | None:
        """The scan job of the current cycle, if one runs."""
        return self._job_id

    def snapshot(self) -> LineSnapshot:
        r = self._record
        return LineSnapshot(self.state, self.mode, self.part_id, self._cycle_job_id, r.processed,
                            r.defective, StopReason(r.stop_reason_id), r.stop_reason,
                            None if r.last_result is None else CycleResult.from_dict(r.last_result),
                            self._message)

    async def written(self) -> None:
        """Once the transitions queued for the store so far are in it: :meth:`transitions` read after it
        holds them, so that a client that saw the line in a state finds the transition into it."""
        if self._writer is not None and not self._writer.done():
            written = asyncio.Event()
            self._writes.put_nowait(written)
            await written.wait()

    def transitions(self, limit: int, before_id: int | None) -> list[tuple[int, LineTransition]]:
        """The transitions the store holds, newest first (those queued for it too once :meth:`written`); it
        blocks: on a worker thread."""
        return self._store.line_transitions(self._cell, limit=limit, before_id=before_id)

    # ------------------------------------------------------------------ commands

    def say(self, text: str) -> None:
        """Make ``text`` the outcome of the last request (the snapshot's ``message``): what a way in refused
        by itself, e.g. a write to the OPC UA server."""
        self._message = text
        self._notify()

    def check_part_id(self, part_id: str) -> str:
        """``part_id`` if this cell can take it, else ``ServiceError`` (invalid, field ``part_id``): the
        line's rule (:func:`cell.line.result.check_part_id`) and, in a sim or dry-run cell, the feeder's
        syntax (:func:`cell.line.result.feeder_part`), so that a malformed placement is refused when it is
        set, not at Start. Whether the object exists is checked at Start (a defective part then)."""
        check_part_id(part_id)
        if self._service.objects.virtual:
            feeder_part(part_id)
        return part_id

    def set_part_id(self, part_id: str) -> None:
        """The part id the next Start scans (``Command/Parameter/PartId``); ``ServiceError`` (invalid)."""
        self.part_id = self.check_part_id(part_id)
        self._part_id_pending = True
        self._notify()

    @property
    def pending_part_id(self) -> str | None:
        """The part id set for the coming part (OPC UA's PartId or SetPartId, a REST command's ``part_id``)
        that no Start has taken yet; None when the parameter holds an earlier part's or none."""
        return self.part_id if self._part_id_pending else None

    async def command(self, command: Command, source: str, part_id: str | None = None) -> str:
        """Act on ``command`` from ``source`` (e.g. ``opcua (key line-1)``); ``part_id`` sets the parameter
        when the command is accepted, before it acts. Returns what was done, in words; ``ServiceError``
        (conflict) when the command is not valid now, the state and the part id unchanged (a refused Start
        in Execute must not rename the part being scanned), or (invalid) when ``part_id`` is."""
        given = None if part_id is None else self.check_part_id(part_id)
        why = packml.refusal(self.state, command) or self._precondition(command, given or self.part_id)
        if why is not None:
            self.say(f"refused {command.label} from {source}: {why}")
            raise ServiceError(why, reason="conflict")
        if given is not None:
            self.part_id, self._part_id_pending = given, True
        if command is Command.START:
            self._part_id_pending = False
        elif command is Command.RESET:
            self._cycle_job_id = None  # the cycle is over: its job stays in the last result and the history
        self._message = f"{command.label} from {source}"
        self._source = source
        if command is Command.STOP:
            self._set_stop_reason(StopReason.LINE_STOP, f"Stop from {source}")
        elif command is Command.ABORT:
            self._set_stop_reason(StopReason.LINE_ABORT, f"Abort from {source}")
        self._enter(packml.ACTING[command], self._message)
        return f"{command.label} accepted: {self.state.label}"

    def _precondition(self, command: Command, part_id: str) -> str | None:
        if not self._service.ready:  # its OPC UA server serves on while the service closes
            return "the service is starting or shutting down"
        if command is Command.START:
            if not self.owns_cell:
                return f"the cell is in {self.mode.label} mode: the line starts scans in Production only"
            if not part_id:
                return "no part id: set Command/Parameter/PartId (or part_id) before Start"
        if command is Command.RESET and self._service.arm.faulted:
            return (f"the arm is faulted ({', '.join(self._service.arm.status.faults)}): Abort, then Clear "
                    "recovers it")
        held = self._service.hold_reason() if command is Command.RESET else None
        if held is not None:
            # an operator's STOP, a worker that died: a person looks before the line moves the arm again
            return f"the queue is {held}; the line may Reset after that, not instead"
        return None

    async def set_mode(self, mode: UnitMode, source: str) -> str:
        """Change the unit mode; ``ServiceError`` (conflict or invalid) when it may not change now. The
        outcome is the snapshot's ``message``, as a command's."""
        try:
            self._check_mode(mode)
        except ServiceError as exc:
            self.say(f"refused unit mode {mode.label} from {source}: {exc}")
            raise
        if mode is self.mode:
            self.say(f"unit mode {mode.label} from {source}: already {mode.label}")
            return f"{mode.label} mode"
        self._message = f"unit mode {mode.label} from {source}"
        self.mode = mode
        self._save(mode=int(mode))
        self._record_transition(self.state, self._message)
        return f"{mode.label} mode"

    def _check_mode(self, mode: UnitMode) -> None:
        if mode not in packml.OFFERED_MODES:
            offered = ", ".join(f"{m.value} {m.label}" for m in sorted(packml.OFFERED_MODES))
            raise ServiceError(f"unit mode {int(mode)} ({mode.label}) is not offered; offered: {offered}",
                               reason="invalid", field="mode")
        if mode is self.mode:
            return  # accepted in any state: nothing changes
        if self.state not in packml.MODE_CHANGE_STATES:
            allowed = ", ".join(s.label for s in sorted(packml.MODE_CHANGE_STATES))
            raise ServiceError(f"the unit mode changes in {allowed} only, not in {self.state.label}",
                               reason="conflict")
        if mode is UnitMode.PRODUCTION and self._service.operator_jobs():
            raise ServiceError("operator jobs are queued or running: let them end (or stop them) before the "
                               "line takes the cell in Production mode", reason="conflict")

    def operator_stop(self, reason: str) -> None:
        """The operator's STOP (``POST /api/v1/stop``): a Stop, whatever the mode; Reset is refused until an
        operator resumes the queue."""
        self._stop_for(StopReason.OPERATOR_STOP, reason, f"operator STOP: {reason}")

    def service_stopping(self, reason: str) -> None:
        """The service shuts down: a Stop from now (the PLC sees Stopping while the scan stops, and Stopped
        once it has, before the OPC UA server closes), whatever the mode."""
        self._stop_for(StopReason.SHUTDOWN, reason, reason)

    def _stop_for(self, reason: StopReason, text: str, cause: str) -> None:
        if packml.refusal(self.state, Command.STOP) is None:
            self._set_stop_reason(reason, text)
            self._enter(State.STOPPING, cause)

    # ------------------------------------------------------------------ the scan job

    def job_ended(self, job_id: str, status: str, termination: str, result: dict[str, Any] | None, *,
                  requested: bool = False) -> None:
        """The service's word that a job ended; ``requested``: the service stopped it on someone's request
        (``POST /api/v1/jobs/{id}/stop``, an operator's STOP, its shutdown), not the safety layer by
        itself nor the service for a worker that stopped answering. The line acts on its own cycle's job
        only."""
        if job_id != self._job_id:
            return
        self._job_id = None
        state = self.state
        if state in (State.HOLDING, State.SUSPENDING):
            if status == "completed":
                self._done = cycle_result(job_id, self._cycle_part, status, termination, result)
            after = State.HELD if state is State.HOLDING else State.SUSPENDED
            self._enter(after, f"the scan ended: {status}")
        elif state is State.STOPPING:
            self._enter(State.STOPPED, f"the scan ended: {status}")
        elif state is State.ABORTING:
            self._enter(State.ABORTED, f"the scan ended: {status}")
        elif state is State.EXECUTE:
            self._execute_ended(job_id, status, termination, result, requested)

    def _execute_ended(self, job_id: str, status: str, termination: str, result: dict[str, Any] | None,
                       requested: bool) -> None:
        if status in ("completed", "no_object"):
            self._complete(cycle_result(job_id, self._cycle_part, status, termination, result))
            return
        faulted = self._service.arm.faulted
        # a job stopped on request ends `stopped`; one that failed meanwhile (its worker died) failed
        if not faulted and (status == "cancelled" or (requested and status == "stopped")):
            # stopped on request, not by the line (its own stops end in Stopping or Aborting): a job
            # stopped or cancelled through the API, or the service shutting down
            reason = StopReason.OPERATOR_STOP if self._service.ready else StopReason.SHUTDOWN
            self._set_stop_reason(reason, f"scan {job_id} {status}: {termination}")
            self._record_transition(State.STOPPING, f"the scan was {status}")
            self._record_transition(State.STOPPED, "no scan runs")
            return
        if faulted:
            reason = StopReason.ARM_FAULT
        elif termination.startswith(OPERATOR_STOP):
            reason = StopReason.OPERATOR_STOP
        elif termination.startswith(SAFETY_STOP):
            reason = StopReason.SAFETY_STOP
        elif termination.startswith(SHUTDOWN_STOP):
            reason = StopReason.SHUTDOWN
        else:
            reason = StopReason.JOB_FAILED
        self._fault(reason, f"scan {job_id} {status}: {termination}")

    # ------------------------------------------------------------------ states

    def _enter(self, state: State, cause: str) -> None:
        self._record_transition(state, cause)
        work = self._acting_work.get(state)
        if work is not None:
            self._spawn(work, state)

    def _spawn(self, work: Callable[[], Awaitable[None]], state: State) -> None:
        async def run() -> None:
            if self.state is not state:  # left before its task began (the scan's end came first, a Stop)
                return
            try:
                await work()
            except Exception as exc:  # an acting state that cannot finish is a fault, never a hang
                log.exception("line: %s failed", state.label)
                if self.state is state:
                    self._fault(StopReason.JOB_FAILED, f"{state.label} failed: {type(exc).__name__}: {exc}")

        task = asyncio.create_task(run(), name=f"line {state.label}")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _starting(self) -> None:
        self._cycle_part = self.part_id
        self._done = None
        await self._scan(self._cycle_part, State.STARTING)

    async def _restarting(self) -> None:
        state = self.state
        if self._done is not None:
            done, self._done = self._done, None
            self._enter(State.EXECUTE, "the held part's scan had completed")
            self._complete(done)
            return
        await self._scan(self._cycle_part, state)

    async def _scan(self, part_id: str, acting: State) -> None:
        """Submit the part's scan job and enter Execute; a part the cell cannot scan completes as a
        defective one."""
        service = self._service
        name: str | None = part_id
        pose: tuple[float, float, float] | None = None
        try:
            if service.objects.virtual:
                name, pose = feeder_part(part_id)
            else:
                name = None
            seed = self._record.processed
            request = JobRequest(object=name, object_pose=pose, seed=seed, max_time_s=self._config.max_time_s,
                                 part_id=part_id)
            job = await service.submit(request, f"line: {self._source}", origin="line")
        except ServiceError as exc:
            if exc.reason != "invalid" or self.state is not acting:
                raise
            self._enter(State.EXECUTE, f"part {part_id!r} cannot be scanned")
            self._complete(rejected(part_id, f"{exc.field}: {exc}"))
            return
        if self.state is not acting:  # stopped or aborted meanwhile: the job is not the line's any more
            await service.stop_job(job.id, f"the line left {acting.label}")
            return
        self._job_id = self._cycle_job_id = job.id
        self._enter(State.EXECUTE, f"scan {job.id} of part {part_id!r}")

    def _complete(self, result: CycleResult) -> None:
        """Completing: the result and the counters, then Complete."""
        self._enter(State.COMPLETING, f"{result.status}: {result.message}")
        r = self._record
        self._save(processed=r.processed + 1, defective=r.defective + (not result.fits),
                   last_result=result.as_dict())
        self._enter(State.COMPLETE, "the result is written" + ("" if result.fits else " (defective)"))

    async def _stop_scan(self) -> None:
        acting = self.state
        job_id = self._job_id
        if job_id is not None:  # the job says who: "the line: Stopping (Stop from OPC UA (key plc-1))"
            await self._service.stop_job(job_id, f"the line: {acting.label} ({self._cause})")
            return  # job_ended moves on
        after = {State.STOPPING: State.STOPPED, State.ABORTING: State.ABORTED, State.HOLDING: State.HELD,
                 State.SUSPENDING: State.SUSPENDED}[acting]
        if self.state is acting:
            self._enter(after, "no scan was running")

    async def _clearing(self) -> None:
        service = self._service
        if service.arm.faulted:
            outcome = await service.recover_arm()
            if not outcome["ok"]:
                self._fault(StopReason.CLEAR_FAILED, f"the arm did not recover: {outcome['message']}")
                return
        if self.state is State.CLEARING:
            self._enter(State.STOPPED, "cleared")

    async def _resetting(self) -> None:
        if self.state is State.RESETTING:
            self._enter(State.IDLE, "reset")

    # ------------------------------------------------------------------ recording

    def _fault(self, reason: StopReason, text: str) -> None:
        """The fault path with no scan left to stop: Aborting, then Aborted, with the stop reason."""
        self._set_stop_reason(reason, text)
        self._record_transition(State.ABORTING, text)
        self._record_transition(State.ABORTED, "nothing moves")

    def _set_stop_reason(self, reason: StopReason, text: str) -> None:
        self._save(stop_reason_id=int(reason), stop_reason=text[:500])

    def _save(self, **changes: Any) -> None:
        self._record = record = replace(self._record, **changes)
        self._writes.put_nowait(lambda: self._store.put_line(record))

    def _record_transition(self, to: State, cause: str) -> None:
        transition = LineTransition(cell=self._cell, at=datetime.now(UTC), from_state=int(self.state),
                                    to_state=int(to), mode=int(self.mode), cause=cause[:500])
        log.info("line: %s -> %s (%s)", self.state.label, to.label, cause)
        self.state, self._cause = to, cause
        self._writes.put_nowait(lambda: self._store.add_line_transition(transition))
        self._notify()

    def _notify(self) -> None:
        snapshot = self.snapshot()
        for listener in self._listeners:
            try:
                listener(snapshot)
            except Exception:  # one broken way in must not stop the others from hearing
                log.exception("line: a listener failed")

    async def _write_all(self) -> None:
        while (write := await self._writes.get()) is not None:
            if isinstance(write, asyncio.Event):
                write.set()
                continue
            # the writes after it wait, in order
            await until_stored(write, "line: a state or transition", lambda: self._closing, log)
