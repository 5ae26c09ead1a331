"""Recovery gaps a chaos review found, against a real ``cell serve`` (``tests.service_process``) on the
Franka sim cell with its SQLite store: an arm fault's hold across a ``kill -9``, the store's file deleted
while serving, a store locked by another process, a read-only jobs folder, a worker killed mid-scan."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from cell.service import startup
from cell.service.instance import DataDirClaim
from cell.service.store import open_store, sqlite_url
from drivers.errors import CellError, StoreError
from tests.conftest import FRANKA
from tests.service_process import REPO, ServedCell, free_port, submit

LONG_S = 120.0  # a budget no test's job reaches: it is stopped first [s]


@pytest.fixture
def franka(tmp_path: Path) -> Iterator[ServedCell]:
    """The Franka + RGB-D sim cell served on a data dir of its own (these tests break its store)."""
    with ServedCell(FRANKA, tmp_path / "data") as cell:
        yield cell


def _faulty_cell(tmp_path: Path) -> Path:
    """The Franka sim cell whose arm reports a protective stop 3.5 s into each job (sim time)."""
    data = yaml.safe_load(FRANKA.read_text())
    data["sim"]["faults"] = [{"at_s": 3.5, "kind": "protective stop"}]
    path = tmp_path / "faulty.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _cell(cell: ServedCell) -> dict[str, Any]:
    with cell.client("viewer") as client:
        answer: dict[str, Any] = client.get("/api/v1/cell").json()
    return answer


@pytest.mark.parametrize("stop_after_fault", [False, True])
def test_an_arm_faults_hold_outlives_a_kill_9_until_the_arm_is_recovered(tmp_path: Path,
                                                                          stop_after_fault: bool) -> None:
    """The hold was read from the arm's live latch alone (``held_at`` null): after a ``kill -9`` and a
    restart the queue was free, ``/readyz`` ready and the next job would have run on a faulted arm. A
    STOP pressed after the fault replaced the stored hold with its own, and the restart forgot the fault
    the same way. A recovery then released the STOP's hold with the fault's: the next scan would have
    moved the arm of a cell someone had stopped to reach into."""
    with ServedCell(_faulty_cell(tmp_path), tmp_path / "data", key_prefix="faulty") as cell:
        job = submit(cell, object="bunny", max_time_s=8.0)
        ended = cell.wait_job(job["id"], ("stopped", "failed", "completed"))
        assert ended["termination"] == "safety stop: arm fault: protective stop", ended
        if stop_after_fault:
            with cell.client("operator") as client:
                assert client.post("/api/v1/stop", json={"reason": "hands in"}).status_code == 200
        before = _cell(cell)["queue"]
        assert "recover the arm first" in before["held"] and before["held_at"] is not None, before
        cell.kill()
        cell.start()
        after = _cell(cell)
        assert after["queue"]["held"] == before["held"] and after["queue"]["held_at"] == before["held_at"]
        assert after["arm"]["faults"] == ["protective stop"], after["arm"]
        with cell.client("operator") as client:
            ready = client.get("/readyz")
            assert ready.status_code == 503 and "recover the arm first" in ready.json()["status"]
            assert client.post("/api/v1/queue/resume").status_code == 409  # the arm first
            recovered = client.post("/api/v1/arm/recover")
            assert recovered.status_code == 200 and recovered.json()["ok"], recovered.text
            if stop_after_fault:  # the STOP's own hold waits for the operator, in the store too
                held = client.get("/api/v1/cell").json()["queue"]
                assert held["held"].startswith("held after a stop (hands in") and \
                    held["held_at"] == before["held_at"], held
                assert client.get("/readyz").status_code == 503
                cell.kill()
                cell.start()
                assert _cell(cell)["queue"] == held
        with cell.client("operator") as client:
            if stop_after_fault:
                assert client.post("/api/v1/queue/resume").status_code == 200
            assert client.get("/api/v1/cell").json()["queue"]["held"] is None
            assert client.get("/readyz").status_code == 200
        # the recovery (or the resume) released the hold in the store too
        cell.kill()
        cell.start()
        assert _cell(cell)["queue"]["held"] is None


def test_a_store_file_deleted_while_serving_makes_the_service_unready_and_refuse_jobs(
        franka: ServedCell) -> None:
    """``cell.db`` and its WAL deleted by hand: the service wrote on into the deleted file, ``/readyz`` 200,
    and every key and job was gone after a restart. The running job's stop still works."""
    running = submit(franka, object="bunny", max_time_s=LONG_S)
    franka.wait_job(running["id"], ("running",))
    for name in ("cell.db", "cell.db-wal", "cell.db-shm"):
        (franka.data_dir / name).unlink(missing_ok=True)
    with franka.client("operator") as client:
        for _ in range(2):
            ready = client.get("/readyz")
            assert ready.status_code == 503, ready.text
            assert "cell.db was deleted while the service ran" in ready.json()["status"]
            assert "restore the file from a backup" in ready.json()["status"]
        refused = client.post("/api/v1/jobs", json={"object": "cube"})
        assert refused.status_code == 503 and "was deleted" in refused.json()["detail"], refused.text
        assert client.post(f"/api/v1/jobs/{running['id']}/stop").status_code == 200
    assert franka.wait_job(running["id"], ("stopped", "completed", "failed"))["status"] == "stopped"
    assert franka.log().count("was deleted while the service ran") == 1  # logged once


