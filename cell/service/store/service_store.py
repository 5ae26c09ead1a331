"""Which store a data folder's service uses, so that a command given only the data folder never opens
another.

``cell serve`` writes its store's URL (password hidden) into its data folder (:data:`STORE_RECORD`). The
commands that find a store by the data folder (``cell keys``, ``cell backup``, ``cell doctor``, and
``cell serve`` itself, started by hand without the unit's environment) check it first
(:func:`service_store_url`): ``cell keys create`` without the service's ``CELL_DB`` had made a
new SQLite store in the data folder beside a service on PostgreSQL, whose keys it then lacked (401).
"""

from __future__ import annotations

from pathlib import Path

from cell.service.store.engine import hide_password, sqlite_url
from drivers.atomic_file import write_text_atomic
from drivers.errors import StoreError

STORE_RECORD = "store-url"
"""The file in the data folder that holds the URL of its service's store, password hidden."""


def record_service_store(data_dir: Path, url: str) -> None:
    """Record ``url`` (its password hidden) as the store of ``data_dir``'s service, replacing what an
    earlier run recorded; ``StoreError`` naming the file if it cannot be written."""
    path = data_dir / STORE_RECORD
    try:
        write_text_atomic(path, hide_password(url) + "\n")
    except OSError as exc:
        raise StoreError(f"cannot record the service's store in {path}: {exc.strerror}") from None


def service_store_url(data_dir: Path, db_url: str | None, *, serving: bool = False) -> str:
    """The URL of the store a command of data folder ``data_dir`` opens: ``db_url``, else the folder's
    SQLite file; ``StoreError`` naming both stores when ``data_dir``'s service recorded another store
    (with ``serving``, the service itself: its jobs' folders are the other store's, the error says how to
    move it on purpose). A folder whose service recorded none (none ran there yet) takes any."""
    url = db_url or sqlite_url(data_dir)
    path = data_dir / STORE_RECORD
    try:
        recorded = path.read_text().strip()
    except FileNotFoundError:
        return url
    except OSError as exc:
        raise StoreError(f"cannot read which store the service of {data_dir} uses ({path}): "
                         f"{exc.strerror}") from None
    shown = hide_password(url)
    if recorded != shown:
        move = (f"; to move the cell to this store on purpose, delete {path} first (the jobs of the other "
                "store stay in it)") if serving else ""
        raise StoreError(f"the service of data folder {data_dir} uses the job store {recorded}, and this "
                         f"command would open {shown}: give it the service's store with --db or CELL_DB "
                         f"(as the service's user: docs/deploy.md, section 6){move}")
    return url
