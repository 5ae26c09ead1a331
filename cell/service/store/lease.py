"""One service per cell on a job store: the cell's lease.

Jobs belong to a cell by its name, and a service settles its cell's ``running`` jobs when it starts and
prunes them by age (``cell.service.recovery``, ``cell.service.retention``). A second service of the same
name on the same store (a duplicate start, a copied cell file, a ``cell init`` left with its template's
name) would end the first one's running scan and rewrite its record. So a service holds its cell's lease
for as long as it runs, and one that cannot take it refuses to start, before it touches a job.

The lease is a lock the database's host releases when the holder dies, so that a killed service never
leaves it taken: on PostgreSQL a session advisory lock on a connection of its own (the two-key form,
whose keys never meet the one-key migration lock), keyed by the cell's name; on SQLite an ``flock`` on a
file beside the database. A PostgreSQL connection lost in an outage loses its lock with it:
:meth:`CellLease.keep` takes it again once the database answers.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from pathlib import Path

from sqlalchemy import Connection, Engine, text
from sqlalchemy.exc import SQLAlchemyError

from cell.service.store.engine import sqlite_access_problem, store_error
from drivers.errors import StoreError
from drivers.file_lock import try_lock

LEASE_NAMESPACE = 0x63656C6C
"""The first key of the PostgreSQL advisory lock of every cell's lease ("cell" in ASCII)."""


def _key(cell: str) -> int:
    """The second key: a signed 32-bit digest of the cell's name (two names sharing one is 1 in 4e9)."""
    return int.from_bytes(hashlib.sha256(cell.encode()).digest()[:4], "big", signed=True)


def _taken(cell: str, url: str) -> StoreError:
    return StoreError(f"cell {cell!r} is served by another service on the job store {url}: a second one "
                      f"would end its running scan; stop that one first, or give this cell file another "
                      f"name (its `name:`)")


class CellLease:
    """The lease of ``cell`` on the store at ``engine`` (``url`` its URL, password hidden), taken at once;
    ``StoreError`` when another service holds it or the database does not answer."""

    def __init__(self, engine: Engine, cell: str, url: str) -> None:
        self.cell = cell
        self._engine, self._url = engine, url
        self._connection: Connection | None = None
        self._fd: int | None = None
        self.taken = False  # by another service, found by the last keep()
        if engine.dialect.name == "sqlite":
            self._lock_file()
        elif not self._lock_advisory():
            raise _taken(cell, url)

    def _lock_file(self) -> None:
        database = Path(str(self._engine.url.database))
        path = database.with_name(f"{database.name}.lease-{_key(self.cell) & 0xFFFFFFFF:08x}")
        try:
            fd = try_lock(path, 0o600)
        except OSError as exc:
            problem = sqlite_access_problem(database)
            raise StoreError(f"cannot open the cell's lease file {path}: {exc.strerror}"
                             + (f"; {problem}" if problem is not None else "")) from None
        if fd is None:
            raise _taken(self.cell, self._url)
        self._fd = fd

    def _lock_advisory(self) -> bool:
        """Take the advisory lock on a new connection of the lease's own; False when another holds it."""
        try:
            connection = self._engine.connect()
            got = bool(connection.execute(text("SELECT pg_try_advisory_lock(:ns, :key)"),
                                          {"ns": LEASE_NAMESPACE, "key": _key(self.cell)}).scalar())
            connection.commit()
        except SQLAlchemyError as exc:
            raise store_error(self._url, f"taking cell {self.cell!r}'s lease", exc,
                              self._engine.url.password) from None
        if got:
            self._connection = connection
        else:
            connection.close()
        return got

    def keep(self) -> str | None:
        """Check the lease is still held, taking it again where an outage lost it; what is wrong, in
        words (the database still away, or another service took the cell meanwhile: ``taken``), or None."""
        self.taken = False
        if self._fd is not None:
            return None
        if self._connection is not None:
            try:
                self._connection.execute(text("SELECT 1"))
                self._connection.commit()
                return None
            except SQLAlchemyError:
                with contextlib.suppress(SQLAlchemyError):
                    self._connection.invalidate()
                self._connection = None
        try:
            if self._lock_advisory():
                return None
        except StoreError as exc:
            return f"the cell's lease is lost while the job store does not answer ({exc})"
        self.taken = True
        return str(_taken(self.cell, self._url))

    def release(self) -> None:
        """Give the lease up (the service has stopped)."""
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor releases its flock
            self._fd = None
        if self._connection is not None:
            with contextlib.suppress(SQLAlchemyError):
                # unlocked first: a closed connection's lock goes only when its server process has seen
                # the close and ended, after this returns (a service restarted at once found it taken)
                self._connection.execute(text("SELECT pg_advisory_unlock(:ns, :key)"),
                                         {"ns": LEASE_NAMESPACE, "key": _key(self.cell)})
                self._connection.commit()
            with contextlib.suppress(SQLAlchemyError):
                # closed, not returned to the pool: whatever the unlock did, the lock ends with the session
                self._connection.invalidate()
            self._connection = None
