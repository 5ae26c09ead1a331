"""A STOP never waits on another request's work: the app of ``cell serve`` on a uvicorn server on loopback
(with the service's connection guards), its thread pool taken by a slow sync route, and bulk reads that
take turns.

FastAPI runs a plain ``def`` route or dependency in anyio's pool of 40 threads; the STOP routes took the
service through such a dependency, and 45 clients polling a slow sync route delayed a STOP by 27 s (the
arm of a running job moved on for 52 s). Every dependency of the STOP path is a coroutine now.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import pytest

from cell.api.app import create_app
from cell.api.connections import ConnectionLimits
from cell.service import retention
from cell.service.keys import create_key
from cell.service.startup import ServiceSettings
from cell.service.store import Store, open_data_store, sqlite_url
from tests.conftest import FRANKA
from tests.service_process import serving_guarded

WAIT_S = 60.0  # a bound on waiting for the server, never a timed check [s]
POOL_THREADS = 40  # anyio's default thread limiter
SLOW_CLIENTS = POOL_THREADS + 5


def _viewer_key(data: Path) -> str:
    """A viewer's key, made in the store of the data dir ``data``."""
    store = open_data_store(data, sqlite_url(data))
    try:
        return create_key(store, "viewer", "viewer")[1]
    finally:
        store.close()


def test_stop_answers_while_a_slow_sync_route_holds_every_thread_of_the_pool(tmp_path: Path) -> None:
    data = tmp_path / "data"
    viewer = _viewer_key(data)
    app = create_app(ServiceSettings(config_file=FRANKA, data_dir=data))
    release = threading.Event()
    busy: list[int] = []

    @app.get("/test/slow")
    def slow() -> dict[str, str]:
        """A sync route that holds its thread until the test releases it."""
        busy.append(threading.get_ident())
        release.wait(WAIT_S)
        return {"status": "ok"}

    limits = ConnectionLimits(256)
    with serving_guarded(app, limits, WAIT_S) as port, ThreadPoolExecutor(SLOW_CLIENTS) as clients:
        url = f"http://127.0.0.1:{port}"
        try:
            slow_calls = [clients.submit(httpx.get, f"{url}/test/slow", timeout=WAIT_S)
                          for _ in range(SLOW_CLIENTS)]
            deadline = time.monotonic() + WAIT_S
            while len(busy) < POOL_THREADS:  # every thread of the pool is held, and more wait for one
                assert time.monotonic() < deadline, f"only {len(busy)} slow requests run"
                time.sleep(0.01)
            auth = {"Authorization": f"Bearer {viewer}"}
            # answered while the pool is still held: the timeout only bounds the wait (the release is later)
            stop = httpx.post(f"{url}/api/v1/stop", headers=auth, json={"reason": "pool"}, timeout=WAIT_S / 2)
            assert not release.is_set()
            assert stop.status_code == 200 and stop.json()["queue_held"] is True, stop.text
            assert len(busy) == POOL_THREADS  # the slow ones still wait
        finally:
            release.set()
        assert all(call.result().status_code == 200 for call in slow_calls)


BULK_CLIENTS = 6  # clients of each bulk read at once


def test_bulk_reads_of_every_kind_run_one_at_a_time(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A page of jobs and retention's preview each hold the GIL for as long as they read
    (``cell.api.bulk``): run on a worker thread per client, six of them at once left the event loop a
    seventh of it, and a STOP waited for seconds. They take turns, whatever their kind."""
    data = tmp_path / "data"
    viewer = _viewer_key(data)
    inside: list[int] = []  # bulk reads running now, as each one entered or left
    lock = threading.Lock()

    def counted(read: Callable[..., Any]) -> Callable[..., Any]:
        def bulk_read(*args: Any, **kwargs: Any) -> Any:
            with lock:
                inside.append(inside[-1] + 1 if inside else 1)
            try:
                time.sleep(0.02)  # room for another read to enter, if it may
                return read(*args, **kwargs)
            finally:
                with lock:
                    inside.append(inside[-1] - 1)
        return bulk_read

    monkeypatch.setattr(retention, "plan_prune", counted(retention.plan_prune))
    monkeypatch.setattr(Store, "list_jobs", counted(Store.list_jobs))
    app = create_app(ServiceSettings(config_file=FRANKA, data_dir=data))
    limits = ConnectionLimits(256)
    with serving_guarded(app, limits, WAIT_S) as port, ThreadPoolExecutor(2 * BULK_CLIENTS) as pool, \
            httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=WAIT_S,
                         headers={"Authorization": f"Bearer {viewer}"}) as client:
        reads = [pool.submit(client.get, path) for path in ("/api/v1/jobs?limit=500", "/api/v1/retention")
                 for _ in range(BULK_CLIENTS)]
        answers = [read.result() for read in reads]
    assert all(answer.status_code == 200 for answer in answers), [a.text for a in answers]
    assert len(inside) == 4 * BULK_CLIENTS and max(inside) == 1, inside