@contextlib.contextmanager
def _locked(database: Path) -> Iterator[None]:
    """An exclusive lock on the SQLite store ``database``, held by this process as another program would."""
    other = sqlite3.connect(database, isolation_level=None)
    try:
        other.execute("BEGIN EXCLUSIVE")
        yield
        other.execute("ROLLBACK")
    finally:
        other.close()


def test_readyz_is_503_while_the_store_refuses_writes_and_ready_once_it_takes_them(
        franka: ServedCell) -> None:
    """A lock held by another process: each ``POST /jobs`` was 503 after the store's busy timeout, while
    ``/readyz`` (which only reads) answered 200."""
    with franka.client("operator") as client:
        assert client.get("/readyz").status_code == 200
        with _locked(franka.data_dir / "cell.db"):
            refused = client.post("/api/v1/jobs", json={"object": "cube"})
            assert refused.status_code == 503, refused.text
            ready = client.get("/readyz")
            assert ready.status_code == 503 and "takes no write" in ready.json()["status"], ready.text
        assert client.get("/readyz").status_code == 200


@contextlib.contextmanager
def _read_only(folder: Path) -> Iterator[None]:
    """``folder`` taking no new entry: its write permissions taken for a user, immutable for root (whom
    permissions do not stop), as a read-only mount would."""
    if os.geteuid() != 0:
        folder.chmod(0o555)
        try:
            yield
        finally:
            folder.chmod(0o755)
        return
    try:
        made = subprocess.run(["chattr", "+i", str(folder)], capture_output=True, text=True)
    except FileNotFoundError:
        pytest.skip("no chattr on this machine (e2fsprogs)")
    if made.returncode != 0:  # a file system or a container that allows no immutable flag
        pytest.skip(f"chattr +i {folder}: {made.stderr.strip()}")
    try:
        yield
    finally:
        subprocess.run(["chattr", "-i", str(folder)], check=True)


def test_a_read_only_jobs_folder_keeps_jobs_waiting_until_it_is_writable(franka: ServedCell) -> None:
    """As with a full disk: each job posted was started and failed within a second while ``/readyz`` said
    the folder was not writable."""
    with _read_only(franka.data_dir / "jobs"):
        job = submit(franka, object="cube", max_time_s=2.0)
        deadline = time.monotonic() + 30.0
        while "is not writable" not in str(_cell(franka)["queue"]["held"]):
            assert time.monotonic() < deadline, _cell(franka)
            time.sleep(0.1)
        with franka.client("viewer") as client:
            assert client.get(f"/api/v1/jobs/{job['id']}").json()["status"] == "queued"
            ready = client.get("/readyz")
            assert ready.status_code == 503 and "is not writable" in ready.json()["status"], ready.text
    assert franka.wait_job(job["id"], ("completed", "failed", "stopped"))["status"] == "completed"


