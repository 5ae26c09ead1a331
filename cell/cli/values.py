"""Values given on the command line in a form of their own, read alike by every command that takes them."""

from __future__ import annotations

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
