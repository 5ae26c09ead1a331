"""From the sensor's per-zone integers to a ``DepthFrame``, the same for the serial and the I2C backend.

Zone geometry is the simulated sensor's (:func:`drivers.depth.sim_tof.zone_directions`): the zones tile
the square field of view evenly in angle, row-major from the top-left zone as seen in the sensor frame
(z along the optical axis, x right, y down), and a zone's distance is taken along its central ray.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from drivers.depth.base import DepthFrame, SensorModel, ToFZones
from drivers.depth.config import VL53L8CXConfig
from drivers.depth.sim_tof import zone_directions
from drivers.depth.vl53l8cx.protocol import RangingFrame
from drivers.depth.zone_correction import ZoneCorrection, load_zone_correction

Array = NDArray[np.float64]


@lru_cache(maxsize=8)
def central_rays(resolution: int, fov_deg: float) -> Array:
    """Unit central ray of each zone (resolution**2, 3), sensor frame, row-major (read-only)."""
    rays = zone_directions(resolution, fov_deg, 1)[:, 0, :]
    rays.setflags(write=False)
    return rays


def valid_zones(raw: RangingFrame, valid_statuses: tuple[int, ...]) -> NDArray[np.bool_]:
    """Zones with a target, a positive distance and a status in ``valid_statuses``."""
    return ((raw.nb_target_detected > 0) & (raw.distance_mm > 0)
            & np.isin(raw.target_status, np.asarray(valid_statuses)))


def depth_frame(raw: RangingFrame, *, seq: int, timestamp: float, fov_deg: float,
                valid_statuses: tuple[int, ...], correction: ZoneCorrection | None = None) -> DepthFrame:
    """The ``DepthFrame`` of one measurement: ``zones`` in SI units (distance and sigma [m], NaN where
    the zone has no target; reflectance [%]) and one point [m, sensor frame] per valid zone (see
    :func:`valid_zones`), distance times the zone's central ray. ``seq`` and ``timestamp`` [s] are the
    host's. ``correction``: each zone's distance less its calibrated bias (the zones and the points)."""
    rays = central_rays(raw.resolution, float(fov_deg))
    has_target = raw.nb_target_detected > 0
    distance = np.where(has_target, raw.distance_mm.astype(np.float64) / 1000.0, np.nan)
    if correction is not None:
        distance = correction.apply(distance)
    sigma = np.where(has_target, raw.range_sigma_mm.astype(np.float64) / 1000.0, np.nan)
    reflectance = np.where(has_target, raw.reflectance_pct.astype(np.float64), np.nan)
    zones = ToFZones(distance_m=distance, sigma_m=sigma, status=raw.target_status.copy(),
                     nb_targets=raw.nb_target_detected.copy(), reflectance_pct=reflectance,
                     directions=rays.copy())
    keep = valid_zones(raw, valid_statuses)
    points = distance[keep, None] * rays[keep]
    return DepthFrame(seq=seq, timestamp=timestamp, points=points, zones=zones)


def configured_correction(c: VL53L8CXConfig) -> ZoneCorrection | None:
    """The zone correction file a configured VL53L8CX names, read (None when it names none)."""
    return None if c.zone_correction is None else load_zone_correction(c.zone_correction, c.resolution)


def sensor_model(c: VL53L8CXConfig) -> SensorModel:
    """The viewing geometry of a configured VL53L8CX (either backend)."""
    return SensorModel(kind="tof", width=c.resolution, height=c.resolution, fov_x_deg=c.fov_deg,
                       fov_y_deg=c.fov_deg, range_min_m=c.range_min_m, range_max_m=c.range_max_m)
