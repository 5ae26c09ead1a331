"""Configuration of the packing result: the container catalogue and the clearance kept around the object."""

from __future__ import annotations

from pydantic import Field, PositiveFloat, model_validator

from drivers.config_base import CellDistance, CellSize, StrictModel
from drivers.depth.config import DepthNoiseConfig


class ContainerConfig(StrictModel):
    """One container of the catalogue: ``name`` and ``inner_dims_m`` (L, W, H) [m], its inside lengths."""

    name: str = Field(min_length=1)
    inner_dims_m: tuple[CellSize, CellSize, CellSize]


class BoxUncertaintyConfig(StrictModel):
    """What the packing box's upper bound (``cell.packing.uncertainty``) takes from outside the scan.

    ``range_noise`` sigma(r) = sigma0_m + k_per_m r^2 [m] of a range (None: the sensor's own noise model,
    ``sensor.noise``, for the sim sensors; for a real sensor, which has none in its config, the sim
    VL53L8CX's 4 mm + 0.01 r^2, the spread ``cell calibrate tof`` measures on a calibrated device);
    ``range_bias_m`` [m] the standard deviation of the range offset left after ``cell calibrate tof``
    (common to the zones: 2 mm, the size the sim cell draws, ``drivers.sim.errors``); ``pose_translation_m``
    [m] and ``pose_rotation_rad`` [rad] the standard deviations of the sensor pose the job believes
    against the true one along any one axis: the ToF shape calibration's hand-eye residual, 1.5 mm and
    0.15 deg per axis, and a calibrated arm's kinematics, about 0.4 mm at the flange
    (``drivers.sim.errors`` gives the sources), rounded up to 2 mm and 3.5 mrad (0.2 deg)
    by default; ``capture_pose_translation_m`` [m] and ``capture_pose_rotation_rad`` [rad] the part of
    that error that differs from capture to capture (the arm's: its joints' zero offsets move the flange
    differently in every configuration; the mount's error is the same in all), per axis: a calibrated
    arm's 0.4 mm at the flange, and its six joints' 0.2 mrad offsets, sqrt 6 x 0.2 = 0.5 mrad, by default
    (the table correction's per-capture term, ``cell.packing.table_calibration``); ``coverage_factor``
    the multiple of the combined standard deviation of those Gaussian terms that the bound adds (2: 97.7 %
    one-sided for each face)."""

    range_noise: DepthNoiseConfig | None = None
    range_bias_m: float = Field(default=0.002, ge=0.0, le=0.05)
    pose_translation_m: float = Field(default=0.002, ge=0.0, le=0.05)
    pose_rotation_rad: float = Field(default=0.0035, ge=0.0, le=0.1)
    capture_pose_translation_m: float = Field(default=0.0004, ge=0.0, le=0.05)
    capture_pose_rotation_rad: float = Field(default=0.0005, ge=0.0, le=0.1)
    coverage_factor: PositiveFloat = 2.0
    """[1] the multiple of the combined standard deviation that the upper bound adds."""


class PackingConfig(StrictModel):
    """The packing result (LR-NBV paper, section 4.1).

    ``containers`` the catalogue to choose from (empty: no container is ever proposed); ``margin_m`` [m]
    the clearance kept between the object's box and the container's walls on every side in the table
    plane and above the object (the object stands on the container floor); ``coverage_radius_m`` [m] a
    ground-truth surface sample counts as reconstructed when an object voxel centre lies this close (None:
    the occupancy map's resolution, so that a surface point anywhere in an occupied voxel of a thin shell
    is found by the voxel or its neighbour); ``trim_fraction`` the share of object voxels each face of the
    box may leave outside (noise on the segmented shell, see ``cell.packing.box.box_from_points``);
    ``uncertainty`` the error model of the box's upper bound (:class:`BoxUncertaintyConfig`), on which
    the container is chosen.
    """

    containers: list[ContainerConfig] = Field(default_factory=list)
    margin_m: CellDistance = 0.01
    coverage_radius_m: CellSize | None = None
    trim_fraction: float = Field(default=0.02, ge=0.0, lt=0.5)
    """[1] the share of object voxels each face of the box may leave outside."""
    uncertainty: BoxUncertaintyConfig = BoxUncertaintyConfig()

    @model_validator(mode="after")
    def _unique_names(self) -> PackingConfig:
        names = [c.name for c in self.containers]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"container names must be unique; repeated: {', '.join(duplicates)}")
        return self
