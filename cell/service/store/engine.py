"""Opening the job store's database: URL checks, the engine with SQLite's pragmas, and the schema brought
to this software's newest Alembic revision.

Two databases are supported: SQLite (``sqlite:///ABS/PATH/cell.db``, a single cell's default, in WAL mode
so that the API's readers never wait for the worker's writes) and PostgreSQL through psycopg 3
(``postgresql+psycopg://USER:PASSWORD@HOST:PORT/DATABASE``, which several cells may share; a plain
``postgresql://`` means the same). Every failure is a one-line :class:`drivers.errors.StoreError` naming
the URL with its password hidden.
"""

from __future__ import annotations

import logging
import re
import sqlite3
import threading
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from alembic.util import CommandError
from sqlalchemy import Connection, Engine, create_engine, event, make_url, text
from sqlalchemy.engine import URL
from sqlalchemy.exc import ArgumentError, DBAPIError, IntegrityError, SQLAlchemyError

from drivers.errors import StoreDamaged, StoreError
from drivers.file_access import AccessProblem, files_problem

MIGRATIONS = Path(__file__).resolve().parent / "migrations"
SUPPORTED_URLS = "sqlite:///ABS/PATH/cell.db or postgresql+psycopg://USER:PASSWORD@HOST:PORT/DATABASE"
SQLITE_FILE = "cell.db"  # the store's file in a cell's data folder
# Set on every SQLite connection: wait up to 5 s for another writer (first, so that switching to WAL
# waits too), write-ahead log (readers and one writer at once), fsync at checkpoints only (WAL stays
# consistent after a crash; the last transactions may be lost on power loss), enforced foreign keys.
SQLITE_PRAGMAS = ("PRAGMA busy_timeout=5000", "PRAGMA journal_mode=WAL", "PRAGMA synchronous=NORMAL",
                  "PRAGMA foreign_keys=ON")
POSTGRES_CONNECT_TIMEOUT_S = 10  # how long a connection attempt to PostgreSQL may take [s]
# Key of the PostgreSQL advisory lock held while migrating, so that cells starting together on one
# database migrate one after the other ("cell" in ASCII).
MIGRATION_LOCK_ID = 0x63656C6C
# How long a cell starting beside another waits for that one's SQLite migration [ms]: longer than the
# 5 s a request waits, as a migration on a loaded machine can take several seconds.
SQLITE_MIGRATION_WAIT_MS = 60_000
# How long it waits for the lock without a word first [ms]: cells started together take it in turns for
# their migrations, each well under a second on an idle machine; a wait past this one is said.
SQLITE_QUIET_WAIT_MS = 1_000
log = logging.getLogger("cell.service.store")
# Alembic's ``context`` and ``op`` are module-level proxies: one migration at a time in a process.
_MIGRATING = threading.Lock()


def sqlite_url(data_dir: Path) -> str:
    """The URL of the SQLite store in ``data_dir`` (``<data_dir>/cell.db``, made absolute)."""
    return f"sqlite:///{(data_dir / SQLITE_FILE).resolve()}"


def sqlite_database(url: str | URL) -> Path | None:
    """The database file of the SQLite store at ``url`` (text, or an engine's URL); None for another
    database, or a URL that does not parse or names no file (opening it says why)."""
    try:
        parsed = make_url(url)
    except (ArgumentError, ValueError):
        return None
    if parsed.get_backend_name() != "sqlite" or not parsed.database or parsed.database == ":memory:":
        return None
    return Path(parsed.database)


def sqlite_access_problem(database: Path) -> AccessProblem | None:
    """What stops this user at the SQLite store ``database``: its folder, or one of its files (the database,
    its WAL and shared memory, the cells' lease files: ``cell.db*``) that is not this user's to read and
    write, as a trial ``sudo cell serve`` leaves them; SQLite itself says only "unable to open database
    file", or nothing until a write fails."""
    return files_problem(database.parent, f"{database.name}*",
                         "choose a data dir on a writable file system (--data-dir; --db for the store alone)")


def hide_password(url: str) -> str:
    """``url`` with its password shown as ``***``, also when it does not parse as a URL."""
    try:
        return make_url(url).render_as_string(hide_password=True)
    except (ArgumentError, ValueError):
        return re.sub(r"(://[^/@:]*:)[^@]*@", r"\1***@", url)


