"""Configuration of each depth-sensor backend, selected by ``type:`` (a pydantic discriminated union)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, PositiveFloat, PositiveInt, model_validator

from drivers.config_base import StrictModel


class RangedConfig(StrictModel):
    """A sensor that reports returns between ``range_min_m`` and ``range_max_m`` [m]."""

    range_min_m: PositiveFloat
    range_max_m: PositiveFloat

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
    height: PositiveInt = 480
    fx: PositiveFloat
    fy: PositiveFloat
    cx: float
    cy: float
    noise: DepthNoiseConfig
    grazing_deg: float = Field(default=80.0, gt=15.0, le=90.0)


class SimToFConfig(RangedConfig):
    """A simulated multizone time-of-flight sensor (VL53L8CX-like): ``resolution`` x ``resolution`` zones
    over a square ``fov_deg`` field of view, each zone rendered from ``subrays`` x ``subrays`` rays.
    A zone whose sorted sub-ray ranges jump by more than ``edge_gap_m`` [m] spans a depth edge and gets
    status 9 (merged target)."""

    type: Literal["sim-tof"]
    resolution: Literal[4, 8] = 8
    fov_deg: float = Field(default=45.0, gt=0.0, lt=90.0)
    subrays: PositiveInt = 4
    range_min_m: PositiveFloat = 0.02
    range_max_m: PositiveFloat = 4.0
    noise: DepthNoiseConfig
    min_hit_fraction: float = Field(default=0.25, gt=0.0, le=1.0)
    edge_gap_m: PositiveFloat = 0.025


class VL53L8CXConfig(StrictModel):
    """A VL53L8CX behind a bridge board; ``port`` is a pyserial URL (device path, ``socket://``, ...)."""

    type: Literal["vl53l8cx"]
    port: str
    resolution: Literal[4, 8] = 8
    frequency_hz: PositiveFloat = 15.0
    fov_deg: float = 45.0


class RealSenseConfig(StrictModel):
    """An Intel RealSense camera through Open3D's RealSense support."""

    type: Literal["realsense"]
    serial: str = ""
    width: PositiveInt = 640
    height: PositiveInt = 480
    fps: PositiveInt = 30


class ReplayConfig(StrictModel):
    """The frames of a recorded job, played back as a sensor."""

    type: Literal["replay"]
    job_dir: str


DepthConfig = Annotated[
    SimRGBDConfig | SimToFConfig | VL53L8CXConfig | RealSenseConfig | ReplayConfig,
    Field(discriminator="type"),
]
