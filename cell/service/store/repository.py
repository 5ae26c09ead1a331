"""The job store: jobs, API keys and the packing line's state and transitions, in SQLite or PostgreSQL.

:class:`Store` is synchronous and may be called from several threads at once: every call runs in its own
SQLAlchemy session and transaction. It takes and returns the frozen records of
:mod:`cell.service.store.records`, never ORM rows. A database error during use becomes a one-line
:class:`drivers.errors.StoreError` naming the operation; a caller's mistake (an unknown field or status,
a naive datetime) is a ``ValueError``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import stat
import threading
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, fields, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import ColumnElement, Connection, CursorResult, Engine, func, select, update
from sqlalchemy.exc import IntegrityError, SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from cell.service.store.engine import (
    SQLITE_FILE,
    check_integrity,
    check_oldest,
    hide_password,
    is_corrupt,
    open_engine,
    read_only_engine,
    schema_revisions,
    sqlite_database,
    store_error,
)
from cell.service.store.lease import CellLease
from cell.service.store.models import HoldRow, JobRow, KeyRow, LineStateRow, LineTransitionRow
from cell.service.store.records import (
    JOB_STATUSES,
    HoldRecord,
    JobRecord,
    KeyRecord,
    LineRecord,
    LineTransition,
)
from drivers.errors import ServiceError, StoreError
from drivers.file_access import make_folder

log = logging.getLogger("cell.service")

JOB_FIELDS = tuple(field.name for field in fields(JobRecord))
JOB_ID = re.compile(r"[0-9a-f]{16}")  # a job id: 16 lowercase hex characters
_CHANGEABLE = frozenset(JOB_FIELDS) - {"id"}
_TIME_FIELDS = ("created_at", "started_at", "finished_at")


JOBS_FOLDER = "jobs"
"""The folder of a data dir that holds its cell's job folders, one per job, named by its id."""
KEYS_SCHEMA = "0001"
"""The oldest schema revision the key methods of :class:`Store` work on: ``api_keys`` is the first
revision's table, unchanged since."""


def open_store(url: str, *, migrate: bool = True, oldest: str | None = None,
               jobs_dir: Path | None = None) -> Store:
    """Open the store at ``url`` (see :mod:`cell.service.store.engine`), its schema migrated to this
    software's newest revision; with ``migrate`` False (a command beside ``cell serve``), a schema there
    is left as it is, accepted from revision ``oldest`` on (:func:`open_engine`). ``jobs_dir`` is the
    cell's job folders' folder, against which the stored job folders are resolved (:class:`Store`).
    Raises :class:`drivers.errors.StoreError` with a one-line message naming the URL without its
    password."""
    return Store(open_engine(url, migrate=migrate, oldest=oldest), jobs_dir=jobs_dir)


def read_store(url: str, oldest: str, connect_timeout_s: int) -> Store | None:
    """The store at ``url`` opened to read only (:func:`read_only_engine`, PostgreSQL given up after
    ``connect_timeout_s`` [s]), its schema accepted from revision ``oldest`` on and never changed; None
    when there is none yet (no SQLite file, or no schema). :class:`StoreError` naming the URL without its
    password when it cannot be reached or read, or its schema is newer than this software's or older
    than ``oldest``."""
    with _reading(url, connect_timeout_s) as reading:
        if reading is None:
            return None
        connection, engine, shown = reading
        revisions = schema_revisions(connection, shown)
        if revisions:
            check_oldest(revisions, oldest, shown)
    if not revisions:
        engine.dispose()
        return None
    return Store(engine)


