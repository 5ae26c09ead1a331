"""Where an object may be put: on the simulated table, whole, and only an object of a size the cell can
scan.

Sim and dry-run jobs place a virtual object at (x [m], y [m], yaw [deg]) relative to the station; its
footprint (the mesh's vertices turned by the yaw, projected on the table) must lie on the table of the
cell's ``sim`` section, or the object would float beside it and the scan would report nonsense.

Before that, the mesh's size must be plausible for the cell (:func:`check_object_size`): a CAD export in
millimetres loads as an object a thousand times too large, which no view sees whole, and whose scan ends
at 0 % coverage; the refusal says what a scale would make of it. A part too thin for segmentation to find
(:func:`thinnest_part_m`) is refused too: its scan could only end ``no_object``; and so is one taller
than the room the cell's start views leave above the table (:func:`tallest_part_m`).

Then the placement itself must be safe and seen: an object the arm would stand in at its home joints (the
robot base included) is refused (:func:`check_clear_of_arm`: the arm would fault the moment it moved), and
so is one that none of the planner's search views looks at (:func:`check_in_view`: the scan could only
end ``no_object``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import NDArray

from cell.config.models import CellConfig
from cell.perception.cloud import crop_box
from drivers.errors import JobError
from drivers.robots import get_robot_model
from drivers.sim.objects import Array, ObjectMesh, sample_surface
from drivers.transforms import T_from_xyz_rpy, transform_points

if TYPE_CHECKING:  # FCL and the collision world (Open3D) load only to check: the service checks placements
    from cell.safety.collision import CollisionWorld

VIEW_CHECK_POINTS = 4096
"""Surface points [count] drawn (from a fixed seed: a placement's verdict never changes) to tell whether a
view sees an object: at the shipped objects' sizes a few millimetres apart, closer than the crop box's
edges need."""

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
    """The height [m] a part must exceed for segmentation to be able to find it
    (``cell.perception.segmentation``): the object is the occupied voxels whose centres lie more than
    ``plane_distance_m`` above the table plane, and a top face at height h lies in a voxel whose centre is
    at most half a map voxel above it. A part no taller (3.5 mm on the RGB-D cell: 6 mm less 2.5 mm) is
    table to segmentation. Up to ``plane_distance_m`` plus half a voxel (8.5 mm) a part is found only
    where the map's voxel layers put its top's voxel centre above the cut: the RGB-D cell's table lies on
    a voxel boundary, a top above 5 mm is found, and a 5 mm plate, at the boundary, was not."""
    perception = config.perception
    return perception.segmentation.plane_distance_m - perception.occupancy.resolution_m / 2.0


def tallest_part_m(config: CellConfig) -> float:
    """The tallest part [m] the cell takes: below the workspace's top, and below the servo scans' start
    view from above (``cell.planning.vs.servo_scan.start_views``: ``scan.standoff_m`` over the start target
    ``planners.vs.start.target_height_m``) by the crop box's near side (``perception.crop_box.z_m[0]``),
    nearer than which the sensor's points are dropped: a taller part reaches where the cell's sensor
    looks from, and the arm's first move towards that view runs the camera into it (a 1 m post did)."""
    start_view = config.planners.vs.start.target_height_m + config.scan.standoff_m
    workspace_top = config.safety.workspace.max_m[2] - config.station.table_z_m
    return min(workspace_top, start_view - config.perception.crop_box.z_m[0])


def _plausible(config: CellConfig, extents: np.ndarray) -> bool:
    """Whether a bounding box (x, y, z) [m] could stand on the cell's table, with a largest side of at
    least ``MIN_OBJECT_SIZE_M``, taller than :func:`thinnest_part_m` and at most :func:`tallest_part_m`."""
    across = np.sort(extents[:2])[::-1]
    table = np.sort(np.asarray(config.sim.table_size_m))[::-1]
    return bool(extents.max() >= MIN_OBJECT_SIZE_M and np.all(across <= table)
                and thinnest_part_m(config) < extents[2] <= tallest_part_m(config))


def check_object_size(config: CellConfig, mesh: Placed, scale: float = 1.0,
                      option: str = "--object-scale") -> None:
    """Raise ``JobError`` when ``mesh`` (loaded at ``scale``) is not a size the cell can scan: its size,
    the limits, and what ``option`` with a CAD unit's scale would make of it."""
    extents = mesh.extents_m
    if _plausible(config, extents):
        return
    table = np.asarray(config.sim.table_size_m)
    text = (f"object {mesh.name} is {_dims(extents)} (x, y, z), not a size this cell scans: its largest side "
            f"at least {MIN_OBJECT_SIZE_M:g} m, at most the table's {table[0]:g} x {table[1]:g} m across, "
            f"taller than {thinnest_part_m(config) * 1000.0:g} mm (what segmentation can tell from the "
            "table: perception.segmentation.plane_distance_m less half a map voxel) and at most "
            f"{tallest_part_m(config):.3f} m tall (the start view from above, scan.standoff_m over "
            "planners.vs.start.target_height_m, less perception.crop_box.z_m[0], within the workspace's top)")
    if extents.max() < MIN_OBJECT_SIZE_M:
        raise JobError(f"{text}; if the mesh is not in metres, {option} converts it")
    fits = [(unit, name) for unit, name in UNIT_SCALES if _plausible(config, extents * unit)]
    if not fits:  # a scale is worth suggesting only when it makes a size the cell takes
        raise JobError(text)
    unit, name = fits[0]
    raise JobError(f"{text}; a mesh in {name}? {option} {scale * unit:g} would make it "
                   f"{_dims(extents * unit)}")


def object_pose_in_base(config: CellConfig, pose: tuple[float, float, float]) -> NDArray[np.float64]:
    """T_base_object for an object at (x, y, yaw_deg) relative to the station, resting on the table."""
    x, y, yaw_deg = pose
    st = config.station
    return T_from_xyz_rpy([st.xy_m[0] + x, st.xy_m[1] + y, st.table_z_m], [0.0, 0.0, np.deg2rad(yaw_deg)])


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


def check_clear_of_arm(config: CellConfig, mesh: ObjectMesh, pose: tuple[float, float, float],
                       world: CollisionWorld | None = None) -> None:
    """Raise ``JobError`` naming the body when the object at ``pose`` intersects the arm standing at its
    home joints (``arm.home_joints_rad``, else the robot model's home): its links' capsules, the robot base
    (``link0``) included, and the cell file's tool bodies, as the guard and the simulated arm's contact
    check them (``world.arm_bodies``, ``world`` the cell's, ``CollisionWorld.for_cell``, built here when
    None). Such a job's arm
    faulted on its first tick. A body wholly inside the object, crossing none of its triangles, is not
    found (FCL tests the mesh's surface); the bodies are 4 cm and more across, and an object that large
    around the arm crosses another one."""
    import fcl

    from cell.safety.collision import CollisionWorld
    from drivers.fcl_bodies import fcl_transform, mesh_bvh

    if world is None:
        world = CollisionWorld.for_cell(config)
    model = get_robot_model(config.arm.model)
    frames = model.fk_all(model.home(config.arm.home_joints_rad))
    T = object_pose_in_base(config, pose)
    placed = fcl.CollisionObject(mesh_bvh(transform_points(T, mesh.vertices), mesh.triangles))
    for body in world.arm_bodies():
        part = fcl.CollisionObject(body.geometry, fcl_transform(frames[body.frame] @ body.T_frame_body))
        if fcl.collide(part, placed, fcl.CollisionRequest(), fcl.CollisionResult()):
            what = "the robot base (link0)" if body.frame == 0 else f"the arm's {body.name}"
            raise JobError(f"object pose {list(pose)} puts {mesh.name} into {what} at the arm's home joints: "
                           "place it further from the robot")


def where_views_look(config: CellConfig) -> str:
    """Where the cell's views look, in words: at the station, each keeping what lies in its crop box."""
    st, crop = config.station.xy_m, config.perception.crop_box
    return (f"the station ({st[0]:g}, {st[1]:g}) m, each view keeping its crop box (perception.crop_box: x "
            f"{crop.x_m[0]:g}..{crop.x_m[1]:g} m, y {crop.y_m[0]:g}..{crop.y_m[1]:g} m across its axis, "
            f"{crop.z_m[0]:g}..{crop.z_m[1]:g} m along it)")


def _seen(config: CellConfig, views: list[NDArray[np.float64]], points_base: NDArray[np.float64]) -> bool:
    """Whether a view of ``views`` (T_base_sensor) has one of ``points_base`` (N, 3) [m] in its crop box."""
    crop = config.perception.crop_box
    return any(crop_box((points_base - T_view[:3, 3]) @ T_view[:3, :3], crop.x_m, crop.y_m, crop.z_m).shape[0]
               for T_view in views)


def view_points(mesh: ObjectMesh) -> Array:
    """The points (``VIEW_CHECK_POINTS``, 3) [m, object frame] on ``mesh``'s whole surface that
    :func:`check_in_view` tests, from a fixed seed: the same for the same mesh, wherever it is worked out
    (the service keeps an upload's, ``cell.service.objects.ObjectOutline.surface``)."""
    return sample_surface(mesh, VIEW_CHECK_POINTS, np.random.default_rng(0), exclude_down_deg=-1.0)


def check_in_view(config: CellConfig, shape: Placed, surface: Array, pose: tuple[float, float, float],
                  views: list[NDArray[np.float64]], planner: str) -> None:
    """Raise ``JobError`` when none of ``views`` (``planner``'s search views, T_base_sensor) has a point of
    the object ``shape`` at ``pose``, of its ``surface`` points (:func:`view_points`), inside its crop box
    (``perception.crop_box``, sensor frame: what perception keeps of a frame), so that its scan could only
    end ``no_object``. Occlusion and the sensor's field of view are not counted: a view that might see it
    is enough. Nothing is refused without views, nor when none of them sees the station on the table
    either: then the cell file is what is wrong (its mount, standoff), not the placement, and the scan
    fails saying what to check."""
    T = object_pose_in_base(config, pose)
    station = object_pose_in_base(config, (0.0, 0.0, 0.0))[:3, 3]
    if _seen(config, views, transform_points(T, surface)) or not _seen(config, views, station[None]):
        return
    lo_xy, hi_xy = footprint_bounds(config, shape, pose)
    raise JobError(f"object pose {list(pose)} puts {shape.name} (footprint x {lo_xy[0]:.3f}..{hi_xy[0]:.3f} "
                   f"m, y {lo_xy[1]:.3f}..{hi_xy[1]:.3f} m, base frame) where none of the {len(views)} views "
                   f"{planner} looks for an object from sees it: they look at {where_views_look(config)}; "
                   "place it nearer the station")


def check_placement(config: CellConfig, mesh: ObjectMesh, pose: tuple[float, float, float],
                    scale: float = 1.0, option: str = "--object-scale", world: CollisionWorld | None = None,
                    ) -> None:
    """The checks of a placement that need no planner, the size first (a mesh in the wrong units is
    also off the table, and its size is the better reason), then on the table, then clear of the arm in
    ``world`` (the cell's, ``CollisionWorld.for_cell``, built here when None): ``JobError`` saying what
    is wrong."""
    check_object_size(config, mesh, scale, option)
    check_on_table(config, mesh, pose)
    check_clear_of_arm(config, mesh, pose, world)
