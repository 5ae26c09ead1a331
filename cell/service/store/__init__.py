"""The service's persistent job store (SQLite or PostgreSQL, schema by Alembic migrations): jobs, API
keys and the packing line as frozen records."""

from cell.service.store.engine import sqlite_url
from cell.service.store.records import (
    FINISHED_STATUSES,
    JOB_STATUSES,
    RUNNING_STATUSES,
    STORE_RETRY_S,
    HoldRecord,
    JobRecord,
    KeyRecord,
    LineRecord,
    LineTransition,
)
from cell.service.store.repository import (
    Store,
    data_folder_not_made,
    open_data_store,
    open_store,
    restrict_store_files,
)

__all__ = ["FINISHED_STATUSES", "JOB_STATUSES", "RUNNING_STATUSES", "STORE_RETRY_S", "HoldRecord",
           "JobRecord", "KeyRecord", "LineRecord", "LineTransition", "Store", "data_folder_not_made",
           "open_data_store", "open_store", "restrict_store_files", "sqlite_url"]
