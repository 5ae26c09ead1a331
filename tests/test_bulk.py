"""The bulk answers' turn (``cell.api.bulk``) on an event loop of its own: a request whose client has gone
is not built, the queue is bounded, a cancelled holder keeps the turn until its thread is done, and
retention's automatic prune plans in the turn as well."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path
from typing import Any

import pytest
from fastapi import HTTPException, Request
from starlette.types import Message

from cell.api.bulk import CLIENT_GONE, BulkReads
from cell.config.models import RetentionConfig
from cell.service import retention
from cell.service.retention import PrunePlan, plan_prune
from cell.service.store import open_store, sqlite_url

WAIT_S = 30.0  # a bound on waiting for a thread, never a timed check [s]


def _request(connected: bool = True) -> Request:
    """A GET whose client is still there, or has closed its connection."""

    async def receive() -> Message:
        if connected:
            return {"type": "http.request", "body": b"", "more_body": False}
        return {"type": "http.disconnect"}

    return Request({"type": "http", "method": "GET", "path": "/", "headers": []}, receive)


def test_a_request_whose_client_has_gone_is_not_built() -> None:
    built: list[str] = []

    def build(name: str) -> bytes:
        built.append(name)
        return b"[]"

    async def scenario() -> tuple[int, int]:
        bulk = BulkReads()
        gone = await bulk.answer(_request(connected=False), lambda: build("gone"))
        there = await bulk.answer(_request(), lambda: build("there"))
        return gone.status_code, there.status_code

    assert asyncio.run(scenario()) == (CLIENT_GONE, 200)
    assert built == ["there"]


def test_requests_beyond_the_queue_are_answered_503_with_retry_after() -> None:
    release = threading.Event()

    async def scenario() -> HTTPException:
        bulk = BulkReads(waiting=2)
        holder = asyncio.create_task(bulk.answer(_request(), lambda: b"[]" if release.wait(WAIT_S) else b""))
        while not bulk._turns.locked():
            await asyncio.sleep(0)
        waiters = [asyncio.create_task(bulk.answer(_request(), lambda: b"[]")) for _ in range(2)]
        await asyncio.sleep(0)  # the waiters queue for the turn
        with pytest.raises(HTTPException) as refused:
            await bulk.answer(_request(), lambda: b"[]")
        release.set()
        assert [a.status_code for a in await asyncio.gather(holder, *waiters)] == [200, 200, 200]
        return refused.value

    refused = asyncio.run(scenario())
    assert refused.status_code == 503 and refused.headers == {"Retry-After": "1"}
    assert "waiting already" in refused.detail


def test_a_cancelled_request_keeps_the_turn_until_its_thread_has_finished() -> None:
    release, first_done = threading.Event(), threading.Event()

    def first() -> bytes:
        release.wait(WAIT_S)
        first_done.set()
        return b"[]"

    async def scenario() -> bool:
        bulk = BulkReads()
        holder = asyncio.create_task(bulk.answer(_request(), first))
        while not bulk._turns.locked():
            await asyncio.sleep(0)
        await asyncio.sleep(0)  # the holder's thread is started
        holder.cancel()
        second = asyncio.create_task(bulk.run(first_done.is_set))
        await asyncio.sleep(0)
        release.set()
        return await second

    assert asyncio.run(scenario())  # the second ran once the first's thread was done


def test_the_automatic_prune_plans_in_the_bulk_turn(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    store = open_store(sqlite_url(tmp_path))
    release = threading.Event()
    planned_after_release: list[bool] = []

    def plan(*args: Any) -> PrunePlan:
        planned_after_release.append(release.is_set())
        return plan_prune(*args)

    monkeypatch.setattr(retention, "plan_prune", plan)

    async def scenario() -> None:
        bulk = BulkReads()
        pruner = retention.Retention(store, "cell-a", tmp_path / "jobs", RetentionConfig(days=1))
        pruner.on_thread = bulk.run  # as cell serve's app does
        holder = asyncio.create_task(bulk.run(lambda: release.wait(WAIT_S)))
        while not bulk._turns.locked():
            await asyncio.sleep(0)
        pruning = asyncio.create_task(pruner.prune())
        await asyncio.sleep(0.05)  # room for a plan made out of turn to run (no timed check: it only fails)
        release.set()
        await asyncio.gather(holder, pruning)

    try:
        asyncio.run(scenario())
    finally:
        store.close()
    assert planned_after_release == [True]
