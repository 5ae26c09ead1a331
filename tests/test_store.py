"""The job store on SQLite and on a real PostgreSQL server (``tests/postgres.py``): jobs and keys round
trip, filters and pages, the queue's order, migrations (once, never backwards), errors that hide the
password, and two cells sharing one PostgreSQL database."""

from __future__ import annotations

import logging
import sqlite3
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import replace
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from sqlalchemy import Connection, create_engine, make_url, text
from typer.testing import CliRunner

from cell.cli.main import app
from cell.doctor import machine
from cell.doctor.findings import Status
from cell.service.arm_status import after_fault, held_fault
from cell.service.keys import create_key
from cell.service.recovery import hold_after_end
from cell.service.store import (
    FINISHED_STATUSES,
    JOB_STATUSES,
    HoldRecord,
    JobRecord,
    Store,
    open_store,
    sqlite_url,
)
from cell.service.store.engine import MIGRATIONS, open_engine, schema_head
from cell.service.store.models import Base
from cell.service.store.repository import StoreState, inspect_store
from drivers.errors import ServiceError, StoreDamaged, StoreError
from tests.postgres import free_port, fresh_database, postgres_url  # noqa: F401  (a fixture)

T0 = datetime(2026, 3, 2, 8, 0, tzinfo=UTC)


def make_job(n: int, **fields: object) -> JobRecord:
    """Job number ``n``: created ``n`` minutes after T0 on cell ``a``, queued, with a distinct id."""
    values: dict[str, object] = dict(
        id=f"{n:016x}", cell="a", status="queued", planner="vs-local", object="bunny",
        object_pose=(0.01, -0.02, 30.0), seed=n, max_time_s=120.0, part_id=None, folder=f"/data/jobs/{n}",
        submitted_by="op", created_at=T0 + timedelta(minutes=n))
    values.update(fields)
    return JobRecord(**values)


@pytest.fixture(params=["sqlite", "postgresql"])
def store_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """An empty store's URL: a SQLite file, or a fresh database on the session's PostgreSQL server."""
    if request.param == "sqlite":
        yield sqlite_url(tmp_path)
    else:
        with fresh_database(request.getfixturevalue("postgres_url")) as url:
            yield url


@pytest.fixture
def store(store_url: str) -> Iterator[Store]:
    opened = open_store(store_url)
    yield opened
    opened.close()


def test_statuses():
    assert set(JOB_STATUSES) > FINISHED_STATUSES
    assert set(JOB_STATUSES) - FINISHED_STATUSES == {"queued", "running", "stopping"}


def test_job_round_trip(store: Store):
    job = make_job(1, result={"status": "completed", "metrics": {"coverage_pct": 91.5, "chamfer_mm": None}},
                   progress={"t_s": 3.5, "n_captures": 4}, part_id="P-7", worker_pid=4242,
                   started_at=datetime(2026, 3, 2, 10, 1, 2, 345678, tzinfo=timezone(timedelta(hours=2))))
    store.add_job(job)
    back = store.get_job(job.id)
    assert back == job
    assert back is not None
    for moment in (back.created_at, back.started_at):
        assert moment is not None and moment.tzinfo is not None and moment.utcoffset() == timedelta(0)
    assert back.started_at == datetime(2026, 3, 2, 8, 1, 2, 345678, tzinfo=UTC)
    assert back.object_pose == (0.01, -0.02, 30.0) and isinstance(back.object_pose, tuple)
    assert back.result == job.result and back.progress == job.progress
    assert store.get_job("ffffffffffffffff") is None


def test_nulls_round_trip(store: Store):
    job = make_job(2, object=None, object_pose=None, max_time_s=None, submitted_by=None)
    store.add_job(job)
    assert store.get_job(job.id) == job


