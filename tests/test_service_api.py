"""The service in process (FastAPI's TestClient runs the app and its lifespan; each job still runs in a
real worker process): validation, a fault latched until recovery, the queue held by STOP, metrics,
and the pieces the service is made of: event logs, restart reconciliation, placement on the table."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import gc
import io
import json
import logging
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import warnings
from collections.abc import Iterator
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
import yaml
from fastapi.testclient import TestClient
from sqlalchemy import create_engine
from typer.testing import CliRunner

from cell.api.app import create_app
from cell.api.body_limit import JSON_MAX_BYTES
from cell.cli.main import app as cli
from cell.config import load_config
from cell.jobs.placement import check_on_table
from cell.jobs.progress import TICK_BUCKETS_S, ControlTicks
from cell.service.arm_status import ArmTracker, held_fault
from cell.service.events import JobEvents
from cell.service.keys import create_key
from cell.service.metrics import ServiceMetrics
from cell.service.protocol import WORKER_MODULE
from cell.service.recovery import RESTART_CANCEL, RESTART_TERMINATION, _started, reconcile
from cell.service.startup import ServiceSettings
from cell.service.store import FINISHED_STATUSES, JobRecord, Store, open_data_store, sqlite_url
from cell.service.store.engine import RESTORE
from cell.service.worker import SERVICE_GONE
from drivers.errors import JobError, StoreDamaged, StoreError
from drivers.sim.objects import load_object

from .conftest import FRANKA, wait_started


def _client(tmp_path: Path, config: Path = FRANKA) -> tuple[TestClient, dict[str, str]]:
    data = tmp_path / "data"
    store = open_data_store(data, sqlite_url(data))
    keys = {role: create_key(store, role, role)[1] for role in ("viewer", "operator", "admin")}
    store.close()
    return TestClient(create_app(ServiceSettings(config_file=config, data_dir=data))), keys


def _client_with(tmp_path: Path, name: str, **sections: dict[str, Any]) -> tuple[TestClient, dict[str, str]]:
    """``_client`` on the Franka sim cell with ``sections`` merged into its top-level sections."""
    data = yaml.safe_load(FRANKA.read_text())
    for section, values in sections.items():
        data.setdefault(section, {}).update(values)
    config = tmp_path / f"{name}.yaml"
    config.write_text(yaml.safe_dump(data))
    return _client(tmp_path, config)


def _auth(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


def _wait(client: TestClient, key: str, job_id: str, statuses: set[str], timeout_s: float = 90.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        job = client.get(f"/api/v1/jobs/{job_id}", headers=_auth(key)).json()
        if job["status"] in statuses:
            return job
        assert time.monotonic() < deadline, f"job {job_id} stayed {job['status']}"
        time.sleep(0.05)


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[TestClient, dict[str, str]]]:
    client, keys = _client(tmp_path)
    with client:
        yield client, keys


@pytest.mark.parametrize(("body", "field", "words"), [
    ({"object": "bunny", "planner": "teleport"}, "planner", "unknown planner 'teleport'"),
    ({"object": "unicorn"}, "object", "unknown object 'unicorn'"),
    ({}, "object", "scans a virtual object"),
    ({"object": "bunny", "object_pose": [2.0, 2.0, 0.0]}, "object_pose", "off the table"),
    ({"object": "bunny", "object_pose": [-0.42, 0.0, 0.0]}, "object_pose", "into the robot base (link0)"),
    ({"object": "bunny", "max_time_s": 0}, "max_time_s", "greater than 0"),
    ({"object": "bunny", "seed": -1}, "seed", "greater than or equal to 0"),
    ({"object": "bunny", "object_pose": [0.0, "0.1", 0.0]}, 1, "a valid number"),
    ({"object": "bunny", "object_pose": [0.0, 0.0, 1e308]}, "object_pose", "within +-360 deg"),
    ({"object": "bunny", "seed": "1"}, "seed", "a valid integer"),
    ({"object": "bunny", "seed": True}, "seed", "a valid integer"),
    ({"object": "bunny", "colour": "red"}, "colour", "Extra inputs are not permitted"),
])
def test_invalid_submissions_answer_422_naming_the_field(served, body, field, words):
    client, keys = served
    res = client.post("/api/v1/jobs", json=body, headers=_auth(keys["operator"]))
    assert res.status_code == 422, res.text
    detail = res.json()["detail"]
    assert any(d["loc"][-1] == field or field in d["loc"] for d in detail), detail
    assert any(words in d["msg"] for d in detail), detail
    assert client.get("/api/v1/jobs", headers=_auth(keys["viewer"])).json()["total"] == 0


def test_a_pose_no_search_view_sees_is_a_422_in_cell_scans_words_and_one_they_see_is_queued(served):
    """0.5,0,0 was a 201, and the job failed with 0 captures: 'JobError: object pose [0.5, 0.0, 0.0] puts
    bunny ... where none of the 2 views vs-local looks for an object from sees it', which ``cell scan``
    refuses before it starts."""
    client, keys = served
    res = client.post("/api/v1/jobs", json={"object": "bunny", "object_pose": [0.5, 0.0, 0.0]},
                      headers=_auth(keys["operator"]))
    assert res.status_code == 422, res.text
    [detail] = res.json()["detail"]
    assert detail["loc"][-1] == "object_pose", detail
    assert detail["msg"].startswith("object pose [0.5, 0.0, 0.0] puts bunny (footprint x "), detail
    assert "where none of the 2 views vs-local looks for an object from sees it: they look at the station" \
        in detail["msg"], detail
    ok = client.post("/api/v1/jobs", json={"object": "bunny", "object_pose": [0.1, 0.1, 0.0]},
                     headers=_auth(keys["operator"]))
    assert ok.status_code == 201, ok.text


def test_the_docs_page_works_without_the_internet(served):
    client, _ = served
    page = client.get("/docs")
    assert page.status_code == 200 and "https://" not in page.text
    script = next(part.split('"')[0] for part in page.text.split('src="')[1:] if "swagger-ui-bundle" in part)
    assert client.get(script).status_code == 200


def test_keys_are_checked_and_never_echoed(served):
    client, keys = served
    assert client.get("/healthz").status_code == 200
    missing = client.get("/api/v1/cell")
    assert missing.status_code == 401 and missing.headers["www-authenticate"] == "Bearer"
    assert client.get("/api/v1/cell", headers=_auth("cell_" + "x" * 43)).status_code == 401
    forbidden = client.post("/api/v1/jobs", json={"object": "bunny"}, headers=_auth(keys["viewer"]))
    assert forbidden.status_code == 403
    for res in (missing, forbidden):
        assert all(k not in res.text for k in keys.values())


def test_a_protective_stop_holds_the_queue_until_the_arm_is_recovered(tmp_path):
    fault = {"at_s": 3.5, "kind": "protective stop"}
    client, keys = _client_with(tmp_path, "faulty", sim={"faults": [fault]})
    op = _auth(keys["operator"])
    with client:
        first = client.post("/api/v1/jobs", json={"object": "bunny", "max_time_s": 8}, headers=op).json()
        second = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 2}, headers=op).json()
        ended = _wait(client, keys["viewer"], first["id"], {"stopped", "failed", "completed"})
        assert ended["status"] == "stopped" and "arm fault: protective stop" in ended["termination"]
        cell = client.get("/api/v1/cell", headers=op).json()
        assert cell["arm"]["protective_stop"] and cell["arm"]["state"] == "protective stop"
        assert "recover" in cell["queue"]["held"]
        time.sleep(0.5)  # a dispatcher that ignored the latch would have started the next job by now
        assert client.get(f"/api/v1/jobs/{second['id']}", headers=op).json()["status"] == "queued"
        assert client.post("/api/v1/queue/resume", headers=op).status_code == 409
        assert client.post("/api/v1/arm/recover", headers=_auth(keys["viewer"])).status_code == 403
        recovered = client.post("/api/v1/arm/recover", headers=op).json()
        assert recovered["ok"] and not recovered["arm"]["faults"]
        assert _wait(client, keys["viewer"], second["id"], {"completed", "failed", "stopped"})["status"] \
            == "completed"


def test_a_worker_that_does_not_confirm_a_stop_is_killed_and_the_job_ends_stopped(tmp_path):
    """A worker that cannot answer a stop in ``stop_confirm_timeout_s`` (still starting on a loaded
    machine, or hung) is killed; the job was stopped by the operator, not failed by itself."""
    # no worker answers in a microsecond
    client, keys = _client_with(tmp_path, "impatient", service={"stop_confirm_timeout_s": 1e-6})
    op = _auth(keys["operator"])
    with client:
        job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 30}, headers=op).json()
        wait_started(client, _auth(keys["viewer"]), job["id"])
        stop = client.post(f"/api/v1/jobs/{job['id']}/stop", json={"reason": "hands in the cell"}, headers=op)
        assert stop.status_code == 200 and "was killed" in stop.json()["message"]
        ended = _wait(client, keys["viewer"], job["id"], {"stopped", "failed", "completed"})
        assert ended["status"] == "stopped", ended["termination"]
        # the operator's stop, as a confirmed one reads, and the kill (it read "safety stop: ...")
        assert ended["termination"].startswith("operator stop: hands in the cell (key "), ended["termination"]
        assert ended["termination"].endswith("and was killed)"), ended["termination"]


def _store_outage(store: Store) -> threading.Event:
    """An event that, while set, makes the store's job updates fail as a database that does not answer."""
    away = threading.Event()
    update = store.update_job

    def flaky(job_id: str, **changes: Any) -> JobRecord:
        if away.is_set():
            raise StoreError("job store: the database does not answer")
        return update(job_id, **changes)

    store.update_job = flaky  # type: ignore[method-assign]
    return away