@contextlib.contextmanager
def _reading(url: str, connect_timeout_s: int) -> Iterator[tuple[Connection, Engine, str] | None]:
    """A connection to the store at ``url`` that changes nothing (:func:`read_only_engine`, PostgreSQL
    given up after ``connect_timeout_s`` [s]), with its engine and the URL as shown (password hidden);
    None for an SQLite file not made yet. An SQLAlchemy error becomes :class:`StoreError` naming the URL,
    and any error disposes of the engine."""
    shown = hide_password(url)
    engine = read_only_engine(url, connect_timeout_s)
    if engine is None:
        yield None
        return
    try:
        with engine.connect() as connection:
            yield connection, engine, shown
    except SQLAlchemyError as exc:
        engine.dispose()
        raise store_error(shown, "cannot read", exc, engine.url.password) from None
    except BaseException:
        engine.dispose()
        raise


@dataclass(frozen=True)
class StoreState:
    """A store as read without changing it: its schema revisions (empty: no schema yet, the service
    makes it) and how many API keys are not revoked."""

    revisions: frozenset[str]
    n_active_keys: int


def inspect_store(url: str, connect_timeout_s: int) -> StoreState | None:
    """Read the store at ``url`` without changing it (:func:`read_only_engine`, PostgreSQL given up after
    ``connect_timeout_s`` [s]); None for an SQLite file not made yet. :class:`StoreError` naming the URL
    without its password when it cannot be reached or read, or its schema is newer than this software's;
    :class:`drivers.errors.StoreDamaged` when an SQLite store fails its integrity check."""
    with _reading(url, connect_timeout_s) as reading:
        if reading is None:
            return None
        connection, engine, shown = reading
        check_integrity(connection, shown)
        revisions = schema_revisions(connection, shown)
        # api_keys is the first revision's table, unchanged since: counted on a store of any revision
        active = select(func.count()).select_from(KeyRow).where(KeyRow.revoked_at.is_(None))
        n_keys = int(connection.scalar(active) or 0) if revisions else 0
    engine.dispose()
    return StoreState(frozenset(revisions), n_keys)


STORE_FILE_MODE = 0o600
"""The embedded store's files (``cell.db``, and its WAL and shared memory, which SQLite makes with the
database's mode) are the service user's alone, whatever the umask: they hold the API keys' hashes. Under
the usual umask 022 all three were 0644, readable by every user of the machine."""


def data_folder_not_made(data_dir: Path, exc: OSError) -> str:
    """Why the data folder ``data_dir`` could not be made (``exc``), with the command that makes it this
    user's (its parents stay whose they are)."""
    return f"cannot create the data folder {data_dir}: {exc.strerror or exc}; fix: {make_folder(data_dir)}"


def open_data_store(data_dir: Path, url: str, *, migrate: bool = True, oldest: str | None = None) -> Store:
    """The store at ``url`` of a cell's data dir ``data_dir`` (created if missing), the URL its command
    chose (``service_store_url``: ``--db``, else the embedded SQLite file ``cell.db`` in it, which is made
    with ``STORE_FILE_MODE`` if new), migrated or not as :func:`open_store` says, its job folders resolved
    in ``data_dir/jobs`` (:data:`JOBS_FOLDER`). ``StoreError`` when it cannot be opened."""
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StoreError(data_folder_not_made(data_dir, exc)) from None
    database = sqlite_database(url)
    if database is not None and database.resolve() == (data_dir / SQLITE_FILE).resolve():
        # an empty file is an empty database; one that cannot be made is reported by opening it
        with contextlib.suppress(OSError):
            os.close(os.open(data_dir / SQLITE_FILE, os.O_WRONLY | os.O_CREAT | os.O_EXCL, STORE_FILE_MODE))
    return open_store(url, migrate=migrate, oldest=oldest, jobs_dir=data_dir.resolve() / JOBS_FOLDER)


def restrict_store_files(data_dir: Path) -> list[tuple[Path, int, int]]:
    """Take the group's and others' access from the embedded store's files in ``data_dir`` (``cell.db*``)
    that have any; returns each file changed with its former and its new mode. A file this user cannot
    change is left (opening the store says what is wrong with it)."""
    changed = []
    for path in sorted(data_dir.glob(f"{SQLITE_FILE}*")):
        with contextlib.suppress(OSError):
            mode = stat.S_IMODE(path.stat().st_mode)
            if mode & ~STORE_FILE_MODE:
                path.chmod(mode & STORE_FILE_MODE)
                changed.append((path, mode, mode & STORE_FILE_MODE))
    return changed