def test_add_job_refuses_duplicates_and_bad_values(store: Store):
    store.add_job(make_job(1))
    with pytest.raises(ServiceError) as err:
        store.add_job(make_job(1))
    assert err.value.reason == "conflict"
    with pytest.raises(ValueError, match="hex"):
        store.add_job(make_job(2, id="NOT-HEX-00000000"))
    with pytest.raises(ValueError, match="status"):
        store.add_job(make_job(3, status="paused"))
    with pytest.raises(ValueError, match="naive"):
        store.add_job(make_job(4, created_at=datetime(2026, 3, 2, 8, 0)))
    assert store.list_jobs()[1] == 1


def test_update_job(store: Store):
    job = make_job(1)
    store.add_job(job)
    started = T0 + timedelta(hours=1)
    updated = store.update_job(job.id, status="running", started_at=started, worker_pid=99,
                               progress={"t_s": 1.0, "coverage_pct": 12.5})
    assert updated == replace(job, status="running", started_at=started, worker_pid=99,
                              progress={"t_s": 1.0, "coverage_pct": 12.5})
    assert store.get_job(job.id) == updated
    finished = store.update_job(job.id, status="completed", finished_at=started + timedelta(seconds=30),
                                termination="coverage converged", result={"status": "completed"},
                                progress=None, worker_pid=None)
    assert finished.progress is None and finished.worker_pid is None
    assert store.get_job(job.id) == finished


def test_update_job_refuses(store: Store):
    store.add_job(make_job(1))
    with pytest.raises(ValueError, match="colour"):
        store.update_job(make_job(1).id, colour="red")
    with pytest.raises(ValueError, match="id"):
        store.update_job(make_job(1).id, id="0000000000000002")
    with pytest.raises(ValueError, match="status"):
        store.update_job(make_job(1).id, status="paused")
    with pytest.raises(ValueError, match="naive"):
        store.update_job(make_job(1).id, finished_at=datetime(2026, 1, 1))
    with pytest.raises(KeyError):
        store.update_job("0000000000000009", status="running")
    assert store.get_job(make_job(1).id) == make_job(1)


@pytest.fixture
def many_jobs(store: Store) -> list[JobRecord]:
    """Eight jobs over two cells, statuses, planners and part ids, created a minute apart (and two at
    the same time, to order by id)."""
    jobs = [
        make_job(1, status="completed"),
        make_job(2, status="failed", planner="lrnbv"),
        make_job(3, cell="b", status="completed", part_id="P-1"),
        make_job(4, status="running", part_id="P-1"),
        make_job(5, status="queued", planner="lrnbv"),
        make_job(6, status="queued"),
        make_job(7, status="queued", created_at=T0 + timedelta(minutes=6)),
        make_job(8, cell="b", status="queued"),
    ]
    for job in jobs:
        store.add_job(job)
    return jobs


def ids(jobs: list[JobRecord]) -> list[int]:
    return [int(job.id, 16) for job in jobs]


def test_list_jobs_filters(store: Store, many_jobs: list[JobRecord]):
    page, total = store.list_jobs()
    assert ids(page) == [8, 7, 6, 5, 4, 3, 2, 1] and total == 8  # newest first; 6 and 7 tie: by id
    assert ids(store.list_jobs(cell="a")[0]) == [7, 6, 5, 4, 2, 1]
    assert ids(store.list_jobs(statuses=["completed", "failed"])[0]) == [3, 2, 1]
    assert ids(store.list_jobs(statuses=[])[0]) == []
    assert ids(store.list_jobs(planner="lrnbv")[0]) == [5, 2]
    assert ids(store.list_jobs(part_id="P-1")[0]) == [4, 3]
    assert ids(store.list_jobs(created_after=T0 + timedelta(minutes=5))[0]) == [8, 7, 6, 5]
    assert ids(store.list_jobs(created_before=T0 + timedelta(minutes=3))[0]) == [2, 1]
    # a time in another zone means the same instant
    after = (T0 + timedelta(minutes=3)).astimezone(timezone(timedelta(hours=-5)))
    assert ids(store.list_jobs(created_after=after, created_before=T0 + timedelta(minutes=5))[0]) == [4, 3]
    page, total = store.list_jobs(cell="a", statuses=["queued"], planner="vs-local")
    assert ids(page) == [7, 6] and total == 2
    with pytest.raises(ValueError, match="status"):
        store.list_jobs(statuses=["paused"])
    with pytest.raises(ValueError, match="naive"):
        store.list_jobs(created_after=datetime(2026, 1, 1))


