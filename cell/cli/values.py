"""Values given on the command line in a form of their own, read alike by every command that takes them."""

from __future__ import annotations

import math

import typer

from cell.cli.errors import fail


def parse_pose(option: str, text: str) -> tuple[float, float, float]:
    """``x,y,yaw_deg`` (metres, metres, degrees) as three finite numbers; else the input error (exit 1)
    naming ``option``, the way every ``cell`` command reports bad input (a usage error's box named no
    option: "Invalid value: expected x,y,yaw_deg")."""
    try:
        x, y, yaw = (float(part) for part in text.split(","))
    except ValueError:  # not a number, or not three of them
        raise _bad_pose(option, text) from None
    if not all(math.isfinite(v) for v in (x, y, yaw)):
        raise _bad_pose(option, text)
    return x, y, yaw


def _bad_pose(option: str, text: str) -> typer.Exit:
    return fail(f"{option}: expected x,y,yaw_deg (three finite numbers), got {text!r}")