def _files(cell: ServedCell, job_id: str) -> list[str]:
    with cell.client("viewer") as client:
        return [f["name"] for f in client.get(f"/api/v1/jobs/{job_id}/files").json()]


def _worker_pid(cell: ServedCell, job_id: str) -> int:
    """The pid of the running job's worker, as the store records it."""
    store = open_store(sqlite_url(cell.data_dir), migrate=False)
    try:
        record = store.get_job(job_id)
    finally:
        store.close()
    assert record is not None and record.worker_pid is not None
    return record.worker_pid


def test_a_worker_killed_mid_scan_leaves_no_temporary_file_listed_and_says_how_to_rebuild(
        franka: ServedCell) -> None:
    """A half-written frame (``frames/.NNNNNN.PID.tmp.npz``, as a worker killed mid-write leaves) was
    listed by ``GET /jobs/{id}/files``, and the folder without ``cloud.ply`` did not say how to make one."""
    job = submit(franka, object="bunny", max_time_s=LONG_S)
    folder = franka.data_dir / "jobs" / job["id"]
    deadline = time.monotonic() + 60.0
    while not list((folder / "frames").glob("[0-9]*.npz")):
        assert time.monotonic() < deadline, "no frame recorded"
        time.sleep(0.1)
    half = folder / "frames" / ".000999.4242.tmp.npz"
    half.write_bytes(b"PK\x03\x04 cut short")
    assert not [name for name in _files(franka, job["id"]) if ".tmp" in name]  # a write under way
    os.killpg(_worker_pid(franka, job["id"]), signal.SIGKILL)
    ended = franka.wait_job(job["id"], ("failed", "stopped", "completed"))
    assert ended["status"] == "failed" and "ended unexpectedly" in ended["termination"], ended
    assert not half.exists() and not [name for name in _files(franka, job["id"]) if ".tmp" in name]
    result = json.loads((folder / "result.json").read_text())
    assert result["rebuild"].startswith(f"no cloud.ply: `cell reprocess {folder}` makes a cloud"), result


def _protocol_pipe(pid: int) -> int:
    """Open, for writing, the pipe on which the worker ``pid`` sends its lines to the service: its only
    write-only pipe (its standard output goes to its log, the pipe is a copy of it made at its start)."""
    for name in os.listdir(f"/proc/{pid}/fd"):
        flags = int((Path(f"/proc/{pid}/fdinfo") / name).read_text().split("flags:")[1].split()[0], 8)
        if os.readlink(f"/proc/{pid}/fd/{name}").startswith("pipe:") and flags & os.O_ACCMODE == os.O_WRONLY:
            return os.open(f"/proc/{pid}/fd/{name}", os.O_WRONLY | os.O_NONBLOCK)
    raise AssertionError(f"worker {pid} has no pipe to the service")


def test_a_worker_killed_after_it_wrote_its_result_is_recorded_as_its_folder_says(franka: ServedCell) -> None:
    """A worker killed between its ``result.json`` (its last output) and its last line to the service was
    recorded ``failed`` ("ended unexpectedly") and the queue held, while its folder held the job's whole
    result; the service then rewrote that result.json as failed. The worker is held there by its pipe to
    the service, filled (with lines the service ignores) while the service is stopped (SIGSTOP)."""
    job = submit(franka, object="cube", max_time_s=2.0)
    franka.wait_job(job["id"], ("running",))
    worker = _worker_pid(franka, job["id"])
    folder = franka.data_dir / "jobs" / job["id"]
    assert franka.proc is not None
    os.kill(franka.proc.pid, signal.SIGSTOP)
    try:
        pipe = _protocol_pipe(worker)
        try:
            with contextlib.suppress(BlockingIOError):
                while True:
                    os.write(pipe, b"{}\n")
        finally:
            os.close(pipe)
        deadline = time.monotonic() + 60.0
        while not (folder / "result.json").exists():  # its end written, its last line waits for the pipe
            assert time.monotonic() < deadline, "the job wrote no result"
            time.sleep(0.05)
        written = json.loads((folder / "result.json").read_text())
        os.killpg(worker, signal.SIGKILL)
    finally:
        os.kill(franka.proc.pid, signal.SIGCONT)
    assert written["status"] == "completed", written
    ended = franka.wait_job(job["id"], ("failed", "stopped", "completed"))
    assert (ended["status"], ended["termination"]) == ("completed", written["termination"]), ended
    assert json.loads((folder / "result.json").read_text()) == written  # left as the worker wrote it
    log_txt = (folder / "log.txt").read_text()
    assert "ended unexpectedly (killed by SIGKILL) after it wrote its result" in log_txt
    assert _cell(franka)["queue"]["held"] is None  # the arm was at rest through the guard
    assert franka.wait_job(submit(franka, object="cube", max_time_s=1.0)["id"],
                           ("completed", "failed", "stopped"))["status"] == "completed"