def test_list_jobs_pages(store: Store, many_jobs: list[JobRecord]):
    pages = [store.list_jobs(limit=3, offset=offset) for offset in (0, 3, 6, 9)]
    assert [(ids(page), total) for page, total in pages] \
        == [([8, 7, 6], 8), ([5, 4, 3], 8), ([2, 1], 8), ([], 8)]
    page, total = store.list_jobs(cell="a", limit=2, offset=1)
    assert ids(page) == [6, 5] and total == 6
    with pytest.raises(ValueError):
        store.list_jobs(limit=-1)


def test_queue_order_and_counts(store: Store, many_jobs: list[JobRecord]):
    assert ids(store.jobs_in_status("a", ["queued"])) == [5, 6, 7]  # oldest first; 6 and 7 tie: by id
    assert ids(store.jobs_in_status("a", ["queued", "running"])) == [4, 5, 6, 7]
    assert ids(store.jobs_in_status("b", ["queued"])) == [8]
    assert store.jobs_in_status("c", ["queued"]) == []
    assert store.count_by_status("a") == {"queued": 3, "running": 1, "stopping": 0, "completed": 1,
                                          "no_object": 0, "failed": 1, "stopped": 0, "cancelled": 0,
                                          "interrupted": 0}
    assert store.count_by_status("c") == dict.fromkeys(JOB_STATUSES, 0)


def test_a_running_job_is_marked_stopping_and_an_ended_one_never(store: Store, many_jobs: list[JobRecord]):
    """A stop's ``stopping`` never overwrites an end the worker stored first."""
    (running,) = store.jobs_in_status("a", ["running"])
    assert store.mark_stopping(running.id) and store.get_job(running.id).status == "stopping"
    assert ids(store.jobs_in_status("a", ["running", "stopping"])) == ids([running])
    store.update_job(running.id, status="stopped")
    assert not store.mark_stopping(running.id) and store.get_job(running.id).status == "stopped"


def test_each_cell_keeps_its_own_queue_hold_until_released(store: Store):
    assert store.get_hold("a") is None
    held = HoldRecord(cell="a", reason="held after a stop (hands in): resume", held_at=T0)
    store.set_hold("a", held)
    assert store.get_hold("a") == held and store.get_hold("b") is None
    later = HoldRecord(cell="a", reason="held after a worker that died", held_at=T0 + timedelta(minutes=1))
    store.set_hold("a", later)
    store.set_hold("b", replace(held, cell="b"))
    assert store.get_hold("a") == later and store.get_hold("b") == replace(held, cell="b")
    store.set_hold("a", None)
    store.set_hold("a", None)  # releasing a queue that is not held changes nothing
    assert store.get_hold("a") is None and store.get_hold("b") == replace(held, cell="b")
    with pytest.raises(ValueError, match="naive"):
        store.set_hold("a", replace(held, held_at=datetime(2026, 3, 2, 8, 0)))


@pytest.mark.parametrize("first", ["held after a stop (hands in): resume", None])
def test_an_arm_fault_recorded_only_in_a_folder_goes_first_in_a_stored_hold(store: Store, first: str | None):
    """The restart's hold for a job whose folder records an arm fault: the fault first, so that the start
    latches it, and a STOP stored before it kept after it with its time (it had been overwritten, and the
    arm's recovery would then have released a stopped queue); any other end leaves a stored hold as it
    is."""
    if first is not None:
        store.set_hold("a", HoldRecord(cell="a", reason=first, held_at=T0))
    job = make_job(1, status="running")
    hold_after_end(store, job, {}, "safety stop: arm fault: protective stop")
    held = store.get_hold("a")
    assert held is not None and held_fault(held.reason) == "protective stop", held
    assert after_fault(held.reason) == first
    assert (held.held_at == T0) is (first is not None)
    store.set_hold("a", None if first is None else HoldRecord(cell="a", reason=first, held_at=T0))
    hold_after_end(store, job, {"worker": {}}, "safety stop: the job's worker ended unexpectedly")
    held = store.get_hold("a")
    assert held is not None and (held.reason == first if first else held.reason.startswith("held after job"))