def test_a_job_store_outage_delays_a_job_start_and_end_but_loses_neither(tmp_path):
    client, keys = _client(tmp_path)
    op, viewer = _auth(keys["operator"]), keys["viewer"]
    with client:
        store = client.app.state.service.store  # type: ignore[attr-defined]
        away = _store_outage(store)
        away.set()
        try:
            first = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 2}, headers=op).json()
            time.sleep(2.5)  # the start tried thrice
            waiting = store.get_job(first["id"])
            assert waiting.status == "queued"
            assert not (Path(waiting.folder) / "frames").exists()  # its worker never had the job
        finally:
            away.clear()
        assert _wait(client, viewer, first["id"], set(FINISHED_STATUSES))["status"] == "completed"

        second = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 2}, headers=op).json()
        _wait(client, viewer, second["id"], {"running"})
        away.set()
        deadline = time.monotonic() + 90.0
        folder = Path(store.get_job(second["id"]).folder)
        while not (folder / "result.json").exists():  # the job ends meanwhile
            assert time.monotonic() < deadline
            time.sleep(0.05)
        time.sleep(1.5)
        assert store.get_job(second["id"]).status == "running"
        # shown running where the store says so, until its end is recorded
        assert client.get("/api/v1/cell", headers=op).json()["job"]["id"] == second["id"]
        away.clear()
        ended = _wait(client, viewer, second["id"], set(FINISHED_STATUSES), timeout_s=10.0)
        assert ended["status"] == "completed" and ended["result"]["status"] == "completed"
        third = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 2}, headers=op).json()
        assert _wait(client, viewer, third["id"], set(FINISHED_STATUSES))["status"] == "completed"


def test_a_stop_ends_a_job_whose_worker_is_still_starting_at_once(tmp_path):
    """A worker loading its libraries cannot confirm a stop for seconds, and has not touched the arm: it
    is ended at once rather than after ``stop_confirm_timeout_s`` (here longer than any load)."""
    client, keys = _client_with(tmp_path, "cold", service={"warm_worker": False,
                                                          "stop_confirm_timeout_s": 60})
    op = _auth(keys["operator"])
    with client:
        job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 30}, headers=op).json()
        stop = client.post(f"/api/v1/jobs/{job['id']}/stop", json={"reason": "wrong part"}, headers=op)
        assert stop.status_code == 200 and stop.json()["arm_commanded"] is False
        ended = _wait(client, keys["viewer"], job["id"], set(FINISHED_STATUSES))
        assert ended["status"] == "stopped", ended["termination"]
        assert "wrong part" in ended["termination"] and "before any motion" in ended["termination"]


def test_a_stop_is_answered_before_the_store_has_its_stopping(tmp_path, monkeypatch):
    """The stop's answer never waits for the store (a slow or lost database held it for its timeout): with
    the record's ``stopping`` write held up, the stop answers, the arm commanded, and the job reads
    ``stopping``, alone and in the list; the record takes it once the store answers."""
    client, keys = _client(tmp_path)
    op = _auth(keys["operator"])
    release, outwaited = threading.Event(), threading.Event()
    with client:
        store = client.app.state.service.store  # type: ignore[attr-defined]
        mark_stopping = store.mark_stopping

        def held(job_id: str) -> bool:
            if not release.wait(20.0):
                outwaited.set()
            return mark_stopping(job_id)

        monkeypatch.setattr(store, "mark_stopping", held)
        job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 30}, headers=op).json()
        wait_started(client, op, job["id"])
        try:
            stop = client.post(f"/api/v1/jobs/{job['id']}/stop", json={"reason": "wrong part"}, headers=op)
            assert stop.status_code == 200 and stop.json()["arm_commanded"] is True, stop.text
            shown = client.get(f"/api/v1/jobs/{job['id']}", headers=op).json()["status"]
            listed = {j["id"]: j["status"] for j in client.get("/api/v1/jobs", headers=op).json()["items"]}
            assert {shown, listed[job["id"]]} <= {"stopping", "stopped"}, (shown, listed)
        finally:
            release.set()
        assert not outwaited.is_set()
        assert _wait(client, keys["viewer"], job["id"], set(FINISHED_STATUSES))["status"] == "stopped"


def _states(client: TestClient, headers: dict[str, str], job_id: str) -> list[str]:
    """The statuses the job's event log said, in order (its ``state`` events)."""
    blocks = client.get(f"/api/v1/jobs/{job_id}/events", headers=headers).text.split("\n\n")
    states = [block.splitlines() for block in blocks if "event: state" in block.splitlines()]
    return [json.loads(line[len("data: "):])["status"] for lines in states for line in lines
            if line.startswith("data: ")]


ENDED_STARTING = ("operator stop: wrong part (key operator) (ended while its worker was starting, before any "
                  "motion)")
"""How a stop of ``wrong part`` by the test's operator key ends a job whose worker had not started it."""


def _held_start(store: Store) -> tuple[threading.Event, threading.Event]:
    """Hold the write of a job's start to the store (the job popped from the queue, its worker not yet
    handed it): the first event is set once the write is held, the second releases it."""
    held, release = threading.Event(), threading.Event()
    update = store.update_job

    def slow_start(job_id: str, **changes: Any) -> JobRecord:
        if changes.get("status") == "running":
            held.set()
            assert release.wait(30.0), "the job's start was never released"
        return update(job_id, **changes)

    store.update_job = slow_start  # type: ignore[method-assign]
    return held, release


def test_a_stop_while_the_next_worker_is_spawned_stops_the_running_job_through_its_guard(tmp_path):
    """The next job's worker is spawned beside a job once the job is announced, never before: a job whose
    worker has it is followed from the start, and a stop while the spare's spawn is under way (held here
    until the test releases it) reaches the moving arm through the worker's guard, as any stop during
    motion does (it had been taken for a stop before any motion and the worker killed)."""
    client, keys = _client_with(tmp_path, "warm", service={"warm_worker": True,
                                                          "stop_confirm_timeout_s": 60})
    op = _auth(keys["operator"])
    spawn = threading.Event()
    with client:
        service = client.app.state.service  # type: ignore[attr-defined]
        deadline = time.monotonic() + 60.0
        # a loaded spare: the job starts at once
        while client.get("/readyz", headers=op).json()["warm_worker"] != "loaded":
            assert time.monotonic() < deadline, "the spare worker never loaded"
            time.sleep(0.02)
        warm = service._warm

        async def held_warm() -> None:
            await asyncio.to_thread(spawn.wait, 60.0)
            await warm()

        service._warm = held_warm
        try:
            job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 30}, headers=op).json()
            live_cloud = Path(service.store.get_job(job["id"]).folder) / "cloud_live.npy"
            while not live_cloud.exists():  # the worker has moved the arm and captured
                assert time.monotonic() < deadline, "the job never captured"
                time.sleep(0.02)
            stop = client.post(f"/api/v1/jobs/{job['id']}/stop", json={"reason": "wrong part"}, headers=op)
            assert stop.status_code == 200, stop.text
            assert stop.json()["arm_commanded"] is True, stop.json()
            cell = client.get("/api/v1/cell", headers=op).json()
            assert cell["job"]["id"] == job["id"] and cell["job"]["status"] == "stopping", cell["job"]
            assert cell["queue"]["held"] is None
        finally:
            spawn.set()
        ended = _wait(client, keys["viewer"], job["id"], set(FINISHED_STATUSES))
        assert ended["status"] == "stopped", ended["termination"]
        assert ended["termination"] == "operator stop: wrong part (key operator)"  # confirmed: no kill
        assert ended["result"]["status"] == "stopped"  # the worker's own result.json, written as it stopped
        assert service.store.get_job(job["id"]).status == "stopped"
        assert _states(client, op, job["id"]) == ["queued", "running", "stopping", "stopped"]
        assert client.get("/api/v1/cell", headers=op).json()["queue"]["held"] is None


def test_a_stop_before_the_worker_has_its_job_reads_running_then_stopping(tmp_path):
    """A stop asked for while the job is being started (its start written to the store, held here) is
    passed on once its worker has it, after the service says the job runs: the worker, which cannot have
    moved, is ended at once, and a page or ``cell jobs wait`` reading the events in order never shows the
    job running again after its stop."""
    client, keys = _client_with(tmp_path, "cold", service={"warm_worker": False,
                                                          "stop_confirm_timeout_s": 60})
    op = _auth(keys["operator"])
    with client:
        held, release = _held_start(client.app.state.service.store)  # type: ignore[attr-defined]
        try:
            job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 30}, headers=op).json()
            assert held.wait(30.0), "the job never started"
            stop = client.post(f"/api/v1/jobs/{job['id']}/stop", json={"reason": "wrong part"}, headers=op)
            assert stop.status_code == 200, stop.text
            assert "before its first motion" in stop.json()["message"], stop.json()
        finally:
            release.set()
        ended = _wait(client, keys["viewer"], job["id"], set(FINISHED_STATUSES))
        assert ended["status"] == "stopped", ended["termination"]
        assert ended["termination"].startswith(ENDED_STARTING), ended["termination"]
        assert _states(client, op, job["id"]) == ["queued", "running", "stopping", "stopped"]


