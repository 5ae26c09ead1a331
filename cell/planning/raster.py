"""The ``raster`` planner: a predetermined ring of views around the object station.

The naive baseline of the visual-servoing paper's introduction: scan the object from all sides along a
fixed path, capture at each view, accumulate. Views lie on rings at ``standoff_m`` (Z*) from a target
point above the station, each looking at it; rings are visited in a serpentine order so that consecutive
views are neighbours. Views without a reachable joint solution are skipped and counted.
"""

from __future__ import annotations

import numpy as np

from cell.config.models import CellConfig
from cell.planning.base import Array, Planner, ScanSession
from drivers.transforms import look_at


def raster_views(config: CellConfig) -> list[Array]:
    """The T_base_sensor poses of the raster, in visiting order."""
    rc = config.planners.raster
    station = config.station
    target = np.array([station.xy_m[0], station.xy_m[1], station.table_z_m + rc.target_height_m])
    views: list[Array] = []
    for i, ring in enumerate(rc.rings):
        full = rc.azimuth_span_deg >= 360.0
        steps = ring.n_views if full else max(ring.n_views - 1, 1)
        az = np.deg2rad(rc.start_azimuth_deg + rc.azimuth_span_deg * np.arange(ring.n_views) / steps)
        if i % 2:
            az = az[::-1]
        el = np.deg2rad(ring.elevation_deg)
        for a in az:
            offset = np.array([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)])
            eye = target + config.scan.standoff_m * offset
            # At the zenith "up" in the image is taken as pointing away from the robot base (+x).
            up = np.array([1.0, 0.0, 0.0]) if ring.elevation_deg >= 89.9 else None
            views.append(look_at(eye, target, up_hint=up))
    return views


class RasterPlanner(Planner):
    def search_views(self) -> list[Array]:
        """Every view of the raster: it has no feedback, and looks from all of them."""
        return raster_views(self.config)

    def run(self, session: ScanSession) -> str:
        views = raster_views(self.config)
        settle = self.config.planners.raster.settle_s
        unreachable = 0
        for T in views:
            if not session.move_to_sensor_pose(T):
                unreachable += 1
                continue
            session.wait(settle)
            session.capture()
        visited = len(views) - unreachable
        return f"raster complete: {visited} of {len(views)} views captured, {unreachable} unreachable"