def test_delete_job(store: Store, many_jobs: list[JobRecord]):
    store.delete_job(many_jobs[0].id)
    assert store.get_job(many_jobs[0].id) is None
    assert store.list_jobs()[1] == 7
    with pytest.raises(KeyError):
        store.delete_job(many_jobs[0].id)


def test_keys_round_trip(store: Store):
    added = store.add_key("op", "operator", "ab" * 32)
    assert added.active and added.created_at.tzinfo is not None
    store.add_key("admin-1", "admin", "cd" * 32)
    assert [k.name for k in store.list_keys()] == ["admin-1", "op"]
    assert store.list_keys()[1] == added
    revoked = store.revoke_key("op")
    assert not revoked.active and revoked.revoked_at is not None and revoked.revoked_at.tzinfo is not None
    assert [k.name for k in store.active_keys()] == ["admin-1"]
    assert store.list_keys()[1] == revoked
    with pytest.raises(ServiceError) as err:
        store.revoke_key("op")
    assert err.value.reason == "conflict"
    with pytest.raises(ServiceError) as err:
        store.revoke_key("nobody")
    assert err.value.reason == "not found"
    with pytest.raises(ServiceError) as err:
        store.add_key("op", "viewer", "ef" * 32)  # a revoked key's name stays taken
    assert err.value.reason == "conflict"


def test_threads_share_a_store(store: Store):
    """Several threads add and update jobs at once (one session per call)."""
    errors: list[BaseException] = []

    def work(t: int) -> None:
        try:
            for i in range(5):
                job = make_job(100 * t + i, cell=f"t{t}")
                store.add_job(job)
                store.update_job(job.id, status="running", progress={"i": i})
                store.list_jobs(cell=f"t{t}")
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(t,)) for t in range(1, 7)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    assert store.list_jobs(statuses=["running"])[1] == 30


def test_schema_matches_models(store_url: str):
    """The hand-written migrations leave exactly the schema the models describe."""
    engine = open_engine(store_url)
    try:
        with engine.connect() as connection:
            diff = compare_metadata(MigrationContext.configure(connection, opts={"compare_type": True}),
                                    Base.metadata)
    finally:
        engine.dispose()
    assert diff == []


def test_reopen_runs_no_migration(store_url: str, monkeypatch: pytest.MonkeyPatch):
    first = open_store(store_url)
    first.add_job(make_job(1))
    first.close()

    def no_upgrade(*args: object, **kwargs: object) -> None:
        raise AssertionError("a migration ran on a database already at head")

    monkeypatch.setattr("cell.service.store.engine.command.upgrade", no_upgrade)
    again = open_store(store_url)
    try:
        assert again.get_job(make_job(1).id) == make_job(1)
    finally:
        again.close()
    _assert_at_head(store_url)


def _assert_at_head(store_url: str) -> None:
    """The store's database records one schema revision, this software's newest."""
    engine = create_engine(store_url)
    with engine.connect() as connection:
        assert connection.execute(text("SELECT version_num FROM alembic_version")).scalars().all() \
            == [schema_head()]
    engine.dispose()


def test_newer_schema_is_refused(store_url: str):
    open_store(store_url).close()
    engine = create_engine(store_url)
    with engine.begin() as connection:
        connection.execute(text("UPDATE alembic_version SET version_num = '9999_future'"))
    engine.dispose()
    with pytest.raises(StoreError, match=r"9999_future.*newer") as err:
        open_store(store_url)
    assert "\n" not in str(err.value)