@pytest.mark.parametrize("failures", [1, 2])
def test_an_error_before_a_job_is_announced_still_announces_it_and_passes_on_its_pending_stop_first(
        tmp_path, failures: int):
    """The service's follower failing before it said the job runs (here at the arm's state) leaves nothing
    undone: the job still reads running, then stopping, and an operator's stop asked for while it was
    being started stays the stop it ends with, before the service's own stop for its failure. When the
    announce fails again after the follower's error, the operator's stop is still the one the job ends
    with (it ended ``failed``, the stop dropped, through the dispatcher's catch-all)."""
    client, keys = _client_with(tmp_path, "cold", service={"warm_worker": False,
                                                          "stop_confirm_timeout_s": 60})
    op = _auth(keys["operator"])
    with client:
        service = client.app.state.service  # type: ignore[attr-defined]
        job_started = service.arm.job_started
        failed: list[bool] = []

        def failing() -> None:
            if len(failed) < failures:
                failed.append(True)
                raise RuntimeError("a bug")
            job_started()

        service.arm.job_started = failing
        held, release = _held_start(service.store)
        try:
            job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 30}, headers=op).json()
            assert held.wait(30.0), "the job never started"
            stop = client.post(f"/api/v1/jobs/{job['id']}/stop", json={"reason": "wrong part"}, headers=op)
            assert stop.status_code == 200, stop.text
        finally:
            release.set()
        ended = _wait(client, keys["viewer"], job["id"], set(FINISHED_STATUSES))
        assert failed == [True] * failures
        assert ended["status"] == "stopped", ended["termination"]
        assert ended["termination"].startswith(ENDED_STARTING), ended["termination"]
        if failures == 1:
            assert _states(client, op, job["id"]) == ["queued", "running", "stopping", "stopped"]
        second = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 1}, headers=op).json()
        assert _wait(client, keys["viewer"], second["id"], set(FINISHED_STATUSES))["status"] == "completed"


def test_two_stops_at_once_of_a_worker_that_confirms_neither_end_the_job_with_the_first(tmp_path):
    """An operator's stop and the line's behind it (``stop_all``) both time out on a wedged worker: the job
    and the queue's hold name the first stop's cause; the second, arriving while the first waited, had
    overwritten it."""
    client, keys = _client_with(tmp_path, "c", service={"warm_worker": False, "stop_confirm_timeout_s": 1.0})
    op = _auth(keys["operator"])
    with client:
        service = client.app.state.service  # type: ignore[attr-defined]
        job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 30}, headers=op).json()
        wait_started(client, op, job["id"])
        os.killpg(service._running.proc.pid, signal.SIGSTOP)  # a worker that confirms nothing

        async def both() -> None:
            await asyncio.gather(service.stop_job(job["id"], "first (key operator)"),
                                 service.stop_job(job["id"], "second (key line)"))

        client.portal.call(both)  # type: ignore[union-attr]
        ended = _wait(client, keys["viewer"], job["id"], set(FINISHED_STATUSES))
        assert "first" in ended["termination"] and "second" not in ended["termination"], ended["termination"]
        held = client.get("/api/v1/cell", headers=op).json()["queue"]["held"]
        assert "first" in held and "second" not in held, held


def test_a_worker_that_dies_holds_the_queue_until_an_operator_resumes_it(tmp_path):
    client, keys = _client(tmp_path)
    op, viewer = _auth(keys["operator"]), keys["viewer"]
    with client:
        store = client.app.state.service.store  # type: ignore[attr-defined]
        first = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 30}, headers=op).json()
        second = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 2}, headers=op).json()
        wait_started(client, _auth(viewer), first["id"])
        os.kill(store.get_job(first["id"]).worker_pid, signal.SIGKILL)
        ended = _wait(client, viewer, first["id"], set(FINISHED_STATUSES))
        assert ended["status"] == "failed"
        assert "ended unexpectedly (killed by SIGKILL)" in ended["termination"]
        held = client.get("/api/v1/cell", headers=op).json()["queue"]["held"]
        assert "worker ended unexpectedly" in held and "check the arm" in held
        time.sleep(1.0)  # what would start the next job starts at once: a second is ample
        assert client.get(f"/api/v1/jobs/{second['id']}", headers=op).json()["status"] == "queued"
        assert client.post("/api/v1/queue/resume", headers=op).status_code == 200
        assert _wait(client, viewer, second["id"], set(FINISHED_STATUSES))["status"] == "completed"


def test_a_store_outage_keeps_a_queued_job_a_stop_could_not_cancel_and_does_not_fail_the_shutdown(tmp_path):
    client, keys = _client(tmp_path)
    op = _auth(keys["operator"])
    with client:
        store = client.app.state.service.store  # type: ignore[attr-defined]
        away = _store_outage(store)
        assert client.post("/api/v1/stop", headers=op).status_code == 200  # the queue held
        first, second = (client.post("/api/v1/jobs", json={"object": "cube"}, headers=op).json()
                         for _ in range(2))
        away.set()
        refused = client.post(f"/api/v1/jobs/{first['id']}/stop", headers=op)
        assert refused.status_code == 503
        assert client.get("/api/v1/cell", headers=op).json()["queue"]["length"] == 2  # kept, in order
        away.clear()
        assert client.post(f"/api/v1/jobs/{first['id']}/stop", headers=op).status_code == 200
        assert store.get_job(first["id"]).status == "cancelled"
        away.set()  # the service shuts down while the store is away
    assert store.get_job(second["id"]).status == "queued"  # the next start cancels it


def _open_pipes() -> int:
    """The pipes this process holds open (a worker's stdin and stdout are pipes)."""
    pipes = 0
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(FileNotFoundError):  # the listing's own descriptor, closed by now
            pipes += os.readlink(f"/proc/self/fd/{fd}").startswith("pipe:")
    return pipes


def test_a_service_shut_down_kills_its_spare_worker_and_leaves_none_of_its_pipes_open(tmp_path, monkeypatch):
    """The warm spare worker, still loading when the service shuts down, is killed rather than waited for
    (it would read the end of its input only once loaded, seconds later), with its pipes closed while the
    event loop runs. Awaiting only its exit left its output pipe open, to be closed by the garbage
    collector on the ended loop: "Event loop is closed" raised in a finaliser, which on CPython 3.11
    could land inside an unrelated ``ast.parse``."""
    client, _ = _client(tmp_path)
    unraisable: list[Any] = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    before = _open_pipes()
    for _ in range(3):
        with client:
            spare = client.app.state.service._spare
            assert spare is not None and spare.returncode is None
        assert spare.returncode == -signal.SIGKILL
        assert _open_pipes() == before
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ResourceWarning)
        gc.collect()
    assert [(u.exc_type, str(u.exc_value)) for u in unraisable] == []


def test_readyz_says_whether_the_next_jobs_worker_has_loaded(tmp_path):
    """``/readyz`` answers 200 while the warm spare imports its libraries (a job would wait for them) and
    says so, ``loading``, then ``loaded`` once the spare's notice came; a cell without a warm worker says
    ``off``."""
    client, keys = _client(tmp_path)
    viewer = _auth(keys["viewer"])
    seen: list[str] = []
    with client:
        deadline = time.monotonic() + 60.0
        while not seen or seen[-1] != "loaded":
            assert time.monotonic() < deadline, seen
            answer = client.get("/readyz", headers=viewer)
            assert answer.status_code == 200, answer.json()
            seen.append(answer.json()["warm_worker"])
            time.sleep(0.02)
        assert set(seen) <= {"loading", "loaded"}
    (tmp_path / "cold").mkdir()
    client, keys = _client_with(tmp_path / "cold", "cold", service={"warm_worker": False})
    with client:
        assert client.get("/readyz", headers=_auth(keys["viewer"])).json()["warm_worker"] == "off"


def _spawns_fail(service: Any) -> threading.Event:
    """An event that, while set, makes the service's worker processes fail to start as a process out of
    file descriptors does (its worker's log file cannot be opened)."""
    out = threading.Event()
    start = service._start_worker

    async def failing(log_path: Path, label: str) -> Any:
        if out.is_set():
            raise OSError(errno.EMFILE, "Too many open files", str(log_path))
        return await start(log_path, label)

    service._start_worker = failing
    return out


def test_a_stale_network_mount_as_jobs_folder_keeps_jobs_waiting(tmp_path, monkeypatch):
    """A jobs folder on a network mount gone stale (ESTALE; EIO from a failing disk alike) was no verdict
    on the folder: each queued job started and failed within a second. It waits now, as on a read-only
    folder, and starts once the folder takes files again."""
    import cell.service.manager as manager

    stale = threading.Event()
    make = manager.tempfile.TemporaryFile

    def probing(*args: Any, **kwargs: Any) -> Any:
        if stale.is_set():
            raise OSError(errno.ESTALE, "Stale file handle")
        return make(*args, **kwargs)

    monkeypatch.setattr(manager.tempfile, "TemporaryFile", probing)
    client, keys = _client(tmp_path)
    op = _auth(keys["operator"])
    with client:
        stale.set()
        job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 1}, headers=op).json()
        deadline = time.monotonic() + 30.0
        while "is not writable (Stale file handle)" not in str(
                client.get("/api/v1/cell", headers=op).json()["queue"]["held"]):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert client.get(f"/api/v1/jobs/{job['id']}", headers=op).json()["status"] == "queued"
        stale.clear()
        assert _wait(client, keys["viewer"], job["id"], set(FINISHED_STATUSES))["status"] == "completed"


