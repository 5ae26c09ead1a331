"""``cell planners`` and ``cell objects``: what a scan can be asked for."""

from __future__ import annotations

from rich.console import Console

from cell.planning.registry import PLANNERS
from drivers.sim.objects import list_objects

console = Console(soft_wrap=True)


def planners() -> None:
    """List the registered planners."""
    for name, entry in sorted(PLANNERS.items()):
        console.print(f"{name:12s} {entry.description}", markup=False, highlight=False)


def objects() -> None:
    """List the shipped objects with their size in metres."""
    for info in list_objects():
        dims = " x ".join(f"{v:.3f}" for v in info.extents_m)
        console.print(f"{info.name:16s} {dims} m", markup=False, highlight=False)