def test_sqlite_pragmas(tmp_path: Path):
    open_store(sqlite_url(tmp_path)).close()
    with sqlite3.connect(tmp_path / "cell.db") as raw:
        assert raw.execute("PRAGMA journal_mode").fetchone() == ("wal",)
    engine = open_engine(sqlite_url(tmp_path))
    try:
        with engine.connect() as connection:
            answers = {name: connection.exec_driver_sql(f"PRAGMA {name}").scalar()
                       for name in ("journal_mode", "synchronous", "busy_timeout", "foreign_keys")}
    finally:
        engine.dispose()
    assert answers == {"journal_mode": "wal", "synchronous": 1, "busy_timeout": 5000, "foreign_keys": 1}


def test_sqlite_url(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.chdir(tmp_path)
    assert sqlite_url(Path("data")) == f"sqlite:///{tmp_path / 'data' / 'cell.db'}"


@pytest.mark.parametrize(("url", "words"), [
    ("not a url", "not a database URL"),
    ("mysql://cell:s3cret@localhost/cell", "unsupported database"),
    ("postgresql+asyncpg://cell:s3cret@localhost/cell", "unsupported database"),
    ("sqlite://", "needs a file"),
    ("sqlite:////no/such/folder/cell.db", "does not exist"),
])
def test_bad_urls(url: str, words: str):
    with pytest.raises(StoreError, match=words) as err:
        open_store(url)
    message = str(err.value)
    assert "s3cret" not in message and "\n" not in message


def test_unreachable_postgres_hides_the_password():
    url = f"postgresql+psycopg://cell:s3cret@127.0.0.1:{free_port()}/cell"  # nothing listens there
    with pytest.raises(StoreError) as err:
        open_store(url)
    message = str(err.value)
    assert "s3cret" not in message and "\n" not in message
    assert "postgresql+psycopg://cell:***@127.0.0.1" in message and "cannot open" in message


def open_at_once(url: str, n: int) -> list[Store]:
    """``n`` stores opened on ``url`` by as many threads at once."""
    stores: list[Store] = []
    errors: list[BaseException] = []

    def start() -> None:
        try:
            stores.append(open_store(url))
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=start) for _ in range(n)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for opened in stores if errors else []:
        opened.close()
    assert errors == []
    return stores


def test_stores_opened_at_once_migrate_once(store_url: str):
    for opened in open_at_once(store_url, 4):
        opened.close()
    _assert_at_head(store_url)


def test_processes_open_one_sqlite_store_at_once(tmp_path: Path):
    """Cells (or ``cell keys`` and ``cell serve``) starting together on one new SQLite file: SQLite's
    write lock serializes their migrations. One that waits for another's past a moment says so (a loaded
    machine), and nothing else."""
    code = "import sys; from cell.service.store import open_store; open_store(sys.argv[1]).close()"
    url = sqlite_url(tmp_path)
    starts = [subprocess.Popen([sys.executable, "-c", code, url], stderr=subprocess.PIPE, text=True)
              for _ in range(4)]
    outcomes = [(start.wait(timeout=60), start.stderr.read() if start.stderr else "") for start in starts]
    waited = f"job store {url}: another process holds its lock (another cell starting on it, "
    assert [rc for rc, _ in outcomes] == [0] * 4, outcomes
    assert all(line.startswith(waited) for _, said in outcomes for line in said.splitlines()), outcomes
    with sqlite3.connect(tmp_path / "cell.db") as raw:
        assert raw.execute("SELECT version_num FROM alembic_version").fetchall() == [(schema_head(),)]


def test_two_cells_share_a_postgres_database(postgres_url: str):  # noqa: F811  (the imported fixture)
    """Two cells on one database, started at once, each see the other's jobs only when they do not
    filter by cell."""
    with fresh_database(postgres_url) as url:
        a, b = open_at_once(url, 2)
        try:
            a.add_job(make_job(1, cell="a"))
            b.add_job(make_job(2, cell="b"))
            assert ids(b.list_jobs(cell="a")[0]) == [1]
            assert ids(a.list_jobs(cell="b")[0]) == [2]
            assert ids(a.list_jobs()[0]) == [2, 1]
            assert ids(a.jobs_in_status("a", ["queued"])) == [1]
            assert b.count_by_status("b")["queued"] == 1 and b.count_by_status("a")["queued"] == 1
        finally:
            a.close()
            b.close()