def test_a_worker_that_cannot_be_started_never_leaves_a_job_untracked_and_the_service_recovers(tmp_path,
                                                                                               caplog):
    """Out of file descriptors, the warm spare beside a running job cannot be started: the running job is
    followed to its end all the same (it was marked failed while its worker scanned on, untracked, and the
    dispatcher died for good), the next job waits in the queue saying why (``/readyz`` too), the failure is
    logged once, and the next job runs by itself once worker processes start again."""
    client, keys = _client(tmp_path)
    op, viewer = _auth(keys["operator"]), keys["viewer"]
    with client, caplog.at_level(logging.INFO, logger="cell.service"):
        service = client.app.state.service  # type: ignore[attr-defined]
        assert service._spare is not None  # the first job takes it; no other can start
        out = _spawns_fail(service)
        out.set()
        first, second = (client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 2},
                                     headers=op).json() for _ in range(2))
        assert _wait(client, viewer, first["id"], set(FINISHED_STATUSES))["status"] == "completed"
        time.sleep(2.5)  # the second job's start tried twice or more
        assert client.get(f"/api/v1/jobs/{second['id']}", headers=op).json()["status"] == "queued"
        cell = client.get("/api/v1/cell", headers=op).json()
        assert cell["job"] is None and "Too many open files" in cell["queue"]["held"]
        ready = client.get("/readyz", headers=op)  # a job submitted now would not run: not ready
        assert ready.status_code == 503 and "Too many open files" in ready.json()["status"]
        out.clear()
        _wait(client, viewer, second["id"], {"running"})
        assert client.get("/api/v1/cell", headers=op).json()["job"]["id"] == second["id"]
        assert _wait(client, viewer, second["id"], set(FINISHED_STATUSES))["status"] == "completed"
        assert client.get("/api/v1/cell", headers=op).json()["queue"]["held"] is None
    failures = [r.getMessage() for r in caplog.records if "could not be started" in r.getMessage()]
    assert len(failures) == 1 and "trying again" in failures[0], failures
    assert any(r.getMessage() == "worker processes start again" for r in caplog.records)


def test_an_error_of_the_service_while_a_job_runs_stops_it_through_its_worker_and_records_its_end(tmp_path):
    """A job whose worker has it is never left to itself: an error of the service while it follows the
    job (here taking its first progress) stops it through its worker, whose guard stops the arm, and
    its end is recorded (it was marked failed at once while its worker scanned on); the next job runs."""
    client, keys = _client(tmp_path)
    op, viewer = _auth(keys["operator"]), keys["viewer"]
    with client:
        service = client.app.state.service  # type: ignore[attr-defined]
        take = service._take
        failed: list[str] = []

        def failing_once(running: Any, message: dict[str, Any]) -> None:
            if message.get("type") == "progress" and not failed:
                failed.append(running.job.id)
                raise RuntimeError("a bug")
            take(running, message)

        service._take = failing_once
        first = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 60}, headers=op).json()
        ended = _wait(client, viewer, first["id"], set(FINISHED_STATUSES))
        assert failed == [first["id"]]
        assert ended["status"] == "stopped", ended["termination"]
        # the service stopped it, nobody asked: the safety layer's stop, not an operator's
        assert ended["termination"].startswith("safety stop: the service failed while it ran the job "
                                               "(RuntimeError: a bug)"), ended["termination"]
        assert ended["result"]["status"] == "stopped"  # the worker's own result.json, written as it stopped
        second = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 1}, headers=op).json()
        assert _wait(client, viewer, second["id"], set(FINISHED_STATUSES))["status"] == "completed"


def test_a_dispatcher_that_ends_on_an_error_is_logged_and_makes_the_service_not_ready(tmp_path, caplog):
    """An error the job dispatcher did not expect ends it: said in the log and in the queue's hold, and
    ``/readyz`` answers 503 (``cell.api.server`` stops the systemd watchdog's pings on it)."""
    client, keys = _client(tmp_path)
    op = _auth(keys["operator"])
    with client, caplog.at_level(logging.INFO, logger="cell.service"):
        service = client.app.state.service  # type: ignore[attr-defined]

        def broken() -> bool:
            raise RuntimeError("a bug")

        service._may_start = broken
        client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 1}, headers=op)
        deadline = time.monotonic() + 30.0
        while client.get("/readyz", headers=op).status_code != 503:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        held = client.get("/api/v1/cell", headers=op).json()["queue"]["held"]
        assert "dispatcher stopped" in held and "RuntimeError: a bug" in held and service.broken == held
    assert any(r.levelno == logging.CRITICAL and "dispatcher stopped" in r.getMessage()
               for r in caplog.records)


def test_a_job_folder_listing_never_holds_the_event_loop_and_so_a_stop(served, monkeypatch):
    """Listing a job folder walks it and stats every file (a scan's thousands of frames): on a thread, a
    STOP answers while a listing still walks (here one held until the STOP has answered). On the event
    loop, the STOP waited for it: 0.66-2.15 s under 100 viewers."""
    client, keys = served
    op = _auth(keys["operator"])
    assert client.post("/api/v1/stop", json={"reason": "a folder to list"}, headers=op).status_code == 200
    job = client.post("/api/v1/jobs", json={"object": "cube"}, headers=op).json()
    Path(client.app.state.service.store.get_job(job["id"]).folder).mkdir(parents=True)  # type: ignore[attr-defined]
    walking, stopped = threading.Event(), threading.Event()
    released: list[bool] = []
    rglob = Path.rglob

    def held_rglob(self: Path, pattern: str) -> Any:
        walking.set()
        released.append(stopped.wait(30.0))  # a bound on waiting: False when the STOP never answered
        return rglob(self, pattern)

    monkeypatch.setattr(Path, "rglob", held_rglob)
    listing = threading.Thread(target=lambda: client.get(f"/api/v1/jobs/{job['id']}/files", headers=op))
    listing.start()
    assert walking.wait(30.0)
    stop = client.post("/api/v1/stop", json={"reason": "hands in the cell"}, headers=op)
    stopped.set()
    listing.join(60.0)
    assert stop.status_code == 200 and released == [True]


def test_a_fault_that_ends_a_stopped_job_goes_first_in_the_queues_hold(served, monkeypatch):
    """A job stopped by the operator whose end names an arm fault (the fault came as the arm stopped):
    the fault was kept only in the arm's live latch, since a hold (the STOP's) was already there, so a
    restart forgot it and the next resume ran a job on the faulted arm. It now goes first in the hold,
    and the recovery leaves the STOP's part for the operator's resume."""
    from cell.service.arm_status import ArmTracker

    def faulted(self: ArmTracker, termination: str) -> str:  # the job's end names the fault
        self.latch("protective stop")
        return "protective stop"

    monkeypatch.setattr(ArmTracker, "job_ended", faulted)
    client, keys = served
    op = _auth(keys["operator"])
    job = client.post("/api/v1/jobs", json={"object": "bunny", "max_time_s": 60}, headers=op).json()
    _wait(client, keys["viewer"], job["id"], {"running"})
    assert client.post("/api/v1/stop", json={"reason": "hands in"}, headers=op).status_code == 200
    _wait(client, keys["viewer"], job["id"], {"stopped"})
    service = client.app.state.service  # type: ignore[attr-defined]
    deadline = time.monotonic() + 10.0  # the hold is written beside, by a task of its own
    while not (stored := service.store.get_hold(service.name).reason).startswith("the arm reported a fault"):
        assert time.monotonic() < deadline, stored
        time.sleep(0.05)
    assert stored.startswith("the arm reported a fault: protective stop") and \
        "; then held after a stop (hands in" in stored, stored
    assert client.post("/api/v1/arm/recover", headers=op).status_code == 200
    assert client.get("/api/v1/cell", headers=op).json()["queue"]["held"].startswith(
        "held after a stop (hands in")
    assert client.post("/api/v1/queue/resume", headers=op).status_code == 200
    assert client.get("/api/v1/cell", headers=op).json()["queue"]["held"] is None


def test_a_stop_of_a_job_whose_end_is_recorded_is_refused_while_its_worker_exits(served, monkeypatch):
    """A job stopped, its end recorded, its worker still exiting (a loaded machine): a second stop was
    answered 200 "the job had already ended" while its record said ``stopped``; it is now refused as for
    any ended job."""
    from cell.service.manager import CellService

    finish = CellService._finish

    async def exits_slowly(self: CellService, *args: Any, **kwargs: Any) -> None:
        await asyncio.sleep(2.0)
        await finish(self, *args, **kwargs)

    monkeypatch.setattr(CellService, "_finish", exits_slowly)
    client, keys = served
    op = _auth(keys["operator"])
    job = client.post("/api/v1/jobs", json={"object": "bunny", "max_time_s": 60}, headers=op).json()
    deadline = time.monotonic() + 60.0  # its worker has the job (its first progress): it writes the end
    while client.get(f"/api/v1/jobs/{job['id']}", headers=op).json()["progress"] is None:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert client.post(f"/api/v1/jobs/{job['id']}/stop", headers=op).status_code == 200
    _wait(client, keys["viewer"], job["id"], {"stopped"})
    service = client.app.state.service  # type: ignore[attr-defined]
    assert service._running is not None and service._running.job.id == job["id"]  # its worker still exits
    again = client.post(f"/api/v1/jobs/{job['id']}/stop", headers=op)
    assert again.status_code == 409, again.text
    assert again.json()["detail"] == f"job {job['id']} is stopped: nothing to stop"


