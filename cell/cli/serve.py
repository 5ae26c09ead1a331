"""``cell serve``: run the cell as a long-running service (FastAPI under uvicorn).

Under systemd (``deploy/systemd/cell.service``, ``Type=notify``) it reports ready, alive and stopping
over ``NOTIFY_SOCKET``; its log is JSON lines on standard error unless that is a terminal. It binds
127.0.0.1 by default; on any other interface it refuses to start until at least one API key
exists (``cell keys create``), since every route but ``/healthz`` needs one.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer
import uvicorn
from rich.console import Console

from cell.api.app import create_app
from cell.api.connections import ConnectionLimits, protocol_class
from cell.api.server import NotifyingServer
from cell.cli.commands import DB_ENVVAR
from cell.cli.errors import fail
from cell.cli.values import data_folder
from cell.config import load_config
from cell.line.opcua_endpoint import check_endpoint
from cell.service.logs import configure_logging
from cell.service.notify import Notifier
from cell.service.startup import DEFAULT_CONFIG, DEFAULT_DATA_DIR, ServiceSettings, build_service
from cell.service.store import restrict_store_files
from cell.templates import DEFAULT_TEMPLATE
from drivers.errors import CellError
from drivers.hosts import is_loopback, listen_problem

err_console = Console(stderr=True)
log = logging.getLogger("cell.service")
SHUTDOWN_GRACE_S = 2
"""How long open requests may run on after SIGTERM before they are cut [s]; the running job's arm is
stopped before this wait, and event streams end by themselves within it."""


def serve(
    config: Annotated[Path, typer.Option(help=f"cell file (default: the shipped {DEFAULT_TEMPLATE} cell)",
                                         show_default=False)] = DEFAULT_CONFIG,
    host: Annotated[str, typer.Option(help="interface to bind (another than loopback needs an API key)")]
    = "127.0.0.1",
    port: Annotated[int, typer.Option(min=1, max=65535)] = 8080,
    data_dir: Annotated[Path, typer.Option(help="jobs, uploads, logs and the embedded database",
                                           callback=data_folder)]
    = DEFAULT_DATA_DIR,
    db: Annotated[str | None, typer.Option(envvar=DB_ENVVAR,
                                           help="store URL, e.g. postgresql+psycopg://user@host/db (default: "
                                                "SQLite in the data dir)")] = None,
) -> None:
    """Run the cell as a service: REST API under /api/v1, docs at /docs."""
    try:
        # before the service takes its cell and settles what a previous run left
        problem = listen_problem(host, port)
        if problem is not None:
            raise CellError(f"cannot listen on {host}:{port}: {problem} (--host, --port)")
        # the line's OPC UA port: free, and a host of this machine; before the store, its lease and the
        # data folder's files are made, so that a refused start leaves nothing behind
        check_endpoint(load_config(config).line)
        notifier = Notifier()
        service = build_service(ServiceSettings(config_file=config, data_dir=data_dir, db_url=db))
        has_keys = bool(service.store.active_keys())
        # the store's URL is not repeated: it may hold a password
        where = f"--data-dir {data_dir}" if db is None else f"with this --db or {DB_ENVVAR}"
        if not is_loopback(host) and not has_keys:
            service.store.close()
            raise CellError(f"refusing to listen on {host}, beyond this machine, with no API key: create one "
                            f"first (cell keys create --role admin {where})")
    except CellError as exc:
        raise fail(exc) from None
    if not has_keys:
        err_console.print(f"no API key yet: every route but /healthz needs one (cell keys create --role "
                          f"operator {where})", markup=False, highlight=False, soft_wrap=True)
    configure_logging()
    if db is None:
        for path, before, after in restrict_store_files(data_dir):
            log.warning("%s was mode %04o, open beyond the service's user: made %04o (the store holds the "
                        "API keys' hashes)", path, before, after)
    # On SIGTERM or Ctrl-C the running job's arm is stopped first (cell.api.server), then uvicorn waits for
    # open connections (event streams end by themselves within a second) before the app shuts down; what is
    # left is cut after a short grace. The connections are capped under the descriptor limit, and must
    # deliver their headers and bodies in time (cell.api.connections).
    limits = ConnectionLimits.of_process()
    server = NotifyingServer(uvicorn.Config(create_app(ServiceSettings(config, data_dir, db), service),
                                            host=host, port=port, log_config=None,
                                            timeout_graceful_shutdown=SHUTDOWN_GRACE_S,
                                            http=protocol_class(limits), backlog=limits.backlog), notifier)
    server.run()
    if not server.started:
        raise typer.Exit(code=1)
