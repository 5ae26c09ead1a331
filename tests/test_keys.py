"""API keys: roles and permissions, creation (only the hash is stored), the in-memory key ring, and the
``cell keys`` commands."""

from __future__ import annotations

import asyncio
import hashlib
import re
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cell.api.auth import ACTIONS
from cell.cli.main import app
from cell.doctor import machine
from cell.doctor.findings import Status
from cell.service.keys import (
    PERMISSIONS,
    KeyRing,
    Permission,
    Role,
    allowed,
    create_key,
    hash_key,
    new_key,
)
from cell.service.startup import ServiceSettings, build_service
from cell.service.store import Store, open_store, sqlite_url
from cell.service.store.service_store import STORE_RECORD, record_service_store
from drivers.errors import ServiceError, StoreError
from tests.conftest import UR5E

KEY = re.compile(r"cell_[A-Za-z0-9_-]{43}")
UTC_SECONDS = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ"  # how `cell keys list` shows a time


@pytest.fixture
def store(tmp_path: Path) -> Iterator[Store]:
    opened = open_store(sqlite_url(tmp_path))
    yield opened
    opened.close()


def raw_rows(db: Path) -> list[tuple[object, ...]]:
    with sqlite3.connect(db) as raw:
        return raw.execute("SELECT * FROM api_keys").fetchall()


def test_permission_table():
    expected = {
        Role.VIEWER: {Permission.READ, Permission.STOP},
        Role.OPERATOR: {Permission.READ, Permission.STOP, Permission.SUBMIT, Permission.CANCEL,
                        Permission.RECOVER, Permission.UPLOAD, Permission.MODE, Permission.KEEP},
        Role.LINE: {Permission.READ, Permission.STOP, Permission.LINE, Permission.MODE},
        Role.ADMIN: set(Permission),
    }
    assert expected == PERMISSIONS
    assert not allowed("viewer", Permission.SUBMIT)
    assert allowed("operator", Permission.SUBMIT)
    assert all(allowed(role, Permission.STOP) for role in Role)
    assert [role for role in Role if allowed(role, Permission.KEYS)] == [Role.ADMIN]
    assert not allowed("nobody", Permission.READ)
    # every permission has the words a 403 says it in (a missing one made the refusal a 500)
    assert set(ACTIONS) == set(Permission)


def test_new_keys_are_random():
    keys = {new_key() for _ in range(100)}
    assert len(keys) == 100 and all(KEY.fullmatch(key) for key in keys)
    assert hash_key("cell_x") == hashlib.sha256(b"cell_x").hexdigest()


def test_create_key_stores_only_the_hash(store: Store, tmp_path: Path):
    record, key = create_key(store, "operator", "op-1")
    assert KEY.fullmatch(key)
    assert (record.name, record.role, record.active) == ("op-1", "operator", True)
    assert record.key_hash == hashlib.sha256(key.encode()).hexdigest()
    rows = raw_rows(tmp_path / "cell.db")
    assert len(rows) == 1
    assert record.key_hash in rows[0]
    assert not any(key in str(value) for value in rows[0])
    assert store.list_keys() == [record]


def test_default_name(store: Store):
    record, _ = create_key(store, "viewer", None)
    assert re.fullmatch(r"viewer-[0-9a-f]{6}", record.name)


def test_create_key_refuses(store: Store):
    with pytest.raises(ServiceError) as err:
        create_key(store, "root", "x")
    assert (err.value.reason, err.value.field) == ("invalid", "role")
    assert "viewer, operator, line, admin" in str(err.value)
    for name in ("", "has space", "x" * 65, "semi;colon", "cell_" + "A" * 43):  # the last: a key's shape
        with pytest.raises(ServiceError) as err:
            create_key(store, "viewer", name)
        assert (err.value.reason, err.value.field) == ("invalid", "name")
        assert "A" * 20 not in str(err.value)
    create_key(store, "viewer", "screen.1")
    with pytest.raises(ServiceError) as err:
        create_key(store, "admin", "screen.1")
    assert err.value.reason == "conflict"
    assert [k.name for k in store.list_keys()] == ["screen.1"]


def test_key_ring(store: Store):
    operator, operator_key = create_key(store, "operator", "op")
    ring = KeyRing(store)
    assert len(ring) == 1
    assert ring.authenticate(operator_key) == operator
    assert ring.authenticate(new_key()) is None
    assert ring.authenticate("") is None
    line, line_key = create_key(store, "line", "plc")
    assert ring.authenticate(line_key) is None  # not before the next refresh
    ring.refresh()
    assert ring.authenticate(line_key) == line and len(ring) == 2
    store.revoke_key("op")
    ring.refresh()
    assert ring.authenticate(operator_key) is None and len(ring) == 1


