"""Configuration of each depth-sensor backend, selected by ``type:`` (a pydantic discriminated union)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, PositiveFloat, PositiveInt, field_validator, model_validator

from drivers.config_base import Bounds, StrictModel
from drivers.depth.vl53l8cx.protocol import MAX_FREQUENCY_HZ

SENSOR_RANGE_MAX_M = 10.0
"""The farthest [m] the cell's depth sensors measure, and so the largest range and crop box coordinate a
cell file may give: the VL53L8CX ranges to 4 m, a RealSense D400 to about 10 m; 4000 (millimetres written
in a metres field) is refused."""

SensorRange = Annotated[float, Bounds(0.001, SENSOR_RANGE_MAX_M, "m", "a depth sensor measures from a "
                                      f"millimetre to {SENSOR_RANGE_MAX_M:g} m")]
"""[m] a distance from the sensor along its optical axis (:data:`SENSOR_RANGE_MAX_M`)."""

SensorCoordinate = Annotated[float, Bounds(-SENSOR_RANGE_MAX_M, SENSOR_RANGE_MAX_M, "m", "a depth sensor "
                                           f"measures within {SENSOR_RANGE_MAX_M:g} m")]
"""[m] one coordinate of a place in the sensor frame (:data:`SENSOR_RANGE_MAX_M`)."""

TOF_FOV_DEG = (10.0, 65.0)
"""The square field of view [deg] a multizone time-of-flight sensor may have: 45 deg for the VL53L5CX and
the VL53L8CX, 60 deg for the VL53L7CX; narrower than 10 deg, its zones would be finer than any of them
(and 0.785 is 45 deg written in radians)."""

ToFFieldOfView = Annotated[float, Bounds(*TOF_FOV_DEG, "deg", "a multizone ToF sensor's square field of view "
                                         "(VL53L5CX, VL53L8CX 45 deg, VL53L7CX 60 deg)")]
"""[deg] the square field of view of a multizone ToF sensor (:data:`TOF_FOV_DEG`)."""


class RangedConfig(StrictModel):
    """A sensor that reports returns between ``range_min_m`` and ``range_max_m`` [m]."""

    range_min_m: SensorRange
    range_max_m: SensorRange

    @model_validator(mode="after")
    def _range_ordered(self) -> RangedConfig:
        if self.range_min_m >= self.range_max_m:
            raise ValueError(f"range_min_m {self.range_min_m} must be below range_max_m {self.range_max_m}")
        return self


class DepthNoiseConfig(StrictModel):
    """Axial depth noise, a Gaussian whose standard deviation grows with distance z [m]:
    sigma(z) = sigma0_m + k_per_m * z**2."""

    sigma0_m: float = Field(ge=0.0, le=0.05)
    k_per_m: float = Field(ge=0.0, le=0.1)


class SimRGBDConfig(RangedConfig):
    """A simulated RGB-D depth camera rendered by ray casting (pinhole model).

    Grazing returns, whose incidence angle to the surface normal exceeds ``grazing_deg``, are dropped;
    between ``grazing_deg - 15`` and ``grazing_deg`` they are dropped with a probability rising linearly.
    """

    type: Literal["sim-rgbd"]
    width: PositiveInt = 640
    """[px] the image's width."""
    height: PositiveInt = 480
    """[px] the image's height."""
    fx: PositiveFloat
    """[px] the focal length along x."""
    fy: PositiveFloat
    """[px] the focal length along y."""
    cx: float
    """[px] the principal point's x."""
    cy: float
    """[px] the principal point's y."""
    noise: DepthNoiseConfig
    grazing_deg: float = Field(default=80.0, gt=15.0, le=90.0)


class ZoneBiasConfig(StrictModel):
    """The simulated ToF sensor's own range error: each zone's distance is off by a constant offset drawn
    once from N(0, ``offset_std_m``^2) [m] by a generator of its own seeded with ``seed`` (a property of
    the device, the same in every job, and no draw from the job's generator)."""

    offset_std_m: float = Field(ge=0.0, le=0.05)
    seed: int = Field(default=0, ge=0)


class SimToFConfig(RangedConfig):
    """A simulated multizone time-of-flight sensor (VL53L8CX-like): ``resolution`` x ``resolution`` zones
    over a square ``fov_deg`` field of view, each zone rendered from ``subrays`` x ``subrays`` rays.
    A zone whose sorted sub-ray ranges jump by more than ``edge_gap_m`` [m] spans a depth edge and gets
    status 9 (merged target). ``zone_bias``: the device's per-zone range bias (None: none);
    ``zone_correction``: a per-zone correction file to apply, as the ``vl53l8cx`` backend does."""

    type: Literal["sim-tof"]
    resolution: Literal[4, 8] = 8
    fov_deg: ToFFieldOfView = 45.0
    subrays: PositiveInt = 4
    range_min_m: SensorRange = 0.02
    range_max_m: SensorRange = 4.0
    noise: DepthNoiseConfig
    min_hit_fraction: float = Field(default=0.25, gt=0.0, le=1.0)
    """[1] the share of a zone's sub-rays that must hit for the zone to have a target."""
    edge_gap_m: SensorRange = 0.025
    zone_bias: ZoneBiasConfig | None = None
    zone_correction: str | None = None


VL53L8CX_VALID_STATUSES: tuple[int, ...] = (5, 9)
"""ST's target statuses of a fully trusted range: 5 (range valid) and 9 (range valid, large pulse)."""


