"""The collision world, checked with python-fcl (safety issue, item 2).

Bodies:

- the robot's links: the capsules of its kinematic model (``drivers.robots``), posed by forward kinematics;
- the tool: bodies carried by the flange (the sensor and its bracket), from ``safety.collision.tool``;
- the table: a slab whose top is the station's table height raised by its ``clearance_m``;
- the object's ROI: its axis-aligned box inflated by ``roi_margin_m``, replaced whenever perception
  updates the ROI; on a face whose margin would reach the arm where it stands, the margin is shrunk
  (:meth:`CollisionWorld.set_roi`);
- static obstacles from ``safety.collision.obstacles`` (boxes, cylinders, meshes);
- what the sensor has seen standing on the table outside the object's ROI (``perception.seen_obstacles``),
  replaced whenever perception updates it: the cells as meshes, one per 16 cm block, without the cells
  the arm stands in (:meth:`CollisionWorld.set_seen`).

A configuration collides when a moving body (link or tool) touches the table, the ROI or an obstacle (seen
or configured), or
when two moving bodies that are not adjacent touch (self-collision). Adjacent pairs are the robot model's
(capsules of consecutive frames touch by construction) plus the tool with the flange's own capsules. The
links on the base and the first joint's frames stand on the table and are not checked against it.

A cheap bounding-sphere test in numpy selects the candidate pairs; FCL decides each candidate exactly.
Two link capsules whose distance only one joint changes, and that stay apart over that joint's whole range,
can never touch: they are not checked at all (:meth:`CollisionWorld._never_touching`).

A joint path (:meth:`CollisionWorld.check_path`) is checked continuously, not only at its samples: as the
joints move, every point of a body moves at most a bound derived from the robot model's geometry
(:meth:`CollisionWorld.sweep_bound`). Each pair keeps a lower bound on its distance where it was last
measured (FCL's distance, or its bounding spheres' gap) and is measured again only when that bound, less
how far the pair can have come closer since, no longer clears it (conservative advancement); a stretch
whose distances at both ends do not add up to more than the pair's bound over it is bisected.

The guard checks the arm's way ahead every control period (:meth:`CollisionWorld.check_motion`); those
paths start a fraction of a millimetre apart, and the distances are kept from one tick to the next: most
ticks need no FCL call at all.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import fcl
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from cell.perception.seen_obstacles import SeenCells
from cell.safety.config import Body, BoxBody, CollisionConfig, CylinderBody, MeshBody
from drivers.errors import ConfigError
from drivers.fcl_bodies import ArmBody, fcl_transform, mesh_bvh
from drivers.robots import get_robot_model
from drivers.robots.model import RobotModel

if TYPE_CHECKING:  # the cell file's model imports the planners, which import this module's users
    from cell.config.models import CellConfig

Array = NDArray[np.float64]

# Frames at or below this index stand on the table (robot base and first joint housing).
_BASE_FRAMES = 1
# On a joint path, two bodies closer than this [m] count as touching: bisection must end somewhere, and a
# move that grazes a body by a tenth of a millimetre is one to refuse.
PATH_CONTACT_M = 1e-4
# A ROI margin shrunk because it would reach the arm where it stands keeps the arm's bodies this far [m]
# from the box: further than a path check's contact distance, so that a move from there is not refused
# at its first sample.
ROI_ARM_CLEARANCE_M = 2.0 * PATH_CONTACT_M
# Such a margin is found by bisection to within this [m].
_ROI_MARGIN_TOL_M = 1e-4
# A pair looked at again for the paths checked again and again (CollisionWorld.check_motion) gets FCL's
# distance when its spheres come within this many times the path's bound: its reference then lasts while
# the arm covers about twice that path again before the spheres' gap would have to be looked at closer.
REFERENCE_REACH = 3.0
# A pair of capsules is proven never to touch on this many angles across its joint's range at first, and
# on at most this many more when they do not suffice.
_SWEEP_ANGLES = 1025
_SWEEP_ANGLES_MAX = 1 << 17


@dataclass(frozen=True)
class Collision:
    """Two bodies in contact; ``str`` names them for a refusal."""

    body_a: str
    body_b: str

    def __str__(self) -> str:
        return f"{self.body_a} would touch {self.body_b}"


@dataclass
class _Static:
    name: str
    obj: fcl.CollisionObject
    center: Array
    radius: float


@dataclass
class _Reference:
    """For each of the path check's ``pairs`` (p, 2), with their ``levers`` (p, n) [m/rad]
    (``CollisionWorld._path_pairs``): a lower bound ``distance`` (p,) [m] on its distance at joints ``q``
    (p, n) [rad], where it was last looked at (``CollisionWorld.check_motion``); ``statics`` are the
    static bodies they were found with."""

    q: Array
    distance: Array
    pairs: Array
    levers: Array
    statics: list[_Static]


def _geometry(body: Body) -> tuple[fcl.CollisionGeometry, float, Array]:
    """The FCL geometry of a configured body, the radius of a sphere about its pose that encloses it, and
    the lower and upper corners (2, 3) of a box about its pose that holds it [m]."""
    if isinstance(body, BoxBody):
        size = np.asarray(body.size_m, dtype=float)
        return fcl.Box(*size), float(np.linalg.norm(size) / 2.0), np.array([-size / 2.0, size / 2.0])
    if isinstance(body, CylinderBody):
        half = np.array([body.radius_m, body.radius_m, body.length_m / 2.0])
        return (fcl.Cylinder(body.radius_m, body.length_m),
                float(np.hypot(body.radius_m, body.length_m / 2.0)), np.array([-half, half]))
    assert isinstance(body, MeshBody)
    mesh = o3d.io.read_triangle_mesh(Path(body.path))
    vertices = np.asarray(mesh.vertices, dtype=float)
    triangles = np.asarray(mesh.triangles, dtype=np.int32)
    if triangles.shape[0] == 0:
        raise ConfigError("the mesh has no triangles or cannot be read", field=f"obstacle {body.name}",
                          allowed="a triangle mesh file Open3D reads (.ply, .stl, .obj, ...)")
    return (mesh_bvh(vertices, triangles), float(np.max(np.linalg.norm(vertices, axis=1))),
            np.array([vertices.min(axis=0), vertices.max(axis=0)]))


def _capsule_pose(a: Array, b: Array) -> Array:
    """A pose whose z axis runs from ``a`` to ``b``, centred between them (FCL capsules lie along z)."""
    T = np.eye(4)
    axis = b - a
    length = float(np.linalg.norm(axis))
    z = axis / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    T[:3, 0], T[:3, 1], T[:3, 2] = x, np.cross(z, x), z
    T[:3, 3] = (a + b) / 2.0
    return T


def _segment_distances(p1: Array, q1: Array, p2: Array, q2: Array) -> Array:
    """Distances [m] between the segments ``p1``-``q1`` and ``p2``-``q2`` (..., 3), in closed form: the
    closest points' parameters on the two lines, clamped to the segments (Ericson, Real-Time Collision
    Detection, section 5.1.9)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e = np.einsum("...i,...i", d1, d1), np.einsum("...i,...i", d2, d2)
    b, c, f = np.einsum("...i,...i", d1, d2), np.einsum("...i,...i", d1, r), np.einsum("...i,...i", d2, r)
    a_, e_ = np.maximum(a, 1e-300), np.maximum(e, 1e-300)  # a point for a segment: its parameter stays 0
    denom = a * e - b * b
    s = np.where(denom > 1e-12 * a_ * e_, np.clip((b * f - c * e) / np.maximum(denom, 1e-300), 0.0, 1.0), 0.0)
    t = np.where(e > 0.0, (b * s + f) / e_, 0.0)
    s = np.where(t < 0.0, np.clip(-c / a_, 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / a_, 0.0, 1.0), s))
    s = np.where(a > 0.0, s, 0.0)
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(p1 + d1 * s[..., None] - p2 - d2 * t[..., None], axis=-1)