# the command line

runner = CliRunner()


def test_cli_create_list_revoke(tmp_path: Path):
    data = tmp_path / "data"
    created = runner.invoke(app, ["keys", "create", "--data-dir", str(data), "--role", "operator",
                                  "--name", "op-1"])
    assert created.exit_code == 0, created.output
    lines = created.stdout.splitlines()
    key = lines[-1]
    assert KEY.fullmatch(key)
    assert lines[-2] == "created key 'op-1' (role operator); it is shown once, store it now:"
    assert (data / "cell.db").exists()

    listed = runner.invoke(app, ["keys", "list", "--data-dir", str(data)])
    assert listed.exit_code == 0, listed.output
    assert re.fullmatch(rf"op-1\s+operator\s+created {UTC_SECONDS}\s+active\n", listed.stdout)
    assert key not in listed.output and hash_key(key) not in listed.output

    revoked = runner.invoke(app, ["keys", "revoke", "op-1", "--data-dir", str(data)])
    assert revoked.exit_code == 0, revoked.output
    listed = runner.invoke(app, ["keys", "list", "--data-dir", str(data)])
    assert re.fullmatch(rf"op-1\s+operator\s+created {UTC_SECONDS}\s+revoked {UTC_SECONDS}\n", listed.stdout)

    again = runner.invoke(app, ["keys", "revoke", "op-1", "--data-dir", str(data)])
    assert again.exit_code == 1
    assert again.stderr.startswith("error: key 'op-1' was already revoked") and again.stderr.count("\n") == 1


def test_cli_create_warns_when_it_makes_a_new_store(tmp_path: Path):
    """A commissioning engineer who mistyped --data-dir (/var/lib/cel) got a key and no hint that it went
    into a new store no running service reads: the PLC's login was then refused. create says so on
    standard error; the key stays alone on standard output's last line."""
    data = tmp_path / "cel"
    made = runner.invoke(app, ["keys", "create", "--data-dir", str(data), "--role", "line", "--name",
                               "plc-1"])
    assert made.exit_code == 0, made.output
    assert KEY.fullmatch(made.stdout.splitlines()[-1])
    assert made.stderr == (f"warning: no store in {data} yet: made {data / 'cell.db'}; the key works for a "
                           f"cell serve with --data-dir {data} (the first key of a new cell; else check that "
                           f"{data} is the service's data folder)\n")
    # the folder a service (or cell init, then the first create) made a store in: no warning
    again = runner.invoke(app, ["keys", "create", "--data-dir", str(data), "--role", "line", "--name",
                                "plc-2"])
    assert (again.exit_code, again.stderr) == (0, "")
    # a store named on purpose with --db: no warning either
    (tmp_path / "shared").mkdir()
    shared = sqlite_url(tmp_path / "shared")
    named = runner.invoke(app, ["keys", "create", "--db", shared, "--role", "viewer"])
    assert (named.exit_code, named.stderr) == (0, "")


