"""Opening a cell's service: its cell file, read once, and its data dir and store.

The data dir holds everything the service writes: ``cell.db`` (the embedded SQLite store, unless
``--db`` names another), ``store-url`` (which store that is, for the commands given only the data dir:
:mod:`cell.service.store.service_store`), ``jobs/<id>/`` (one folder per job, the layout ``cell scan``
writes, with the job's log ``log.txt``), ``objects/`` (uploaded meshes), ``cells/``
(the cell files its jobs ran: :func:`keep_cell_file`) and ``logs/`` (a job worker's
standard error, kept when the process printed anything there: a crash's traceback, a library's messages).
"""

from __future__ import annotations

import contextlib
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from cell.config.load import load_config_data
from cell.config.placeholders import require_measured
from cell.service.instance import DataDirClaim
from cell.service.manager import CellService
from cell.service.store import open_data_store
from cell.service.store.service_store import record_service_store, service_store_url
from cell.templates import DEFAULT_TEMPLATE, template_path
from drivers.atomic_file import write_text_atomic
from drivers.errors import StoreError

DEFAULT_CONFIG = template_path(DEFAULT_TEMPLATE)
DEFAULT_DATA_DIR = Path("data")
CELLS_DIR = "cells"
"""The data dir's folder of the cell files its service's jobs ran (:func:`keep_cell_file`)."""


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
    with contextlib.ExitStack() as undo:  # what was taken is given back, in reverse, if a later step fails
        # the data dir first: a second service on it (of this cell or another) is refused naming the first
        # before it opens the store, which a newer release would migrate under the one running
        claim = DataDirClaim(settings.data_dir, config.name)
        undo.callback(claim.release)
        store = open_data_store(settings.data_dir, url)
        undo.callback(store.close)
        lease = store.claim_cell(config.name)  # the cell served from another data dir on a shared store
        undo.callback(lease.release)
        record_service_store(settings.data_dir, url)
        kept = keep_cell_file(settings.data_dir, settings.config_file, data)
        undo.pop_all()
    return CellService(config=config, config_data=data, config_file=str(kept),
                       data_dir=settings.data_dir.resolve(), store=store, lease=lease, data_dir_claim=claim)


def keep_cell_file(data_dir: Path, source: Path, data: Any) -> Path:
    """Keep the cell file the service runs its jobs with in ``data_dir``/cells/<digest>.yaml and return
    that file's absolute path. It holds ``data``, the cell file's parsed YAML with its relative names
    already made absolute (``load_config_data``), so that it loads as it is from there; one file per
    content, so that an older job keeps the cell file it ran after the one at ``source`` was edited.

    A job's ``result.json`` and ``job.json`` name this copy relative to the job folder
    (``../../cells/<digest>.yaml``): they are served to every viewer and must not show where the
    service's files are on its host, and ``cell scan --replay`` and ``cell reprocess`` find the cell
    file from the job folder alone (also in a data dir moved whole). ``source`` is named in the copy's
    first line, for a person; the data dir is never served. ``StoreError`` naming the file if it
    cannot be written."""
    body = yaml.safe_dump(data, sort_keys=False)
    path = data_dir.resolve() / CELLS_DIR / f"{hashlib.sha256(body.encode()).hexdigest()[:16]}.yaml"
    with contextlib.suppress(OSError, yaml.YAMLError):
        if path.is_file() and yaml.safe_load(path.read_text()) == data:
            return path
    try:  # durable before a job's result names it; one lost to a power cut (empty, cut short) is rewritten
        path.parent.mkdir(exist_ok=True)
        write_text_atomic(path, f"# cell serve --config {source}, as its jobs ran it (relative names made "
                                f"absolute)\n{body}", durable=True)
    except OSError as exc:
        raise StoreError(f"cannot keep the cell file the jobs run in {path}: {exc.strerror}") from None
    return path
