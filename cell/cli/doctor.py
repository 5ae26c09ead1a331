"""``cell doctor``: commissioning checks of this machine and the cell file's devices (``cell.doctor``).

Each check prints ``ok``, ``warn`` or ``FAIL`` with what it found, and the fix on the next line; the exit
code is 0 only when nothing fails (warnings included), 1 otherwise.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from cell.cli.commands import DB_ENVVAR
from cell.doctor.findings import Status
from cell.doctor.report import failed, run_checks
from cell.service.startup import DEFAULT_CONFIG, DEFAULT_DATA_DIR
from cell.templates import DEFAULT_TEMPLATE

console = Console(soft_wrap=True)
LABEL = {Status.OK: "ok  ", Status.WARN: "warn", Status.FAIL: "FAIL"}


def doctor(
    config: Annotated[Path, typer.Option(help=f"the cell file (default: the shipped {DEFAULT_TEMPLATE} cell, "
                                              "as cell serve runs it)", show_default=False)] = DEFAULT_CONFIG,
    data_dir: Annotated[Path, typer.Option(help="the service's data folder")] = DEFAULT_DATA_DIR,
    host: Annotated[str, typer.Option(help="the interface cell serve will bind")] = "127.0.0.1",
    port: Annotated[int, typer.Option(min=1, max=65535, help="the port cell serve will listen on")] = 8080,
    db: Annotated[str | None, typer.Option(envvar=DB_ENVVAR,
                                           help="the store's URL, if not the data folder's SQLite")] = None,
) -> None:
    """Check this machine and the cell's devices before the first scan: ok / warn / FAIL, with each fix."""
    found = run_checks(config, data_dir, host, port, db)
    width = max(len(f.name) for f in found)
    for finding in found:
        console.print(f"{LABEL[finding.status]}  {finding.name:{width}s}  {finding.detail}", markup=False,
                      highlight=False)
        if finding.fix:
            console.print(f"      {'':{width}s}  fix: {finding.fix}", markup=False, highlight=False)
    n_fail = sum(f.status is Status.FAIL for f in found)
    n_warn = sum(f.status is Status.WARN for f in found)
    console.print(f"{len(found)} checks: {n_fail} failed, {n_warn} warnings", markup=False, highlight=False)
    if failed(found):
        raise typer.Exit(code=1)