def test_stop_holds_the_queue_and_resume_releases_it(served):
    client, keys = served
    op = _auth(keys["operator"])
    stop = client.post("/api/v1/stop", json={"reason": "hands in the cell"}, headers=_auth(keys["viewer"]))
    assert stop.status_code == 200 and stop.json() == {
        "job_id": None, "arm_commanded": False, "queue_held": True,
        "message": "nothing was moving; the queue is held"}
    job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 1}, headers=op).json()
    time.sleep(0.5)
    assert client.get(f"/api/v1/jobs/{job['id']}", headers=op).json()["status"] == "queued"
    assert "hands in the cell" in client.get("/api/v1/cell", headers=op).json()["queue"]["held"]
    # a queued job can be cancelled, and its event stream ends
    cancelled = client.delete(f"/api/v1/jobs/{job['id']}", headers=op)
    assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
    events = client.get(f"/api/v1/jobs/{job['id']}/events", headers=op).text
    assert "event: result" in events and '"cancelled"' in events
    again = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 1}, headers=op).json()
    assert client.post("/api/v1/queue/resume", headers=op).json()["queue"]["held"] is None
    done = _wait(client, keys["viewer"], again["id"], {"completed", "failed", "stopped"})
    assert done["status"] == "completed" and done["result"]["control"]["n_ticks"] > 0
    metrics = client.get("/metrics", headers=op).text
    assert 'cell_jobs{status="completed"} 1.0' in metrics and 'cell_jobs{status="cancelled"} 1.0' in metrics
    assert "cell_control_tick_period_seconds_count" in metrics
    assert 'cell_scan_duration_seconds_count{planner="vs-local"} 1.0' in metrics
    # an ended job is purged by an admin only
    refused = client.delete(f"/api/v1/jobs/{again['id']}", headers=op)
    assert refused.status_code == 403
    assert refused.json()["detail"] == "an operator key may not purge an ended job"  # not "a operator"
    assert client.delete(f"/api/v1/jobs/{again['id']}", headers=_auth(keys["admin"])).status_code == 200
    assert client.get(f"/api/v1/jobs/{again['id']}", headers=op).status_code == 404


def test_stop_is_never_refused_for_its_body(served):
    """Every valid key may stop, whatever body it sends: one that a model would refuse (an empty, absent
    or non-string reason, an extra field, not JSON, NaN, far too long) stops as the default reason does,
    and a reason's control characters cannot forge a line of the job's log, nor its words the stop's kind
    (a client's ``shutdown stop:`` was recorded as the service's shutdown)."""
    client, keys = served
    viewer, op = _auth(keys["viewer"]), _auth(keys["operator"])
    job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 60}, headers=op).json()
    _wait(client, keys["viewer"], job["id"], {"running"})
    forged = "shutdown stop: safety stop:lunch\n[    1.000] completed: forged\u001b[31m"
    stop = client.post(f"/api/v1/jobs/{job['id']}/stop", json={"reason": forged, "why": "extra"},
                       headers=viewer)
    assert stop.status_code == 200 and stop.json()["job_id"] == job["id"]
    done = _wait(client, keys["viewer"], job["id"], {"stopped", "completed", "failed"})
    assert done["status"] == "stopped"
    assert done["termination"].startswith("operator stop: lunch [ 1.000] completed: forged [31m (key viewer)")
    log = client.get(f"/api/v1/jobs/{job['id']}/files/log.txt", headers=viewer).text
    assert not any(line.startswith("[    1.000] completed: forged") for line in log.splitlines())
    json_type = {"content-type": "application/json"}
    for body in (b'{"reason": ""}', b'{"reason": null}', b'{"reason": NaN}', b"not json", b"",
                 json.dumps({"reason": "x" * 100_000}).encode()):
        answer = client.post("/api/v1/stop", content=body, headers={**viewer, **json_type})
        assert answer.status_code == 200 and answer.json()["queue_held"], (body[:20], answer.text)
        held = client.get("/api/v1/cell", headers=viewer).json()["queue"]["held"]
        assert "requested over the API (key viewer)" in held
    assert client.post("/api/v1/stop", json={"reason": "x"}, headers={}).status_code == 401
    client.post("/api/v1/queue/resume", headers=op)


def test_a_body_over_its_bound_is_refused_unread_and_nan_is_a_422(served):
    """A JSON body over ``JSON_MAX_BYTES`` is answered 413 before anything reads it, whether it gives its
    length or not; a NaN or infinite number is a 422 naming the field (FastAPI's own answer failed on
    echoing it, a 500)."""
    client, keys = served
    op = _auth(keys["operator"])
    big = json.dumps({"object": "a" * JSON_MAX_BYTES}).encode()
    assert client.post("/api/v1/jobs", content=big, headers={**op, "content-type": "application/json"}
                       ).status_code == 413
    chunked = client.post("/api/v1/jobs", content=iter([big[:1000], big[1000:]]),
                          headers={**op, "content-type": "application/json"})
    assert chunked.status_code == 413 and f"over {JSON_MAX_BYTES} bytes" in chunked.json()["detail"]
    for field, body in (("max_time_s", b'{"object": "bunny", "max_time_s": NaN}'),
                        ("object_pose", b'{"object": "bunny", "object_pose": [Infinity, 0, 0]}')):
        answer = client.post("/api/v1/jobs", content=body, headers={**op, "content-type": "application/json"})
        assert answer.status_code == 422, answer.text
        assert answer.json()["detail"][0]["loc"][:2] == ["body", field]
    assert client.get("/api/v1/jobs", headers=op).status_code == 200  # the service is fine


def test_a_request_without_a_valid_key_is_a_401_before_its_body_is_read(served):
    """The key is checked before the body is read or parsed: no key, an unknown one or a revoked one is
    a 401 whatever the body (FastAPI parsed it first: ``{bad`` was a 422, and a large body was read and
    parsed for a client with no key); a valid key's role is checked by the route as before."""
    client, keys = served
    read: list[bytes] = []

    def body() -> Iterator[bytes]:
        read.append(b"{bad")
        yield b"{bad"

    app = client.app
    app.state.service.store.revoke_key("admin")
    app.state.keys.refresh()
    json_type = {"content-type": "application/json"}
    for headers in ({}, _auth("cell_" + "x" * 43), {"Authorization": "Basic " + keys["operator"]},
                    _auth(keys["admin"])):
        answer = client.post("/api/v1/jobs", content=body(), headers={**headers, **json_type})
        assert answer.status_code == 401, answer.text
        assert answer.headers["www-authenticate"] == "Bearer" and "valid API key" in answer.json()["detail"]
        assert client.post("/api/v1/line/command", content=b"{bad", headers={**headers, **json_type}
                           ).status_code == 401
    assert read == []
    # a valid key with too low a role is the route's 403; a valid key's bad body its 422
    viewer = client.post("/api/v1/jobs", json={"object": "bunny"}, headers=_auth(keys["viewer"]))
    assert viewer.status_code == 403
    assert client.post("/api/v1/jobs", content=b"{bad", headers={**_auth(keys["operator"]), **json_type}
                       ).status_code == 422
    # what needs no key still answers without one
    assert client.get("/healthz").status_code == 200
    assert client.get("/api/v1/openapi.json").status_code == 200
    assert client.get("/api/v1/no-such-route").status_code == 404


def test_a_lone_surrogate_in_a_refused_body_is_a_422_that_echoes_it_escaped(served):
    """A JSON string may hold a lone surrogate (``"\\ud800"``), which is no UTF-8: the 422 that echoed it
    failed to encode, a 500. It is a 422 naming the field, the input escaped as the client wrote it."""
    client, keys = served
    headers = {**_auth(keys["operator"]), "content-type": "application/json"}
    for field, escaped, body in (
            ("object", b"\\ud800", b'{"object": "\\ud800"}'),
            ("part_id", b"\\udfff", b'{"object": "bunny", "part_id": "\\udfff"}'),
            ("max_time_s", b"x\\ud800", b'{"object": "bunny", "max_time_s": "x\\ud800"}')):
        answer = client.post("/api/v1/jobs", content=body, headers=headers)
        assert answer.status_code == 422, answer.text
        assert answer.json()["detail"][0]["loc"] == ["body", field]
        assert b'"input":"' + escaped + b'"' in answer.content
    assert client.get("/api/v1/jobs", headers=headers).json()["total"] == 0


