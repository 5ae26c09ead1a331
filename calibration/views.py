"""The views a calibration plans, and running them as a job through ``cell.jobs`` (every move checked by
the safety layer; a view it refuses, or one out of reach, is skipped and counted in the job's
``result.json``), then reading the captured views back from the job folder.

Mount views (known shape): ``n`` sensor poses looking at the top centre of the box at the station, at
``standoff_m``, their directions spread on a cap of the sphere (elevations between ``ELEVATION_DEG``,
azimuths by the golden angle, then visited in order of azimuth so that the moves between them are
short) and each turned about its optical axis by one of ``ROLLS_DEG``: views from several directions and
with several rotations of the flange are what make every axis of the mount observable.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from calibration.shape_fit import Array, View
from cell.config.models import CellConfig
from cell.jobs.runner import ScanOutcome, ScanRequest, prepare_scan, run_prepared
from cell.planning.base import Planner, ScanSession
from drivers.depth.base import SensorModel
from drivers.depth.projection import back_project
from drivers.transforms import T_from_xyz_rpy, look_at

ELEVATION_DEG = (30.0, 80.0)
ROLLS_DEG = (-30.0, 0.0, 30.0)
GOLDEN_ANGLE_RAD = np.pi * (3.0 - np.sqrt(5.0))
ZONE_STATUS_VALID = 5
"""ToF zones used by a calibration: status 5 only (status 9 marks a zone across a depth edge, whose
distance belongs to no one surface)."""


def mount_views(config: CellConfig, n: int, look_at_height_m: float, standoff_m: float,
                elevation_deg: tuple[float, float] = ELEVATION_DEG) -> list[Array]:
    """``n`` T_base_sensor poses (see the module docstring) looking at the point ``look_at_height_m``
    [m] above the table at the station, at elevations within ``elevation_deg``."""
    st = config.station
    target = np.array([st.xy_m[0], st.xy_m[1], st.table_z_m + look_at_height_m])
    lo, hi = np.deg2rad(elevation_deg)
    views = []
    for i in sorted(range(n), key=lambda k: (k * GOLDEN_ANGLE_RAD) % (2.0 * np.pi)):
        az = np.pi + i * GOLDEN_ANGLE_RAD
        el = lo + (hi - lo) * ((i * 0.618034) % 1.0)
        eye = target + standoff_m * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        roll = np.deg2rad(ROLLS_DEG[i % len(ROLLS_DEG)])
        views.append(look_at(eye, target) @ T_from_xyz_rpy([0.0, 0.0, 0.0], [0.0, 0.0, roll]))
    return views


Precheck = Callable[[SensorModel, list[Array]], None]
"""Called with the connected sensor's model and the planned T_base_sensor poses before the first move;
raises to refuse the views."""


class ViewsPlanner(Planner):
    """Visits given sensor poses in order and captures one frame at each; a pose the arm cannot reach or
    the guard refuses is skipped (the session logs and counts it). ``precheck`` runs before anything
    moves; ``frames_per_view`` frames are taken at each view (more frames average a noisy sensor's
    noise down at no cost in motion)."""

    name = "calibration-views"
    description = "the views a calibration planned, one capture each"

    def __init__(self, config: CellConfig, views: list[Array], precheck: Precheck | None = None,
                 frames_per_view: int = 1, settle_s: float = 0.2) -> None:
        super().__init__(config)
        self.views = views
        self.precheck = precheck
        self.frames_per_view = frames_per_view
        self.settle_s = settle_s

    def run(self, session: ScanSession) -> str:
        if self.precheck is not None:
            self.precheck(session.sensor_model(), self.views)
        skipped = 0
        for T in self.views:
            if not session.move_to_sensor_pose(T):
                skipped += 1
                continue
            session.wait(self.settle_s)
            for _ in range(self.frames_per_view):
                session.capture()
        n = len(self.views)
        return f"calibration views: {n - skipped} of {n} captured, {skipped} skipped"


def capture_views(config: CellConfig, config_path: str, views: list[Array], *, target_object: str,
                  folder: Path, seed: int = 0,
                  object_pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
                  precheck: Precheck | None = None, frames_per_view: int = 1) -> ScanOutcome:
    """Run the views as a job into ``folder`` (created; it keeps the raw frames and poses). In sim and
    dry runs ``target_object`` (a shipped mesh or ``none``) stands at ``object_pose`` (x, y, yaw_deg)
    from the station; on a real cell it is only the job's label. ``precheck``, ``frames_per_view``: see
    ``ViewsPlanner``."""
    request = ScanRequest(config=config, config_path=config_path, object=target_object, planner="raster",
                          seed=seed, out=folder, object_pose=object_pose)
    planner = ViewsPlanner(config, views, precheck, frames_per_view)
    job = dataclasses.replace(prepare_scan(request), planner=planner, planner_name=ViewsPlanner.name)
    return run_prepared(job)


SAME_VIEW_ATOL = 1e-4
"""Consecutive frames whose reported flange poses agree within this (4x4 entries, [m] and unitless) were
taken at one view and are merged."""


def load_views(folder: Path) -> list[View]:
    """The captured views of a job folder, in capture order: the reported flange pose and the measured
    points (sensor frame): a depth image back-projected, or the ToF zones of status 5; the frames of one
    view (``SAME_VIEW_ATOL``) merged."""
    views: list[View] = []
    for path in sorted((folder / "frames").glob("*.npz")):
        with np.load(path) as f:
            if "depth" in f:
                points = back_project(f["depth"], f["K"])
            elif "zone_status" in f:
                ok = (f["zone_status"] == ZONE_STATUS_VALID) & np.isfinite(f["zone_distance_m"])
                points = f["zone_distance_m"][ok, None] * f["zone_directions"][ok]
            else:
                points = f["points"]
            T = np.array(f["T_base_flange"], dtype=np.float64)
        if views and np.allclose(views[-1].T_base_flange, T, atol=SAME_VIEW_ATOL):
            views[-1] = View(views[-1].T_base_flange, np.concatenate([views[-1].points_sensor, points]))
        else:
            views.append(View(T, points))
    return views
