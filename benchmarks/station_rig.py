"""A helper module of the benchmarks, not a benchmark (running it does nothing): what the perception ones
share: an object at a cell's station, a simulated sensor posed at will on a ring around it, and the cell's
perception pipeline (no arm; the pose is exact)."""

from __future__ import annotations

import numpy as np

from cell.config.models import CellConfig
from cell.perception.pipeline import PerceptionPipeline
from drivers.clock import SimClock
from drivers.factory import SimWorld, make_sensor
from drivers.sim.objects import load_object
from drivers.sim.scene import SimScene
from drivers.transforms import look_at, make_T

# Ring views look at this point above the station [m], from 0.6 of the standoff above it.
TARGET_HEIGHT_M = 0.06


class StationRig:
    """``sensor`` renders from ``T`` (T_base_sensor, set by :meth:`view`); ``pipeline`` is seeded 1 and
    computes H_ROI in the job's form (``planners.vs.objective.entropy``), the sensor noise 0."""

    def __init__(self, cfg: CellConfig, object_name: str) -> None:
        station = np.array([*cfg.station.xy_m, cfg.station.table_z_m])
        scene = SimScene(load_object(object_name), make_T(np.eye(3), station),
                         table_center_xy=cfg.sim.table_center_xy_m, table_size_xy=cfg.sim.table_size_m)
        world = SimWorld(clock=SimClock(), rng=np.random.default_rng(0), scene=scene)
        self.T = np.eye(4)
        self.sensor = make_sensor(cfg.sensor, world, lambda: self.T)
        self.pipeline = PerceptionPipeline(cfg.perception, table_z_m=cfg.station.table_z_m,
                                           range_max_m=self.sensor.model.range_max_m,
                                           rng=np.random.default_rng(1),
                                           h_roi_entropy=cfg.planners.vs.objective.entropy)
        self.target = station + np.array([0.0, 0.0, TARGET_HEIGHT_M])

    def view(self, azimuth_deg: float, standoff_m: float) -> np.ndarray:
        """Pose the sensor on the ring at ``azimuth_deg``, ``standoff_m`` from the target, looking at it."""
        az = np.deg2rad(azimuth_deg)
        eye = self.target + standoff_m * np.array([np.cos(az) * 0.8, np.sin(az) * 0.8, 0.6])
        self.T = look_at(eye, self.target)
        return self.T