def test_a_mesh_whose_header_promises_more_than_it_holds_is_refused_and_the_list_stays_whole(served):
    """A 180-byte PLY declaring 200 million vertices made the reader allocate 10 GB; one declaring two
    billion failed outside the upload's error handling, left its staging file, and GET /objects answered
    500 from then on, for every key and after a restart."""
    client, keys = served
    op = _auth(keys["operator"])
    header = (b"ply\nformat binary_little_endian 1.0\nelement vertex 200000000\nproperty float x\n"
              b"property float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\n"
              b"end_header\n")
    answer = client.post("/api/v1/objects", files={"file": ("huge.ply", header)}, headers=op)
    assert answer.status_code == 422 and "declares elements of at least 2400000001 bytes" in answer.text
    folder = client.app.state.service.objects.folder
    (folder / ".upload-stale.ply").write_bytes(header)  # a staging file an older service left
    (folder / "broken.ply").write_bytes(header)  # an uploaded file that no longer reads
    listed = client.get("/api/v1/objects", headers=op)
    assert listed.status_code == 200
    names = {o["name"] for o in listed.json()}
    assert "bunny" in names and not names & {"huge", ".upload-stale", ".upload-huge", "broken"}


def test_an_uploaded_mesh_is_validated_and_scannable(served, tmp_path):
    client, keys = served
    op = _auth(keys["operator"])
    mesh = load_object("cube")

    def stl(scale: float) -> bytes:
        corners = mesh.vertices[mesh.triangles] * scale
        facets = ["facet normal 0 0 0\nouter loop\n" + "".join(f"vertex {x} {y} {z}\n" for x, y, z in c)
                  + "endloop\nendfacet" for c in corners]
        return "\n".join(["solid part", *facets, "endsolid part"]).encode()

    # a CAD export in millimetres: refused, saying what a scale would make of it; accepted with that scale
    mm = client.post("/api/v1/objects", files={"file": ("Part MM.stl", stl(1000.0))}, headers=op)
    assert mm.status_code == 422 and mm.json()["detail"][0]["loc"][-1] == "file"
    assert ("object Part MM is 100.000 x 100.000 x 100.000 m" in mm.text
            and "the upload's scale 0.001 would make it 0.100 x 0.100 x 0.100 m" in mm.text)
    scaled = client.post("/api/v1/objects", files={"file": ("Part MM.stl", stl(1000.0))},
                         data={"scale": "0.001"}, headers=op)
    assert scaled.status_code == 201, scaled.text
    assert scaled.json()["name"] == "part_mm" and scaled.json()["extents_m"] == pytest.approx([0.1] * 3)
    reserved = client.post("/api/v1/objects", files={"file": ("none.stl", stl(1.0))}, headers=op)
    assert reserved.status_code == 409  # the name of an empty table
    ok = client.post("/api/v1/objects", files={"file": ("My Part.stl", stl(1.0))}, headers=op)
    assert ok.status_code == 201, ok.text
    assert ok.json()["name"] == "my_part"
    names = [o["name"] for o in client.get("/api/v1/objects", headers=op).json()]
    assert "my_part" in names and "bunny" in names
    taken = client.post("/api/v1/objects", files={"file": ("my_part.stl", b"x")}, headers=op)
    assert taken.status_code == 409
    bad = client.post("/api/v1/objects", files={"file": ("junk.ply", b"not a mesh")}, headers=op)
    assert bad.status_code == 422 and bad.json()["detail"][0]["loc"][-1] == "file"
    job = client.post("/api/v1/jobs", json={"object": "my_part", "max_time_s": 1}, headers=op)
    assert job.status_code == 201 and job.json()["object"] == "my_part"
    empty = client.post("/api/v1/jobs", json={"object": "none", "max_time_s": 1}, headers=op)
    assert empty.status_code == 201 and empty.json()["object"] == "none"


def test_event_logs_resume_after_the_last_id_and_wake_followers():
    async def scenario() -> list[Any]:
        log = JobEvents()
        log.publish("state", {"status": "queued"})
        log.publish("progress", {"t_s": 1.0})
        assert [e.id for e in log.after(0)] == [1, 2] and [e.id for e in log.after(1)] == [2]
        seen: list[Any] = []

        async def follow() -> None:
            async for event in log.follow(1, idle_s=0.05):
                seen.append(None if event is None else (event.id, event.kind))

        task = asyncio.create_task(follow())
        await asyncio.sleep(0.12)
        log.publish("result", {"status": "completed"})
        await asyncio.wait_for(task, 1.0)
        return seen

    seen = asyncio.run(scenario())
    assert seen[0] == (2, "progress") and seen[-1] == (3, "result")
    assert None in seen  # keep-alives while nothing happened


def _job(tmp_path: Path, status: str, name: str) -> JobRecord:
    return JobRecord(id=name, cell="c", status=status, planner="vs-local", object="bunny",
                     object_pose=(0.0, 0.0, 0.0), seed=0, max_time_s=None, part_id=None,
                     folder=str(tmp_path / "jobs" / name), submitted_by="op", created_at=datetime.now(UTC))


def test_a_restart_settles_running_and_queued_jobs(tmp_path):
    store = open_data_store(tmp_path, sqlite_url(tmp_path))
    killed, finished, queued = (_job(tmp_path, s, n) for s, n in (
        ("running", "a" * 16), ("running", "b" * 16), ("queued", "c" * 16)))
    for job in (killed, finished, queued):
        store.add_job(job)
    frames = Path(killed.folder) / "frames"
    frames.mkdir(parents=True)
    (frames / "index.csv").write_text("seq,t,file,n_points\n0,0.1,000000.npz,10\n1,1.1,000001.npz,12\n")
    (Path(killed.folder) / "log.txt").write_text("[    0.000] job: ...\n")
    Path(finished.folder).mkdir(parents=True)
    outcome = {"status": "completed", "termination": "done"}
    (Path(finished.folder) / "result.json").write_text(json.dumps(outcome))

    reconcile(store, "c", worker_wait_s=0.1)

    got = store.get_job(killed.id)
    assert got is not None and got.status == "interrupted" and got.termination == RESTART_TERMINATION
    written = json.loads((Path(killed.folder) / "result.json").read_text())
    assert written["status"] == "interrupted" and written["n_captures"] == 2
    assert RESTART_TERMINATION in (Path(killed.folder) / "log.txt").read_text()
    done = store.get_job(finished.id)
    assert done is not None and done.status == "completed" and done.termination == "done"
    cancelled = store.get_job(queued.id)
    assert cancelled is not None
    assert (cancelled.status, cancelled.termination) == ("cancelled", RESTART_CANCEL)
    store.close()


def _worker_like(folder: Path, after_s: float) -> subprocess.Popen[bytes]:
    """A process that looks like the warm spare a job was given (the worker module in its command line,
    and ``spare`` where a job id would be): it writes the job's ``result.json`` after ``after_s`` [s], as
    a worker whose service went away does."""
    script = ("import json, sys, time; time.sleep(float(sys.argv[4])); "
              "open(sys.argv[3], 'w').write(json.dumps({'status': 'stopped', 'termination': sys.argv[5]}))")
    return subprocess.Popen([sys.executable, "-c", script, WORKER_MODULE, "spare",
                             str(folder / "result.json"), str(after_s), f"safety stop: {SERVICE_GONE}"])


def test_a_restart_keeps_the_end_a_job_recorded_in_its_folder_and_holds_after_an_arm_fault(tmp_path):
    """A job that ended by itself while the store did not answer, the service then killed: its folder's
    end stands (not ``interrupted``), and an arm fault holds its cell's queue in the store; a job's own
    failure holds nothing."""
    store = open_data_store(tmp_path, sqlite_url(tmp_path))
    faulted = _job(tmp_path, "running", "f" * 16)
    failed = replace(_job(tmp_path, "running", "0" * 16), cell="d")
    ends = {faulted.id: ("stopped", "safety stop: arm fault: protective stop"),
            failed.id: ("failed", "PlanningError: no view reachable")}
    for job in (faulted, failed):
        store.add_job(job)
        Path(job.folder).mkdir(parents=True)
        status, termination = ends[job.id]
        result = {"status": status, "termination": termination}
        (Path(job.folder) / "result.json").write_text(json.dumps(result))
    try:
        settled = reconcile(store, "c", worker_wait_s=0.1) + reconcile(store, "d", worker_wait_s=0.1)
        for job in (faulted, failed):
            got = store.get_job(job.id)
            assert got is not None and (got.status, got.termination) == ends[job.id]
            assert json.loads((Path(job.folder) / "result.json").read_text())["status"] == ends[job.id][0]
        hold = store.get_hold("c")
        # held as a fault (latched by the start, released by the arm's recovery), not as a resumable end
        assert hold is not None and held_fault(hold.reason) == "protective stop", hold
        assert "recover the arm first" in hold.reason
        assert store.get_hold("d") is None
        assert any("held" in line for line in settled)
    finally:
        store.close()


