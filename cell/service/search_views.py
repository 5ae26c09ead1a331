"""The service's check that one of the planner's search views sees an object's placement."""

from __future__ import annotations

import threading

from cell.config.models import CellConfig
from cell.jobs.placement import check_in_view, view_points
from cell.planning.registry import get_planner
from cell.service.objects import ObjectOutline
from drivers.sim.objects import Array, ObjectMesh


class SearchViews:
    """The check that one of a planner's search views sees an object's placement (``check_in_view``), a
    shipped mesh's or an upload's (its outline's surface points, kept at the upload), at every submission
    and Start: a placement none of them sees could only end ``no_object``. A planner's views
    (``Planner.search_views``) are worked out at the first call that names it, which imports the planner
    (SciPy, Open3D: up to a second; the service does so for its default planner before its first job,
    ``CellService._load_checks``), and kept for the next: they depend on the cell's config alone, which
    does not change while the service runs. Callable from several threads at once: the views are worked
    out under a lock and only read after."""

    def __init__(self, config: CellConfig) -> None:
        self._config = config
        self._lock = threading.Lock()
        self._views: dict[str, list[Array]] = {}

    def of(self, planner: str) -> list[Array]:
        """``planner``'s search views, T_base_sensor (4x4, base frame [m]), worked out at the first call."""
        with self._lock:
            if planner not in self._views:
                self._views[planner] = get_planner(planner)(self._config).search_views()
            return self._views[planner]

    def check(self, shape: ObjectMesh | ObjectOutline, pose: tuple[float, float, float],
              planner: str) -> None:
        """``JobError`` saying where the views look when none of ``planner``'s sees ``shape`` at ``pose``
        (x [m], y [m], yaw [deg] from the station); an outline must hold its surface points
        (``ObjectLibrary.shape(name, surface=True)``)."""
        surface = view_points(shape) if isinstance(shape, ObjectMesh) else shape.surface
        if surface is None:
            raise ValueError(f"the outline of {shape.name!r} holds no surface points to check in the views")
        check_in_view(self._config, shape, surface, pose, self.of(planner), planner)