def test_one_service_at_a_time_holds_a_cell_on_a_store(store_url: str):
    first, second = open_store(store_url), open_store(store_url)
    try:
        lease = first.claim_cell("cell-a")
        with pytest.raises(StoreError, match="cell 'cell-a' is served by another service"):
            second.claim_cell("cell-a")
        other = second.claim_cell("cell-b")  # another cell of the same store
        assert lease.keep() is None and other.keep() is None
        lease.release()
        other.release()
        second.claim_cell("cell-a").release()  # free once given up
    finally:
        first.close()
        second.close()


def test_a_released_lease_is_free_when_release_returns(store_url: str, monkeypatch: pytest.MonkeyPatch):
    """As a service restarted at once finds it. On PostgreSQL a lock that went only with its connection
    stayed until the server process behind it had seen the close and ended, after ``release`` returned;
    here that moment is held back (the lease's connection is not closed until the end)."""
    first, second = open_store(store_url), open_store(store_url)
    unclosed: list[Connection] = []
    monkeypatch.setattr(Connection, "invalidate", lambda self, exception=None: unclosed.append(self))
    try:
        first.claim_cell("c").release()
        second.claim_cell("c").release()
    finally:
        monkeypatch.undo()
        for connection in unclosed:
            connection.invalidate()
        first.close()
        second.close()


def test_a_lease_lost_with_its_connection_is_taken_again_unless_another_took_it(
        postgres_url: str):  # noqa: F811  (the imported fixture)
    with fresh_database(postgres_url) as url:
        first, second = open_store(url), open_store(url)
        try:
            lease = first.claim_cell("c")
            with create_engine(url).connect() as admin:  # an outage, for the lease's connection
                # waits (up to 10 s) for the backend to end: the lock goes with it, not with the signal
                admin.execute(text("SELECT pg_terminate_backend(pid, 10000) FROM pg_locks "
                                   "WHERE locktype = 'advisory' AND database = "
                                   "(SELECT oid FROM pg_database WHERE datname = current_database())"))
            taken = second.claim_cell("c")  # the lock ended with its connection
            lost = lease.keep()
            assert lost is not None and "served by another service" in lost and lease.taken
            taken.release()
            assert lease.keep() is None and not lease.taken  # taken again
            with pytest.raises(StoreError, match="served by another service"):
                second.claim_cell("c")
            lease.release()
        finally:
            first.close()
            second.close()


def test_a_store_is_inspected_read_only(store_url: str):
    """``cell doctor`` reads a store's schema and key count, and changes nothing: an SQLite store not made
    yet is not made, a database without the schema is not migrated."""
    state = inspect_store(store_url, connect_timeout_s=2)
    if store_url.startswith("sqlite"):
        assert state is None and not Path(make_url(store_url).database).exists()
    else:
        assert state == StoreState(frozenset(), 0)
        assert inspect_store(store_url, connect_timeout_s=2) == StoreState(frozenset(), 0)
    opened = open_store(store_url)
    try:
        create_key(opened, "admin", "admin-1")
        create_key(opened, "operator", "op-1")
        opened.revoke_key("op-1")
    finally:
        opened.close()
    assert inspect_store(store_url, connect_timeout_s=2) == StoreState(frozenset({schema_head()}), 1)


def _revisions(url: str) -> list[str]:
    engine = create_engine(url)
    try:
        with engine.connect() as connection:
            return list(connection.execute(text("SELECT version_num FROM alembic_version")).scalars())
    finally:
        engine.dispose()