def test_a_restart_waits_for_the_warm_worker_of_a_running_job_and_not_for_a_reused_pid(tmp_path, caplog):
    store = open_data_store(tmp_path, sqlite_url(tmp_path))
    now = datetime.now(UTC)
    job = replace(_job(tmp_path, "running", "d" * 16), started_at=now + timedelta(seconds=1))
    Path(job.folder).mkdir(parents=True)
    worker = _worker_like(Path(job.folder), after_s=1.0)
    store.add_job(replace(job, worker_pid=worker.pid))
    # a job that started a minute before a process of the worker module took its worker's pid
    old = replace(_job(tmp_path, "running", "e" * 16), started_at=now - timedelta(seconds=60))
    Path(old.folder).mkdir(parents=True)
    stranger = _worker_like(Path(old.folder), after_s=30.0)
    store.add_job(replace(old, worker_pid=stranger.pid))
    try:
        began = time.monotonic()
        with caplog.at_level(logging.INFO, logger="cell.service"):
            reconcile(store, "c", worker_wait_s=20.0)
        assert time.monotonic() - began < 10.0  # the stranger was neither waited for nor signalled
        waits = [r.getMessage() for r in caplog.records if "waiting for worker pid" in r.getMessage()]
        assert len(waits) == 1 and f"pid {worker.pid} " in waits[0] and "up to 20 s" in waits[0], waits
        # on failure, what the reconcile judged the worker by
        assert worker.poll() == 0 and stranger.poll() is None, \
            f"worker started {_started(worker.pid) - now.timestamp():+.3f} s after now (its job at +1 s)"
        written = json.loads((Path(job.folder) / "result.json").read_text())
        assert written["status"] == "interrupted" and written["worker"]["status"] == "stopped"
        got = store.get_job(job.id)
        assert got is not None and got.result == written and got.status == "interrupted"
    finally:
        stranger.kill()
        stranger.wait()
        store.close()


def test_an_object_must_stand_on_the_table():
    cfg = load_config(FRANKA)
    bunny = load_object("bunny")
    check_on_table(cfg, bunny, (0.1, -0.2, 45.0))
    with pytest.raises(JobError, match=r"off the table: .* the table spans x -0.100..1.100 m"):
        check_on_table(cfg, bunny, (0.63, 0.0, 0.0))


def test_cell_scan_refuses_an_object_off_the_table_before_making_its_folder(tmp_path):
    out = tmp_path / "job"
    res = CliRunner().invoke(cli, ["scan", "--object", "bunny", "--object-pose", "2,2,0", "--out", str(out)])
    assert res.exit_code == 1 and "off the table" in res.output
    assert not out.exists()


def test_control_ticks_count_periods_into_cumulative_buckets_and_overruns():
    ticks = ControlTicks(period_s=0.01)
    for t in (0.0, 0.01, 0.02, 0.045, 0.055, 0.355):  # periods 10, 10, 25, 10, 300 ms
        ticks.record(t)
    hist = ticks.histogram()
    bounds = dict(zip(TICK_BUCKETS_S, hist["buckets"], strict=True))
    assert (bounds[0.008], bounds[0.015], bounds[0.03], bounds[0.25], bounds[0.5]) == (0, 3, 4, 4, 5)
    assert hist["count"] == 5 and hist["sum_s"] == pytest.approx(0.355) and hist["overruns"] == 2
    summary = ticks.summary()
    assert summary["n_ticks"] == 6 and summary["period_max_s"] == pytest.approx(0.3)
    assert summary["period_p50_s"] == pytest.approx(0.01)


def test_a_perfect_loop_counts_every_tick_in_the_bucket_of_its_period():
    """A sim job's 10 ms ticks all read p50 = p99 = max = 0.01 s, yet near a third of 1999 fell into the
    15 ms bucket: job time is a sum of periods, and a period taken from two such sums is 0.01 s up to float
    error."""
    ticks, t = ControlTicks(period_s=0.01), 0.0
    for _ in range(2000):  # as the control loop's simulated clock advances
        ticks.record(t)
        t += 0.01
    bounds = dict(zip(TICK_BUCKETS_S, ticks.histogram()["buckets"], strict=True))
    assert (bounds[0.008], bounds[0.01], bounds[0.015]) == (0, 1999, 1999)


@pytest.mark.parametrize("termination, state", [
    ("safety stop: arm fault: power off, control script not running", "fault"),
    ("safety stop: arm fault: control script not running", "fault"),
    ("safety stop: arm fault: safeguard stop", "protective stop"),
    ("safety stop: arm fault: emergency stop, power off", "emergency stop"),
])
def test_every_fault_an_arm_driver_names_latches_until_a_recovery(termination, state):
    tracker = ArmTracker(load_config(FRANKA))
    tracker.job_ended(termination)
    assert tracker.faulted and tracker.status.state == state
    tracker.recovered([], None)
    assert not tracker.faulted and tracker.status.state == "idle"


# ------------------------------------------------------------------------------------- holds, liveness


def _queue(client: TestClient, key: str) -> dict[str, Any]:
    queue: dict[str, Any] = client.get("/api/v1/cell", headers=_auth(key)).json()["queue"]
    return queue


def test_a_stop_its_worker_does_not_confirm_holds_the_queue(tmp_path):
    """A worker killed for a stop it did not confirm left the arm to its connection watchdog: the next
    job waits for an operator, as after a worker that died."""
    client, keys = _client_with(tmp_path, "impatient", service={"stop_confirm_timeout_s": 1e-6})
    op, viewer = _auth(keys["operator"]), keys["viewer"]
    with client:
        first = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 30}, headers=op).json()
        second = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 2}, headers=op).json()
        wait_started(client, _auth(viewer), first["id"])
        stop = client.post(f"/api/v1/jobs/{first['id']}/stop", json={"reason": "hands in"}, headers=op)
        assert stop.status_code == 200 and stop.json()["queue_held"] is True, stop.json()
        assert _wait(client, viewer, first["id"], set(FINISHED_STATUSES))["status"] == "stopped"
        held = _queue(client, viewer)["held"]
        assert "did not confirm" in held and "check the arm" in held
        time.sleep(1.0)  # what would start the next job starts at once: a second is ample
        assert client.get(f"/api/v1/jobs/{second['id']}", headers=op).json()["status"] == "queued"
        assert client.get("/readyz", headers=op).status_code == 503


def test_a_held_queue_stays_held_across_a_restart_until_resumed(tmp_path, caplog):
    client, keys = _client(tmp_path)
    op = _auth(keys["operator"])
    with client:
        stop = client.post("/api/v1/stop", json={"reason": "hands in the cell"}, headers=op)
        assert stop.status_code == 200
        before = _queue(client, keys["viewer"])
        assert "hands in the cell" in before["held"] and before["held_at"] is not None
    with client, caplog.at_level(logging.INFO, logger="cell.service"):
        assert _queue(client, keys["viewer"]) == before
        ready = client.get("/readyz", headers=op)
        assert ready.status_code == 503 and "hands in the cell" in ready.json()["status"]
        assert "cell_queue_held 1.0" in client.get("/metrics", headers=op).text
        assert client.post("/api/v1/queue/resume", headers=op).status_code == 200
    messages = [r.getMessage() for r in caplog.records]
    assert any("held since" in m and "hands in the cell" in m for m in messages)
    with client:
        assert _queue(client, keys["viewer"])["held"] is None
        assert client.get("/readyz", headers=op).status_code == 200
        assert "cell_queue_held 0.0" in client.get("/metrics", headers=op).text


def _damage_page_of(database: Path, marker: bytes) -> None:
    """Overwrite the whole page of the SQLite file ``database`` that holds ``marker`` (a table's leaf page:
    the row that holds it), as a failing disk would."""
    with contextlib.closing(sqlite3.connect(database)) as connection:
        (page_size,) = connection.execute("PRAGMA page_size").fetchone()
    page = database.read_bytes().index(marker) // page_size
    with database.open("r+b") as f:
        f.seek(page * page_size)
        f.write(b"\xa5" * page_size)


def test_the_placement_checks_are_loaded_before_the_first_job_starts(tmp_path, built_worlds, monkeypatch):
    """The dispatcher builds the collision world and the default planner's search views before it starts
    a job, so that no import of theirs (FCL, Open3D, the planner: the GIL held for up to 0.1 s at a time)
    falls while a job runs; the job's submission builds no world of its own."""
    from cell.service.manager import CellService

    order: list[str] = []
    load, run = CellService._load_checks, CellService._run

    def loading(self: CellService) -> None:
        load(self)
        order.append(f"loaded {sorted(self._search_views._views)}")

    async def running(self: CellService, *args: Any) -> float | None:
        order.append("job started")
        return await run(self, *args)

    monkeypatch.setattr(CellService, "_load_checks", loading)
    monkeypatch.setattr(CellService, "_run", running)
    client, keys = _client(tmp_path)
    with client:
        planner = client.app.state.service.config.scan.planner  # type: ignore[attr-defined]
        job = client.post("/api/v1/jobs", json={"object": "bunny", "max_time_s": 1},
                          headers=_auth(keys["operator"]))
        assert job.status_code == 201, job.text
        _wait(client, keys["viewer"], job.json()["id"], {"completed", "failed", "stopped"})
    assert order == [f"loaded {[planner]}", "job started"] and len(built_worlds) == 1


def test_a_scrape_whose_job_counts_fail_still_says_the_store_is_damaged():
    """A store damaged in the pages the job counts read made the whole scrape fail (500), hiding the
    gauge that says it is damaged: now ``cell_jobs`` has no samples and the rest is scraped."""

    def counts() -> dict[str, int]:
        raise StoreDamaged(f"job store sqlite:///cell.db: counting jobs: database disk image is malformed; "
                           f"{RESTORE}")

    text = ServiceMetrics(counts, lambda: 2, lambda: True, lambda: True).render().decode()
    assert "cell_store_damaged 1.0" in text and "cell_queue_held 1.0" in text
    assert "cell_queue_length 2.0" in text and "cell_jobs{" not in text


