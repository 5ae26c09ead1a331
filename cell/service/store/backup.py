"""A consistent copy of the embedded SQLite store, taken while the service runs.

SQLite's online backup copies the database page by page inside one read transaction: in WAL mode the
service's writers go on meanwhile, and the copy is the database as it was when the read began, never a
torn mix. The copy is written beside its destination, checked (``PRAGMA integrity_check``) and only then
renamed into place, so that a failed backup never leaves a file that looks like one. It is its owner's
alone to read (mode 0600): it holds the API keys' hashes.
"""

from __future__ import annotations

import os
import sqlite3
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from sqlalchemy import make_url
from sqlalchemy.exc import ArgumentError

from cell.service.store.engine import hide_password
from drivers.errors import StoreError
from drivers.file_access import access_problem, make_folder

BACKUP_MODE = 0o600
"""A backup's permissions: its owner's alone, as it holds the API keys' hashes."""


@dataclass(frozen=True)
class BackupInfo:
    """A backup made: its file, size [bytes], the schema revision and the number of jobs it holds."""

    path: Path
    size_bytes: int
    revision: str | None
    n_jobs: int


def sqlite_file(url: str) -> Path:
    """The database file of an SQLite store URL; ``StoreError`` for another database (a PostgreSQL store
    is backed up with its own tools)."""
    try:
        parsed = make_url(url)
    except (ArgumentError, ValueError):
        raise StoreError(f"job store {hide_password(url)}: not a database URL") from None
    if parsed.get_backend_name() == "postgresql":
        raise StoreError(f"job store {hide_password(url)} is PostgreSQL: back it up with pg_dump "
                         "(pg_dump -Fc -f cell.dump DBNAME) on its server")
    if parsed.get_backend_name() != "sqlite" or not parsed.database:
        raise StoreError(f"job store {hide_password(url)}: only an SQLite file can be backed up here")
    return Path(parsed.database)


def _destination(dest: Path, now: datetime, *, folder: bool) -> Path:
    """``dest`` itself, or in the folder ``dest`` ``cell-<UTC time>.db``; ``StoreError`` if that exists.
    ``dest`` is a folder when it is one or when ``folder`` says so (its name ended in '/'); such a folder
    is made when its parent exists (a name that lost its '/' had written a file of the folder's name)."""
    if folder or dest.is_dir():
        if not dest.is_dir():
            if dest.exists():
                raise StoreError(f"{dest} is not a folder")
            if not dest.parent.is_dir():
                raise StoreError(f"folder {dest.parent} does not exist")
            try:
                dest.mkdir()
            except OSError as exc:
                raise StoreError(f"cannot make the backup folder {dest}: {exc.strerror}; fix: "
                                 f"{make_folder(dest)}") from None
        dest = dest / f"cell-{now.strftime('%Y%m%dT%H%M%SZ')}.db"
    if dest.exists():
        raise StoreError(f"{dest} exists: a backup never overwrites a file")
    if not dest.parent.is_dir():
        raise StoreError(f"folder {dest.parent} does not exist")
    problem = access_problem(dest.parent, folder=True, instead="write the backup on a writable file system")
    if problem is not None:
        raise StoreError(f"cannot write the backup {dest}: {problem}")
    return dest


def _new_private_file(path: Path) -> None:
    """Make the empty file ``path``, readable and writable by its owner alone whatever the umask (a backup
    holds the API keys' hashes); ``StoreError`` naming it if it exists or cannot be made."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, BACKUP_MODE)
    except FileExistsError:
        raise StoreError(f"{path} exists: another backup is being written, or one failed there; delete it "
                         "if none runs") from None
    except OSError as exc:
        raise StoreError(f"cannot write the backup {path}: {exc.strerror}") from None
    os.close(fd)


def backup_sqlite(source: Path, dest: Path, *, folder: bool = False) -> BackupInfo:
    """Copy the store at ``source`` to ``dest`` (a file, or a folder to put a dated file in, made if
    ``folder`` says that it is one) while it may be written; ``StoreError`` with the reason if it
    cannot."""
    if not source.is_file():
        raise StoreError(f"no store at {source}")
    target = _destination(dest, datetime.now(UTC), folder=folder)
    partial = target.with_name(target.name + ".partial")
    _new_private_file(partial)
    try:
        src = sqlite3.connect(source, timeout=30)
        try:
            copy = sqlite3.connect(partial)
            try:
                src.backup(copy)  # every page in one step: one read transaction, one snapshot
                check = copy.execute("PRAGMA integrity_check").fetchone()[0]
                if check != "ok":
                    raise StoreError(f"the copy of {source} fails its integrity check: {check}")
                revision = copy.execute("SELECT version_num FROM alembic_version").fetchone()
                n_jobs = copy.execute("SELECT count(*) FROM jobs").fetchone()[0]
            finally:
                copy.close()
        finally:
            src.close()
        with partial.open("rb") as written:
            os.fsync(written.fileno())
        partial.replace(target)
    except sqlite3.Error as exc:
        partial.unlink(missing_ok=True)
        raise StoreError(f"cannot back up {source} to {target}: {exc}") from None
    except OSError as exc:  # syncing or renaming the copy
        partial.unlink(missing_ok=True)
        raise StoreError(f"cannot write the backup {target}: {exc.strerror}") from None
    except StoreError:
        partial.unlink(missing_ok=True)
        raise
    return BackupInfo(target, target.stat().st_size, revision[0] if revision else None, int(n_jobs))
