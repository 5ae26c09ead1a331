"""The job store's tables as SQLAlchemy ORM models: ``jobs``, ``api_keys``, ``line_transitions``,
``line_state`` and ``queue_holds``.

The schema itself is created and changed only by the Alembic migrations in ``migrations/versions``;
these models must describe the schema the newest migration leaves (``tests/test_store.py`` compares
them). Times are ``TIMESTAMP WITH TIME ZONE`` on PostgreSQL and naive UTC on SQLite, and come back
timezone-aware UTC from both (:class:`UTCDateTime`).
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Dialect,
    Double,
    Index,
    Integer,
    MetaData,
    String,
    Text,
    false,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator

# Constraint and index names that later migrations can refer to (SQLite's batch mode needs them).
NAMING_CONVENTION = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class UTCDateTime(TypeDecorator[datetime]):
    """A point in time, written as UTC and read back timezone-aware UTC on every database: PostgreSQL
    keeps the offset (``timestamptz``), SQLite stores the naive UTC time. A naive datetime is refused
    rather than guessed."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError(f"naive datetime {value.isoformat()}: the job store needs timezone-aware times")
        utc = value.astimezone(UTC)
        return utc.replace(tzinfo=None) if dialect.name == "sqlite" else utc

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    """Declarative base of the job store's models."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)


class JobRow(Base):
    """A row of ``jobs``: one :class:`cell.service.store.records.JobRecord` (see it for the meaning and
    units of each column). ``object_pose``, ``result`` and ``progress`` are JSON (SQL NULL when None)."""

    __tablename__ = "jobs"
    __table_args__ = (
        # the queue of one cell (jobs in a status, oldest first) and its counts per status
        Index("ix_jobs_cell_status_created_at", "cell", "status", "created_at"),
        # one cell's jobs, newest first
        Index("ix_jobs_cell_created_at", "cell", "created_at"),
        # every cell's jobs, newest first, and time ranges
        Index("ix_jobs_created_at", "created_at"),
        # a line asking for its part's jobs
        Index("ix_jobs_part_id", "part_id"),
    )

    id: Mapped[str] = mapped_column(String(16), primary_key=True)
    cell: Mapped[str] = mapped_column(String(64))
    status: Mapped[str] = mapped_column(String(16))
    planner: Mapped[str] = mapped_column(String(64))
    object: Mapped[str | None] = mapped_column(Text)
    object_pose: Mapped[list[float] | None] = mapped_column(JSON(none_as_null=True))
    seed: Mapped[int] = mapped_column(BigInteger)
    max_time_s: Mapped[float | None] = mapped_column(Double)
    part_id: Mapped[str | None] = mapped_column(Text)
    folder: Mapped[str] = mapped_column(Text)
    submitted_by: Mapped[str | None] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    termination: Mapped[str | None] = mapped_column(Text)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))
    progress: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))
    worker_pid: Mapped[int | None] = mapped_column(Integer)
    keep: Mapped[bool] = mapped_column(Boolean, server_default=false())


class KeyRow(Base):
    """A row of ``api_keys``: one :class:`cell.service.store.records.KeyRecord`. Names stay taken after
    revocation, so that a log's key name always means one key; a hash is unique."""

    __tablename__ = "api_keys"
    __table_args__ = (Index("ix_api_keys_key_hash", "key_hash", unique=True),)

    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    role: Mapped[str] = mapped_column(String(16))
    key_hash: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime)
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


class LineTransitionRow(Base):
    """A row of ``line_transitions``: one :class:`cell.service.store.records.LineTransition`, numbered in
    the order they were recorded."""

    __tablename__ = "line_transitions"
    __table_args__ = (Index("ix_line_transitions_cell_id", "cell", "id"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    cell: Mapped[str] = mapped_column(String(64))
    at: Mapped[datetime] = mapped_column(UTCDateTime)
    from_state: Mapped[int] = mapped_column(Integer)
    to_state: Mapped[int] = mapped_column(Integer)
    mode: Mapped[int] = mapped_column(Integer)
    cause: Mapped[str] = mapped_column(Text)


class LineStateRow(Base):
    """A row of ``line_state``: one :class:`cell.service.store.records.LineRecord` per cell."""

    __tablename__ = "line_state"

    cell: Mapped[str] = mapped_column(String(64), primary_key=True)
    mode: Mapped[int] = mapped_column(Integer)
    processed: Mapped[int] = mapped_column(BigInteger)
    defective: Mapped[int] = mapped_column(BigInteger)
    stop_reason_id: Mapped[int] = mapped_column(Integer)
    stop_reason: Mapped[str] = mapped_column(Text)
    last_result: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))


class HoldRow(Base):
    """A row of ``queue_holds``: one :class:`cell.service.store.records.HoldRecord`, the held queue of a
    cell (no row: its queue is not held)."""

    __tablename__ = "queue_holds"

    cell: Mapped[str] = mapped_column(String(64), primary_key=True)
    reason: Mapped[str] = mapped_column(Text)
    held_at: Mapped[datetime] = mapped_column(UTCDateTime)
