"""The line's transition history as a client reads it: the controller queues its store writes (the event
loop never waits for the store), and a read of the history waits for the writes queued before it."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from cell.line.config import LineConfig
from cell.line.controller import LineController
from cell.line.packml import State, UnitMode
from cell.service.store import LineTransition, open_store, sqlite_url

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
        seen = [[(t.to_state, t.mode) for _, t in await line.history(limit=10, before_id=None)]]
        await line.set_mode(UnitMode.MANUAL, "test")
        seen.append([(t.to_state, t.mode) for _, t in await line.history(limit=10, before_id=None)])
        await line.close()
        return seen

    started, changed = asyncio.run(scenario())
    stopped, production, manual = int(State.STOPPED), int(UnitMode.PRODUCTION), int(UnitMode.MANUAL)
    assert started == [(stopped, production)]
    assert changed == [(stopped, manual), (stopped, production)]  # newest first
