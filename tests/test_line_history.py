"""The line's transition history as a client reads it: the controller queues its store writes (the event
loop never waits for the store), and a read of the history waits for the writes queued before it; and,
with the controller's service standing in, what the line makes of a scan's end: a scan that completed
while the line held it, an acting state left at once, a scan stopped by someone else than the line."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import pytest

from cell.line.config import LineConfig
from cell.line.controller import LineController
from cell.line.packml import Command, State, UnitMode
from cell.service.store import LineTransition, Store, open_store, sqlite_url
from drivers.errors import StoreError

STORE_DELAY_S = 0.3


def test_a_read_of_the_history_finds_the_transitions_just_made(tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    store = open_store(sqlite_url(tmp_path))
    add = store.add_line_transition

    def slow_add(transition: LineTransition) -> None:
        time.sleep(STORE_DELAY_S)  # a store slow to write: a loaded machine, a remote PostgreSQL
        add(transition)

    monkeypatch.setattr(store, "add_line_transition", slow_add)

    async def scenario() -> list[list[tuple[int, int]]]:
        line = LineController(SimpleNamespace(name="cell-a"), LineConfig(), store)  # type: ignore[arg-type]
        await line.start()
        await line.written()
        seen = [[(t.to_state, t.mode) for _, t in line.transitions(limit=10, before_id=None)]]
        await line.set_mode(UnitMode.MANUAL, "test")
        await line.written()
        seen.append([(t.to_state, t.mode) for _, t in line.transitions(limit=10, before_id=None)])
        await line.close()
        return seen

    started, changed = asyncio.run(scenario())
    stopped, production, manual = int(State.STOPPED), int(UnitMode.PRODUCTION), int(UnitMode.MANUAL)
    assert started == [(stopped, production)]
    assert changed == [(stopped, manual), (stopped, production)]  # newest first


class _Service:
    """What the controller asks of its service: a sim cell whose scans end when the test says."""

    name = "cell-a"
    ready = True
    arm = SimpleNamespace(faulted=False)
    objects = SimpleNamespace(virtual=True)

    def __init__(self) -> None:
        self.submitted: list[str] = []
        self.stops: list[str] = []

    @staticmethod
    def hold_reason() -> None:
        return None

    async def submit(self, request: object, submitted_by: str, origin: str) -> SimpleNamespace:
        self.submitted.append(f"job-{len(self.submitted) + 1}")
        return SimpleNamespace(id=self.submitted[-1])

    async def stop_job(self, job_id: str, reason: str) -> None:
        self.stops.append(job_id)  # the job's end comes when the test says


async def _until(line: LineController, done: Callable[[], bool], what: str) -> None:
    for _ in range(100):  # the acting states' tasks: a few turns of the loop, no time passes
        if done():
            return
        await asyncio.sleep(0)
    raise AssertionError(f"{what}: the line is {line.state.label}")


async def _reach(line: LineController, state: State) -> None:
    await _until(line, lambda: line.state is state, f"not {state.label}")


async def _executing(service: _Service, store: Store) -> LineController:
    """A line of ``service`` in Execute, scanning job-1."""
    line = LineController(service, LineConfig(), store)  # type: ignore[arg-type]
    await line.start()
    await line.command(Command.RESET, "test")
    await _reach(line, State.IDLE)
    await line.command(Command.START, "test", part_id="cube")
    await _reach(line, State.EXECUTE)
    return line


def test_unhold_of_a_scan_that_completed_while_held_shows_its_job_in_execute(tmp_path: Path) -> None:
    store = open_store(sqlite_url(tmp_path))

    async def scenario() -> tuple[list[tuple[State, str | None]], str]:
        service = _Service()
        line = await _executing(service, store)
        seen: list[tuple[State, str | None]] = []
        line.subscribe(lambda s: seen.append((s.state, s.job_id)))
        await line.command(Command.HOLD, "test")
        await _until(line, lambda: bool(service.stops), "the Hold did not stop the scan")
        line.job_ended("job-1", "completed", "done", None)  # the scan had completed
        await _reach(line, State.HELD)
        seen.clear()
        await line.command(Command.UNHOLD, "test")
        await _reach(line, State.COMPLETE)
        result = line.snapshot().result
        await line.close()
        assert result is not None
        return seen, result.job_id

    seen, result_job = asyncio.run(scenario())
    # the cycle's job, from the Hold through its result, until Reset
    assert seen == [(State.UNHOLDING, "job-1"), (State.EXECUTE, "job-1"), (State.COMPLETING, "job-1"),
                    (State.COMPLETE, "job-1")]
    assert result_job == "job-1"


def test_an_acting_state_left_before_its_work_began_does_nothing(tmp_path: Path,
                                                                caplog: pytest.LogCaptureFixture) -> None:
    """A command's acting state is left in the same turn of the loop (the scan's end, a Stop, came first):
    its work, queued to a task, does nothing when the task begins."""
    store = open_store(sqlite_url(tmp_path))

    async def scenario() -> tuple[State, State, list[str]]:
        service = _Service()
        line = await _executing(service, store)
        await line.command(Command.HOLD, "test")
        line.job_ended("job-1", "completed", "done", None)  # its end was on its way
        await line.command(Command.UNHOLD, "test")
        await _reach(line, State.COMPLETE)  # the held scan's result: the Holding's work has nothing to do
        completed = line.state
        await line.command(Command.RESET, "test")
        await _reach(line, State.IDLE)
        await line.command(Command.START, "test", part_id="bunny")
        await line.command(Command.STOP, "test")  # before Starting submitted the scan: none is
        await _reach(line, State.STOPPED)
        for _ in range(10):  # turns in which a Starting's work would have submitted the scan
            await asyncio.sleep(0)
        stopped = line.state
        await line.close()
        return completed, stopped, service.submitted

    completed, stopped, submitted = asyncio.run(scenario())
    assert (completed, stopped, submitted) == (State.COMPLETE, State.STOPPED, ["job-1"])
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text


@pytest.mark.parametrize(("termination", "requested", "state", "reason"), [
    ("operator stop: wrong part (key op)", True, State.STOPPED, 2),  # POST /jobs/{id}/stop
    ("operator stop: wrong part (key op) (the job's worker did not confirm the stop in 2 s and was killed)",
     True, State.STOPPED, 2),
    ("safety stop: the job's worker sent nothing for 5 s (it beats every 0.5 s): hung (the job's worker did "
     "not confirm the stop in 2 s and was killed)", False, State.ABORTED, 4),
    ("safety stop: refused: the twist leaves the workspace", False, State.ABORTED, 4),
    ("safety stop: watchdog: no perception for 0.5 s", False, State.ABORTED, 4),
])
def test_a_scan_stopped_in_execute_by_someone_else_than_the_line(tmp_path: Path, termination: str,
                                                                  requested: bool, state: State,
                                                                  reason: int) -> None:
    """A stop on request (through the API, also when its worker had to be killed) is a Stop; the safety
    layer's own stops are faults."""
    store = open_store(sqlite_url(tmp_path))

    async def scenario() -> tuple[State, int]:
        line = await _executing(_Service(), store)
        line.job_ended("job-1", "stopped", termination, None, requested=requested)
        ended = line.snapshot()
        await line.close()
        return ended.state, int(ended.stop_reason_id)

    assert asyncio.run(scenario()) == (state, reason)


