"""Where an object may be put: on the simulated table, whole, and only an object of a size the cell can
scan.

Sim and dry-run jobs place a virtual object at (x [m], y [m], yaw [deg]) relative to the station; its
footprint (the mesh's vertices turned by the yaw, projected on the table) must lie on the table of the
cell's ``sim`` section, or the object would float beside it and the scan would report nonsense.

Before that, the mesh's size must be plausible for the cell (:func:`check_object_size`): a CAD export in
millimetres loads as an object a thousand times too large, which no view sees whole, and whose scan ends
at 0 % coverage; the refusal says what a scale would make of it. A part too thin for segmentation to find
(:func:`thinnest_part_m`) is refused too: its scan could only end ``no_object``.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from cell.config.models import CellConfig
from drivers.errors import JobError
from drivers.sim.objects import Array

MIN_OBJECT_SIZE_M = 0.01
"""The smallest largest side [m] of an object a cell scans: below it an object covers a handful of the
2.5 mm map's voxels and at most one zone of an 8x8 ToF frame at the scan's distance, and the mesh is far
more likely in the wrong units than a part to pack."""

MAX_YAW_DEG = 360.0
"""The largest turn about the vertical [deg] a placement may give: every placement has one within it, and a
yaw of 1e308 deg is a finite number whose sine is rounding noise, not a turn of the part."""

UNIT_SCALES = ((0.001, "millimetres"), (0.01, "centimetres"), (0.0254, "inches"))
"""The scales that turn a CAD export's usual units into metres, the first one a refusal suggests."""


class Placed(Protocol):
    """What the checks read of an object: its ``name``, its bounding box's size ``extents_m`` (3,) [m] and
    ``vertices`` (V, 3) [m, object frame], of which only the footprint counts: a mesh's
    (``drivers.sim.objects.ObjectMesh``), or the few that span the same footprint at every yaw (an
    upload's outline, ``cell.service.objects.ObjectOutline``, which spares the service the mesh)."""

    @property
    def name(self) -> str: ...

    @property
    def extents_m(self) -> Array: ...

    @property
    def vertices(self) -> Array: ...


def _dims(extents: np.ndarray) -> str:
    """A bounding box's size (x, y, z), in metres, or in millimetres (3 significant digits) when its
    largest side is below ``MIN_OBJECT_SIZE_M``, where "0.000 x 0.000 x 0.000 m" would hide it."""
    if extents.max() >= MIN_OBJECT_SIZE_M:
        return " x ".join(f"{v:.3f}" for v in extents) + " m"
    return " x ".join(f"{v * 1000.0:.3g}" for v in extents) + " mm"


def thinnest_part_m(config: CellConfig) -> float:
    """The height [m] a part must exceed for segmentation to find it (``cell.perception.segmentation``):
    the object is the occupied voxels whose centres lie more than ``plane_distance_m`` above the table
    plane, and a top face at height h lands in a voxel whose centre may lie half a map voxel below it.
    A thinner part (a 5 mm plate in the RGB-D cell: 6 mm + 2.5 mm) is table to segmentation."""
    perception = config.perception
    return perception.segmentation.plane_distance_m + perception.occupancy.resolution_m / 2.0


def _plausible(config: CellConfig, extents: np.ndarray) -> bool:
    """Whether a bounding box (x, y, z) [m] could stand on the cell's table and under its workspace's top,
    with a largest side of at least ``MIN_OBJECT_SIZE_M`` and taller than :func:`thinnest_part_m`."""
    across = np.sort(extents[:2])[::-1]
    table = np.sort(np.asarray(config.sim.table_size_m))[::-1]
    height = config.safety.workspace.max_m[2] - config.station.table_z_m
    return bool(extents.max() >= MIN_OBJECT_SIZE_M and np.all(across <= table)
                and thinnest_part_m(config) < extents[2] <= height)


def check_object_size(config: CellConfig, mesh: Placed, scale: float = 1.0,
                      option: str = "--object-scale") -> None:
    """Raise ``JobError`` when ``mesh`` (loaded at ``scale``) is not a size the cell can scan: its size,
    the limits, and what ``option`` with a CAD unit's scale would make of it."""
    extents = mesh.extents_m
    if _plausible(config, extents):
        return
    table = np.asarray(config.sim.table_size_m)
    height = config.safety.workspace.max_m[2] - config.station.table_z_m
    text = (f"object {mesh.name} is {_dims(extents)} (x, y, z), not a size this cell scans: its largest side "
            f"at least {MIN_OBJECT_SIZE_M:g} m, at most the table's {table[0]:g} x {table[1]:g} m across, "
            f"taller than {thinnest_part_m(config) * 1000.0:g} mm (what segmentation tells from the table: "
            f"perception.segmentation.plane_distance_m and half a map voxel) and at most {height:g} m tall "
            "(the workspace's top)")
    if extents.max() < MIN_OBJECT_SIZE_M:
        raise JobError(f"{text}; if the mesh is not in metres, {option} converts it")
    fits = [(unit, name) for unit, name in UNIT_SCALES if _plausible(config, extents * unit)]
    if not fits:  # a scale is worth suggesting only when it makes a size the cell takes
        raise JobError(text)
    unit, name = fits[0]
    raise JobError(f"{text}; a mesh in {name}? {option} {scale * unit:g} would make it "
                   f"{_dims(extents * unit)}")


def footprint_bounds(config: CellConfig, mesh: Placed,
                     pose: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) (2,) [m] of the object's footprint in the base frame at ``pose`` from the station."""
    x, y, yaw_deg = pose
    c, s = np.cos(np.deg2rad(yaw_deg)), np.sin(np.deg2rad(yaw_deg))
    xy = mesh.vertices[:, :2] @ np.array([[c, s], [-s, c]]) + np.asarray(config.station.xy_m) + (x, y)
    return xy.min(axis=0), xy.max(axis=0)


def check_on_table(config: CellConfig, mesh: Placed, pose: tuple[float, float, float]) -> None:
    """Raise ``JobError`` naming the table's extent when the object's footprint at ``pose`` leaves it, or
    when the yaw is not within ``MAX_YAW_DEG``."""
    if not abs(pose[2]) <= MAX_YAW_DEG:
        raise JobError(f"object pose {list(pose)}: its yaw must lie within +-{MAX_YAW_DEG:g} deg")
    lo, hi = footprint_bounds(config, mesh, pose)
    centre, size = np.asarray(config.sim.table_center_xy_m), np.asarray(config.sim.table_size_m)
    t_lo, t_hi = centre - size / 2.0, centre + size / 2.0
    if np.all(lo >= t_lo - 1e-9) and np.all(hi <= t_hi + 1e-9):
        return
    raise JobError(f"object pose {list(pose)} puts {mesh.name} off the table: its footprint spans "
                   f"x {lo[0]:.3f}..{hi[0]:.3f} m, y {lo[1]:.3f}..{hi[1]:.3f} m (base frame); the table "
                   f"spans x {t_lo[0]:.3f}..{t_hi[0]:.3f} m, y {t_lo[1]:.3f}..{t_hi[1]:.3f} m")


def check_placement(config: CellConfig, mesh: Placed, pose: tuple[float, float, float],
                    scale: float = 1.0, option: str = "--object-scale") -> None:
    """Both checks, the size first (a mesh in the wrong units is also off the table, and its size is
    the better reason): ``JobError`` saying what is wrong."""
    check_object_size(config, mesh, scale, option)
    check_on_table(config, mesh, pose)
