"""The service's persistent job store (SQLite or PostgreSQL, schema by Alembic migrations): jobs and API
keys as frozen records."""

from cell.service.store.engine import sqlite_url
from cell.service.store.records import FINISHED_STATUSES, JOB_STATUSES, JobRecord, KeyRecord
from cell.service.store.repository import Store, open_store

__all__ = ["FINISHED_STATUSES", "JOB_STATUSES", "JobRecord", "KeyRecord", "Store", "open_store", "sqlite_url"]
