"""A data folder or store files the service's user may not write (left by a trial ``sudo cell serve``):
``cell serve`` and ``cell doctor`` say which path, whose it is and the command that gives it back; and
store files no one else may read."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cell.cli.main import app
from cell.config import load_config
from cell.service.startup import ServiceSettings, build_service
from cell.service.store import open_data_store, open_store, sqlite_url
from drivers.errors import CellError
from drivers.file_access import user_name
from tests.conftest import UR5E
from tests.service_process import ServedCell, create_key, free_port
from tests.unprivileged import AS_ROOT, foreign, run_unprivileged, service_folder


def _serve_error(data: Path) -> str:
    """What opening the service of the sim cell on ``data`` raises (it must not open)."""
    try:
        service = build_service(ServiceSettings(config_file=UR5E, data_dir=data))
    except CellError as exc:  # the data dir's claim, or the store's
        return str(exc)
    service.store.close()
    raise AssertionError("the service opened its store")


def _doctor(data: Path) -> tuple[int, str]:
    res = CliRunner().invoke(app, ["doctor", "--config", str(UR5E), "--data-dir", str(data),
                                   "--port", str(free_port())])
    return res.exit_code, res.output


def test_a_data_folder_the_user_may_not_write_is_named_with_its_owner_and_the_chown():
    """'job store sqlite:///...: cannot open: unable to open database file', with no fix."""
    with service_folder() as base:
        data = base / "data"
        data.mkdir()
        foreign(data)
        error = run_unprivileged(lambda: _serve_error(data))
        me = run_unprivileged(user_name)
        owner = "root:root" if AS_ROOT else f"{me}:"
        assert f"folder {data} belongs to {owner}" in error and f"user {me} may not write in it" in error
        fix = f"sudo chown -R {me}: {data}" if AS_ROOT else f"chmod u+rwx {data}"
        assert error.endswith(f"; fix: {fix}"), error
        # a data folder not made yet is made for the user: the folder above it is not given away
        error = run_unprivileged(lambda: _serve_error(data / "cell"))
        assert error == (f"cannot create the data folder {data / 'cell'}: Permission denied; fix: "
                         f"sudo install -d -o {me} -m 0750 {data / 'cell'}")


def test_a_lease_file_left_by_root_stops_serve_and_doctor_with_the_chown():
    """A root-owned cell.db.lease-* (mode 0600) made the service's user fail with 'Permission denied' alone,
    and cell doctor reported 0 failed."""
    with service_folder() as data:
        run_unprivileged(lambda: open_store(sqlite_url(data)).close())  # the service's own store
        store = open_store(sqlite_url(data))  # the trial `sudo cell serve`
        store.claim_cell(load_config(UR5E).name).release()
        store.close()
        (lease,) = data.glob("cell.db.lease-*")
        foreign(lease)
        me = run_unprivileged(user_name)
        error = run_unprivileged(lambda: _serve_error(data))
        assert f"file {lease} belongs to" in error and f"user {me} may not read and write it" in error
        fix = f"sudo chown {me}: {data}/cell.db*" if AS_ROOT else f"chmod u+rw {data}/cell.db*"
        assert error.endswith(f"; fix: {fix}"), error
        code, output = run_unprivileged(lambda: _doctor(data))
        assert code == 1, output
        line = next(line for line in output.splitlines() if "job store" in line)
        assert line.startswith("FAIL") and f"file {lease} belongs to" in line, output
        assert f"fix: {fix}" in output


def test_the_store_files_are_the_service_users_alone_whatever_the_umask(tmp_path: Path) -> None:
    """``cell keys create`` and ``cell serve`` left cell.db, cell.db-wal and cell.db-shm at 0644 under umask
    022: readable by every user, and they hold the API keys' hashes. A new store's files are made 0600; an
    existing store's are made so when the service starts, with a log line each."""
    fresh, old = tmp_path / "fresh", tmp_path / "old"
    previous = os.umask(0o022)
    try:
        create_key(fresh, "viewer", "v")
        create_key(old, "viewer", "v")
        for path in old.glob("cell.db*"):
            path.chmod(0o644)  # as an older version left it
        for data in (fresh, old):
            with ServedCell(UR5E, data) as cell:
                with cell.client("admin") as client:  # a write: the WAL and shared memory are in use
                    assert client.post("/api/v1/retention/prune").status_code == 200
                modes = {p.name: stat.S_IMODE(p.stat().st_mode) for p in data.glob("cell.db*")}
                log = cell.log()
            assert {"cell.db", "cell.db-wal", "cell.db-shm"} <= set(modes), modes
            assert set(modes.values()) == {0o600}, modes
            assert ("was mode 0644, open beyond the service's user: made 0600" in log) == (data == old), log
    finally:
        os.umask(previous)


def test_the_data_folders_own_store_named_by_its_url_is_made_the_users_alone(tmp_path: Path) -> None:
    """``--db`` naming the data folder's own cell.db (the URL a command chose, ``service_store_url``) had
    SQLite make the file under the umask (0644 under 022), where the same store chosen by default was made
    0600."""
    data = tmp_path / "data"
    previous = os.umask(0o022)
    try:
        open_data_store(data, sqlite_url(data)).close()
    finally:
        os.umask(previous)
    assert stat.S_IMODE((data / "cell.db").stat().st_mode) == 0o600


def test_the_data_folders_own_store_named_relative_to_the_working_folder_is_made_the_users_alone(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--db sqlite:///data/cell.db`` from the folder holding ``data`` names the same file as the data
    folder's own URL, and is made 0600 as that one is."""
    monkeypatch.chdir(tmp_path)
    previous = os.umask(0o022)
    try:
        open_data_store(Path("data"), "sqlite:///data/cell.db").close()
    finally:
        os.umask(previous)
    assert stat.S_IMODE((tmp_path / "data" / "cell.db").stat().st_mode) == 0o600
