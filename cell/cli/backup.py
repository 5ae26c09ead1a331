"""``cell backup DEST``: a consistent copy of the service's SQLite store, while it runs.

Restoring: stop the service, copy the backup to ``<data dir>/cell.db`` (and delete any ``cell.db-wal``
and ``cell.db-shm`` beside it), start the service. Job folders are plain files: copy them with rsync.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from cell.cli.commands import DB_ENVVAR
from cell.cli.errors import fail
from cell.cli.values import data_folder
from cell.service.startup import DEFAULT_DATA_DIR
from cell.service.store.backup import backup_sqlite, sqlite_file
from cell.service.store.service_store import service_store_url
from drivers.errors import CellError

console = Console(soft_wrap=True)


def backup(
    # a string, not a Path: a Path drops the trailing '/' that makes a new name a folder
    dest: Annotated[str, typer.Argument(metavar="DEST", help="the backup file, or a folder to write "
                                                             "cell-{UTC time}.db in (a name ending in '/' "
                                                             "is a folder, made if new)")],
    data_dir: Annotated[Path, typer.Option(help="the service's data folder (its store: cell.db)",
                                           callback=data_folder)]
    = DEFAULT_DATA_DIR,
    db: Annotated[str | None, typer.Option(envvar=DB_ENVVAR,
                                           help="the store's URL instead of the data folder's (SQLite only: "
                                                "PostgreSQL is backed up with pg_dump)")] = None,
) -> None:
    """Back up the job store while the service runs (SQLite's online backup); never overwrites a file."""
    try:
        source = sqlite_file(service_store_url(data_dir, db))
        info = backup_sqlite(source, Path(dest), folder=dest.endswith(os.sep))
    except CellError as exc:
        raise fail(exc) from None
    console.print(f"wrote {info.path}: {info.n_jobs} jobs, {info.size_bytes / 1e6:.1f} MB, schema revision "
                  f"{info.revision}", markup=False, highlight=False)
