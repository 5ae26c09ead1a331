"""``cell deploy files DIR``: the files that put the cell into service on its PC (``cell.deploy``), written
out of the installed package, with the commands that install them (docs/deploy.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from cell.cli.commands import command_group
from cell.cli.errors import fail
from cell.deploy import install_commands, write_deploy_files
from drivers.errors import CellError

deploy_app = command_group(help="Putting the cell into service: its systemd unit, user and udev rule.",
                           no_args_is_help=True)
console = Console(soft_wrap=True)


@deploy_app.command("files")
def files(folder: Annotated[Path, typer.Argument(metavar="FOLDER", help="where to write them (made if "
                                                                                  "missing)")]) -> None:
    """Write the systemd unit, the service user's sysusers file and the sensor's udev rule into FOLDER.

    Never overwrites a file. Prints the files and the commands that install them."""
    try:
        written = write_deploy_files(folder)
    except CellError as exc:
        raise fail(exc) from None
    for path in written:
        console.print(f"wrote {path}", markup=False, highlight=False)
    console.print("install them (docs/deploy.md):", markup=False, highlight=False)
    for command in install_commands(folder):
        console.print(f"  {command}", markup=False, highlight=False)
