"""``cell stop``: the operator stop of a scan that ``cell scan`` runs. It loads nothing but the stop file's
module (``cell.jobs.stop_file``), so that it answers at once."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from cell.cli.errors import fail
from cell.jobs.stop_file import request_stop
from drivers.errors import COMMAND_LINE_REASON, CellError

console = Console(soft_wrap=True)


def stop(
    job_dir: Annotated[Path, typer.Argument(metavar="JOB_DIR", help="folder of the running job")],
    reason: Annotated[str, typer.Option(help="recorded in the job's termination, after 'operator stop: '")]
    = COMMAND_LINE_REASON,
) -> None:
    """Operator stop of a running scan.

    The arm stops at the job's next control tick, and the job ends ``stopped`` with everything recorded so
    far."""
    try:
        request_stop(job_dir, reason)
    except CellError as exc:
        raise fail(exc) from None
    console.print(f"stop requested: {job_dir}", markup=False, highlight=False)
