"""The ``DepthSensor`` interface every depth backend implements (sim-rgbd, sim-tof, vl53l8cx, realsense,
replay).

Sensor frame: z along the optical axis, x right, y down (the papers' convention); points in metres.
"""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from drivers.device import Device
from drivers.errors import DeviceFault

Array = NDArray[np.float64]


@dataclass(frozen=True)
class SensorModel:
    """What a planner needs to know about a sensor's viewing geometry.

    ``fov_x_deg`` / ``fov_y_deg`` full field of view [deg]; ``width`` x ``height`` pixels or zones;
    ``range_min_m`` / ``range_max_m`` the range the sensor reports within [m].
    """

    kind: str
    width: int
    height: int
    fov_x_deg: float
    fov_y_deg: float
    range_min_m: float
    range_max_m: float


@dataclass(frozen=True)
class ToFZones:
    """Per-zone data of a multizone time-of-flight frame, flat arrays of length ``n_zones``, row-major
    from the top-left zone as seen by the sensor.

    ``distance_m`` along each zone's central ray [m] (NaN with no target); ``sigma_m`` the sensor's range
    sigma [m]; ``status`` the VL53L8CX target status (5 and 9 valid, 255 no target, ...);
    ``nb_targets`` targets detected; ``reflectance_pct`` estimated reflectance [%];
    ``directions`` (n_zones, 3) unit central ray of each zone in the sensor frame.
    """

    distance_m: Array
    sigma_m: Array
    status: NDArray[np.uint8]
    nb_targets: NDArray[np.uint8]
    reflectance_pct: Array
    directions: Array


@dataclass(frozen=True)
class DepthFrame:
    """One capture.

    ``points`` (N, 3) [m] in the sensor frame: every return the sensor reports (for the ToF, one per zone
    with a target whose status the backend counts as a range: 5 and 9 for ``sim-tof``, the config's
    ``valid_statuses`` for ``vl53l8cx``; perception filters by status again with its own set).
    ``timestamp`` [s] on the job's clock. ``depth`` (H, W) [m], 0 where there is no return, with
    ``intrinsics`` its 3x3 pinhole matrix K [px] (RGB-D only): pixel (u, v) at depth z is the point
    ((u - cx) z / fx, (v - cy) z / fy, z).
    ``zones`` (ToF only). ``intensity`` (H, W) uint8, the grey image registered to ``depth`` (same
    intrinsics), for a camera that gives one (``sim-rgbd``; calibration boards are found in it).
    """

    seq: int
    timestamp: float
    points: Array
    depth: NDArray[np.float32] | None = None
    intrinsics: Array | None = None
    zones: ToFZones | None = None
    intensity: NDArray[np.uint8] | None = None


class DepthSensor(Device):
    """A depth sensor. Use as a context manager, or call ``connect`` / ``disconnect``."""

    name: str = "depth"

    @property
    @abstractmethod
    def model(self) -> SensorModel: ...

    @property
    def device(self) -> str:
        """The sensor as its ``DriverError``s name it; backends with an address (port, serial) add it."""
        return self.name

    @abstractmethod
    def capture(self) -> DepthFrame:
        """Return the newest frame; raises ``DriverError`` when the device is silent or gone."""

    def latched_fault(self) -> DeviceFault | None:
        """The fault the sensor latched while connected (its link gone, noticed between captures by a
        backend that reads on its own thread), or None; cheap enough for every control tick. Backends
        that find faults only when they capture have none to report here."""
        return None
