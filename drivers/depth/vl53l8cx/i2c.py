"""``vl53l8cx`` on a Linux I2C bus (``sensor.i2c`` in the config): the CircuitPython VL53L8CX driver
(``circuitpython-vl53lxcx``, ST's ULD ported to Python) on Adafruit Blinka, with ``adafruit-extended-bus``
to open /dev/i2c-N by number. All of them are an optional extra, imported when connecting:
``pip install 'cell[i2c]'``.

``connect`` resets the sensor through LPn when ``lpn_pin`` is given, checks its identity, uploads its
firmware (the library's ``init``, several seconds over I2C), sets resolution and ranging frequency and
starts ranging with distance, sigma, status, reflectance and target count. ``capture`` polls for a new
measurement for up to ``timeout_s``.

Units as ST's ULD reports them: the library returns the raw register values, so distance is already in
mm, sigma in mm (a float, raw / 128), reflectance raw / 2 in percent. ST's zone order is mirrored left to
right relative to the scene (as the bridge firmware also corrects): :func:`uld_to_sensor_order` puts the
zones row-major from the top-left as seen in the sensor frame, as the serial backend receives them.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.clock import Clock, WallClock
from drivers.depth.base import DepthFrame, DepthSensor, SensorModel
from drivers.depth.config import VL53L8CXConfig
from drivers.depth.vl53l8cx.frames import configured_correction, depth_frame, sensor_model
from drivers.depth.vl53l8cx.protocol import RangingFrame
from drivers.errors import DriverError

INSTALL_HINT = ("the I2C backend needs circuitpython-vl53lxcx, adafruit-blinka and adafruit-extended-bus; "
                "install them with: pip install 'cell[i2c]'")
POLL_S = 0.002


def uld_to_sensor_order(values: NDArray[Any], resolution: int) -> NDArray[Any]:
    """Per-zone values from ST's ULD order (each row mirrored) to row-major sensor-frame order."""
    return np.asarray(values).reshape(resolution, resolution)[:, ::-1].reshape(-1)


def _import_libraries() -> tuple[Any, Any, Any, Any]:
    """``board``, ``digitalio``, ``adafruit_extended_bus`` and ``vl53lxcx``, or a ``DriverError`` with the
    install hint."""
    try:
        import adafruit_extended_bus
        import board
        import digitalio
        import vl53lxcx
    except (ImportError, NotImplementedError, RuntimeError) as exc:  # Blinka refuses unknown boards
        raise DriverError(f"{INSTALL_HINT} ({type(exc).__name__}: {exc})",
                          device="depth vl53l8cx i2c") from None
    return board, digitalio, adafruit_extended_bus, vl53lxcx


class VL53L8CXI2C(DepthSensor):
    """A VL53L8CX on a Linux I2C bus (see the module docstring)."""

    name = "vl53l8cx"

    def __init__(self, config: VL53L8CXConfig, clock: Clock | None = None) -> None:
        if config.i2c is None:
            raise DriverError("the I2C backend needs sensor.i2c", device="depth vl53l8cx i2c")
        self.config = config
        self.i2c = config.i2c
        self._correction = configured_correction(config)
        self._clock = clock if clock is not None else WallClock()
        self._tof: Any = None
        self._seq = 0

    @property
    def device(self) -> str:
        return f"depth vl53l8cx on /dev/i2c-{self.i2c.bus} at 0x{self.i2c.address:02x}"

    def connect(self) -> None:
        board, digitalio, extended_bus, vl = _import_libraries()
        c = self.config
        try:
            bus = extended_bus.ExtendedI2C(self.i2c.bus)
            lpn = None
            if self.i2c.lpn_pin is not None:
                lpn = digitalio.DigitalInOut(getattr(board, self.i2c.lpn_pin))
                lpn.direction = digitalio.Direction.OUTPUT
                lpn.value = True
            tof = vl.VL53L8CX(bus, addr=self.i2c.address, lpn=lpn)
            if lpn is not None:
                tof.reset()
            if tof.is_alive() != vl.VL53L8CX_ID:
                raise DriverError("no VL53L8CX answers at this address", device=self.device)
            tof.init()
            tof.resolution = vl.RESOLUTION_8X8 if c.resolution == 8 else vl.RESOLUTION_4X4
            tof.ranging_freq = c.frequency_hz
            started = tof.start_ranging({vl.DATA_DISTANCE_MM, vl.DATA_RANGE_SIGMA_MM, vl.DATA_TARGET_STATUS,
                                         vl.DATA_REFLECTANCE, vl.DATA_NB_TARGET_DETECTED})
        except (OSError, ValueError, AttributeError) as exc:
            raise DriverError(f"cannot set the sensor up: {exc}", device=self.device) from None
        if not started:
            raise DriverError("the sensor refused to start ranging", device=self.device)
        self._tof = tof

    def disconnect(self) -> None:
        if self._tof is not None:
            tof, self._tof = self._tof, None
            with contextlib.suppress(OSError):  # a bus that is gone has nothing left to stop
                tof.stop_ranging()

    @property
    def is_connected(self) -> bool:
        return self._tof is not None

    @property
    def model(self) -> SensorModel:
        return sensor_model(self.config)

    def capture(self) -> DepthFrame:
        if self._tof is None:
            raise DriverError("capture while disconnected; call connect() first", device=self.device)
        c = self.config
        deadline = time.monotonic() + c.timeout_s
        try:
            while not self._tof.check_data_ready():
                if time.monotonic() > deadline:
                    raise DriverError(f"no measurement for {c.timeout_s:g} s", device=self.device)
                time.sleep(POLL_S)
            r = self._tof.get_ranging_data()
        except OSError as exc:
            raise DriverError(f"I2C error: {exc}", device=self.device) from None
        res = c.resolution

        def zones(values: Any, dtype: type) -> NDArray[Any]:
            return uld_to_sensor_order(np.asarray(values)[:res * res], res).astype(dtype)

        raw = RangingFrame(seq=self._seq, timestamp_us=int(time.monotonic() * 1e6), resolution=res,
                           distance_mm=zones(np.clip(r.distance_mm, -32768, 32767), np.int16),
                           range_sigma_mm=zones(np.rint(r.range_sigma_mm), np.uint16),
                           target_status=zones(r.target_status, np.uint8),
                           reflectance_pct=zones(np.asarray(r.reflectance) // 2, np.uint8),
                           nb_target_detected=zones(r.nb_target_detected, np.uint8))
        frame = depth_frame(raw, seq=self._seq, timestamp=self._clock.now(), fov_deg=c.fov_deg,
                            valid_statuses=c.valid_statuses, correction=self._correction)
        self._seq += 1
        return frame
