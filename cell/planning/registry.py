"""The planners a job can run, registered explicitly by name (no import-time side effects).

Each entry says what the planner does and where its class lives; the class, with what it needs (Open3D,
SciPy, seconds of imports), is imported only when a job runs it or asks where it looks: the service lists
and validates planners by name and runs the scans in a worker process of their own; it imports a planner
only to check a placement in its search views (``cell.service.search_views``), off its event loop.
"""

from __future__ import annotations

import pkgutil
from dataclasses import dataclass
from typing import TYPE_CHECKING

from drivers.errors import PlanningError

if TYPE_CHECKING:  # the base imports the perception pipeline, which the service does not need
    from cell.planning.base import Planner


@dataclass(frozen=True)
class PlannerEntry:
    """A registered planner: a one-line ``description`` and its class's ``location``
    (``module:Class``)."""

    description: str
    location: str

    def load(self) -> type[Planner]:
        """The planner's class, its module imported."""
        planner: type[Planner] = pkgutil.resolve_name(self.location)
        return planner


PLANNERS: dict[str, PlannerEntry] = {
    "raster": PlannerEntry(
        "predetermined rings of views around the station (naive baseline, no feedback)",
        "cell.planning.raster:RasterPlanner"),
    "lr-nbv": PlannerEntry(
        "Low-Resolution NBV (packing paper, Algorithm 1): RRT with cached nodes, all four gains",
        "cell.planning.lrnbv.planner:LRNBVPlanner"),
    "nbv": PlannerEntry(
        "NBV baseline of the packing paper: Algorithm 1 with only the exploration and quality gains",
        "cell.planning.lrnbv.planner:NBVPlanner"),
    "heu": PlannerEntry(
        "packing paper's heuristic baseline: 13 poses on an ellipse around the known object",
        "cell.planning.lrnbv.heu:HEUPlanner"),
    "vs-local": PlannerEntry(
        "visual-servoing active vision, gradient of the entropy objective (paper eq. 1-9, Local)",
        "cell.planning.vs.local:VSLocalPlanner"),
    "vs-global": PlannerEntry(
        "visual servoing towards the best of 5000 sampled views (paper eq. 10-11, Global)",
        "cell.planning.vs.goals:VSGlobalPlanner"),
    "vs-hybrid": PlannerEntry(
        "visual-servoing Local until converged, then one Global goal, repeated (paper II-D, Hybrid)",
        "cell.planning.vs.hybrid:VSHybridPlanner"),
}


def check_planner(name: str) -> None:
    """Raise ``PlanningError`` listing the registered planners when ``name`` is not one of them."""
    if name not in PLANNERS:
        raise PlanningError(f"unknown planner {name!r}; registered: {', '.join(sorted(PLANNERS))}")


def get_planner(name: str) -> type[Planner]:
    """The planner class registered as ``name``, imported; an unknown name raises ``PlanningError``
    listing the registered ones."""
    check_planner(name)
    return PLANNERS[name].load()
