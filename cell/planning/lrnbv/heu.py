"""The ``heu`` baseline of the LR-NBV paper (section 4): 13 evenly spaced poses on an ellipse centred on the
object, each looking at it. Unlike LR-NBV it needs the object's position: the cell's station."""

from __future__ import annotations

import numpy as np

from cell.config.models import CellConfig
from cell.packing.result import ReconstructionHistory
from cell.planning.base import Array, Planner, ScanSession
from drivers.transforms import look_at


def heu_views(config: CellConfig) -> list[Array]:
    """The T_base_sensor poses of the ellipse, in visiting order (``planners.heu``)."""
    h = config.planners.heu
    st = config.station
    centre = np.array([st.xy_m[0], st.xy_m[1], st.table_z_m])
    target = centre + np.array([0.0, 0.0, h.target_height_m])
    angles = np.deg2rad(h.start_angle_deg) + 2.0 * np.pi * np.arange(h.n_poses) / h.n_poses
    a, b = h.semi_axes_m
    return [look_at(centre + np.array([a * np.cos(t), b * np.sin(t), h.height_m]), target) for t in angles]


class HEUPlanner(Planner):
    def __init__(self, config: CellConfig) -> None:
        super().__init__(config)
        self.reconstruction = ReconstructionHistory()

    def search_views(self) -> list[Array]:
        """Every pose of the ellipse: it looks from all of them."""
        return heu_views(self.config)

    def run(self, session: ScanSession) -> str:
        views = heu_views(self.config)
        skipped = 0
        for T in views:
            if not session.move_to_sensor_pose(T):
                skipped += 1
                continue
            session.wait(self.config.planners.heu.settle_s)
            session.capture()
            self.reconstruction.record(session.perception)
        return f"heu complete: {len(views) - skipped} of {len(views)} poses captured, {skipped} refused"