def test_commands_beside_serve_never_migrate_a_store(store_url: str, tmp_path: Path):
    """A read-only `cell keys list` migrated a shared store to the newest schema, after which the cells of
    the previous version on it refused to start. The key commands work on the older schema and leave it;
    doctor says the next serve migrates it; serve does."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    config.set_main_option("path_separator", "os")
    engine = create_engine(store_url)
    with engine.begin() as connection:  # the store as a cell of the previous version left it
        config.attributes["connection"] = connection
        command.upgrade(config, "0002")
    engine.dispose()
    runner = CliRunner()
    data = ["--data-dir", str(tmp_path / "data")]
    listed = runner.invoke(app, ["keys", "list", *data], env={"CELL_DB": store_url})
    assert (listed.exit_code, listed.stdout) == (0, "no keys\n"), listed.output
    assert _revisions(store_url) == ["0002"]
    created = runner.invoke(app, ["keys", "create", "--role", "admin", "--name", "a-1", *data],
                            env={"CELL_DB": store_url})
    assert created.exit_code == 0, created.output
    assert runner.invoke(app, ["keys", "list", *data], env={"CELL_DB": store_url}).stdout.startswith("a-1 ")
    assert _revisions(store_url) == ["0002"]
    with pytest.raises(StoreError, match=r"schema revision 0002 is older than 0003, which this command "
                                         r"needs, and only cell serve migrates a store") as err:
        open_store(store_url, migrate=False, oldest="0003")
    assert "\n" not in str(err.value)

    (found,) = machine.store(tmp_path, store_url, "127.0.0.1")
    assert f"schema 0002, older than this software's {schema_head()}: the next cell serve migrates it" \
        in found.detail
    shared = store_url.startswith("postgresql")
    assert found.status is (Status.WARN if shared else Status.OK)
    if shared:
        assert found.fix is not None and "stop them all" in found.fix
    open_store(store_url).close()  # cell serve
    assert _revisions(store_url) == [schema_head()]


def test_job_folders_are_stored_relative_to_the_data_dir_and_older_stores_upgrade(store_url: str,
                                                                                  tmp_path: Path):
    """Absolute folders had lost every job's files once the data dir moved: the folder is stored by its
    name in the cell's jobs folder, read back in the serving data dir, and a store of revision 0003
    upgrades its absolute folders."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    config.set_main_option("path_separator", "os")
    engine = create_engine(store_url)
    with engine.begin() as connection:  # a store as the previous version left it: absolute folders
        config.attributes["connection"] = connection
        command.upgrade(config, "0003")
        for n, folder in ((1, f"/old/data/jobs/{1:016x}"), (2, "/elsewhere/scan-2")):
            connection.execute(text(
                "INSERT INTO jobs (id, cell, status, planner, seed, folder, created_at, keep) VALUES "
                "(:id, 'a', 'completed', 'vs-local', 0, :folder, :at, false)"),
                {"id": f"{n:016x}", "folder": folder, "at": T0})
    engine.dispose()
    jobs_dir = tmp_path / "moved" / "jobs"
    store = open_store(store_url, jobs_dir=jobs_dir)
    try:
        assert store.get_job(f"{1:016x}").folder == str(jobs_dir / f"{1:016x}")
        assert store.get_job(f"{2:016x}").folder == "/elsewhere/scan-2"  # no folder of a data dir: as it was
        store.add_job(make_job(3, folder=str(jobs_dir / f"{3:016x}")))
        assert store.get_job(make_job(3).id).folder == str(jobs_dir / f"{3:016x}")
    finally:
        store.close()
    engine = create_engine(store_url)
    with engine.connect() as connection:
        stored = dict(connection.execute(text("SELECT id, folder FROM jobs")).all())
    engine.dispose()
    assert stored == {f"{1:016x}": f"{1:016x}", f"{2:016x}": "/elsewhere/scan-2", f"{3:016x}": f"{3:016x}"}


def _corrupt(database: Path) -> None:
    """Overwrite 2 KB at offset 12288 (inside the fourth page) of an SQLite file, as a failing disk would."""
    with database.open("r+b") as f:
        f.seek(12288)
        f.write(b"\xa5" * 2048)