class VL53L8CXI2CConfig(StrictModel):
    """The sensor on a Linux I2C bus through Blinka: ``bus`` the /dev/i2c-N number, ``address`` the 7-bit
    address (0x29 is ST's 0x52 write address), ``lpn_pin`` the Blinka ``board`` pin name wired to LPn (it
    resets the sensor at connect) or None."""

    bus: int = Field(default=1, ge=0)
    address: int = Field(default=0x29, ge=0x08, le=0x77)
    lpn_pin: str | None = None


class VL53L8CXConfig(RangedConfig):
    """A VL53L8CX multizone time-of-flight sensor, reached either through a bridge board speaking the frame
    format of ``docs/vl53l8cx-serial.md`` (``port``: any pyserial URL, a device path, ``socket://host:port``
    or ``loop://``) or directly on a Linux I2C bus (``i2c``); exactly one of the two.

    ``resolution`` zones per side and ``frequency_hz`` [Hz] are sent to the sensor (at most 15 Hz at 8x8,
    60 Hz at 4x4); ``fov_deg`` [deg] the square field of view the zones tile (45 for the VL53L8CX).
    A zone becomes a point when it has a target and its status is in ``valid_statuses``.
    ``timeout_s`` [s]: a link that delivers no frame for this long is faulted (silent or gone); it must
    cover at least two frame periods. ``baudrate`` only matters for a real UART (USB CDC ignores it).
    ``zone_correction``: a per-zone range correction file written by ``cell calibrate tof``
    (``drivers.depth.zone_correction``), applied to every frame; None: distances as the sensor reports.
    Loaded from a cell file, a relative path is taken from the file's folder (``cell.config.load``).
    """

    type: Literal["vl53l8cx"]
    port: str | None = None
    baudrate: PositiveInt = 921600
    """[bit/s] the UART's rate (a USB CDC port ignores it)."""
    i2c: VL53L8CXI2CConfig | None = None
    resolution: Literal[4, 8] = 8
    frequency_hz: int = Field(default=15, ge=1, le=60)
    fov_deg: ToFFieldOfView = 45.0
    valid_statuses: tuple[int, ...] = Field(default=VL53L8CX_VALID_STATUSES, min_length=1)
    range_min_m: SensorRange = 0.02
    range_max_m: SensorRange = 4.0
    timeout_s: PositiveFloat = 1.0
    zone_correction: str | None = None

    @field_validator("port")
    @classmethod
    def _named(cls, port: str | None) -> str | None:
        # an empty port passed every check and failed the scan, its job folder already made
        if port is not None and not port.strip():
            raise ValueError("the port is empty: give the bridge board's device (e.g. /dev/vl53l8cx) or a "
                             "pyserial URL")
        return port

    @model_validator(mode="after")
    def _consistent(self) -> VL53L8CXConfig:
        if (self.port is None) == (self.i2c is None):
            raise ValueError("give exactly one of port (a bridge board) and i2c (a Linux I2C bus)")
        limit = MAX_FREQUENCY_HZ[self.resolution]
        if self.frequency_hz > limit:
            raise ValueError(f"frequency_hz {self.frequency_hz} is above the sensor's {limit} Hz at "
                             f"{self.resolution}x{self.resolution}")
        if self.timeout_s < 2.0 / self.frequency_hz:
            raise ValueError(f"timeout_s {self.timeout_s} must cover two frame periods "
                             f"({2.0 / self.frequency_hz:.3f} s at {self.frequency_hz} Hz)")
        if any(not 0 <= s <= 255 for s in self.valid_statuses):
            raise ValueError(f"valid_statuses must be target status codes 0..255, got {self.valid_statuses}")
        return self


class RealSenseConfig(RangedConfig):
    """An Intel RealSense camera through Open3D's RealSense support (``open3d.t.io.RealSenseSensor``).

    ``serial`` picks a camera (empty: the first one found); ``width`` x ``height`` [px] and ``fps`` [Hz]
    of the depth stream; ``preset`` a librealsense visual preset name (e.g. ``RS2_RS400_VISUAL_PRESET_
    HIGH_ACCURACY``) or empty for the camera's default; ``record_bag`` a ``.bag`` file to record the
    session into, or empty. Depth outside [``range_min_m``, ``range_max_m``] [m] counts as no return.
    Intrinsics and depth scale come from the device's metadata, not from here.
    """

    type: Literal["realsense"]
    serial: str = ""
    width: PositiveInt = 640
    """[px] the depth stream's width."""
    height: PositiveInt = 480
    """[px] the depth stream's height."""
    fps: PositiveInt = 30
    """[Hz] the depth stream's frame rate."""
    preset: str = ""
    record_bag: str = ""
    range_min_m: SensorRange = 0.1
    range_max_m: SensorRange = 2.0


class ReplayConfig(RangedConfig):
    """The frames of a recorded job folder (``job_dir``), played back as a sensor on the job's clock.
    ``range_min_m`` / ``range_max_m`` [m]: the recorded sensor's range, which the folder does not hold
    (perception carves free space up to the maximum along ToF zones without a target)."""

    type: Literal["replay"]
    job_dir: str
    range_min_m: SensorRange = 0.02
    range_max_m: SensorRange = 4.0


DepthConfig = Annotated[
    SimRGBDConfig | SimToFConfig | VL53L8CXConfig | RealSenseConfig | ReplayConfig,
    Field(discriminator="type"),
]
