"""The collision world, checked with python-fcl (safety issue, item 2).

Bodies:

- the robot's links: the capsules of its kinematic model (``drivers.robots``), posed by forward kinematics;
- the tool: bodies carried by the flange (the sensor and its bracket), from ``safety.collision.tool``;
- the table: a slab whose top is the station's table height;
- the object's ROI: its axis-aligned box inflated by ``roi_margin_m``, replaced whenever perception
  updates the ROI;
- static obstacles from ``safety.collision.obstacles`` (boxes, cylinders, meshes).

A configuration collides when a moving body (link or tool) touches the table, the ROI or an obstacle, or
when two moving bodies that are not adjacent touch (self-collision). Adjacent pairs are the robot model's
(capsules of consecutive frames touch by construction) plus the tool with the flange's own capsules. The
links on the base and the first joint's frames stand on the table and are not checked against it.

A cheap bounding-sphere test in numpy selects the candidate pairs; FCL decides each candidate exactly.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import fcl
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from cell.safety.config import Body, BoxBody, CollisionConfig, CylinderBody, MeshBody
from drivers.errors import ConfigError
from drivers.robots.model import RobotModel

Array = NDArray[np.float64]

# Frames at or below this index stand on the table (robot base and first joint housing).
_BASE_FRAMES = 1


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


def _fcl_transform(T: Array) -> fcl.Transform:
    return fcl.Transform(np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]))


def _geometry(body: Body) -> tuple[fcl.CollisionGeometry, float]:
    """The FCL geometry of a configured body and the radius of a sphere about its pose that encloses it."""
    if isinstance(body, BoxBody):
        size = np.asarray(body.size_m)
        return fcl.Box(*size), float(np.linalg.norm(size) / 2.0)
    if isinstance(body, CylinderBody):
        return (fcl.Cylinder(body.radius_m, body.length_m),
                float(np.hypot(body.radius_m, body.length_m / 2.0)))
    assert isinstance(body, MeshBody)
    mesh = o3d.io.read_triangle_mesh(Path(body.path))
    vertices = np.asarray(mesh.vertices, dtype=float)
    triangles = np.asarray(mesh.triangles, dtype=np.int32)
    if triangles.shape[0] == 0:
        raise ConfigError("the mesh has no triangles or cannot be read", field=f"obstacle {body.name}",
                          allowed="a triangle mesh file Open3D reads (.ply, .stl, .obj, ...)")
    bvh = fcl.BVHModel()
    bvh.beginModel(vertices.shape[0], triangles.shape[0])
    bvh.addSubModel(vertices, triangles)
    bvh.endModel()
    return bvh, float(np.max(np.linalg.norm(vertices, axis=1)))


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


class CollisionWorld:
    """The robot, its tool and the environment of one cell; :meth:`check` tests a joint configuration."""

    def __init__(self, model: RobotModel, config: CollisionConfig, table_z_m: float) -> None:
        self._model = model
        self._request = fcl.CollisionRequest()
        specs = model.capsule_specs
        self._link_names = [c.name for c in specs]
        lengths = [float(np.linalg.norm(np.subtract(c.b, c.a))) for c in specs]
        geoms: list[fcl.CollisionGeometry] = [fcl.Capsule(c.radius, h) for c, h in zip(specs, lengths,
                                                                                       strict=True)]
        # Each body's pose relative to the frame that carries it is fixed: precomputed once.
        local = [_capsule_pose(np.asarray(c.a, dtype=float), np.asarray(c.b, dtype=float)) for c in specs]
        radii = [c.radius + h / 2.0 for c, h in zip(specs, lengths, strict=True)]
        flange_frame = model.n_joints + (1 if model.flange is not None else 0)
        frames = [c.frame for c in specs]
        for body in config.tool:
            geom, radius = _geometry(body)
            geoms.append(geom)
            local.append(body.pose.matrix())
            radii.append(radius)
            frames.append(flange_frame)
        self.moving_names = self._link_names + [b.name for b in config.tool]
        n_moving = len(self.moving_names)
        self._objs = [fcl.CollisionObject(g) for g in geoms]
        self._frames = np.asarray(frames)
        self._local = np.array(local)
        self._radii = np.asarray(radii)
        self._on_base = self._frames <= _BASE_FRAMES
        allowed = np.eye(n_moving, dtype=bool)
        for i, a in enumerate(self.moving_names):
            for j, b in enumerate(self.moving_names):
                if i < len(specs) and j < len(specs):
                    allowed[i, j] |= model.are_adjacent(a, b)
                elif abs(frames[i] - frames[j]) <= 1:
                    allowed[i, j] = True
        self._self_pairs = np.argwhere(np.triu(~allowed, 1))
        table = config.table
        slab = np.eye(4)
        slab[:3, 3] = [table.center_xy_m[0], table.center_xy_m[1], table_z_m - table.thickness_m / 2.0]
        size = (table.size_m[0], table.size_m[1], table.thickness_m)
        self._table = self._static("table", fcl.Box(*size), slab, float(np.linalg.norm(size) / 2.0))
        self._obstacles = []
        for body in config.obstacles:
            geom, radius = _geometry(body)
            self._obstacles.append(self._static(body.name, geom, body.pose.matrix(), radius))
        self._roi: _Static | None = None
        self._roi_margin = config.roi_margin_m

    @staticmethod
    def _static(name: str, geom: fcl.CollisionGeometry, T: Array, radius: float) -> _Static:
        return _Static(name, fcl.CollisionObject(geom, _fcl_transform(T)), T[:3, 3].copy(), radius)

    def set_roi(self, aabb_min: Array | Sequence[float] | None,
                aabb_max: Array | Sequence[float] | None) -> None:
        """Replace the object's ROI box (base frame [m]); it is inflated by the configured margin. None
        removes it."""
        if aabb_min is None or aabb_max is None:
            self._roi = None
            return
        lo = np.asarray(aabb_min, dtype=float) - self._roi_margin
        hi = np.asarray(aabb_max, dtype=float) + self._roi_margin
        T = np.eye(4)
        T[:3, 3] = (lo + hi) / 2.0
        size = hi - lo
        self._roi = self._static("object ROI", fcl.Box(*size), T, float(np.linalg.norm(size) / 2.0))

    def _place(self, q: Array) -> Array:
        """Pose every moving body at ``q``; returns their poses (k, 4, 4) in the base frame."""
        T = self._model.fk_all(q)[self._frames] @ self._local
        for obj, Tk in zip(self._objs, T, strict=True):
            obj.setTransform(_fcl_transform(Tk))
        return T

    def _touch(self, a: fcl.CollisionObject, b: fcl.CollisionObject) -> bool:
        return fcl.collide(a, b, self._request, fcl.CollisionResult()) > 0

    def check(self, q: Array) -> Collision | None:
        """The first pair of bodies in contact at joints ``q`` [rad], or None when it is collision-free."""
        T = self._place(np.asarray(q, dtype=float))
        centers, radii, objs = T[:, :3, 3], self._radii, self._objs
        statics = [self._table, *self._obstacles] + ([self._roi] if self._roi is not None else [])
        for st in statics:
            near = np.linalg.norm(centers - st.center, axis=1) <= radii + st.radius
            if st is self._table:
                near &= ~self._on_base
            for i in np.nonzero(near)[0]:
                if self._touch(objs[i], st.obj):
                    return Collision(self.moving_names[i], st.name)
        ia, ib = self._self_pairs[:, 0], self._self_pairs[:, 1]
        near = np.linalg.norm(centers[ia] - centers[ib], axis=1) <= radii[ia] + radii[ib]
        for a, b in self._self_pairs[near]:
            if self._touch(objs[a], objs[b]):
                return Collision(self.moving_names[a], self.moving_names[b])
        return None

    def check_path(self, q_path: Array, max_step_rad: float) -> tuple[int, Collision] | None:
        """Check a joint path (K, n) densely: consecutive samples further apart than ``max_step_rad`` in
        any joint are subdivided. Returns the index of the first sample at or after the contact and the
        contact, or None."""
        q_path = np.asarray(q_path, dtype=float)
        hit = self.check(q_path[0])
        if hit is not None:
            return 0, hit
        for k in range(1, q_path.shape[0]):
            step = float(np.max(np.abs(q_path[k] - q_path[k - 1])))
            n_sub = max(1, int(np.ceil(step / max_step_rad)))
            for s in range(1, n_sub + 1):
                hit = self.check(q_path[k - 1] + (q_path[k] - q_path[k - 1]) * (s / n_sub))
                if hit is not None:
                    return k, hit
        return None
