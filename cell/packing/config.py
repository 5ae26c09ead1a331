"""Configuration of the packing result: the container catalogue and the clearance kept around the object."""

from __future__ import annotations

from pydantic import Field, PositiveFloat, model_validator

from drivers.config_base import StrictModel


class ContainerConfig(StrictModel):
    """One container of the catalogue: ``name`` and ``inner_dims_m`` (L, W, H) [m], its inside lengths."""

    name: str = Field(min_length=1)
    inner_dims_m: tuple[PositiveFloat, PositiveFloat, PositiveFloat]


class PackingConfig(StrictModel):
    """The packing result (LR-NBV paper, section 4.1).

    ``containers`` the catalogue to choose from (empty: no container is ever proposed); ``margin_m`` [m]
    the clearance kept between the object's box and the container's walls on every side in the table
    plane and above the object (the object stands on the container floor); ``coverage_radius_m`` [m] a
    ground-truth surface sample counts as reconstructed when an object voxel centre lies this close (None:
    the occupancy map's resolution, so that a surface point anywhere in an occupied voxel of a thin shell
    is found by the voxel or its neighbour); ``trim_fraction`` the share of object voxels each face of the
    box may leave outside (noise on the segmented shell, see ``cell.packing.box.box_from_points``).
    """

    containers: list[ContainerConfig] = Field(default_factory=list)
    margin_m: float = Field(default=0.01, ge=0.0)
    coverage_radius_m: PositiveFloat | None = None
    trim_fraction: float = Field(default=0.02, ge=0.0, lt=0.5)

    @model_validator(mode="after")
    def _unique_names(self) -> PackingConfig:
        names = [c.name for c in self.containers]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"container names must be unique; repeated: {', '.join(duplicates)}")
        return self
