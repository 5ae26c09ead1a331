"""Opening a cell's service: its cell file, read once, and its data dir and store.

The data dir holds everything the service writes: ``cell.db`` (the embedded SQLite store, unless
``--db`` names another), ``store-url`` (which store that is, for the commands given only the data dir:
:mod:`cell.service.store.service_store`), ``jobs/<id>/`` (one folder per job, the layout ``cell scan``
writes, with the job's log ``log.txt``), ``objects/`` (uploaded meshes) and ``logs/`` (a job worker's
standard error, kept when the process printed anything there: a crash's traceback, a library's messages).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from cell.config.load import load_config_data
from cell.config.placeholders import require_measured
from cell.service.manager import CellService
from cell.service.store import open_data_store
from cell.service.store.service_store import record_service_store, service_store_url
from cell.templates import DEFAULT_TEMPLATE, template_path
from drivers.errors import StoreError

DEFAULT_CONFIG = template_path(DEFAULT_TEMPLATE)
DEFAULT_DATA_DIR = Path("data")


@dataclass(frozen=True)
class ServiceSettings:
    """``cell serve``'s choices: the cell file, the data dir and the store's URL (None: SQLite in the data
    dir)."""

    config_file: Path = DEFAULT_CONFIG
    data_dir: Path = DEFAULT_DATA_DIR
    db_url: str | None = None


def build_service(settings: ServiceSettings) -> CellService:
    """The service of the cell file, on its store; call ``start`` on the event loop that will run it."""
    config, data = load_config_data(settings.config_file)
    require_measured(settings.config_file, config.mode)
    url = service_store_url(settings.data_dir, settings.db_url, serving=True)
    store = open_data_store(settings.data_dir, url)
    try:
        lease = store.claim_cell(config.name)
    except StoreError:
        store.close()
        raise
    try:
        record_service_store(settings.data_dir, url)
    except StoreError:
        lease.release()
        store.close()
        raise
    return CellService(config=config, config_data=data, config_file=str(settings.config_file),
                       data_dir=settings.data_dir.resolve(), store=store, lease=lease)