class Store:
    """Jobs and API keys in one database. ``url`` is the database's URL with its password hidden.

    A job's folder is stored relative to its cell's job folders (its name there, the job id), so that a
    data dir moved or restored elsewhere keeps its jobs' files: ``jobs_dir`` (the serving data dir's
    ``jobs``) turns it into a path when read, and a folder given inside it is stored by its name. Without
    ``jobs_dir``, or for a folder elsewhere, the folder is stored and read as given.

    The first call that finds the data damaged (a :class:`StoreDamaged`) latches :attr:`damaged`; the first
    :meth:`check_file` that finds an SQLite store's file deleted or replaced latches :attr:`lost`; a write
    that fails makes :attr:`write_failing` say so until a write succeeds (:meth:`probe_write`)."""

    def __init__(self, engine: Engine, jobs_dir: Path | None = None) -> None:
        """A store on ``engine``, whose schema must already be at the head revision (:func:`open_store`
        makes sure of it), or at least at the revision the caller's methods need (:func:`open_store`
        with ``migrate`` False, :func:`read_store`); job folders resolved in ``jobs_dir``."""
        self._engine = engine
        self.jobs_dir = jobs_dir
        self._sessions = sessionmaker(engine, expire_on_commit=False)
        self.url = engine.url.render_as_string(hide_password=True)
        self._damaged = False
        self._damage_seen = threading.Lock()
        self._database = sqlite_database(engine.url)
        self._identity: tuple[int, int] | None = None
        if self._database is not None:
            with contextlib.suppress(OSError):  # not told: the file is not checked
                self._identity = _file_identity(self._database)
        self._lost: str | None = None
        self._unchecked = False  # the newest check_file could not stat the file (logged once per spell)
        self._write_failure: str | None = None

    @property
    def damaged(self) -> bool:
        """Whether a call of this store found its pages corrupt (a read or a write, by any thread), latched:
        the damage is on the disk, so a later call that answers (one that reads other pages) does not clear
        it. An integrity error no caller expected is raised as damage too (:class:`StoreDamaged`) but does
        not latch: it says that rows break a constraint, which the next call need not meet. Only a new
        store object starts clear: for the service, a restart after a restore from a backup (docs/deploy.md,
        section 9); an SQLite store still damaged is refused then (:func:`open_store` checks its
        integrity). Logged once, when it latches."""
        return self._damaged

    @property
    def lost(self) -> str | None:
        """Why this store's writes are lost, latched by :meth:`check_file`: what to do, in words; or None."""
        return self._lost

    def check_file(self) -> str | None:
        """Whether an SQLite store's file was deleted (``cell.db`` and its WAL removed by hand) or replaced
        by another since it was opened: the open connections write on into the deleted file, which is gone
        with them, every key and job of it. Latched and logged once (:attr:`lost`); a file that cannot be
        looked at (EACCES, EIO) is no verdict, logged once until it can be again; None while the file is
        the one opened, and always for PostgreSQL (no file). A ``stat`` of one path: cheap, but a file
        system call, so callers on the event loop run it on a thread."""
        if self._lost is None and self._identity is not None and self._database is not None:
            try:
                now = _file_identity(self._database)
            except OSError as exc:  # no verdict (an I/O error, a permission changed a moment): not lost
                if not self._unchecked:  # once, not at every probe and submission while it lasts
                    log.warning("cannot check the job store's file %s: %s", self._database, exc.strerror)
                self._unchecked = True
                return None
            self._unchecked = False
            if now != self._identity:
                happened = "deleted" if now is None else "replaced by another file"
                lost = (f"the job store's file {self._database} was {happened} while the service ran: what "
                        "it writes now is lost when it stops; restore the file from a backup "
                        "(docs/deploy.md, section 9) and restart the service")
                with self._damage_seen:
                    first, self._lost = self._lost is None, lost
                if first:
                    log.error("%s", lost)
        return self._lost

    @property
    def write_failing(self) -> str | None:
        """The error of the newest write when it failed (a lock another process holds, a database that does
        not answer), until a later write succeeds; else None."""
        return self._write_failure

    def probe_write(self) -> str | None:
        """While :attr:`write_failing`, try a write that changes nothing (an update of no row, which takes
        the database's write lock all the same): :attr:`write_failing` as it is then."""
        if self._write_failure is not None:
            with contextlib.suppress(StoreError), self._session("probing a write", writes=True) as session:
                session.execute(update(HoldRow).where(HoldRow.cell.is_(None)).values(reason=""))
        return self._write_failure

    def close(self) -> None:
        """Close every pooled connection; the store is not used afterwards."""
        self._engine.dispose()

    def claim_cell(self, cell: str) -> CellLease:
        """Cell ``cell``'s lease (:mod:`cell.service.store.lease`), for a service to hold while it serves
        the cell; ``StoreError`` when another service holds it."""
        return CellLease(self._engine, cell, self.url)

    @contextlib.contextmanager
    def _session(self, action: str, *, conflict: str | None = None,
                 writes: bool = False) -> Iterator[Session]:
        """A session in a transaction, committed at the end. A database error becomes a
        :class:`StoreError` naming ``action``; with ``conflict``, an integrity error (a duplicate key)
        becomes a ``ServiceError`` of reason ``conflict`` with that message. A session that ``writes`` sets
        :attr:`write_failing` by how it ended (an integrity error is the caller's, not the store's)."""
        try:
            with self._sessions.begin() as session:
                yield session
        except IntegrityError as exc:
            if conflict is None:
                raise self._error(action, exc) from None
            raise ServiceError(conflict, reason="conflict") from None
        except SQLAlchemyError as exc:
            error = self._error(action, exc)
            if writes:
                self._write_failure = str(error)
            raise error from None
        if writes:
            self._write_failure = None

    def _error(self, action: str, exc: SQLAlchemyError) -> StoreError:
        """:func:`store_error` for ``exc``, raised while doing ``action``; corrupt pages (:func:`is_corrupt`)
        latch :attr:`damaged`."""
        error = store_error(self.url, action, exc, self._engine.url.password)
        if is_corrupt(exc):
            with self._damage_seen:
                first, self._damaged = not self._damaged, True
            if first:
                log.critical("%s; taken for damaged until the store is opened again (a service's queue "
                             "is held until it is restarted)", error)
        return error

    # jobs

    def add_job(self, job: JobRecord) -> None:
        """Store a new job. ``ServiceError`` (``conflict``) if a job with its id exists; ``ValueError`` for
        an id that is not 16 lowercase hex characters, an unknown status or a naive time."""
        if not JOB_ID.fullmatch(job.id):
            raise ValueError(f"job id {job.id!r}: expected 16 lowercase hex characters")
        columns = self._job_columns(asdict(job))
        with self._session(f"adding job {job.id}", conflict=f"job {job.id} already exists",
                           writes=True) as session:
            session.add(JobRow(**columns))

    def get_job(self, job_id: str) -> JobRecord | None:
        """The job ``job_id``, or None if there is none."""
        with self._session(f"reading job {job_id}") as session:
            row = session.get(JobRow, job_id)
            return None if row is None else self._job_record(row)

    def update_job(self, job_id: str, **changes: Any) -> JobRecord:
        """Set some of job ``job_id``'s fields (names of :class:`JobRecord` fields other than ``id``) and
        return the job as stored. ``KeyError`` if there is no such job, ``ValueError`` for another name,
        an unknown status or a naive time."""
        unknown = sorted(set(changes) - _CHANGEABLE)
        if unknown:
            raise ValueError(f"cannot update job field(s) {', '.join(unknown)} (changeable: "
                             f"{', '.join(sorted(_CHANGEABLE))})")
        columns = self._job_columns(changes)
        with self._session(f"updating job {job_id}", writes=True) as session:
            row = session.get(JobRow, job_id)
            if row is None:
                raise KeyError(job_id)
            for name, value in columns.items():
                setattr(row, name, value)
            session.flush()
            return self._job_record(row)

    def mark_stopping(self, job_id: str) -> bool:
        """Job ``job_id`` is ``stopping`` if it is ``running`` (its worker has taken a stop); False, and the
        job as it is, when it is not running any more: its end, stored meanwhile, is never overwritten."""
        query = (update(JobRow).where(JobRow.id == job_id, JobRow.status == "running")
                 .values(status="stopping"))
        with self._session(f"marking job {job_id} stopping", writes=True) as session:
            result: CursorResult[Any] = session.execute(query)  # type: ignore[assignment]  # an UPDATE's is one
            return bool(result.rowcount)

    def list_jobs(self, *, cell: str | None = None, statuses: Sequence[str] | None = None,
                  planner: str | None = None, part_id: str | None = None,
                  created_after: datetime | None = None, created_before: datetime | None = None,
                  limit: int = 50, offset: int = 0) -> tuple[list[JobRecord], int]:
        """One page of the jobs that match every given filter, newest first (by creation time, then id),
        and how many match in all. ``created_after`` is inclusive, ``created_before`` exclusive; ``limit``
        and ``offset`` count jobs (``ValueError`` if negative)."""
        if limit < 0 or offset < 0:
            raise ValueError(f"limit and offset must not be negative (got {limit}, {offset})")
        conditions: list[ColumnElement[bool]] = []
        if cell is not None:
            conditions.append(JobRow.cell == cell)
        if statuses is not None:
            conditions.append(JobRow.status.in_(_checked_statuses(statuses)))
        if planner is not None:
            conditions.append(JobRow.planner == planner)
        if part_id is not None:
            conditions.append(JobRow.part_id == part_id)
        if created_after is not None:
            conditions.append(JobRow.created_at >= _aware("created_after", created_after))
        if created_before is not None:
            conditions.append(JobRow.created_at < _aware("created_before", created_before))
        with self._session("listing jobs") as session:
            total = session.scalar(select(func.count()).select_from(JobRow).where(*conditions)) or 0
            rows = session.scalars(select(JobRow).where(*conditions)
                                   .order_by(JobRow.created_at.desc(), JobRow.id.desc())
                                   .limit(limit).offset(offset))
            return [self._job_record(row) for row in rows], total

    def jobs_in_status(self, cell: str, statuses: Sequence[str]) -> list[JobRecord]:
        """``cell``'s jobs in one of ``statuses``, oldest first (the queue's order: creation time, then
        id)."""
        query = (select(JobRow).where(JobRow.cell == cell, JobRow.status.in_(_checked_statuses(statuses)))
                 .order_by(JobRow.created_at, JobRow.id))
        with self._session(f"reading cell {cell}'s jobs") as session:
            return [self._job_record(row) for row in session.scalars(query)]

    def count_by_status(self, cell: str) -> dict[str, int]:
        """How many of ``cell``'s jobs are in each status; every status of :data:`JOB_STATUSES` is a key."""
        query = select(JobRow.status, func.count()).where(JobRow.cell == cell).group_by(JobRow.status)
        counts = dict.fromkeys(JOB_STATUSES, 0)
        with self._session(f"counting cell {cell}'s jobs") as session:
            for status, count in session.execute(query):
                counts[status] = count
        return counts

    def delete_job(self, job_id: str) -> None:
        """Remove job ``job_id`` from the store (its folder stays); ``KeyError`` if there is none."""
        with self._session(f"deleting job {job_id}", writes=True) as session:
            row = session.get(JobRow, job_id)
            if row is None:
                raise KeyError(job_id)
            session.delete(row)

    def _job_columns(self, values: Mapping[str, Any]) -> dict[str, Any]:
        """:func:`_job_columns`, a folder inside :attr:`jobs_dir` stored by its name there."""
        columns = _job_columns(values)
        folder = columns.get("folder")
        if folder is not None and self.jobs_dir is not None:
            path = Path(folder)
            if path.is_absolute() and path.parent.resolve() == self.jobs_dir.resolve():
                columns["folder"] = path.name
        return columns

    def _job_record(self, row: JobRow) -> JobRecord:
        """:func:`_job_record`, a relative folder resolved in :attr:`jobs_dir`."""
        record = _job_record(row)
        if self.jobs_dir is None or Path(record.folder).is_absolute():
            return record
        return replace(record, folder=str(self.jobs_dir / record.folder))

    # keys

    def add_key(self, name: str, role: str, key_hash: str) -> KeyRecord:
        """Store a new active key: its name, role and hex SHA-256 (never the key). ``ServiceError``
        (``conflict``) if a key of that name exists, even revoked: a name always means one key."""
        record = KeyRecord(name=name, role=role, key_hash=key_hash, created_at=datetime.now(UTC))
        conflict = f"a key named {name!r} already exists (a revoked key's name stays taken)"
        with self._session(f"adding key {name!r}", conflict=conflict, writes=True) as session:
            if session.get(KeyRow, name) is not None:
                raise ServiceError(conflict, reason="conflict")
            session.add(KeyRow(**asdict(record)))
        return record

    def list_keys(self) -> list[KeyRecord]:
        """Every key, active or revoked, by name."""
        with self._session("listing keys") as session:
            return [_key_record(row) for row in session.scalars(select(KeyRow).order_by(KeyRow.name))]

    def revoke_key(self, name: str) -> KeyRecord:
        """Revoke key ``name`` now and return it. ``ServiceError`` ``not found`` if there is no such key,
        ``conflict`` if it is already revoked."""
        with self._session(f"revoking key {name!r}", writes=True) as session:
            row = session.get(KeyRow, name)
            if row is None:
                raise ServiceError(f"no key named {name!r}", reason="not found")
            if row.revoked_at is not None:
                raise ServiceError(f"key {name!r} was already revoked at {row.revoked_at.isoformat()}",
                                   reason="conflict")
            row.revoked_at = datetime.now(UTC)
            session.flush()
            return _key_record(row)

    def active_keys(self) -> list[KeyRecord]:
        """The keys that are not revoked, by name."""
        query = select(KeyRow).where(KeyRow.revoked_at.is_(None)).order_by(KeyRow.name)
        with self._session("reading the active keys") as session:
            return [_key_record(row) for row in session.scalars(query)]


    # the packing line

    def add_line_transition(self, transition: LineTransition) -> None:
        """Record one PackML transition (``ValueError`` for a naive time)."""
        at = _aware("at", transition.at).astimezone(UTC)
        with self._session(f"recording cell {transition.cell}'s line transition", writes=True) as session:
            session.add(LineTransitionRow(**{**asdict(transition), "at": at}))

    def line_transitions(self, cell: str, *, limit: int = 100,
                         before_id: int | None = None) -> list[tuple[int, LineTransition]]:
        """``cell``'s newest transitions first, with their ids: at most ``limit``, older than
        ``before_id`` when given (the next page)."""
        if limit < 0:
            raise ValueError(f"limit must not be negative (got {limit})")
        query = select(LineTransitionRow).where(LineTransitionRow.cell == cell)
        if before_id is not None:
            query = query.where(LineTransitionRow.id < before_id)
        query = query.order_by(LineTransitionRow.id.desc()).limit(limit)
        with self._session(f"reading cell {cell}'s line transitions") as session:
            return [(row.id, LineTransition(cell=row.cell, at=row.at, from_state=row.from_state,
                                            to_state=row.to_state, mode=row.mode, cause=row.cause))
                    for row in session.scalars(query)]

    def get_line(self, cell: str) -> LineRecord | None:
        """``cell``'s line record, or None before its line first ran."""
        with self._session(f"reading cell {cell}'s line") as session:
            row = session.get(LineStateRow, cell)
            if row is None:
                return None
            return LineRecord(cell=row.cell, mode=row.mode, processed=row.processed, defective=row.defective,
                              stop_reason_id=row.stop_reason_id, stop_reason=row.stop_reason,
                              last_result=row.last_result)

    def put_line(self, record: LineRecord) -> None:
        """Write ``cell``'s line record (created or replaced)."""
        with self._session(f"writing cell {record.cell}'s line", writes=True) as session:
            session.merge(LineStateRow(**asdict(record)))

    # the queue's hold

    def get_hold(self, cell: str) -> HoldRecord | None:
        """Why ``cell``'s queue is held and since when, or None when it is not."""
        with self._session(f"reading cell {cell}'s queue hold") as session:
            row = session.get(HoldRow, cell)
            return None if row is None else HoldRecord(cell=row.cell, reason=row.reason, held_at=row.held_at)

    def set_hold(self, cell: str, hold: HoldRecord | None) -> None:
        """Hold ``cell``'s queue (``hold``, written or replaced), or release it (None); ``ValueError`` for
        a naive time or another cell's hold."""
        with self._session(f"writing cell {cell}'s queue hold", writes=True) as session:
            row = session.get(HoldRow, cell)
            if hold is None:
                if row is not None:
                    session.delete(row)
                return
            if hold.cell != cell:
                raise ValueError(f"a hold of cell {hold.cell!r} given for cell {cell!r}")
            session.merge(HoldRow(cell=cell, reason=hold.reason,
                                  held_at=_aware("held_at", hold.held_at).astimezone(UTC)))


