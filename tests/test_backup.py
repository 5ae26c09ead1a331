"""``cell backup`` while jobs are being written: the copy is consistent, and once restored into a data
dir it opens as the service opens its store."""

from __future__ import annotations

import sqlite3
import stat
import threading
from pathlib import Path

from typer.testing import CliRunner

from cell.cli.main import app
from cell.service.store import open_store, sqlite_url
from cell.service.store.engine import schema_head
from drivers.file_access import user_name
from tests.test_store import make_job
from tests.unprivileged import foreign, run_unprivileged, service_folder


def test_a_backup_taken_while_jobs_are_written_restores_and_opens(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    store = open_store(sqlite_url(data))
    written = 0
    done = threading.Event()

    def writer() -> None:  # the service at work: jobs added, then updated as they run and end
        nonlocal written
        while not done.is_set():
            job = make_job(written + 1, folder=f"/data/jobs/{written + 1}")
            store.add_job(job)
            store.update_job(job.id, status="running", worker_pid=4242)
            store.update_job(job.id, status="completed", result={"coverage_pct": 97.5, "n": written})
            written += 1

    thread = threading.Thread(target=writer)
    thread.start()
    try:
        while written < 20:
            done.wait(0.01)
        backups = tmp_path / "backups"
        backups.mkdir()
        res = CliRunner().invoke(app, ["backup", str(backups), "--data-dir", str(data)])
        during = written
    finally:
        done.set()
        thread.join()
        store.close()
    assert res.exit_code == 0, res.output
    (copy,) = backups.glob("cell-*.db")
    assert f"wrote {copy}" in res.output and f"schema revision {schema_head()}" in res.output
    assert not list(backups.glob("*.partial"))

    restored = tmp_path / "restored"
    restored.mkdir()
    (restored / "cell.db").write_bytes(copy.read_bytes())
    with sqlite3.connect(restored / "cell.db") as db:
        assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    reopened = open_store(sqlite_url(restored))
    try:
        jobs, total = reopened.list_jobs(limit=10_000)
        assert 20 <= total <= during + 1
        # a snapshot, not a torn mix: every job in it is whole, in one of the states the writer gave it
        for job in jobs:
            assert job.status in ("queued", "running", "completed")
            if job.status == "completed":
                assert job.result is not None and job.result["coverage_pct"] == 97.5
    finally:
        reopened.close()


def test_backup_refuses_to_overwrite_and_names_what_it_cannot_copy(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # not the checkout's ./data, which `make serve` makes, its service's store
    runner = CliRunner()
    data = tmp_path / "data"
    data.mkdir()
    open_store(sqlite_url(data)).close()
    target = tmp_path / "copy.db"
    assert runner.invoke(app, ["backup", str(target), "--data-dir", str(data)]).exit_code == 0
    again = runner.invoke(app, ["backup", str(target), "--data-dir", str(data)])
    assert again.exit_code == 1 and "never overwrites" in again.output
    missing = runner.invoke(app, ["backup", str(tmp_path / "x.db"), "--data-dir", str(tmp_path / "none")])
    assert missing.exit_code == 1 and "no store at" in missing.output
    postgres = runner.invoke(app, ["backup", str(tmp_path / "y.db"),
                                   "--db", "postgresql+psycopg://cell:secret@db/cell"])
    assert postgres.exit_code == 1 and "pg_dump" in postgres.output and "secret" not in postgres.output
    assert not Path(tmp_path / "y.db").exists()


def test_a_destination_ending_in_a_slash_is_a_folder_made_if_new(tmp_path):
    """'bk/nodir/' wrote a file named bk/nodir: the '/' was lost and a missing name taken for a file."""
    runner = CliRunner()
    data = tmp_path / "data"
    data.mkdir()
    open_store(sqlite_url(data)).close()
    made = runner.invoke(app, ["backup", f"{tmp_path / 'bk'}/", "--data-dir", str(data)])
    assert made.exit_code == 0, made.output
    assert (tmp_path / "bk").is_dir() and [p.name[:5] for p in (tmp_path / "bk").iterdir()] == ["cell-"]
    deep = runner.invoke(app, ["backup", f"{tmp_path / 'no' / 'dir'}/", "--data-dir", str(data)])
    assert deep.exit_code == 1 and f"folder {tmp_path / 'no'} does not exist" in deep.output
    (tmp_path / "file").write_text("")
    a_file = runner.invoke(app, ["backup", f"{tmp_path / 'file'}/", "--data-dir", str(data)])
    assert a_file.exit_code == 1 and f"{tmp_path / 'file'} is not a folder" in a_file.output
    assert not (tmp_path / "no").exists() and (tmp_path / "file").read_text() == ""


def test_a_backup_is_its_owners_alone(tmp_path):
    """It holds the API keys' hashes, and was written 0644."""
    data = tmp_path / "data"
    data.mkdir()
    open_store(sqlite_url(data)).close()
    res = CliRunner().invoke(app, ["backup", str(tmp_path / "copy.db"), "--data-dir", str(data)])
    assert res.exit_code == 0, res.output
    assert stat.S_IMODE((tmp_path / "copy.db").stat().st_mode) == 0o600


def _backup(dest: str, data: Path) -> tuple[int, str, bool]:
    """Exit code, output and whether it ended on an exception other than its exit (a traceback)."""
    res = CliRunner().invoke(app, ["backup", dest, "--data-dir", str(data)])
    return res.exit_code, res.output, not isinstance(res.exception, SystemExit | None)


def test_a_destination_the_user_may_not_write_is_named_without_a_traceback():
    """A folder it could not make was a PermissionError's traceback; a folder it could not write in was
    'cannot back up .../cell.db: unable to open database file', blaming the store."""
    with service_folder() as base:
        data = base / "data"
        run_unprivileged(lambda: (data.mkdir(), open_store(sqlite_url(data)).close()))
        closed = base / "closed"
        closed.mkdir()
        foreign(closed)
        me = run_unprivileged(user_name)
        code, output, raised = run_unprivileged(lambda: _backup(f"{closed / 'new'}/", data))
        assert (code, raised) == (1, False), output
        # the folder made for the user, never the folder above it given away
        assert output == (f"error: cannot make the backup folder {closed / 'new'}: Permission denied; fix: "
                          f"sudo install -d -o {me} -m 0750 {closed / 'new'}\n")
        code, output, raised = run_unprivileged(lambda: _backup(f"{closed}/", data))
        assert (code, raised) == (1, False), output
        assert output.startswith(f"error: cannot write the backup {closed}/cell-")
        assert "may not write in it; fix: " in output and str(data) not in output
        assert list(closed.iterdir()) == []
