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
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml

from cell.api.app import create_app
from cell.api.connections import ConnectionLimits
from cell.api.routes import clouds
from cell.service import retention
from cell.service.keys import create_key
from cell.service.startup import ServiceSettings
from cell.service.store import JobRecord, Store, open_data_store, sqlite_url
from tests.conftest import FRANKA
from tests.service_process import serving_guarded

WAIT_S = 60.0  # a bound on waiting for the server, never a timed check [s]
POOL_THREADS = 40  # anyio's default thread limiter
SLOW_CLIENTS = POOL_THREADS + 5


def _viewer_key(data: Path, *jobs: JobRecord) -> str:
    """A viewer's key, made in the store of the data dir ``data`` (with ``jobs`` added)."""
    store = open_data_store(data, sqlite_url(data))
    try:
        for job in jobs:
            store.add_job(job)
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
    """A page of jobs, retention's preview, the line's history and a job's cloud each hold the GIL for as
    long as they read (``cell.api.bulk``): run on a worker thread per client, six of them at once left the
    event loop a seventh of it, and a STOP waited for seconds. They take turns, whatever their kind."""
    data = tmp_path / "data"
    job = JobRecord(id="0" * 16, cell=yaml.safe_load(FRANKA.read_text())["name"], status="completed",
                    planner="vs-local", object="bunny", object_pose=(0.0, 0.0, 0.0), seed=1, max_time_s=60.0,
                    part_id=None, folder=str(data / "jobs" / "gone"), submitted_by="op",
                    created_at=datetime.now(UTC))
    viewer = _viewer_key(data, job)
    cell_file = tmp_path / "cell.yaml"
    cell_file.write_text(yaml.safe_dump(yaml.safe_load(FRANKA.read_text()) | {"line": {}}))
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
    monkeypatch.setattr(Store, "line_transitions", counted(Store.line_transitions))
    monkeypatch.setattr(clouds, "job_cloud", counted(clouds.job_cloud))
    app = create_app(ServiceSettings(config_file=cell_file, data_dir=data))
    limits = ConnectionLimits(256)
    with serving_guarded(app, limits, WAIT_S) as port, ThreadPoolExecutor(4 * BULK_CLIENTS) as pool, \
            httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=WAIT_S,
                         headers={"Authorization": f"Bearer {viewer}"}) as client:
        paths = ("/api/v1/jobs?limit=500", "/api/v1/retention", "/api/v1/line/history?limit=1000",
                 f"/api/v1/jobs/{job.id}/cloud")
        reads = [pool.submit(client.get, path) for path in paths for _ in range(BULK_CLIENTS)]
        answers = [read.result() for read in reads]
    assert all(answer.status_code == 200 for answer in answers), [a.text for a in answers]
    assert len(inside) == 2 * len(paths) * BULK_CLIENTS and max(inside) == 1, inside