def _file_identity(path: Path) -> tuple[int, int] | None:
    """The device and inode of ``path``, or None when there is no file there; ``OSError`` when that
    cannot be told (an I/O error, a folder that may not be read)."""
    try:
        info = path.stat()
    except FileNotFoundError:
        return None
    return info.st_dev, info.st_ino


def _aware(name: str, value: datetime) -> datetime:
    if value.tzinfo is None:
        raise ValueError(f"{name} {value.isoformat()} is naive: the job store needs timezone-aware times")
    return value


def _checked_statuses(statuses: Sequence[str]) -> list[str]:
    unknown = sorted(set(statuses) - set(JOB_STATUSES))
    if unknown:
        raise ValueError(f"unknown job status(es) {', '.join(unknown)} (allowed: {', '.join(JOB_STATUSES)})")
    return list(statuses)


def _job_columns(values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` (JobRecord fields) checked and turned into column values: times in UTC, the pose as a
    JSON list."""
    columns = dict(values)
    if "status" in columns:
        _checked_statuses([columns["status"]])
    for name in _TIME_FIELDS:
        if columns.get(name) is not None:
            columns[name] = _aware(name, columns[name]).astimezone(UTC)
    pose = columns.get("object_pose")
    if pose is not None:
        if len(pose) != 3:
            raise ValueError(f"object_pose {pose!r}: expected (x [m], y [m], yaw [deg])")
        columns["object_pose"] = [float(v) for v in pose]
    return columns


def _job_record(row: JobRow) -> JobRecord:
    values = {name: getattr(row, name) for name in JOB_FIELDS}
    pose = values["object_pose"]
    values["object_pose"] = None if pose is None else (float(pose[0]), float(pose[1]), float(pose[2]))
    return JobRecord(**values)


def _key_record(row: KeyRow) -> KeyRecord:
    return KeyRecord(name=row.name, role=row.role, key_hash=row.key_hash, created_at=row.created_at,
                     revoked_at=row.revoked_at)
