"""``cell config check``: whether a cell file is valid, and what is still to be measured in it; ``cell config
reference``: every key a cell file may hold (``docs/config.md``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from cell.cli.commands import command_group
from cell.cli.errors import fail
from cell.config import load_config
from cell.config.placeholders import find_placeholders
from cell.config.reference import reference_markdown
from cell.line.config import LineConfig
from drivers.errors import CellError, ConfigError

config_app = command_group(help="Cell configuration files.", no_args_is_help=True)
console = Console(soft_wrap=True)


@config_app.command("check")
def config_check(file: Annotated[Path, typer.Argument(metavar="FILE", help="the cell file")]) -> None:
    """Validate a cell file.

    Prints a summary or the problem, and the values still marked ``# MEASURE:`` (then exit code 1: the
    file is valid but not ready)."""
    try:
        cfg = load_config(file)
    except CellError as exc:
        raise fail(exc) from None
    console.print(f"{file}: valid ({cfg.name}: mode {cfg.mode}, arm {cfg.arm.type}/{cfg.arm.model}, "
                  f"sensor {cfg.sensor.type}, planner {cfg.scan.planner})", markup=False, highlight=False)
    if cfg.line is not None:
        console.print(_line_summary(cfg.line), markup=False, highlight=False)
    left = find_placeholders(file.read_text())
    if not left:
        console.print("ready: nothing left to measure", markup=False, highlight=False)
        return
    for p in left:
        console.print(f"to measure: line {p.line} {p.field}: {p.what}", markup=False, highlight=False)
    raise fail(ConfigError(f"not ready: {len(left)} values still marked '# MEASURE:' (measure each, write "
                            "it and delete the mark)", file=str(file)))


@config_app.command("reference")
def config_reference(out: Annotated[Path | None, typer.Option(
        help="write it to this file (docs/config.md in the repository) instead of printing it")] = None
                     ) -> None:
    """Every key a cell file may hold, in Markdown: type, unit, default and constraints per section.

    Generated from the models that validate a cell file, so it is what this version of cell accepts."""
    text = reference_markdown()
    if out is None:
        typer.echo(text, nl=False)
        return
    out.write_text(text)
    console.print(f"wrote {out}", markup=False, highlight=False)


def _line_summary(line: LineConfig) -> str:
    """One line: the packing line's unit mode at start and the ways a line controller drives it."""
    ways = ["REST"]
    if line.opcua is not None:
        ways.append(f"OPC UA at {line.opcua.endpoint} (security {line.opcua.security})")
    if line.dio is not None:
        ways.append("the arm's digital I/O")
    return f"line: starts in {line.initial_mode} mode; driven over {', '.join(ways)}"