RESTORE = "the store is damaged: restore it from a backup (docs/deploy.md, section 9)"
"""What a :class:`StoreDamaged` says to do."""
# PostgreSQL's SQLSTATEs of data found corrupt: data_corrupted, index_corrupted
POSTGRES_DAMAGED = frozenset({"XX001", "XX002"})


def is_damage(exc: BaseException) -> bool:
    """Whether the database error ``exc`` (SQLAlchemy's, or the driver's own) says the store's data is
    damaged, not that it does not answer: its pages are (:func:`is_corrupt`), or the stored data breaks a
    constraint (an integrity error no caller expected)."""
    return isinstance(exc, IntegrityError | sqlite3.IntegrityError) or is_corrupt(exc)


def is_corrupt(exc: BaseException) -> bool:
    """Whether the database error ``exc`` says the store's pages are corrupt: SQLite's ``SQLITE_CORRUPT``
    ("database disk image is malformed") or ``SQLITE_NOTADB`` ("file is not a database"), PostgreSQL's
    corrupt data or index."""
    cause = exc.orig if isinstance(exc, DBAPIError) and exc.orig is not None else exc
    name = getattr(cause, "sqlite_errorname", "")
    return ((isinstance(name, str) and name.startswith(("SQLITE_CORRUPT", "SQLITE_NOTADB")))
            or getattr(cause, "sqlstate", None) in POSTGRES_DAMAGED)


def store_error(shown_url: str, action: str, exc: BaseException, password: str | None) -> StoreError:
    """A one-line :class:`StoreError` for ``exc`` raised while doing ``action``: the store's URL (password
    hidden), the action, and the driver's own words (not SQLAlchemy's statement dump), on one line and
    with ``password`` blotted out; a :class:`StoreDamaged` that says to restore a backup when the error
    says the data is damaged (:func:`is_damage`)."""
    cause = exc.orig if isinstance(exc, DBAPIError) and exc.orig is not None else exc
    reason = " ".join(line.strip() for line in str(cause).splitlines() if line.strip())
    if password:
        reason = reason.replace(password, "***")
    message = f"job store {shown_url}: {action}: {reason or type(cause).__name__}"
    if is_damage(exc):
        return StoreDamaged(f"{message}; {RESTORE}")
    return StoreError(message)


def check_integrity(connection: Connection, shown: str) -> None:
    """:class:`StoreDamaged` naming the store ``shown`` when SQLite's ``PRAGMA quick_check`` (every page
    read: 0.4 s for a 250 MB store from the page cache, more from a cold disk) finds damage on
    ``connection``; nothing for PostgreSQL, whose server checks its pages as it reads them."""
    if connection.dialect.name != "sqlite":
        return
    # each row may hold several lines, the first a "*** in database main ***" heading
    found = [line.strip() for row in connection.exec_driver_sql("PRAGMA quick_check(5)")
             for line in str(row[0]).splitlines() if line.strip() and not line.startswith("***")]
    if found != ["ok"]:
        raise StoreDamaged(f"job store {shown}: its integrity check fails ({'; '.join(found)}); {RESTORE}")


def schema_head() -> str:
    """The newest schema revision this software knows (its migrations' head)."""
    head = ScriptDirectory.from_config(_alembic_config()).get_current_head()
    if head is None:
        raise StoreError(f"no migrations found in {MIGRATIONS}")
    return head


def schema_revisions(connection: Connection, shown: str) -> set[str]:
    """The schema revisions of the database on ``connection`` (none: no schema yet); :class:`StoreError`
    naming the store ``shown`` when one is newer than this software's (a newer cell migrated it)."""
    script = ScriptDirectory.from_config(_alembic_config())
    known = {revision.revision for revision in script.walk_revisions()}
    current = set(MigrationContext.configure(connection).get_current_heads())
    unknown = sorted(current - known)
    if unknown:
        raise StoreError(f"job store {shown}: the database's schema revision {', '.join(unknown)} is "
                         f"newer than this software's ({script.get_current_head()}); upgrade cell")
    return current


def check_oldest(revisions: set[str], oldest: str, shown: str) -> None:
    """:class:`StoreError` naming the store ``shown`` unless each of its schema ``revisions`` (known to
    this software: :func:`schema_revisions`) is ``oldest`` or a later one: a command that does not
    migrate the store works on a schema from ``oldest`` on, and says what does migrate it."""
    script = ScriptDirectory.from_config(_alembic_config())
    older = sorted(revision for revision in revisions
                   if oldest not in {r.revision for r in script.walk_revisions("base", revision)})
    if older:
        raise StoreError(f"job store {shown}: its schema revision {', '.join(older)} is older than {oldest}, "
                         f"which this command needs, and only cell serve migrates a store (to "
                         f"{script.get_current_head()}, this software's, when it starts; with several "
                         "cells on the store, docs/deploy.md, 'Updating', says in which order)")