def test_transitions_made_while_the_store_is_away_are_recorded_once_it_answers(tmp_path: Path) -> None:
    store = open_store(sqlite_url(tmp_path))
    add = store.add_line_transition
    away = True

    def flaky(transition: LineTransition) -> None:
        if away:
            raise StoreError("job store: the database does not answer")
        add(transition)

    store.add_line_transition = flaky  # type: ignore[method-assign]

    async def scenario() -> list[int]:
        nonlocal away
        line = await _executing(_Service(), store)  # Stopped, Resetting, Idle, Starting, Execute
        await asyncio.sleep(1.5)  # tried again once at least
        away = False
        await line.written()  # the writes before it
        history = line.transitions(limit=10, before_id=None)
        await line.close()
        return [t.to_state for _, t in reversed(history)]

    assert asyncio.run(scenario()) == [int(s) for s in (State.STOPPED, State.RESETTING, State.IDLE,
                                                        State.STARTING, State.EXECUTE)]


def test_a_job_that_failed_after_a_stop_was_asked_for_is_a_failed_job(tmp_path: Path) -> None:
    """A stop on request ends the job `stopped`; a job whose worker died meanwhile failed (reason 6)."""
    store = open_store(sqlite_url(tmp_path))

    async def scenario() -> tuple[State, int]:
        line = await _executing(_Service(), store)
        line.job_ended("job-1", "failed", "the job's worker process ended unexpectedly (killed by SIGKILL)",
                       None, requested=True)
        ended = line.snapshot()
        await line.close()
        return ended.state, int(ended.stop_reason_id)

    assert asyncio.run(scenario()) == (State.ABORTED, 6)
