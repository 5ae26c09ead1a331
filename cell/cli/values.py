"""Values given on the command line in a form of their own, read alike by every command that takes them."""

from __future__ import annotations

from pathlib import Path

import typer

from cell.cli.errors import fail
from cell.jobs import inputs
from drivers.errors import JobError


def parse_pose(option: str, text: str) -> tuple[float, float, float]:
    """``x,y,yaw_deg`` (metres, metres, degrees) as three finite numbers
    (:func:`cell.jobs.inputs.parse_pose`); else the input error (exit 1) naming ``option``, the way every
    ``cell`` command reports bad input (a usage error's box named no option: "Invalid value: expected
    x,y,yaw_deg")."""
    try:
        return inputs.parse_pose(text)
    except JobError as exc:
        raise fail(f"{option}: {exc}") from None


def data_folder(ctx: typer.Context, path: Path | None) -> Path | None:
    """A ``--data-dir`` option's check (its ``callback``): ``path``, a folder or a name not taken (the
    command makes it) or None (not given, where the option has no default); else the input error (exit
    1) saying so, before anything opens it. A file there was reported as "cannot read which store the
    service of DATA uses (DATA/store-url): Not a directory". Not checked while the shell completes a
    command line (``resilient_parsing``): the error would be printed into the completion."""
    if not ctx.resilient_parsing and path is not None and path.exists() and not path.is_dir():
        raise fail(f"--data-dir {path} is not a folder: give a folder, or a name not taken")
    return path