def test_cli_defaults_and_db_option(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.chdir(tmp_path)
    created = runner.invoke(app, ["keys", "create", "--role", "admin"])
    assert created.exit_code == 0, created.output
    assert (tmp_path / "data" / "cell.db").exists()  # --data-dir defaults to ./data
    assert runner.invoke(app, ["keys", "list"]).stdout.startswith("admin-")
    (tmp_path / "other").mkdir()
    db = sqlite_url(tmp_path / "other")
    assert runner.invoke(app, ["keys", "list", "--db", db]).stdout == "no keys\n"
    # a URL with a password is given in the environment, out of the process list
    created = runner.invoke(app, ["keys", "create", "--role", "viewer", "--name", "v"], env={"CELL_DB": db})
    assert created.exit_code == 0, created.output
    assert runner.invoke(app, ["keys", "list", "--db", db]).stdout.startswith("v ")


def test_cli_errors_are_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.chdir(tmp_path)  # not the checkout's ./data, which `make serve` makes, its service's store
    data = tmp_path / "data"
    bad_role = runner.invoke(app, ["keys", "create", "--data-dir", str(data), "--role", "root"])
    assert bad_role.exit_code == 1
    assert bad_role.stderr == "error: unknown role 'root' (roles: viewer, operator, line, admin)\n"
    assert bad_role.stdout == ""
    assert not data.exists()  # refused before the store was opened
    bad_db = runner.invoke(app, ["keys", "list", "--db", "mysql://cell:s3cret@localhost/cell"])
    assert bad_db.exit_code == 1
    assert bad_db.stderr.startswith("error: job store mysql://cell:***@localhost/cell: unsupported")
    assert bad_db.stderr.count("\n") == 1 and "s3cret" not in bad_db.output
    # a mistyped --data-dir: revoke made an empty store (and the folder) there, then found no such key
    store = sqlite_url(data)
    unknown = runner.invoke(app, ["keys", "revoke", "nobody", "--data-dir", str(data)])
    assert unknown.exit_code == 1 and unknown.stdout == ""
    assert unknown.stderr.splitlines() == [
        f"warning: no store at {store} yet (cell serve and cell keys create make it); is {data} the "
        "service's data folder (--data-dir)?",
        "error: no key named 'nobody': there is no store to revoke it in"]
    assert not data.exists()
    listed = runner.invoke(app, ["keys", "list", "--data-dir", str(data)])
    assert (listed.exit_code, listed.stdout) == (0, "no keys\n")
    assert listed.stderr.startswith("warning: no store")
    assert not data.exists()
    assert runner.invoke(app, ["keys", "create", "--data-dir", str(data), "--role", "viewer"]).exit_code == 0
    unknown = runner.invoke(app, ["keys", "revoke", "nobody", "--data-dir", str(data)])
    assert (unknown.exit_code, unknown.stderr) == (1, "error: no key named 'nobody'\n")


def test_a_data_folder_whose_service_uses_another_store_is_refused(tmp_path: Path):
    """Without the service's CELL_DB, `cell keys create` made a new SQLite store in the data folder of a
    service on PostgreSQL; the key then got 401 with no hint. cell serve records its store; the commands
    of that data folder refuse another, naming both."""
    data, other = tmp_path / "data", tmp_path / "other"
    other.mkdir()
    service = build_service(ServiceSettings(config_file=UR5E, data_dir=data, db_url=sqlite_url(other)))
    asyncio.run(service.close())
    service.store.close()
    assert (data / STORE_RECORD).read_text() == sqlite_url(other) + "\n"
    for command in (["keys", "create", "--role", "admin"], ["keys", "list"], ["keys", "revoke", "x"],
                    ["backup", str(tmp_path / "b.db")]):
        refused = runner.invoke(app, [*command, "--data-dir", str(data)])
        assert refused.exit_code == 1 and refused.stderr.count("\n") == 1, refused.output
        assert refused.stderr.startswith(f"error: the service of data folder {data} uses the job store "
                                         f"{sqlite_url(other)}, and this command would open "
                                         f"{sqlite_url(data)}: give it the service's store with --db or "
                                         "CELL_DB"), refused.stderr
    assert not (data / "cell.db").exists() and not (tmp_path / "b.db").exists()
    found = machine.store(data, None, "127.0.0.1")
    assert [f.status for f in found] == [Status.FAIL] and "uses the job store" in found[0].detail
    created = runner.invoke(app, ["keys", "create", "--role", "admin", "--data-dir", str(data)],
                            env={"CELL_DB": sqlite_url(other)})
    assert created.exit_code == 0, created.output
    # the service itself, started by hand without the unit's CELL_DB, neither (moved only on purpose)
    with pytest.raises(StoreError, match=rf"uses the job store {sqlite_url(other)}, and this command would "
                                         rf"open {sqlite_url(data)}: .*; to move the cell to this store on "
                                         rf"purpose, delete {data / STORE_RECORD} first"):
        build_service(ServiceSettings(config_file=UR5E, data_dir=data))
    assert not (data / "cell.db").exists()

    record_service_store(data, "postgresql+psycopg://cell:s3cret@db-host/cells")
    assert (data / STORE_RECORD).read_text() == "postgresql+psycopg://cell:***@db-host/cells\n"
    refused = runner.invoke(app, ["keys", "list", "--data-dir", str(data)])
    assert refused.exit_code == 1 and "uses the job store postgresql+psycopg://cell:***@db-host/cells" \
        in refused.stderr


@pytest.mark.parametrize("command", [["keys", "create", "--role", "line"], ["keys", "list"],
                                     ["keys", "revoke", "plc-1"], ["backup", "backups/"], ["serve"],
                                     ["init", "c1", "--template", "sim-ur5e-tof"],
                                     ["calibrate", "table", "--config", str(UR5E)]])
def test_a_data_dir_that_is_a_file_is_refused_as_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     command: list[str]):
    """A --data-dir naming a file was refused with "cannot read which store the service of data uses
    (data/store-url): Not a directory", which sends an engineer after the store rather than the path."""
    monkeypatch.chdir(tmp_path)
    Path("data").write_text("")
    refused = runner.invoke(app, [*command, "--data-dir", "data"])
    assert (refused.exit_code, refused.stdout) == (1, "")
    assert refused.stderr == "error: --data-dir data is not a folder: give a folder, or a name not taken\n"
    assert sorted(path.name for path in tmp_path.iterdir()) == ["data"]
