"""A data folder or store files the service's user may not write (left by a trial ``sudo cell serve``):
``cell serve`` and ``cell doctor`` say which path, whose it is and the command that gives it back."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from cell.cli.main import app
from cell.config import load_config
from cell.service.startup import ServiceSettings, build_service
from cell.service.store import open_store, sqlite_url
from drivers.errors import StoreError
from drivers.file_access import user_name
from tests.conftest import UR5E
from tests.service_process import free_port
from tests.unprivileged import AS_ROOT, foreign, run_unprivileged, service_folder


def _serve_error(data: Path) -> str:
    """What opening the service of the sim cell on ``data`` raises (it must not open)."""
    try:
        service = build_service(ServiceSettings(config_file=UR5E, data_dir=data))
    except StoreError as exc:
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