def test_a_store_damaged_while_the_service_runs_holds_the_queue_and_makes_it_not_ready(tmp_path, caplog):
    """A store damaged at run time in pages the job counts do not read (a row of an old job) answered
    ``/readyz`` ready while the jobs' records failed: the first call that meets the damage (here a read
    of that job) latches it, the queue is held saying to restore the store, a resume is refused,
    ``/readyz`` answers 503 and ``/metrics`` says so, and a job submitted then is not started."""
    client, keys = _client(tmp_path)
    op, viewer = _auth(keys["operator"]), _auth(keys["viewer"])
    data = tmp_path / "data"
    store = open_data_store(data, sqlite_url(data))
    old = [replace(_job(data, "completed", f"{n:016x}"), cell="sim-franka-rgbd",
                   termination=f"old scan {n:03d}") for n in range(1, 200)]
    for job in old:
        store.add_job(job)
    store.close()
    with client, caplog.at_level(logging.INFO, logger="cell.service"):
        # the dispatcher has loaded its checks: it now waits for jobs, and looks at the queue as soon as a
        # job wakes it, before the event loop takes the next request
        deadline = time.monotonic() + 60.0
        while (ready := client.get("/readyz", headers=viewer).json())["placement_checks"] != "loaded":
            assert ready["status"] == "ready" and time.monotonic() < deadline, ready
            time.sleep(0.02)
        assert "cell_store_damaged 0.0" in client.get("/metrics", headers=viewer).text
        _damage_page_of(data / "cell.db", b"old scan 100")
        # a write beside the service's (a store opened before the damage): the service's connections then
        # read the file again, not the pages they hold since their integrity check at the start
        beside = Store(create_engine(sqlite_url(data)))
        create_key(beside, "viewer", "beside")
        beside.close()
        assert client.get(f"/api/v1/jobs/{old[99].id}", headers=viewer).status_code == 500
        ready = client.get("/readyz", headers=viewer)
        assert ready.status_code == 503, ready.json()
        assert ready.json()["status"] == f"the queue is held: {RESTORE}"
        metrics = client.get("/metrics", headers=viewer).text
        assert "cell_store_damaged 1.0" in metrics and "cell_queue_held 1.0" in metrics
        resume = client.post("/api/v1/queue/resume", headers=op)
        assert resume.status_code == 409 and RESTORE in resume.json()["detail"]
        job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 1}, headers=op)
        assert job.status_code == 201, job.text  # its row is written to pages the damage left whole
        # the dispatcher looked at the queue before this request was taken: it started nothing
        cell = client.get("/api/v1/cell", headers=viewer).json()
        assert cell["job"] is None and cell["queue"]["held"] == RESTORE and cell["queue"]["length"] == 1, cell
        assert client.get(f"/api/v1/jobs/{job.json()['id']}", headers=viewer).json()["status"] == "queued"
    damaged = [r for r in caplog.records if r.levelno == logging.CRITICAL]
    assert len(damaged) == 1 and "malformed" in damaged[0].getMessage()


def test_a_hung_worker_is_stopped_and_holds_the_queue(tmp_path, caplog):
    """A worker that sends nothing (here stopped by SIGSTOP) for ``WORKER_SILENT_S`` is taken for hung:
    its job is stopped (killed, as it cannot confirm), the queue held and the reason logged."""
    client, keys = _client(tmp_path)
    op, viewer = _auth(keys["operator"]), keys["viewer"]
    with client, caplog.at_level(logging.INFO, logger="cell.service"):
        store = client.app.state.service.store  # type: ignore[attr-defined]
        job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 60}, headers=op).json()
        wait_started(client, _auth(viewer), job["id"])
        pid = store.get_job(job["id"]).worker_pid
        os.kill(pid, signal.SIGSTOP)
        try:
            ended = _wait(client, viewer, job["id"], set(FINISHED_STATUSES), timeout_s=30.0)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
        assert ended["status"] == "stopped" and "hung" in ended["termination"], ended["termination"]
        held = _queue(client, viewer)["held"]
        assert "hung" in held and "check the arm" in held
        assert client.get("/readyz", headers=op).status_code == 503
    assert any(r.levelno == logging.ERROR and "hung" in r.getMessage() for r in caplog.records)


def test_a_data_dir_without_room_for_a_job_holds_the_next_one_and_says_where(tmp_path, monkeypatch, caplog):
    from cell.service import manager

    client, keys = _client(tmp_path)
    op, viewer = _auth(keys["operator"]), keys["viewer"]
    usage = manager.shutil.disk_usage
    full = threading.Event()

    def disk_usage(path: Any) -> Any:
        real = usage(path)
        return real._replace(free=5_000_000) if full.is_set() else real

    monkeypatch.setattr(manager.shutil, "disk_usage", disk_usage)
    full.set()
    with client, caplog.at_level(logging.INFO, logger="cell.service"):
        job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 1}, headers=op).json()
        time.sleep(1.5)
        assert client.get(f"/api/v1/jobs/{job['id']}", headers=op).json()["status"] == "queued"
        held = _queue(client, viewer)["held"]
        assert held.startswith(f"disk full under {tmp_path / 'data'}: 5 MB free"), held
        ready = client.get("/readyz", headers=op)
        assert ready.status_code == 503 and "disk full" in ready.json()["status"]
        full.clear()
        assert _wait(client, viewer, job["id"], set(FINISHED_STATUSES))["status"] == "completed"
    messages = [r.getMessage() for r in caplog.records]
    assert any(m.startswith("disk full under") for m in messages)  # at start, and as the job waits
    assert "the jobs folder takes a job's recording again" in messages


def test_deleting_an_object_of_no_upload_is_refused_without_reading_the_store(tmp_path, monkeypatch):
    """DELETE /objects/{name} read the cell's queued and running jobs before it looked at the name: a
    store that did not answer made a name of no upload a 503."""
    client, keys = _client(tmp_path)
    operator = _auth(keys["operator"])

    def unreadable(*_: Any) -> list[JobRecord]:
        raise StoreError("job store: cannot read")

    with client:
        monkeypatch.setattr(client.app.state.service.store, "jobs_in_status", unreadable)
        assert client.delete("/api/v1/objects/nothing", headers=operator).status_code == 404
        assert client.delete("/api/v1/objects/bunny", headers=operator).status_code == 409


def test_a_start_removes_the_empty_worker_logs_a_previous_run_left(tmp_path):
    client, _ = _client(tmp_path)
    logs = tmp_path / "data" / "logs"
    logs.mkdir(parents=True)
    (logs / "worker-0123456789abcdef.log").touch()
    (logs / "worker-spare-0a1b2c3d.log").touch()
    (logs / "worker-fedcba9876543210.log").write_text("Traceback ...\n")
    with client:
        assert sorted(p.name for p in logs.glob("worker-*.log") if "spare" not in p.name) \
            == ["worker-fedcba9876543210.log"]


def _started_spares_log(client: TestClient) -> Path:
    """The log of the spare worker the running service started (none started: the test would judge the
    name a service holds before it starts one, a file that never exists)."""
    service = client.app.state.service
    assert service._spare is not None and service._spare_log.name.startswith("worker-spare-")
    return service._spare_log


def test_a_service_shut_down_keeps_its_spare_workers_log_only_when_the_spare_printed_something(tmp_path):
    """The service deleted its spare's log at shutdown whatever it held, where every other worker's log is
    kept when its worker printed something."""
    client, _ = _client(tmp_path)
    with client:
        quiet = _started_spares_log(client)
    assert not quiet.exists()
    with client:
        printed = _started_spares_log(client)
        with printed.open("a") as log:
            log.write("a library's warning\n")
    assert printed.read_text() == "a library's warning\n"


def test_a_spare_worker_whose_service_went_away_exits_quietly(tmp_path):
    log_path = tmp_path / "worker-spare-0a1b2c3d.log"
    with log_path.open("wb") as log:
        command = [sys.executable, "-m", WORKER_MODULE, "--job", "spare"]
        spare = subprocess.run(command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log,
                               timeout=120)
    assert spare.returncode == 0 and log_path.read_bytes() == b""
    assert [json.loads(line)["type"] for line in spare.stdout.splitlines()] == ["loaded"]


def test_a_workers_stop_commands_keep_whose_stop_it_is_and_the_services_end_is_the_safety_layers():
    """The worker's command reader passes on whether someone asked for a stop (``operator``, missing in an
    older service's command: someone did), refuses a command whose flag is not a boolean, and stops the job
    as the safety layer's own when the service's end of the pipe closes (nobody asked)."""
    from cell.jobs.control import StopEffect
    from cell.service.protocol import stop_command
    from cell.service.worker import Outbox, _listen

    calls: list[tuple[str, bool]] = []

    def stop(reason: str, *, operator: bool = True) -> StopEffect:
        calls.append((reason, operator))
        return StopEffect.COMMANDED

    lines = [stop_command("hands in the cell").strip(), stop_command("hung", operator=False).strip(),
             b'{"op": "stop", "reason": "older service"}',
             b'{"op": "stop", "reason": "bad", "operator": "no"}']
    _listen(iter(lines), Outbox(io.BytesIO()), stop)
    assert calls == [("hands in the cell", True), ("hung", False), ("older service", True),
                     (SERVICE_GONE, False)]
