"""``--object-scale`` with one object, as ``cell scan`` and ``cell eval limit`` take it (a module of its own:
the shipped objects' list loads numpy, which ``cell jobs`` does not need)."""

from __future__ import annotations

from drivers.errors import JobError
from drivers.sim.objects import mesh_file_scale


def scale_of(object: str, scale: float | None) -> float:
    """The ``--object-scale`` of one ``object`` (default 1); ``JobError`` when one other than 1 is given
    with a shipped object, which is in metres (a scale that is no positive number is left to the job's
    own check, which says so)."""
    if scale is not None and scale > 0.0 and scale != 1.0 and mesh_file_scale(object, scale) == 1.0:
        raise JobError(f"--object-scale is for a mesh file: the shipped object {object} is in metres")
    return scale if scale is not None else 1.0
