"""``cell keys``: the service's API keys, managed on the machine that holds its store.

``create`` makes a key and prints it once (alone on its last line, so that a script can take it with
``tail -n 1``); only its SHA-256 is stored. ``list`` shows names, roles, creation times and whether each
key is active, never a key or a hash. ``revoke`` ends a key; its name stays taken. Every command opens the
store given by ``--db`` or, by default, the SQLite store in ``--data-dir``, and never migrates it: on a
store several cells share, that would stop those of the previous version (``cell serve`` migrates it).
``list`` only reads it; ``create`` gives a new store its schema, and warns that it made one: a key made in a
mistyped ``--data-dir`` is a key no running service knows (the PLC's login is then refused with no hint
where the key went). A data folder whose service uses another store than the one a command would open is
refused (:mod:`cell.service.store.service_store`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from cell.cli.commands import DB_ENVVAR, command_group
from cell.cli.errors import fail, print_warning
from cell.cli.values import data_folder
from cell.service.keys import Role, create_key, parse_role
from cell.service.store import Store, open_data_store
from cell.service.store.engine import POSTGRES_CONNECT_TIMEOUT_S, SQLITE_FILE, hide_password
from cell.service.store.repository import KEYS_SCHEMA, read_store
from cell.service.store.service_store import service_store_url
from drivers.errors import CellError, StoreError

DEFAULT_DATA_DIR = Path("data")

keys_app = command_group(help="API keys of the service: create, list, revoke.", no_args_is_help=True)
console = Console(soft_wrap=True)

DataDirOption = Annotated[Path, typer.Option(help="the service's data folder (its store: cell.db)",
                                             callback=data_folder)]
DbOption = Annotated[str | None, typer.Option(envvar=DB_ENVVAR,
                                              help="store URL instead of the data folder's SQLite file: "
                                                   "sqlite:///ABS/PATH/cell.db or "
                                                   "postgresql+psycopg://USER:PASSWORD@HOST:PORT/DB")]


@contextlib.contextmanager
def _one_line_errors() -> Iterator[None]:
    """Any ``CellError`` inside becomes a one-line ``error: ...`` on stderr and exit code 1."""
    try:
        yield
    except CellError as exc:
        raise fail(exc) from None


@contextlib.contextmanager
def opened_store(data_dir: Path, db: str | None) -> Iterator[Store]:
    """The store at ``db`` or, without it, the SQLite store in ``data_dir`` (the folder created if
    missing), closed at the end: made if there is none yet, never migrated (:data:`KEYS_SCHEMA` on
    will do). ``StoreError`` if it cannot be opened, or if it is not the store the data folder's service
    uses."""
    store = open_data_store(data_dir, service_store_url(data_dir, db), migrate=False, oldest=KEYS_SCHEMA)
    try:
        yield store
    finally:
        store.close()


def _print(text: str) -> None:
    console.print(text, markup=False, highlight=False)


def _utc(moment: datetime) -> str:
    """``moment`` in UTC, ISO 8601 to the second."""
    return moment.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


@keys_app.command("create")
def create(
    role: Annotated[str, typer.Option(help=f"what the key may do: {', '.join(Role)}")],
    name: Annotated[str | None, typer.Option(help="1-64 letters, digits, '.', '_', '-' (default: "
                                                  "{role}-{6 hex digits})")] = None,
    data_dir: DataDirOption = DEFAULT_DATA_DIR,
    db: DbOption = None,
) -> None:
    """Create a key and print it once: only its hash is stored, it cannot be shown again."""
    with _one_line_errors():
        parse_role(role)
        # a store given by --db was named on purpose; a data folder's may be a typo away from the service's
        new_store = not db and not (data_dir / SQLITE_FILE).exists()
        with opened_store(data_dir, db) as store:
            record, key = create_key(store, role, name)
    if new_store:
        print_warning(f"no store in {data_dir} yet: made {data_dir / SQLITE_FILE}; the key works for a cell "
                      f"serve with --data-dir {data_dir} (the first key of a new cell; else check that "
                      f"{data_dir} is the service's data folder)")
    _print(f"created key {record.name!r} (role {record.role}); it is shown once, store it now:")
    _print(key)


def _existing_store(data_dir: Path, db: str | None) -> Store | None:
    """The store the service of ``data_dir`` uses (or ``db``), opened to read only; None, with a warning
    naming where it looked, when there is none yet: a mistyped ``--data-dir`` is no store of keys."""
    url = service_store_url(data_dir, db)
    store = read_store(url, KEYS_SCHEMA, POSTGRES_CONNECT_TIMEOUT_S)
    if store is None:
        asked = "" if db is not None else f"; is {data_dir} the service's data folder (--data-dir)?"
        print_warning(f"no store at {hide_password(url)} yet (cell serve and cell keys create make "
                      f"it){asked}")
    return store


@keys_app.command("list")
def list_keys(data_dir: DataDirOption = DEFAULT_DATA_DIR, db: DbOption = None) -> None:
    """List the keys: name, role, creation time (UTC) and whether each is active or since when revoked."""
    with _one_line_errors():
        store = _existing_store(data_dir, db)
        try:
            records = store.list_keys() if store is not None else []
        finally:
            if store is not None:
                store.close()
    if not records:
        _print("no keys")
        return
    width = max(len(record.name) for record in records)
    for record in records:
        state = "active" if record.revoked_at is None else f"revoked {_utc(record.revoked_at)}"
        _print(f"{record.name:{width}s}  {record.role:8s}  created {_utc(record.created_at)}  {state}")


@keys_app.command("revoke")
def revoke(
    name: Annotated[str, typer.Argument(metavar="NAME", help="the key's name")],
    data_dir: DataDirOption = DEFAULT_DATA_DIR,
    db: DbOption = None,
) -> None:
    """Revoke a key: the service refuses it within a second. Its name stays taken."""
    with _one_line_errors():
        existing = _existing_store(data_dir, db)
        if existing is None:  # opening it to write would make an empty store there, and its folder
            raise StoreError(f"no key named {name!r}: there is no store to revoke it in")
        existing.close()
        with opened_store(data_dir, db) as store:
            record = store.revoke_key(name)
    _print(f"revoked key {record.name!r} (role {record.role})")