def _turned(points: Array, origin: Array, axis: Array, angles: Array) -> Array:
    """``points`` (m, 3) turned about the line through ``origin`` along the unit ``axis`` by each of
    ``angles`` (N,) [rad] (Rodrigues' formula): (N, m, 3)."""
    v = points - origin
    cos, sin = np.cos(angles)[:, None, None], np.sin(angles)[:, None, None]
    return origin + cos * v + sin * np.cross(axis, v) + (1.0 - cos) * (v @ axis)[:, None] * axis


class CollisionWorld:
    """The robot, its tool and the environment of one cell; :meth:`check` tests a joint configuration."""

    @classmethod
    def for_cell(cls, config: CellConfig) -> CollisionWorld:
        """The collision world of the cell ``config`` describes: its arm's robot model (``arm.model``), its
        tool bodies and margins (``safety.collision``) and its table top (``station.table_z_m``). A job
        builds one, checks its placement clear of the arm in it and hands it to its guard
        (``cell.jobs.runner.prepare_scan``, ``MotionGuard.from_config``)."""
        return cls(get_robot_model(config.arm.model), config.safety.collision, config.station.table_z_m)

    def __init__(self, model: RobotModel, config: CollisionConfig, table_z_m: float) -> None:
        self._model = model
        self._request = fcl.CollisionRequest()
        self._distance_request = fcl.DistanceRequest()
        specs = model.capsule_specs
        self._link_names = [c.name for c in specs]
        lengths = [float(np.linalg.norm(np.subtract(c.b, c.a))) for c in specs]
        geoms: list[fcl.CollisionGeometry] = [fcl.Capsule(c.radius, h) for c, h in zip(specs, lengths,
                                                                                       strict=True)]
        # Each body's pose relative to the frame that carries it is fixed: precomputed once.
        local = [_capsule_pose(np.asarray(c.a, dtype=float), np.asarray(c.b, dtype=float)) for c in specs]
        radii = [c.radius + h / 2.0 for c, h in zip(specs, lengths, strict=True)]
        bounds = [np.array([-c.radius, -c.radius, -c.radius - h / 2.0]) * [[1.0], [-1.0]]
                  for c, h in zip(specs, lengths, strict=True)]
        flange_frame = model.n_joints + (1 if model.flange is not None else 0)
        frames = [c.frame for c in specs]
        # How far a body's points lie from the origin of the frame that carries it (sweep_bound).
        extents = [max(float(np.linalg.norm(c.a)), float(np.linalg.norm(c.b))) + c.radius for c in specs]
        for body in config.tool:
            geom, radius, box = _geometry(body)
            geoms.append(geom)
            local.append(body.pose.matrix())
            radii.append(radius)
            bounds.append(box)
            extents.append(float(np.linalg.norm(body.pose.xyz_m)) + radius)
            frames.append(flange_frame)
        self.moving_names = self._link_names + [b.name for b in config.tool]
        n_moving = len(self.moving_names)
        self._geoms, self._bounds = geoms, bounds
        self._objs = [fcl.CollisionObject(g) for g in geoms]
        self._frames = np.asarray(frames)
        self._local = np.array(local)
        self._radii = np.asarray(radii)
        self._on_base = self._frames <= _BASE_FRAMES
        self._lever = self._sweep_levers(model, self._frames, np.asarray(extents))
        origins = model.fk_all(model.q_home)[:, :3, 3]
        along = np.cumsum(np.concatenate([[np.linalg.norm(origins[0])],
                                          np.linalg.norm(np.diff(origins, axis=0), axis=1)]))
        self.reach_m = float(np.max(along[self._frames] + np.asarray(extents)))
        """The farthest [m] any point of the arm's bodies comes from the base frame's origin, in any
        configuration: the origins of consecutive frames are a fixed distance apart (:meth:`_sweep_levers`),
        so by the triangle inequality a body lies within the sum of those up to its frame, plus its extent."""
        self._axial = self._axial_capsules(model, len(self._objs))
        allowed = np.eye(n_moving, dtype=bool)
        for i, a in enumerate(self.moving_names):
            for j, b in enumerate(self.moving_names):
                if i < len(specs) and j < len(specs):
                    allowed[i, j] |= model.are_adjacent(a, b)
                elif abs(frames[i] - frames[j]) <= 1:
                    allowed[i, j] = True
        self_pairs = np.argwhere(np.triu(~allowed, 1))
        self._self_pairs = self_pairs[~self._never_touching(model, self_pairs)]
        table = config.table
        slab = np.eye(4)
        top = table_z_m + table.clearance_m  # the bodies keep the clearance as if the table were that high
        slab[:3, 3] = [table.center_xy_m[0], table.center_xy_m[1], top - table.thickness_m / 2.0]
        size = (table.size_m[0], table.size_m[1], table.thickness_m)
        self._table = self._static("table", fcl.Box(*size), slab, float(np.linalg.norm(size) / 2.0))
        self._obstacles = []
        for body in config.obstacles:
            geom, radius, _ = _geometry(body)
            self._obstacles.append(self._static(body.name, geom, body.pose.matrix(), radius))
        self._roi: _Static | None = None
        self._roi_margin = config.roi_margin_m
        # the seen obstacles' bodies, one per block of cells, by the cells they hold
        self._seen: dict[bytes, _Static] = {}
        self._reference: _Reference | None = None
        self.n_motion_checks = 0
        """Calls of :meth:`check_motion` so far (``benchmarks/guard_tick.py`` tells ticks apart by them)."""
        self.n_distances = 0
        """FCL distance computations so far."""

    def arm_bodies(self) -> list[ArmBody]:
        """The moving bodies (the links' capsules, then the tool's bodies) with the frames that carry them,
        for the simulated cell's contact with the true object (``drivers.sim.contact.SimContact``): the
        sim arm faults on the geometry the guard checks with."""
        return [ArmBody(name, int(frame), T.copy(), geom, box.copy(), levers.copy(), bool(on_base))
                for name, frame, T, geom, box, levers, on_base in zip(
                    self.moving_names, self._frames, self._local, self._geoms, self._bounds, self._lever,
                    self._on_base, strict=True)]

    @staticmethod
    def _sweep_levers(model: RobotModel, frames: Array, extents: Array) -> Array:
        """(bodies, joints) [m]: an upper bound on the distance of any point of each body from each joint's
        axis, over all configurations (zero for a joint that does not move the body).

        Joint i turns about the z axis of ``fk_all`` frame i (standard DH) or i + 1 (modified DH), which
        passes through that frame's origin, and moves frames i + 1 onwards. A point p of a body carried
        by frame f lies within the body's extent e of f's origin, and the origins of consecutive frames
        are a fixed distance apart (a DH transform moves its origin by sqrt(a^2 + d^2) whatever the joint
        angle; the flange is fixed), so by the triangle inequality
        ``dist(p, axis_i) <= |p - o_axis| <= e + sum of the link distances from the axis frame to f``."""
        n = model.n_joints
        origins = model.fk_all(model.q_home)[:, :3, 3]
        reach = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(origins, axis=0), axis=1))])
        axis_frame = model.axis_frames
        lever = extents[:, None] + reach[frames][:, None] - reach[axis_frame][None, :]
        return np.where(np.arange(n)[None, :] < frames[:, None], lever, 0.0)

    @staticmethod
    def _axial_capsules(model: RobotModel, n_moving: int) -> NDArray[np.bool_]:
        """(bodies, joints): True where the body is a link capsule whose segment lies on the joint's axis,
        which is fixed in the capsule's frame: the capsule is carried by the frame whose z axis the joint
        turns about (``_sweep_levers``) and both its ends are on that z axis. Such a capsule is the same set
        of points after any turn of the joint about it, so the joint's turn (of the capsule itself, or of
        the bodies beyond it) does not change the distance between the capsule and any body."""
        n = model.n_joints
        axis_frame = model.axis_frames
        axial = np.zeros((n_moving, n), dtype=bool)
        for i, c in enumerate(model.capsule_specs):
            on_z = not np.any(np.asarray([c.a[:2], c.b[:2]], dtype=float))
            axial[i] = on_z & (axis_frame == c.frame)
        return axial

    def sweep_bound(self, dq: Array) -> Array:
        """How far [m] any point of each moving body (k,) can move while the joints go along a straight
        line by ``dq`` (n,) [rad], from anywhere.

        A revolute joint turning by dθ moves a point by at most dθ times its distance from the joint's
        axis, and the motions of all joints add up, so the length of a point's path is at most
        ``sum_i |dq_i| * lever_i`` with the levers of :meth:`_sweep_levers` (which hold in every
        configuration); a point never ends up further from where it was than the length of its path.
        Along a polyline the bounds of its segments add up."""
        return self._lever @ np.abs(dq)

    @staticmethod
    def _static(name: str, geom: fcl.CollisionGeometry, T: Array, radius: float) -> _Static:
        return _Static(name, fcl.CollisionObject(geom, fcl_transform(T)), T[:3, 3].copy(), radius)

    def set_roi(self, aabb_min: Array | Sequence[float] | None, aabb_max: Array | Sequence[float] | None,
                q_free: Array | None = None) -> Array | None:
        """Replace the object's ROI box (base frame [m]); it is inflated by the configured margin. None
        removes it.

        ``q_free``: the joints [rad] the arm stands at as the ROI is updated. The box is an estimate of
        where the object is and the margin covers its error, but the space the arm's bodies take at
        ``q_free`` is known to hold no object: the margin of a face that would reach them is shrunk, as
        little as keeps them ``ROI_ARM_CLEARANCE_M`` clear (:meth:`_roi_margins`), so that the arm may move
        on from where it stands, and away; towards the object it is still stopped by what is left. The
        object's own box is never shrunk: when it reaches the arm, the full margin stays (and every move
        from there is refused, as without ``q_free``).

        Returns the margins [m] of the faces (-x, -y, -z, +x, +y, +z) when one was shrunk, else None."""
        if aabb_min is None or aabb_max is None:
            self._roi = None
            return None
        lo = np.asarray(aabb_min, dtype=float)
        hi = np.asarray(aabb_max, dtype=float)
        margins = np.full(6, self._roi_margin) if q_free is None else self._roi_margins(lo, hi, q_free)
        self._roi = self._box("object ROI", lo - margins[:3], hi + margins[3:])
        return margins if np.any(margins < self._roi_margin) else None

    def set_seen(self, cells: SeenCells | None, q_free: Array | None = None) -> int:
        """Replace what the sensor has seen outside the object's ROI (``perception.seen_obstacles``; None
        or no cells removes it) by ``cells``, checked as one body per block of cells
        (``SeenCells.chunks``), each "seen obstacle".

        ``q_free``: the joints [rad] the arm stands at as they are updated. The space its bodies take there
        holds nothing (what the sensor saw there, it saw of the arm or before the arm came), so the cells
        within ``ROI_ARM_CLEARANCE_M`` of them are left out (:meth:`_near_arm`), and the arm may move on
        from where it stands. The blocks' bodies come built (on the thread that processes frames); only a
        block some of whose cells are left out is built again here. A block whose cells a body holds
        already keeps that body, and the path references with it. Returns the number of cells left out."""
        if cells is None or len(cells) == 0:
            self._seen = {}
            return 0
        near = np.zeros(len(cells), dtype=bool) if q_free is None else self._near_arm(
            cells.centers(), cells.voxel_m, np.asarray(q_free, dtype=float))
        seen: dict[bytes, _Static] = {}
        for chunk, at in cells.chunks:
            kept = chunk.without(near[at]) if np.any(near[at]) else chunk
            if len(kept) == 0:
                continue
            held = kept.keys.tobytes()
            if held not in self._seen:
                bvh, center, radius = kept.body
                T = np.eye(4)
                T[:3, 3] = center
                seen[held] = self._static("seen obstacle", bvh, T, radius)
            else:
                seen[held] = self._seen[held]
        self._seen = seen
        return int(np.count_nonzero(near))

    def _near_arm(self, points: Array, voxel_m: float, q: Array) -> NDArray[np.bool_]:
        """Which cubes of edge ``voxel_m`` [m] about ``points`` (M, 3) [m, base frame] come within
        ``ROI_ARM_CLEARANCE_M`` of the arm's bodies at joints ``q`` [rad]: FCL's distance between the cube
        and each body whose enclosing sphere (a link capsule's own segment and radius) a ball about the
        cube reaches."""
        reach = voxel_m * np.sqrt(3.0) / 2.0 + ROI_ARM_CLEARANCE_M
        T = self._place(q)
        near = np.zeros(points.shape[0], dtype=bool)
        # only the cells in the box about the bodies' enclosing spheres can be near (most are not: cheap)
        spheres = T[:, :3, 3]
        inside = np.all((points >= (spheres - self._radii[:, None]).min(axis=0) - reach)
                        & (points <= (spheres + self._radii[:, None]).max(axis=0) + reach), axis=1)
        candidates = np.nonzero(inside)[0]
        if candidates.size == 0:
            return near
        capsules = self._model.capsules(q)
        cube = fcl.Box(voxel_m, voxel_m, voxel_m)
        p = points[candidates]
        for k, obj in enumerate(self._objs):
            if k < len(capsules):
                c = capsules[k]
                ball = _segment_distances(p, p, c.a, c.b) <= c.radius + reach
            else:
                ball = np.linalg.norm(p - T[k, :3, 3], axis=1) <= self._radii[k] + reach
            for i in candidates[ball & ~near[candidates]]:
                cell = fcl.CollisionObject(cube, fcl.Transform(points[i]))
                near[i] = self._distance(obj, cell) <= ROI_ARM_CLEARANCE_M
        return near

    def _roi_margins(self, lo: Array, hi: Array, q: Array) -> Array:
        """The margins [m] of the faces (-x, -y, -z, +x, +y, +z) of the box ``lo``..``hi`` (base frame [m])
        that keep the arm's bodies at joints ``q`` [rad] ``ROI_ARM_CLEARANCE_M`` clear of it: on each face
        the configured margin, or less where that would reach them. The full margins when the box itself
        comes that close.

        The box grown by margins is the box and one slab beyond each face, as wide as the grown box. A first
        pass finds, for each face, the largest margin whose slab only as wide as the box is clear: a face
        that does not face the arm keeps its full margin. A second pass shrinks each face further until its
        slab as wide as the box grown by the first pass's margins is clear (an arm over an edge or a
        corner); the final slabs lie within these, so the whole grown box is clear."""
        full = np.full(6, self._roi_margin)
        centers = self._place(np.asarray(q, dtype=float))[:, :3, 3]
        if self._roi_margin == 0.0 or self._box_reaches_arm(lo, hi, centers):
            return full
        facing = np.array([self._clear_margin(lo, hi, f, full[f], np.zeros(6), centers) for f in range(6)])
        return np.array([self._clear_margin(lo, hi, f, facing[f], facing, centers) for f in range(6)])

    def _clear_margin(self, lo: Array, hi: Array, face: int, upper: float, lateral: Array, centers: Array
                      ) -> float:
        """The largest margin [m] in [0, ``upper``] (within ``_ROI_MARGIN_TOL_M``, by bisection: a slab only
        grows with its margin) whose slab beyond ``face`` of the box ``lo``..``hi``, as wide as the box
        grown by ``lateral`` (6,) on the other faces, keeps ``ROI_ARM_CLEARANCE_M`` from the arm's bodies
        (their centres ``centers``, as last placed)."""
        if not self._box_reaches_arm(*self._slab(lo, hi, face, upper, lateral), centers):
            return upper
        clear, reached = 0.0, upper
        while reached - clear > _ROI_MARGIN_TOL_M:
            mid = (clear + reached) / 2.0
            if self._box_reaches_arm(*self._slab(lo, hi, face, mid, lateral), centers):
                reached = mid
            else:
                clear = mid
        return clear

    @staticmethod
    def _slab(lo: Array, hi: Array, face: int, margin: float, lateral: Array) -> tuple[Array, Array]:
        """The lower and upper corners of the slab ``margin`` [m] thick beyond ``face`` (-x, -y, -z, +x,
        +y, +z) of the box ``lo``..``hi``, as wide as the box grown by ``lateral`` (6,) on the other faces."""
        axis = face % 3
        slab_lo, slab_hi = lo - lateral[:3], hi + lateral[3:]
        if face >= 3:
            slab_lo[axis], slab_hi[axis] = hi[axis], hi[axis] + margin
        else:
            slab_lo[axis], slab_hi[axis] = lo[axis] - margin, lo[axis]
        return slab_lo, slab_hi

    def _box_reaches_arm(self, lo: Array, hi: Array, centers: Array) -> bool:
        """Whether the box ``lo``..``hi`` (base frame [m]) comes within ``ROI_ARM_CLEARANCE_M`` of a moving
        body as last placed (their centres ``centers``, (k, 3))."""
        box = self._box("box", lo - ROI_ARM_CLEARANCE_M, hi + ROI_ARM_CLEARANCE_M)
        return self._first_touching(box, centers, np.ones(len(self._objs), dtype=bool)) is not None

    def _box(self, name: str, lo: Array, hi: Array) -> _Static:
        """An axis-aligned box from ``lo`` to ``hi`` (base frame [m])."""
        T = np.eye(4)
        T[:3, 3] = (lo + hi) / 2.0
        size = hi - lo
        return self._static(name, fcl.Box(*size), T, float(np.linalg.norm(size) / 2.0))

    def _poses(self, q: Array) -> Array:
        """The moving bodies' poses (k, 4, 4) at ``q`` in the base frame (their FCL objects not moved)."""
        return self._model.fk_all(q)[self._frames] @ self._local

    def _place(self, q: Array) -> Array:
        """Pose every moving body at ``q``; returns their poses (k, 4, 4) in the base frame."""
        T = self._poses(q)
        for obj, Tk in zip(self._objs, T, strict=True):
            obj.setTransform(fcl_transform(Tk))
        return T

    def _touch(self, a: fcl.CollisionObject, b: fcl.CollisionObject) -> bool:
        return fcl.collide(a, b, self._request, fcl.CollisionResult()) > 0

    def _distance(self, a: fcl.CollisionObject, b: fcl.CollisionObject) -> float:
        """FCL's distance [m] between two bodies (not positive when they touch)."""
        self.n_distances += 1
        return float(fcl.distance(a, b, self._distance_request, fcl.DistanceResult()))

    def check(self, q: Array) -> Collision | None:
        """The first pair of bodies in contact at joints ``q`` [rad], or None when it is collision-free."""
        T = self._place(np.asarray(q, dtype=float))
        centers, radii, objs = T[:, :3, 3], self._radii, self._objs
        statics = self._statics()
        for st in statics:
            i = self._first_touching(st, centers, self._can_touch(st))
            if i is not None:
                return Collision(self.moving_names[i], st.name)
        ia, ib = self._self_pairs[:, 0], self._self_pairs[:, 1]
        near = np.linalg.norm(centers[ia] - centers[ib], axis=1) <= radii[ia] + radii[ib]
        for a, b in self._self_pairs[near]:
            if self._touch(objs[a], objs[b]):
                return Collision(self.moving_names[a], self.moving_names[b])
        return None

    def _first_touching(self, st: _Static, centers: Array, bodies: NDArray[np.bool_]) -> int | None:
        """The first of the moving ``bodies`` (a mask), as last placed (their centres ``centers``), that
        touches the static body ``st``, or None."""
        near = bodies & (np.linalg.norm(centers - st.center, axis=1) <= self._radii + st.radius)
        for i in np.nonzero(near)[0]:
            if self._touch(self._objs[i], st.obj):
                return int(i)
        return None

    def _can_touch(self, st: _Static) -> NDArray[np.bool_]:
        """The moving bodies (a mask) checked against the static body ``st``: all but those on the base and
        the first joint's frames for the table, which they stand on."""
        return ~self._on_base if st is self._table else np.ones(len(self._objs), dtype=bool)

    def _statics(self) -> list[_Static]:
        return [self._table, *self._obstacles] + ([self._roi] if self._roi is not None else []) \
            + list(self._seen.values())

    def _path_pairs(self, statics: list[_Static]) -> tuple[Array, Array]:
        """The pairs a path check watches, as (p, 2) indices into the moving bodies followed by ``statics``:
        (moving body, static) for every static the body can touch, then the self-collision pairs; and their
        levers (p, n) [m/rad]: how far a joint's turn by one radian moves one body of the pair relative to
        the other, at most (:meth:`sweep_bound`). A joint's turn keeps the pair's distance, and its lever is
        zero, when it moves both bodies (as one rigid piece) or when it turns about one of them (a capsule
        on its axis, :meth:`_axial_capsules`; the UR5e's upper arm passes 3 mm from its base, which the
        first joint turns it around)."""
        n_moving = len(self._objs)
        pairs = [self._self_pairs]
        for s, st in enumerate(statics):
            bodies = np.nonzero(self._can_touch(st))[0]
            pairs.insert(-1, np.column_stack([bodies, np.full(bodies.size, n_moving + s)]))
        index = np.concatenate(pairs).astype(int)
        levers = np.vstack([self._lever, np.zeros((len(statics), self._lever.shape[1]))])
        axial = np.vstack([self._axial, np.zeros((len(statics), self._axial.shape[1]), dtype=bool)])
        return index, self._pair_levers(index, levers, axial)

    @staticmethod
    def _pair_levers(index: NDArray[np.intp], levers: Array, axial: NDArray[np.bool_]) -> Array:
        """The levers (p, n) [m/rad] of the pairs ``index`` (p, 2) of bodies with ``levers`` and ``axial``
        (bodies, n) (:meth:`_sweep_levers`, :meth:`_axial_capsules`): zero for a joint that moves both
        bodies or turns one about a capsule on its axis, the sum of the two bodies' levers otherwise."""
        a, b = index[:, 0], index[:, 1]
        kept = ((levers[a] > 0.0) & (levers[b] > 0.0)) | axial[a] | axial[b]
        return np.where(kept, 0.0, levers[a] + levers[b])

    def _never_touching(self, model: RobotModel, pairs: NDArray[np.intp]) -> NDArray[np.bool_]:
        """Which of the self-collision ``pairs`` (p, 2) can never touch: two link capsules whose distance
        one joint alone changes (every other joint moves both as one piece or turns one about a capsule
        on its axis, :meth:`_pair_levers`, and so keeps it) and that stay more than twice
        ``PATH_CONTACT_M`` apart over that joint's whole range, between the limits the arm cannot pass
        (the UR5e's upper arm passes 3 mm from its base at every shoulder angle, and was measured on every
        tick that turned the shoulder).

        With the other joints anywhere (at home), the joint turns one capsule's segment about its axis:
        the distance at N angles across the range is the segments' distance less the radii, in closed form
        (:func:`_segment_distances`), and between two angles h apart it is at least (d_i + d_i+1 - L h) / 2
        with L the pair's lever (:meth:`check_path`'s bound). N grows (up to ``_SWEEP_ANGLES_MAX``) when
        the first angles do not prove it and more could."""
        capsules = model.capsules(model.q_home)
        levers = self._pair_levers(pairs, self._lever, self._axial)
        axis = model.fk_all(model.q_home)[model.axis_frames]
        never = np.zeros(len(pairs), dtype=bool)
        for k, ((a, b), lever) in enumerate(zip(pairs, levers, strict=True)):
            joints = np.nonzero(lever)[0]
            if joints.size != 1 or max(a, b) >= len(capsules):
                continue
            j = int(joints[0])
            moved, still = (capsules[a], capsules[b]) if j < self._frames[a] else (capsules[b], capsules[a])
            lo, hi = model.q_min[j] - model.q_home[j], model.q_max[j] - model.q_home[j]
            n_angles = _SWEEP_ANGLES
            while True:
                angles = np.linspace(lo, hi, n_angles)
                turned = _turned(np.array([moved.a, moved.b]), axis[j, :3, 3], axis[j, :3, 2], angles)
                d = _segment_distances(turned[:, 0], turned[:, 1], still.a, still.b) \
                    - (moved.radius + still.radius)
                step = (hi - lo) / (n_angles - 1)
                if np.min(d[:-1] + d[1:] - lever[j] * step) / 2.0 > 2.0 * PATH_CONTACT_M:
                    never[k] = True
                    break
                # angles close enough for the nearest approach to prove it, if any can
                spare = float(np.min(d)) - 2.0 * PATH_CONTACT_M
                needed = int(np.ceil(2.0 * lever[j] * (hi - lo) / spare)) + 1 if spare > 0.0 else 0
                if not n_angles < needed <= _SWEEP_ANGLES_MAX:
                    break
                n_angles = needed
        return never

    def _clearance(self, q: Array, need: Array, pairs: Array, statics: list[_Static]
                   ) -> tuple[Array, Collision | None]:
        """Lower bounds [m] on the distance of each pair at joints ``q``: the gap between the pair's bounding
        spheres, or FCL's distance where that gap is below ``need`` (p,); and the first pair found within
        ``PATH_CONTACT_M`` (touching), or None. Only the moving bodies of the pairs that need FCL's
        distance have their FCL objects moved to ``q`` (most pairs are cleared by their spheres)."""
        T = self._poses(q)
        n_moving = len(self._objs)
        centers = np.vstack([T[:, :3, 3], [st.center for st in statics]])
        radii = np.concatenate([self._radii, [st.radius for st in statics]])
        a, b = pairs[:, 0], pairs[:, 1]
        gap = np.linalg.norm(centers[a] - centers[b], axis=1) - radii[a] - radii[b]
        objs = self._objs + [st.obj for st in statics]
        placed = np.zeros(n_moving, dtype=bool)
        for p in np.nonzero(gap < np.maximum(need, PATH_CONTACT_M))[0]:
            i, j = pairs[p]
            for body in (i, j):
                if body < n_moving and not placed[body]:
                    objs[body].setTransform(fcl_transform(T[body]))
                    placed[body] = True
            gap[p] = self._distance(objs[i], objs[j])
            if gap[p] <= PATH_CONTACT_M:
                names = self.moving_names + [st.name for st in statics]
                return gap, Collision(names[i], names[j])
        return gap, None

    def check_path(self, q_path: Array, max_step_rad: float) -> tuple[int, Collision] | None:
        """Check a joint path (K, n) [rad], taken as straight lines in joint space between its samples (as
        an arm interpolates them), for contact anywhere along it. Returns the index of the first sample at
        or after the contact and the contact (two bodies closer than ``PATH_CONTACT_M``), or None.

        Segments longer than ``max_step_rad`` in any joint are subdivided, and the stretches between the
        configurations are checked in turn against each pair's reference (:meth:`_advance`): a lower bound
        on the pair's distance where it was last measured, less how far the pair can have come closer
        since. For a static body that is the moving body's :meth:`sweep_bound`; for two moving bodies, the
        same sum over the joints that move one of them and not the other (a joint that moves both turns them
        as one rigid piece, which keeps their distance; the others move one body relative to the other by
        at most that), and nothing for a joint that turns one of them about a capsule on its axis. A pair
        whose bound no longer clears it is measured again (FCL's distance) at the stretch's start; when the
        stretch's own bound does not clear it from there either, its distances at both ends must add up to
        more than that bound, which is sound: at any point of the stretch a body lies within the bound
        times the share of the stretch behind it of where it was relative to the other at the start, and
        within the bound times the share ahead of where it is at the end, so the pair's distance stays
        above ``(d_start + d_end - bound) / 2 > 0``. A stretch that is not clear is bisected until each
        part is, or a configuration on it touches."""
        q_path = np.asarray(q_path, dtype=float)
        dense, owner = [q_path[:1]], [0]
        for k in range(1, q_path.shape[0]):
            step = q_path[k] - q_path[k - 1]
            n_sub = max(1, int(np.ceil(float(np.max(np.abs(step))) / max_step_rad)))
            dense.append(q_path[k - 1] + step * (np.arange(1, n_sub + 1) / n_sub)[:, None])
            owner += [k] * n_sub
        if len(owner) == 1:  # one configuration: a stretch that stays there
            dense.append(q_path[:1])
            owner.append(0)
        q = np.concatenate(dense)
        statics = self._statics()
        ref = self._reference_for(q[0], statics)
        for k in range(1, q.shape[0]):
            hit = self._advance(ref, q[k - 1], q[k], statics)
            if hit is not None:
                return owner[k - 1 + hit[0]], hit[1]
        return None

    def check_motion(self, q_from: Array, q_to: Array) -> tuple[int, Collision] | None:
        """Check the straight joint path from ``q_from`` to ``q_to`` (n,) [rad] as :meth:`check_path` does,
        for a path checked again and again as the arm moves (the guard's way ahead, every control period):
        the pairs' references are kept from one call to the next, so most calls measure nothing. Returns
        ``(0, contact)`` when ``q_from`` itself touches, ``(1, contact)`` for a contact further on, or
        None. The references hold for the static bodies they were found with: another ROI (``set_roi``) or
        other seen obstacles (``set_seen``) drop them."""
        self.n_motion_checks += 1
        q_from, q_to = np.asarray(q_from, dtype=float), np.asarray(q_to, dtype=float)
        statics = self._statics()
        ref = self._reference
        if ref is None or len(ref.statics) != len(statics) or any(
                a is not b for a, b in zip(ref.statics, statics, strict=True)):
            ref = self._reference = self._reference_for(q_from, statics)
        return self._advance(ref, q_from, q_to, statics)

    def _reference_for(self, q: Array, statics: list[_Static]) -> _Reference:
        """References of the path check's pairs with ``statics`` that clear nothing yet (a distance of minus
        infinity, at joints ``q``)."""
        pairs, levers = self._path_pairs(statics)
        return _Reference(np.tile(q, (len(pairs), 1)), np.full(len(pairs), -np.inf), pairs, levers, statics)

    def _advance(self, ref: _Reference, q_from: Array, q_to: Array, statics: list[_Static]
                 ) -> tuple[int, Collision] | None:
        """The straight stretch from ``q_from`` to ``q_to`` (n,) [rad] against the pairs' references ``ref``
        (updated): ``(0, contact)`` when ``q_from`` touches, ``(1, contact)`` for a contact further on, or
        None when it is clear.

        At any q on the stretch, each joint is at most ``max(|q_from - q_r|, |q_to - q_r|)`` from a pair's
        reference joints q_r (the distance to a point moving along a line is largest at an end), so by the
        pair's levers (:meth:`check_path`) the pair's distance there is at least its reference less the
        levers times that; a pair for which that stays above ``PATH_CONTACT_M`` needs no FCL call
        (conservative advancement). The others are measured again at ``q_from`` unless their reference is
        there, with those that would need it within ``REFERENCE_REACH`` such stretches (FCL's distance where
        their spheres come within ``REFERENCE_REACH`` times the stretch's own bound, the spheres' gap
        beyond), which becomes their reference; those the stretch's own bound does not clear from there are
        measured at ``q_to`` and checked along the stretch by bisection (:meth:`_check_stretch`), and then
        keep their distances at ``q_to``, where a path's next stretch starts."""
        span = ref.levers @ np.abs(q_to - q_from)
        reach = np.einsum("pn,pn->p", ref.levers, np.maximum(np.abs(q_from - ref.q), np.abs(q_to - ref.q)))
        # written so that only a bound that clears counts (a NaN never does)
        stale = np.nonzero(~(ref.distance - reach > PATH_CONTACT_M))[0]
        if stale.size == 0:
            return None
        # the pairs not measured right there (nor ever)
        away = np.isneginf(ref.distance) | np.any(ref.q != q_from, axis=1)
        measure = stale[away[stale]]
        if measure.size:
            # the forward kinematics at q_from is paid for now: also measure the pairs about to need it
            soon = ~(ref.distance - reach > PATH_CONTACT_M + REFERENCE_REACH * span)
            measure = np.union1d(measure, np.nonzero(soon & away)[0])
            distance, hit = self._clearance(q_from, REFERENCE_REACH * span[measure], ref.pairs[measure],
                                            statics)
            if hit is not None:
                return 0, hit
            ref.q[measure], ref.distance[measure] = q_from, distance
        opened = stale[~(ref.distance[stale] - span[stale] > PATH_CONTACT_M)]
        if opened.size == 0:
            return None
        pairs, levers = ref.pairs[opened], ref.levers[opened]
        d_to, hit = self._clearance(q_to, span[opened], pairs, statics)
        hit = hit or self._check_stretch(q_from, ref.distance[opened], q_to, d_to, pairs, levers, statics)
        if hit is not None:
            return 1, hit
        ref.q[opened], ref.distance[opened] = q_to, d_to  # where the next stretch starts
        return None

    def _check_stretch(self, qa: Array, da: Array, qb: Array, db: Array, pairs: Array, levers: Array,
                       statics: list[_Static]) -> Collision | None:
        """The straight stretch from ``qa`` to ``qb`` for ``pairs`` with their distance bounds at its ends
        and their levers (:meth:`check_path`): the halves of the stretch are checked for the pairs it does
        not clear, recursively; returns the contact found on it, or None."""
        need = np.abs(qb - qa) @ levers.T
        open_ = da + db <= need
        if not np.any(open_):
            return None
        pairs, levers, da, db = pairs[open_], levers[open_], da[open_], db[open_]
        qm = (qa + qb) / 2.0
        dm, hit = self._clearance(qm, need[open_] / 2.0, pairs, statics)
        if hit is not None:
            return hit
        return (self._check_stretch(qa, da, qm, dm, pairs, levers, statics)
                or self._check_stretch(qm, dm, qb, db, pairs, levers, statics))
