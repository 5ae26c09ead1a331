"""``realsense``: an Intel RealSense depth camera through Open3D's RealSense support
(``open3d.t.io.RealSenseSensor``; librealsense ships inside Open3D's Linux wheels, no pyrealsense2).

``connect`` enumerates the cameras (a clear ``DriverError`` when there is none, or none with the configured
serial number), configures depth and colour streams at ``width`` x ``height`` and ``fps`` with the
``preset``, optionally records the session into ``record_bag``, and reads the intrinsics and the depth
scale from the device's metadata. Frames are taken with depth aligned to the colour camera, whose
intrinsics Open3D's metadata reports, so the sensor frame is the colour camera's optical frame (z along
the optical axis, x right, y down): the hand-eye calibration is done for that frame.

Depth [m] = raw 16-bit value / depth scale (units per metre, 1000 for the D400 series); values outside
[``range_min_m``, ``range_max_m``] count as no return (0). Points come from the shared back-projection.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.clock import Clock, WallClock
from drivers.depth.base import DepthFrame, DepthSensor, SensorModel
from drivers.depth.config import RealSenseConfig
from drivers.depth.projection import back_project, pinhole_fov_deg
from drivers.errors import DriverError

Array = NDArray[np.float64]


def depth_from_raw(raw: NDArray[np.uint16], depth_scale: float,
                   range_m: tuple[float, float]) -> NDArray[np.float32]:
    """Depth image [m] (float32, 0 = no return) from the camera's 16-bit units."""
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    depth[(depth < range_m[0]) | (depth > range_m[1])] = 0.0
    return depth


def _realsense_api() -> Any:
    import open3d as o3d

    api = getattr(o3d.t.io, "RealSenseSensor", None)
    if api is None:
        raise DriverError("this Open3D build has no RealSense support; install the PyPI wheel "
                          "(pip install open3d-cpu), whose Linux x86-64 builds include librealsense",
                          device="depth realsense")
    return o3d


class RealSense(DepthSensor):
    """A RealSense camera (see the module docstring); ``clock`` stamps frames (the wall clock by
    default)."""

    name = "realsense"

    def __init__(self, config: RealSenseConfig, clock: Clock | None = None) -> None:
        self.config = config
        self._clock = clock if clock is not None else WallClock()
        self._sensor: Any = None
        self._K: Array | None = None
        self._depth_scale = 0.0
        self._seq = 0
        self._lock = threading.Lock()
        self.metadata: Any = None

    @property
    def device(self) -> str:
        return f"depth realsense {self.config.serial or '(first camera)'}"

    def connect(self) -> None:
        o3d = _realsense_api()
        self.disconnect()
        c = self.config
        devices = o3d.t.io.RealSenseSensor.enumerate_devices()
        if not devices:
            raise DriverError("no RealSense camera found: check the USB 3 cable and port, and that no other "
                              "program holds the camera", device=self.device)
        serials = [d.serial for d in devices]
        if c.serial and c.serial not in serials:
            raise DriverError(f"no camera with serial {c.serial!r}; found {', '.join(serials)}",
                              device=self.device)
        settings = {"serial": c.serial, "depth_format": "RS2_FORMAT_Z16", "color_format": "RS2_FORMAT_RGB8",
                    "depth_resolution": f"{c.width},{c.height}", "color_resolution": f"{c.width},{c.height}",
                    "fps": str(c.fps)}
        if c.preset:
            settings["visual_preset"] = c.preset
        sensor = o3d.t.io.RealSenseSensor()
        try:
            sensor.init_sensor(o3d.t.io.RealSenseSensorConfig(settings), 0, c.record_bag)
            if not sensor.start_capture(bool(c.record_bag)):
                raise RuntimeError("start_capture refused")
        except RuntimeError as exc:
            raise DriverError(f"cannot start {c.width}x{c.height} at {c.fps} Hz"
                              f"{' with preset ' + c.preset if c.preset else ''}: {exc}",
                              device=self.device) from None
        md = sensor.get_metadata()
        self.metadata = md
        self._K = np.asarray(md.intrinsics.intrinsic_matrix, dtype=np.float64)
        self._depth_scale = float(md.depth_scale)
        self._sensor = sensor

    def disconnect(self) -> None:
        with self._lock:
            if self._sensor is not None:
                self._sensor.stop_capture()
                self._sensor = None

    @property
    def is_connected(self) -> bool:
        return self._sensor is not None

    @property
    def model(self) -> SensorModel:
        c = self.config
        if self._K is None:
            raise DriverError("the field of view is known once connected (from the device's intrinsics)",
                              device=self.device)
        fov_x, fov_y = pinhole_fov_deg(self._K, c.width, c.height)
        return SensorModel(kind="rgbd", width=c.width, height=c.height, fov_x_deg=fov_x, fov_y_deg=fov_y,
                           range_min_m=c.range_min_m, range_max_m=c.range_max_m)

    def capture(self) -> DepthFrame:
        with self._lock:
            if self._sensor is None or self._K is None:
                raise DriverError("capture while disconnected; call connect() first", device=self.device)
            try:
                rgbd = self._sensor.capture_frame(True, True)
            except RuntimeError as exc:  # librealsense gives up waiting for frames after a few seconds
                raise DriverError(f"no frame: {exc}", device=self.device) from None
        raw = np.asarray(rgbd.depth.as_tensor().numpy()).reshape(rgbd.depth.rows, rgbd.depth.columns)
        if raw.size == 0:
            raise DriverError("the camera delivered no frame", device=self.device)
        c = self.config
        depth = depth_from_raw(raw, self._depth_scale, (c.range_min_m, c.range_max_m))
        frame = DepthFrame(seq=self._seq, timestamp=self._clock.now(), points=back_project(depth, self._K),
                           depth=depth, intrinsics=self._K)
        self._seq += 1
        return frame