def open_engine(url: str, *, migrate: bool = True, oldest: str | None = None) -> Engine:
    """An engine on ``url`` whose schema is at :func:`schema_head`, migrated if need be; a database
    already there is not touched. Raises :class:`StoreError` on a bad URL, an unsupported database, a
    database that cannot be reached or migrated, or one whose schema is newer than this software's.

    With ``migrate`` False (the commands beside ``cell serve``), a database with no schema yet is given
    the newest one, but an older schema is left as it is: a shared store migrated by a command would stop
    the cells of the previous version on it. It is accepted from revision ``oldest`` on (the oldest whose
    tables the caller uses, :func:`check_oldest`), refused before."""
    shown = hide_password(url)
    engine = _create_engine(url, shown)
    try:
        _upgrade(engine, shown, oldest=None if migrate else oldest or schema_head())
    except (StoreError, CommandError, SQLAlchemyError) as exc:
        engine.dispose()
        if isinstance(exc, StoreError):
            raise
        raise store_error(shown, "cannot open", exc, engine.url.password) from None
    return engine


def read_only_engine(url: str, connect_timeout_s: int) -> Engine | None:
    """An engine that reads the store at ``url`` and cannot change it (no migration, no pragma written, a
    PostgreSQL session read-only), giving up a connection attempt to PostgreSQL after
    ``connect_timeout_s`` [s, whole seconds: libpq's unit]; None for an SQLite file not made yet (the
    service makes it). :class:`StoreError` for a bad URL or an unsupported database, as
    :func:`open_engine`."""
    shown = hide_password(url)
    parsed = _parse(url, shown)
    if parsed.get_backend_name() == "sqlite":
        if not parsed.database or not Path(parsed.database).is_file():
            return None
        # SQLite's URI form opens the file read-only: a check never makes or changes a store
        return create_engine(parsed.set(database=f"file:{parsed.database}",
                                        query={"mode": "ro", "uri": "true"}))
    return _postgres_engine(parsed, shown, {"connect_timeout": connect_timeout_s,
                                            "options": "-c default_transaction_read_only=on"})


def _parse(url: str, shown: str) -> URL:
    """``url`` parsed, of a supported database; :class:`StoreError` otherwise."""
    try:
        parsed = make_url(url)
    except (ArgumentError, ValueError):
        raise StoreError(f"job store {shown}: not a database URL (expected {SUPPORTED_URLS})") from None
    backend, _, driver = parsed.drivername.partition("+")
    if not ((backend == "sqlite" and driver in ("", "pysqlite")) or
            (backend == "postgresql" and driver in ("", "psycopg"))):
        raise StoreError(f"job store {shown}: unsupported database {parsed.drivername!r} "
                         f"(expected {SUPPORTED_URLS})")
    return parsed


def _create_engine(url: str, shown: str) -> Engine:
    parsed = _parse(url, shown)
    if parsed.get_backend_name() == "sqlite":
        return _sqlite_engine(parsed, shown)
    return _postgres_engine(parsed, shown, {"connect_timeout": POSTGRES_CONNECT_TIMEOUT_S})


def _postgres_engine(parsed: URL, shown: str, connect_args: dict[str, Any]) -> Engine:
    try:
        return create_engine(parsed.set(drivername="postgresql+psycopg"), pool_pre_ping=True,
                             connect_args=connect_args)
    except ImportError:
        raise StoreError(f"job store {shown}: PostgreSQL needs psycopg: pip install 'cell[postgres]'"
                         ) from None


def _sqlite_engine(parsed: URL, shown: str) -> Engine:
    """A file-backed SQLite engine that sets :data:`SQLITE_PRAGMAS` on every new connection."""
    if not parsed.database or parsed.database == ":memory:":
        raise StoreError(f"job store {shown}: an SQLite store needs a file (sqlite:///ABS/PATH/cell.db)")
    folder = Path(parsed.database).parent
    if not folder.is_dir():
        raise StoreError(f"job store {shown}: folder {folder} does not exist")
    problem = sqlite_access_problem(Path(parsed.database))
    if problem is not None:
        raise StoreError(f"job store {shown}: {problem}")
    engine = create_engine(parsed)
    event.listen(engine, "connect", _set_sqlite_pragmas)
    return engine


