"""The planners a job can run, registered explicitly by name (no import-time side effects)."""

from __future__ import annotations

from cell.planning.base import Planner
from cell.planning.lrnbv.heu import HEUPlanner
from cell.planning.lrnbv.planner import LRNBVPlanner, NBVPlanner
from cell.planning.raster import RasterPlanner
from cell.planning.vs.goals import VSGlobalPlanner
from cell.planning.vs.hybrid import VSHybridPlanner
from cell.planning.vs.local import VSLocalPlanner
from drivers.errors import PlanningError

PLANNERS: dict[str, type[Planner]] = {
    RasterPlanner.name: RasterPlanner,
    LRNBVPlanner.name: LRNBVPlanner,
    NBVPlanner.name: NBVPlanner,
    HEUPlanner.name: HEUPlanner,
    VSLocalPlanner.name: VSLocalPlanner,
    VSGlobalPlanner.name: VSGlobalPlanner,
    VSHybridPlanner.name: VSHybridPlanner,
}


def get_planner(name: str) -> type[Planner]:
    """The planner class registered as ``name``; an unknown name raises ``PlanningError`` listing the
    registered ones."""
    try:
        return PLANNERS[name]
    except KeyError:
        raise PlanningError(f"unknown planner {name!r}; registered: {', '.join(sorted(PLANNERS))}") from None