def test_rows_that_break_a_constraint_are_damage_that_does_not_latch(tmp_path: Path):
    """An integrity error no caller expected is a StoreDamaged, but not corrupt pages: the store is not
    taken for damaged (which would hold a service's queue until a restart), and the next call answers."""
    url = sqlite_url(tmp_path)
    store = open_store(url)
    try:
        store.add_job(make_job(1))
        engine = create_engine(url)
        with engine.begin() as connection:  # a constraint of the database's own, as a restore may bring
            connection.exec_driver_sql("CREATE TRIGGER refuse BEFORE UPDATE ON jobs "
                                       "BEGIN SELECT RAISE(ABORT, 'a constraint the rows break'); END")
        engine.dispose()
        with pytest.raises(StoreDamaged, match="a constraint the rows break"):
            store.update_job(make_job(1).id, status="running")
        assert not store.damaged
        assert store.get_job(make_job(1).id) is not None
    finally:
        store.close()


def test_a_damaged_sqlite_store_is_named_damaged_with_its_fix_never_unreachable(tmp_path: Path):
    """A corrupt store passed every check and each request said "does not answer; try again": opening it
    fails its integrity check, reading it is a StoreDamaged naming the backup to restore, and doctor and
    serve say so in one line."""
    url = sqlite_url(tmp_path)
    store = open_store(url)
    for n in range(1, 200):
        store.add_job(make_job(n, result={"coverage_pct": 97.5, "notes": "x" * 200}))
    store.close()
    _corrupt(tmp_path / "cell.db")
    with pytest.raises(StoreDamaged, match=r"integrity check fails .*restore it from a backup "
                                           r"\(docs/deploy.md, section 9\)") as err:
        open_store(url)
    assert "\n" not in str(err.value)
    # a store opened before the damage (no check at opening) reads it: damaged, not unreachable, and says
    # so from then on (Store.damaged, which holds the service's queue)
    unchecked = Store(create_engine(url))
    try:
        assert not unchecked.damaged
        with pytest.raises(StoreDamaged, match=r"malformed.*restore it from a backup"):
            unchecked.add_job(make_job(500))
        assert unchecked.damaged
    finally:
        unchecked.close()
    unreachable = Store(create_engine(sqlite_url(tmp_path / "nowhere")))
    with pytest.raises(StoreError, match="unable to open database file"):
        unreachable.count_by_status("a")
    assert not unreachable.damaged  # a store that does not answer may answer again: nothing latched
    (found,) = machine.store(tmp_path, None, "127.0.0.1")
    assert found.status is Status.FAIL and "integrity check fails" in found.detail
    assert "restore the store from a backup (docs/deploy.md, section 9)" in found.fix
    served = subprocess.run([sys.executable, "-m", "cell.cli.entry", "serve", "--data-dir", str(tmp_path),
                             "--port", str(free_port())], capture_output=True, text=True, timeout=120)
    assert served.returncode != 0
    assert "integrity check fails" in served.stderr and "Traceback" not in served.stderr


def test_a_store_file_that_cannot_be_looked_at_for_a_moment_is_not_taken_for_deleted(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """One failed ``stat`` of ``cell.db`` (an I/O error, a permission changed a moment) had latched the store
    as deleted for the life of the service, which then said to restore a healthy store from a backup. A
    file really gone is still found so. A file that stays unreadable is said once, not at each of the
    checks (every ``/readyz`` and submission), and again after it could be looked at meanwhile."""
    store = open_store(sqlite_url(tmp_path))
    try:
        looked = Path.stat

        def failing(path: Path, **kw: object) -> object:
            if path.name == "cell.db":
                raise OSError(5, "Input/output error")
            return looked(path, **kw)  # type: ignore[arg-type]

        with caplog.at_level(logging.WARNING, logger="cell.service"):
            for _ in range(2):
                with monkeypatch.context() as patched:
                    patched.setattr(Path, "stat", failing)
                    assert [store.check_file() for _ in range(3)] == [None] * 3
                assert store.check_file() is None and store.lost is None
        said = [r for r in caplog.records if r.getMessage().startswith("cannot check the job store's file")]
        assert len(said) == 2, said
        for name in ("cell.db", "cell.db-wal", "cell.db-shm"):
            (tmp_path / name).unlink(missing_ok=True)
        assert "was deleted" in (store.check_file() or "")
    finally:
        store.close()