def _set_sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    try:
        for pragma in SQLITE_PRAGMAS:
            cursor.execute(pragma)
    finally:
        cursor.close()


def _begin_sqlite_write(connection: Connection, shown: str) -> None:
    """Take the SQLite store ``shown``'s write lock on ``connection`` (``BEGIN IMMEDIATE``). When another
    process holds it past ``SQLITE_QUIET_WAIT_MS`` (another cell migrating it on a loaded machine, a
    program with a transaction open on the file), say so on the console, with how long it waits
    (``SQLITE_MIGRATION_WAIT_MS``), and wait; :class:`StoreError` saying who may hold it when the lock
    was not freed meanwhile. A start had waited silently; one beside another, whose migration takes a
    moment, is not worth a word."""
    connection.exec_driver_sql(f"PRAGMA busy_timeout={SQLITE_QUIET_WAIT_MS}")
    try:
        connection.exec_driver_sql("BEGIN IMMEDIATE")
        return
    except SQLAlchemyError as exc:
        if not _is_locked(exc):
            raise
        connection.rollback()
    wait_s = SQLITE_MIGRATION_WAIT_MS / 1000
    log.warning("job store %s: another process holds its lock (another cell starting on it, a program "
                "with a transaction open on the file); waiting up to %g s for it", shown, wait_s)
    connection.exec_driver_sql(f"PRAGMA busy_timeout={SQLITE_MIGRATION_WAIT_MS}")
    try:
        connection.exec_driver_sql("BEGIN IMMEDIATE")
    except SQLAlchemyError as exc:
        if not _is_locked(exc):
            raise
        file = make_url(shown).database
        held_s = (SQLITE_QUIET_WAIT_MS + SQLITE_MIGRATION_WAIT_MS) / 1000
        raise StoreError(f"job store {shown}: another process held its lock for {held_s:g} s, and the store "
                         f"cannot be opened while it does: end that process (`fuser -v {file}` lists those "
                         f"that have the file open), then start again") from None


def _is_locked(exc: SQLAlchemyError) -> bool:
    """Whether ``exc`` is SQLite's "database is locked" (or "busy"): another connection holds the lock."""
    cause = exc.orig if isinstance(exc, DBAPIError) else None
    return isinstance(cause, sqlite3.OperationalError) and (
        "locked" in str(cause) or "busy" in str(cause))


def _alembic_config() -> Config:
    """Alembic's configuration without an ini file: the packaged migrations folder."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS).replace("%", "%%"))
    config.set_main_option("path_separator", "os")
    return config


def _upgrade(engine: Engine, shown: str, oldest: str | None = None) -> None:
    """Migrate ``engine``'s database to the head revision on one connection; refuse a revision this
    software does not know (a newer cell migrated the database). With ``oldest``, only a database with
    no schema yet is given one: a schema there is checked to be ``oldest`` or later, never migrated.

    Stores opened at once never race: in this process a lock serializes migrations, and across processes
    PostgreSQL's advisory lock or SQLite's write lock (``BEGIN IMMEDIATE``, which also makes SQLite's DDL
    one transaction) is held from reading the revision until the migration is committed. An SQLite store
    that fails its integrity check is refused (:func:`check_integrity`) before anything is written."""
    config = _alembic_config()
    head = schema_head()
    postgres = engine.dialect.name == "postgresql"
    with _MIGRATING, engine.connect() as connection:
        if postgres:
            connection.execute(text("SELECT pg_advisory_lock(:id)"), {"id": MIGRATION_LOCK_ID})
            connection.commit()
        else:
            _begin_sqlite_write(connection, shown)
        try:
            check_integrity(connection, shown)
            current = schema_revisions(connection, shown)
            if current and oldest is not None:
                check_oldest(current, oldest, shown)
            elif current != {head}:
                config.attributes["connection"] = connection
                command.upgrade(config, "head")
            connection.commit()
        finally:
            if postgres:
                connection.rollback()
                connection.execute(text("SELECT pg_advisory_unlock(:id)"), {"id": MIGRATION_LOCK_ID})
                connection.commit()
            else:
                connection.rollback()
                connection.exec_driver_sql(SQLITE_PRAGMAS[0])  # the pooled connection waits as any other