def test_a_service_refused_the_data_dir_has_not_opened_its_store(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """The data dir's claim comes before the store: a newer release started beside a running service
    migrated the store under it, and only then was refused (the claim was taken after the store's
    lease)."""
    first = DataDirClaim(tmp_path, "first")
    opened: list[Any] = []
    monkeypatch.setattr(startup, "open_data_store", lambda *args, **kwargs: opened.append(args))
    try:
        with pytest.raises(CellError, match="is served by another cell serve"):
            startup.build_service(startup.ServiceSettings(config_file=FRANKA, data_dir=tmp_path))
    finally:
        first.release()
    assert opened == []


def test_a_second_service_on_the_data_dir_refuses_to_start_naming_the_first(franka: ServedCell,
                                                                            tmp_path: Path) -> None:
    """A second ``cell serve`` on the same data dir, of another cell name (whose lease it gets), overwrote
    the first one's ``service.instance`` and settled its jobs. It is refused, naming the first, which
    keeps working; a ``kill -9`` leaves nothing that blocks a restart."""
    instance = (franka.data_dir / "service.instance").read_text()
    other = yaml.safe_load(FRANKA.read_text()) | {"name": "another-cell"}
    (tmp_path / "other.yaml").write_text(yaml.safe_dump(other))
    command = [sys.executable, "-m", "cell.cli.entry", "serve", "--config", str(tmp_path / "other.yaml"),
               "--data-dir", str(franka.data_dir), "--port", str(free_port())]
    second = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert second.returncode == 1, second.stdout + second.stderr
    assert second.stderr.startswith(f"error: the data dir {franka.data_dir} is served by another cell serve "
                                    f"(pid {franka.proc.pid if franka.proc else None}, cell "
                                    f"'sim-franka-rgbd', started "), second.stderr
    assert "Traceback" not in second.stderr
    assert (franka.data_dir / "service.instance").read_text() == instance
    with franka.client("viewer") as client:
        assert client.get("/healthz").json()["instance"] == instance.split()[0]
    assert franka.wait_job(submit(franka, object="cube", max_time_s=1.0)["id"],
                           ("completed", "failed", "stopped"))["status"] == "completed"
    franka.kill()
    franka.start()  # the lock died with the process
    assert (franka.data_dir / "service.instance").read_text() != instance


def test_a_start_on_a_locked_store_says_what_it_waits_for_and_starts_once_it_is_free(
        tmp_path: Path) -> None:
    """``cell serve`` on a store whose lock another process held waited up to a minute without a word."""
    data = tmp_path / "data"
    data.mkdir()
    store = open_store(sqlite_url(data))  # made, then left to the lock's holder
    store.close()
    command = [sys.executable, "-m", "cell.cli.entry", "serve", "--config", str(FRANKA), "--data-dir",
               str(data), "--port", str(free_port())]
    with _locked(data / "cell.db"):
        serve = subprocess.Popen(command, cwd=REPO, stderr=subprocess.PIPE, text=True)
        try:
            assert serve.stderr is not None
            line = serve.stderr.readline()  # said before it waits, while the lock is held
        except BaseException:
            serve.kill()
            raise
    try:
        assert "another process holds its lock" in line and "waiting up to 60 s for it" in line, line
        assert f"job store {sqlite_url(data)}" in line, line
        deadline = time.monotonic() + 60.0
        while not (data / "service.instance").exists():  # started once the lock was released
            assert serve.poll() is None and time.monotonic() < deadline, serve.returncode
            time.sleep(0.1)
    finally:
        serve.terminate()
        serve.wait(60)


def test_a_store_locked_past_the_wait_is_a_clear_error(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """Given up on after the wait, with what to do, not SQLite's bare "database is locked"."""
    monkeypatch.setattr("cell.service.store.engine.SQLITE_QUIET_WAIT_MS", 100)
    monkeypatch.setattr("cell.service.store.engine.SQLITE_MIGRATION_WAIT_MS", 200)
    open_store(sqlite_url(tmp_path)).close()
    with _locked(tmp_path / "cell.db"), pytest.raises(StoreError) as refused:
        open_store(sqlite_url(tmp_path))
    assert str(refused.value) == (
        f"job store {sqlite_url(tmp_path)}: another process held its lock for 0.3 s, and the store cannot "
        f"be opened while it does: end that process (`fuser -v {tmp_path / 'cell.db'}` lists those that "
        "have the file open), then start again")


def test_a_job_stopped_by_the_services_shutdown_says_so(franka: ServedCell) -> None:
    """SIGTERM of ``cell serve`` while a job ran recorded it as ``operator stop: the service is shutting
    down``, as if someone had stopped the job; the arm still stops through the guard."""
    job = submit(franka, object="bunny", max_time_s=LONG_S)
    deadline = time.monotonic() + 60.0
    while not list((franka.data_dir / "jobs" / job["id"] / "frames").glob("[0-9]*.npz")):  # it moves
        assert time.monotonic() < deadline, "no frame recorded"
        time.sleep(0.1)
    franka.stop()  # SIGTERM
    result = json.loads((franka.data_dir / "jobs" / job["id"] / "result.json").read_text())
    assert result["status"] == "stopped", result
    assert result["termination"] == "shutdown stop: the service is shutting down", result
    assert result["safety"]["stops"], result["safety"]  # the guard stopped the arm
    franka.start()
    recorded = franka.wait_job(job["id"], ("stopped",))
    assert recorded["termination"] == "shutdown stop: the service is shutting down", recorded


def test_an_arm_fault_only_the_job_folder_records_is_latched_by_the_restart(tmp_path: Path) -> None:
    """The service killed after the job's worker wrote its arm fault, before the service stored the
    queue's hold: the restart held the queue as after any end, resumable, and the arm's fault was not
    latched, so the next job would have run on the faulted arm."""
    with ServedCell(_faulty_cell(tmp_path), tmp_path / "data", key_prefix="faulty") as cell:
        job = submit(cell, object="bunny", max_time_s=8.0)
        cell.wait_job(job["id"], ("running",))
        assert cell.proc is not None
        os.kill(cell.proc.pid, signal.SIGSTOP)  # it reads nothing more from the worker
        folder = cell.data_dir / "jobs" / job["id"]
        deadline = time.monotonic() + 60.0
        while not (folder / "result.json").exists():
            assert time.monotonic() < deadline, "the job wrote no result"
            time.sleep(0.05)
        cell.kill()  # SIGKILL reaches a stopped process too
        assert json.loads((folder / "result.json").read_text())["termination"] == \
            "safety stop: arm fault: protective stop"
        store = open_store(sqlite_url(cell.data_dir), migrate=False)
        try:  # what the killed service could not store
            assert store.get_hold("sim-franka-rgbd") is None
            record = store.get_job(job["id"])
            assert record is not None and record.status == "running"
        finally:
            store.close()
        cell.start()
        after = _cell(cell)
        assert after["arm"]["faults"] == ["protective stop"], after["arm"]
        assert "recover the arm first" in after["queue"]["held"], after["queue"]
        with cell.client("operator") as client:
            assert client.post("/api/v1/queue/resume").status_code == 409  # the arm first
            recovered = client.post("/api/v1/arm/recover")
            assert recovered.status_code == 200 and recovered.json()["ok"], recovered.text
            assert client.get("/api/v1/cell").json()["queue"]["held"] is None
