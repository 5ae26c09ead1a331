"""The simulated world the sim sensors ray-cast: a table and one object (or none: an empty table), in the
robot base frame.

Built on Open3D's ``o3d.t.geometry.RaycastingScene`` (Embree BVH, float32 internally, so hit distances
are good to about 1e-7 relative). All coordinates are in the base frame [m].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from drivers.sim.board import INTENSITY_OBJECT, INTENSITY_TABLE, TableTexture
from drivers.sim.objects import ObjectMesh
from drivers.transforms import transform_points

Array = NDArray[np.float64]

HIT_NONE: int = 0
HIT_TABLE: int = 1
HIT_OBJECT: int = 2


@dataclass(frozen=True)
class RayHits:
    """Result of casting N rays.

    ``t`` (N,) distance along each unit ray to the first hit [m], ``inf`` for no hit; ``normals`` (N, 3)
    unit surface normals in the base frame, flipped to face against the ray (``dot(n, d) <= 0``), zero
    for no hit; ``what`` (N,) int8: 0 none, 1 table, 2 object; ``cos_incidence`` (N,) cosine of the
    incidence angle between the ray and the surface normal (in [0, 1], 1 head-on), 0 for no hit.
    """

    t: Array
    normals: Array
    what: NDArray[np.int8]
    cos_incidence: Array

    def points(self, origins: Array, directions: Array) -> Array:
        """Hit points (N, 3) [m, base frame]; rows without a hit are ``inf``/``nan``."""
        return origins + self.t[:, None] * directions


class SimScene:
    """A table and one object placed by ``T_base_object`` (``obj`` None: the table only), ready for ray
    casting.

    The table is a box ``table_thickness_m`` thick whose top face is the plane z = ``table_z`` [m, base
    frame], ``table_size_xy`` [m] wide and centred on ``table_center_xy`` [m]. The object mesh
    (object frame: z-up, base at z = 0) is transformed by ``T_base_object`` (4x4, object frame in the base
    frame); to set an object on the table use a pose with translation z = ``table_z``.
    """

    def __init__(self, obj: ObjectMesh | None, T_base_object: Array, *, table_z: float = 0.0,
                 table_center_xy: tuple[float, float] = (0.5, 0.0),
                 table_size_xy: tuple[float, float] = (1.2, 1.0),
                 table_thickness_m: float = 0.03, texture: TableTexture | None = None) -> None:
        T = np.asarray(T_base_object, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_base_object must be a finite 4x4 matrix, got shape {T.shape}")
        if min(table_size_xy) <= 0.0 or table_thickness_m <= 0.0:
            raise ValueError("table size and thickness must be positive")
        self._T_base_object = T.copy()
        self._T_base_object.setflags(write=False)
        self.object_name: str | None = None if obj is None else obj.name
        self.table_z: float = float(table_z)
        self.table_center_xy: tuple[float, float] = (float(table_center_xy[0]), float(table_center_xy[1]))
        self.table_size_xy: tuple[float, float] = (float(table_size_xy[0]), float(table_size_xy[1]))
        self.table_thickness_m = float(table_thickness_m)

        verts = (np.zeros((0, 3)) if obj is None
                 else transform_points(T, np.asarray(obj.vertices, dtype=np.float64)))
        verts.setflags(write=False)
        tris = np.ascontiguousarray(np.zeros((0, 3)) if obj is None else obj.triangles, dtype=np.int32)
        tris.setflags(write=False)
        self._object_vertices = verts
        self._object_triangles = tris

        table_v, table_t = _box(self.table_center_xy, self.table_size_xy, self.table_z, table_thickness_m)
        self.texture = texture
        self._scene = o3d.t.geometry.RaycastingScene()
        # Open3D's stub of Tensor(np_array, dtype, device) drops the defaults (the array's dtype, CPU:0).
        table_id = self._scene.add_triangles(
            o3d.core.Tensor(table_v.astype(np.float32)),  # type: ignore[call-overload]
            o3d.core.Tensor(table_t.astype(np.uint32)))  # type: ignore[call-overload]
        # geometry id -> what code; any other id (INVALID_ID) maps to HIT_NONE, and no geometry has the
        # id -1 that an empty table gives its missing object
        self._id_table = int(table_id)
        self._id_object = -1
        if obj is not None:
            self._id_object = int(self._scene.add_triangles(
                o3d.core.Tensor(verts.astype(np.float32)),  # type: ignore[call-overload]
                o3d.core.Tensor(tris.astype(np.uint32))))  # type: ignore[call-overload]

    @property
    def T_base_object(self) -> Array:
        """Pose of the object frame in the base frame (4x4, read-only)."""
        return self._T_base_object

    @property
    def object_vertices_base(self) -> Array:
        """Placed object vertices (V, 3) [m, base frame], read-only; ground truth for metrics."""
        return self._object_vertices

    @property
    def object_triangles(self) -> NDArray[np.int32]:
        """Object triangles (F, 3) int32 indices into ``object_vertices_base``."""
        return self._object_triangles

    @property
    def table_box(self) -> tuple[Array, Array]:
        """The table's lower and upper corners (3,) [m, base frame]."""
        (cx, cy), (sx, sy) = self.table_center_xy, self.table_size_xy
        return (np.array([cx - sx / 2.0, cy - sy / 2.0, self.table_z - self.table_thickness_m]),
                np.array([cx + sx / 2.0, cy + sy / 2.0, self.table_z]))

    def cast(self, origins: Array, directions: Array) -> RayHits:
        """Cast rays from ``origins`` (N, 3) or (3,) [m, base frame] along unit ``directions`` (N, 3).

        One Open3D call for all rays. Returns the first hit of each ray (see ``RayHits``).
        """
        d = np.asarray(directions, dtype=np.float64)
        if d.ndim != 2 or d.shape[1] != 3:
            raise ValueError(f"directions must be (N, 3), got {d.shape}")
        o = np.asarray(origins, dtype=np.float64)
        if o.shape not in ((3,), d.shape):
            raise ValueError(f"origins must be (3,) or {d.shape}, got {o.shape}")
        n = len(d)
        rays = np.empty((n, 6), dtype=np.float32)  # fresh per call: cast is safe from several threads
        rays[:, :3] = o
        rays[:, 3:] = d
        ans = self._scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        geom = ans["geometry_ids"].numpy()
        what = np.zeros(n, dtype=np.int8)
        what[geom == self._id_table] = HIT_TABLE
        what[geom == self._id_object] = HIT_OBJECT
        hit = what != HIT_NONE
        t = np.where(hit, ans["t_hit"].numpy(), np.inf)  # float64
        normals = ans["primitive_normals"].numpy().astype(np.float64)  # zero for no hit
        dot = np.einsum("ij,ij->i", normals, d)
        normals *= np.where(dot > 0.0, -1.0, 1.0)[:, None]  # face the ray
        cos_inc = np.where(hit, np.abs(dot), 0.0)
        return RayHits(t=t, normals=normals, what=what, cos_incidence=cos_inc)

    def intensity(self, hits: RayHits, origins: Array, directions: Array) -> NDArray[np.uint8]:
        """The grey level (N,) of each hit: the table's (or what is printed on it, ``texture``), the
        object's, 0 for no hit."""
        out = np.zeros(hits.t.shape[0], dtype=np.uint8)
        out[hits.what == HIT_OBJECT] = INTENSITY_OBJECT
        table = hits.what == HIT_TABLE
        if self.texture is None:
            out[table] = INTENSITY_TABLE
        elif np.any(table):
            # where the table was hit matters only for what is printed there (a per-frame cost otherwise)
            o = origins if origins.ndim == 1 else origins[table]
            out[table] = self.texture.intensity(o + hits.t[table, None] * directions[table])
        return out


def _box(center_xy: tuple[float, float], size_xy: tuple[float, float], top_z: float,
         thickness: float) -> tuple[Array, NDArray[np.int64]]:
    """Axis-aligned box with top face at ``top_z``: vertices (8, 3) and outward-wound triangles (12, 3)."""
    cx, cy = center_xy
    hx, hy = size_xy[0] / 2.0, size_xy[1] / 2.0
    z0, z1 = top_z - thickness, top_z
    v = np.array([[cx - hx, cy - hy, z0], [cx + hx, cy - hy, z0], [cx + hx, cy + hy, z0],
                  [cx - hx, cy + hy, z0], [cx - hx, cy - hy, z1], [cx + hx, cy - hy, z1],
                  [cx + hx, cy + hy, z1], [cx - hx, cy + hy, z1]])
    t = np.array([[0, 2, 1], [0, 3, 2],          # bottom (-z)
                  [4, 5, 6], [4, 6, 7],          # top (+z)
                  [0, 1, 5], [0, 5, 4],          # -y
                  [1, 2, 6], [1, 6, 5],          # +x
                  [2, 3, 7], [2, 7, 6],          # +y
                  [3, 0, 4], [3, 4, 7]])         # -x
    return v, t
