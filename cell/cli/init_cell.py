"""``cell init``: a new cell's folder from a template, ready to fill in.

``cell init DIR --template NAME`` writes ``DIR/cell.yaml`` (the template, its values to measure marked
``# MEASURE:``) and the data folder the service fills (``DIR/data`` or ``--data-dir``: ``jobs``,
``objects``, ``logs``, and ``calibrations`` for the calibration views and results), then lists what is
left to measure and the commands that follow. It never overwrites a cell file.
"""

from __future__ import annotations

import re
import shlex
import shutil
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from calibration import CALIBRATIONS_FOLDER
from cell.cli.errors import fail
from cell.cli.values import data_folder
from cell.config.models import CELL_NAME
from cell.config.placeholders import find_placeholders
from cell.deploy import DATA_DIR
from cell.templates import TEMPLATES, template_path
from drivers.errors import CellError, ConfigError

CELL_FILE = "cell.yaml"
DATA_FOLDERS = ("jobs", "objects", "logs", CALIBRATIONS_FOLDER)

console = Console(soft_wrap=True)


def init_cell(folder: Path, template: str, name: str | None = None, data_dir: Path | None = None) -> Path:
    """Write ``folder/cell.yaml`` from ``template`` (its ``name:`` replaced by ``name``, by default the
    folder's own name where that is a cell name: cells made from one template differ) and the data folder
    layout in ``data_dir`` (default ``folder/data``); returns the cell file. ``ConfigError``
    if the cell file exists, the template or the name is unknown or invalid, or a folder cannot be
    written."""
    text = template_path(template).read_text()
    if name is None and re.fullmatch(CELL_NAME, folder.resolve().name):
        name = folder.resolve().name
    if name is not None:
        if not re.fullmatch(CELL_NAME, name):
            raise ConfigError(f"{name!r} is not a cell name", field="--name",
                              allowed="1-64 letters, digits, '.', '_', '-', starting with a letter or digit")
        text = re.sub(r"^name: .*$", f"name: {name}", text, count=1, flags=re.MULTILINE)
    cell_file = folder / CELL_FILE
    if cell_file.exists():
        raise ConfigError("exists already; cell init never overwrites a cell file", file=str(cell_file))
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for sub in DATA_FOLDERS:
            ((data_dir or folder / "data") / sub).mkdir(parents=True, exist_ok=True)
        with cell_file.open("x") as out:
            out.write(text)
    except OSError as exc:
        raise ConfigError(f"cannot write the cell's folder: {exc.strerror}", file=str(folder)) from None
    return cell_file


def init(
    folder: Annotated[Path, typer.Argument(metavar="FOLDER", help="the cell's folder (created if missing)")],
    template: Annotated[str, typer.Option(help=f"one of: {', '.join(TEMPLATES)}")],
    name: Annotated[str | None, typer.Option(help="the cell's name (default: the folder's name)")] = None,
    data_dir: Annotated[Path | None, typer.Option(help="the service's data folder (default: FOLDER/data; "
                                                       f"{DATA_DIR} under systemd)",
                                                  callback=data_folder)] = None,
) -> None:
    """Start a cell: its cell file from a template and its data folder, with what is left to measure."""
    try:
        cell_file = init_cell(folder, template, name, data_dir)
    except CellError as exc:
        raise fail(exc) from None
    data = data_dir or folder / "data"
    console.print(f"wrote {cell_file} and {data}/", markup=False, highlight=False)
    if name is None and not re.fullmatch(CELL_NAME, folder.resolve().name):
        # two cells of one template on one job store would share a name: one of them refuses to start
        console.print(f"note: the folder's name {folder.resolve().name!r} is not a cell name, so the cell "
                      f"keeps the template's: give it its own with --name or in the file's `name:`",
                      markup=False, highlight=False)
    left = find_placeholders(cell_file.read_text())
    if left:
        console.print(f"{len(left)} values to measure (marked '# MEASURE:'; delete each mark once measured):",
                      markup=False, highlight=False)
        for p in left:
            console.print(f"  line {p.line:3d}  {p.field}: {p.what}", markup=False, highlight=False)
    console.print("next:", markup=False, highlight=False)
    file, folder_ = shlex.quote(str(cell_file)), shlex.quote(str(data))
    cell = _cell_command()
    for step in (f"{cell} config check {file}", f"{cell} doctor --config {file} --data-dir {folder_}",
                 f"{cell} serve --config {file} --data-dir {folder_}"):
        console.print(f"  {step}", markup=False, highlight=False)


def _cell_command() -> str:
    """How to run ``cell`` again from here: ``cell`` when that is the command running now, found on the
    PATH; else the path it was run by (``.venv/bin/cell`` in a checkout whose venv is not activated)."""
    ran = Path(sys.argv[0])
    found = shutil.which("cell")
    if ran.name != "cell" or (found is not None and Path(found).resolve() == ran.resolve()):
        return "cell"
    return shlex.quote(str(ran))
