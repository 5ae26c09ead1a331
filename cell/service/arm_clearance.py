"""The service's check that an object's placement is clear of the arm, in one collision world it keeps."""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING

from cell.config.models import CellConfig
from cell.jobs.placement import check_clear_of_arm
from drivers.sim.objects import ObjectMesh

if TYPE_CHECKING:  # FCL and the collision world load at the first check, not when ``cell serve`` starts
    from cell.safety.collision import CollisionWorld


class ArmClearance:
    """The check that an object's placement is clear of the arm at its home joints (``check_clear_of_arm``):
    a shipped object's at every Start and submission, an upload's at its upload (``ObjectLibrary.add``).
    Both check in the cell's collision world, built at the first call (it loads FCL, Open3D and the tool's
    meshes: the dispatcher makes it before its first job, ``CellService._load_checks``) and kept for the
    next: the arm and its tool do not change while the service runs, and building the world took 10-100 ms
    of every check. Callable from several threads at once: the world is built under a lock and only read
    after."""

    def __init__(self, config: CellConfig) -> None:
        self._config = config
        self._lock = threading.Lock()
        self._world: CollisionWorld | None = None

    def world(self) -> CollisionWorld:
        """The cell's collision world (``CollisionWorld.for_cell``), built at the first call."""
        with self._lock:
            if self._world is None:
                from cell.safety.collision import CollisionWorld

                self._world = CollisionWorld.for_cell(self._config)
            return self._world

    def check(self, mesh: ObjectMesh, pose: tuple[float, float, float]) -> None:
        """``JobError`` naming the body when ``mesh`` at ``pose`` (x [m], y [m], yaw [deg] from the
        station) stands in the arm."""
        check_clear_of_arm(self._config, mesh, pose, self.world())
