"""Oriented bounding boxes standing on the table, and their intersection over union (LR-NBV paper,
section 4.1, metric 1).

A packing box is yaw-aligned: its base is the minimum-area rectangle of the points projected on the table
plane (base frame x, y), its L axis at ``yaw_rad`` about +z with L >= W, and it reaches from ``z_min``
(the table top when known) up to the highest point. All lengths in metres, base frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull, QhullError

from cell.perception.segmentation import min_area_rectangle, rectangles_at
from drivers.sim.objects import ObjectMesh
from drivers.transforms import transform_points

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PackingBox:
    """``center_xy`` (2,) [m] of the base rectangle, ``dims`` (L, W, H) [m] with L >= W, ``yaw_rad`` of
    the L axis about +z in (-pi/2, pi/2], ``z_min`` [m] of the bottom face; base frame."""

    center_xy: Array
    dims: Array
    yaw_rad: float
    z_min: float

    def axes_xy(self) -> tuple[Array, Array]:
        """The unit L and W axes (2,) in the table plane."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.array([c, s]), np.array([-s, c])

    def face_normals(self) -> Array:
        """The outward unit normals (5, 3) of the +L, -L, +W, -W faces and the top, base frame."""
        u, v = self.axes_xy()
        return np.array([[*u, 0.0], [*-u, 0.0], [*v, 0.0], [*-v, 0.0], [0.0, 0.0, 1.0]])

    def faces(self) -> Array:
        """Where the box's +L, -L, +W, -W faces and its top lie (5,) [m]: each face's coordinate along its
        outward normal (the inverse of :func:`box_from_faces`)."""
        u, v = self.axes_xy()
        cu, cv = float(self.center_xy @ u), float(self.center_xy @ v)
        half_l, half_w = self.dims[0] / 2.0, self.dims[1] / 2.0
        return np.array([cu + half_l, half_l - cu, cv + half_w, half_w - cv, self.z_min + self.dims[2]])

    @property
    def volume(self) -> float:
        return float(np.prod(self.dims))

    def footprint(self) -> Array:
        """The 4 corners (4, 2) of the base rectangle, counter-clockwise seen from above."""
        half_l, half_w = self.dims[0] / 2.0, self.dims[1] / 2.0
        local = np.array([[-half_l, -half_w], [half_l, -half_w], [half_l, half_w], [-half_l, half_w]])
        return local @ np.vstack(self.axes_xy()) + self.center_xy


# Yaws tried by the trimmed footprint search [rad]: 0.5 deg apart over a quarter turn (a rectangle's
# footprint repeats every 90 deg); a 0.25 deg yaw error costs a 0.3 m box well under 1 % of IoU.
_YAW_CANDIDATES = np.deg2rad(np.arange(0.0, 90.0, 0.5))


def _trimmed_footprint(xy: Array, trim: float) -> tuple[Array, Array, float]:
    """The rectangle of least area holding all but the ``trim`` share of the points (K, 2) beyond each of
    its four sides, among yaws of ``_YAW_CANDIDATES``: its centre (2,), extent (2,) along its axes and
    yaw [rad].

    The exact minimum-area rectangle takes its yaw from the convex hull, i.e. from a few outlying
    points: on a noisy shell of a square base it can be off by 10 deg or more, which costs more IoU than
    the noise itself. The quantile sides are what the box keeps, so the yaw is chosen on them."""
    c, s = np.cos(_YAW_CANDIDATES), np.sin(_YAW_CANDIDATES)
    u = xy[:, 0:1] * c + xy[:, 1:2] * s  # (K, Y) coordinates along each candidate's first axis
    v = -xy[:, 0:1] * s + xy[:, 1:2] * c
    lo_u, hi_u = np.quantile(u, [trim, 1.0 - trim], axis=0)
    lo_v, hi_v = np.quantile(v, [trim, 1.0 - trim], axis=0)
    best = int(np.argmin((hi_u - lo_u) * (hi_v - lo_v)))
    yaw = float(_YAW_CANDIDATES[best])
    axes = np.array([[c[best], s[best]], [-s[best], c[best]]])
    centre = 0.5 * np.array([lo_u[best] + hi_u[best], lo_v[best] + hi_v[best]]) @ axes
    return centre, np.array([hi_u[best] - lo_u[best], hi_v[best] - lo_v[best]]), yaw


def box_from_points(points_base: Array, table_z: float | None = None, trim: float = 0.0) -> PackingBox:
    """The packing box of object points (N >= 1, 3) [m], base frame: yaw of the minimum-area rectangle of
    their table-plane projection; height from ``table_z`` (or the lowest point when None) up.

    ``trim`` in [0, 0.5): the box's faces are the ``trim`` and ``1 - trim`` quantiles of the points along
    its L and W axes and the ``1 - trim`` quantile of their heights, instead of the extremes, so that a few
    noisy points on the object's shell do not grow it, and the yaw is the one whose trimmed rectangle
    has the least area (:func:`_trimmed_footprint`); 0: every point inside, the exact minimum-area
    rectangle."""
    if points_base.shape[0] == 0:
        raise ValueError("box_from_points: no points")
    if not 0.0 <= trim < 0.5:
        raise ValueError(f"box_from_points: trim must be in [0, 0.5), got {trim}")
    if trim > 0.0:
        centre, extent, yaw = _trimmed_footprint(points_base[:, :2], trim)
    else:
        centre, extent, yaw = min_area_rectangle(points_base[:, :2])
    z_min = float(points_base[:, 2].min()) if table_z is None else float(table_z)
    top = float(np.quantile(points_base[:, 2], 1.0 - trim))
    return _long_side_first(centre, extent, yaw, z_min, top)


def _long_side_first(centre: Array, extent: Array, yaw: float, z_min: float, top: float) -> PackingBox:
    """The box of base rectangle ``centre`` (2,) [m], ``extent`` (2,) [m] along the axes at ``yaw``
    [rad] and its perpendicular, from ``z_min`` up to ``top`` [m], its L axis along the longer side."""
    if extent[1] > extent[0]:
        extent = extent[::-1]
        yaw = yaw + math.pi / 2.0 if yaw <= 0.0 else yaw - math.pi / 2.0
    return PackingBox(center_xy=centre, dims=np.array([extent[0], extent[1], max(top - z_min, 0.0)]),
                      yaw_rad=yaw, z_min=z_min)


def box_from_faces(box: PackingBox, faces: Array) -> PackingBox:
    """The box with ``box``'s yaw and floor whose faces lie at ``faces`` (5,) [m]: the coordinates of
    its +L, -L, +W, -W faces along their outward normals (the L axis at ``box.yaw_rad``, base frame) and
    the height of its top."""
    u, v = box.axes_xy()
    centre = 0.5 * (faces[0] - faces[1]) * u + 0.5 * (faces[2] - faces[3]) * v
    extent = np.array([faces[0] + faces[1], faces[2] + faces[3]])
    return _long_side_first(centre, extent, box.yaw_rad, box.z_min, float(faces[4]))


def box_from_mesh(mesh: ObjectMesh, T_base_object: Array) -> PackingBox:
    """The ground-truth packing box of a mesh posed at ``T_base_object``: the same construction as
    :func:`box_from_points` on its vertices (untrimmed), from its lowest vertex up."""
    return box_from_points(transform_points(T_base_object, mesh.vertices))


# A footprint whose enclosing rectangle's area varies by at most this share over every yaw has no yaw of its
# own: a body of revolution as a mesh tessellates it (its rectangle varies by 1 / cos^2(pi / n) - 1 with n
# segments: 0.4 % with 48, 2.5 % with Open3D's default 20, 3.9 % with 16; the shipped baseball 4.6 %), or a
# regular polygon of many sides. A square varies by 100 %, a 2:1 rectangle by 125 %, the shipped bunny,
# teapot and mustard bottle by 20 % or more; an ellipse of axes up to 1.37:1 is taken as round (its
# rectangles differ by at most 5 % in area, and the comparison at the measured yaw by no more).
ROUND_FOOTPRINT_SHARE = 0.05
# Yaws on which that variation is measured [rad]: a quarter turn (a rectangle repeats every 90 deg).
_ROUND_YAWS = np.deg2rad(np.arange(0.0, 90.0, 0.25))


def _hull_xy(xy: Array) -> Array:
    """The convex hull's vertices of 2D points (K, 2); the points themselves when degenerate."""
    try:
        return xy[ConvexHull(xy).vertices]
    except (QhullError, ValueError):
        return xy


def has_round_footprint(points_base: Array) -> bool:
    """True when the table-plane footprint of points (N, 3) [m] has no yaw of its own: the area of its
    enclosing rectangle varies by at most ``ROUND_FOOTPRINT_SHARE`` over every yaw."""
    lo, hi = rectangles_at(_hull_xy(points_base[:, :2]), _ROUND_YAWS)
    area = np.prod(hi - lo, axis=0)
    return bool(area.max() <= area.min() * (1.0 + ROUND_FOOTPRINT_SHARE))


def truth_box(points_base: Array, measured: PackingBox) -> PackingBox:
    """The ground-truth packing box of an object's points (N, 3) [m] (its posed mesh's vertices) to
    compare ``measured`` with (:func:`packing_iou`).

    A packing line wants the box's dimensions and where it stands. Where the object's footprint has a yaw
    of its own, the truth is :func:`box_from_points` of its points: the minimum-area rectangle, and a
    measured box turned away from it loses IoU, as it should. A footprint without one
    (:func:`has_round_footprint`: a can, a ball, a cone) has a minimum-area rectangle at an arbitrary yaw,
    set by the tessellation of its mesh and by the last digits of its pose (a replay of the same cloud
    with the pose rounded to 9 digits picked another), and so does the measured box; every yaw's
    enclosing rectangle is as good a box of it (within ``ROUND_FOOTPRINT_SHARE`` of the least area). Its
    truth is the rectangle enclosing its points at the measured box's own yaw, computed the same way
    (every point inside, from the lowest point up): the comparison is then of dimensions and placement
    only, the same whatever the yaw of the object, of its mesh or of the measured box."""
    if not has_round_footprint(points_base):
        return box_from_points(points_base)
    lo, hi = rectangles_at(points_base[:, :2], np.array([measured.yaw_rad]))
    u, v = measured.axes_xy()
    middle = 0.5 * (lo[:, 0] + hi[:, 0])
    return _long_side_first(middle[0] * u + middle[1] * v, hi[:, 0] - lo[:, 0], measured.yaw_rad,
                            float(points_base[:, 2].min()), float(points_base[:, 2].max()))


def packing_iou(measured: PackingBox, mesh: ObjectMesh, T_base_object: Array) -> float:
    """IoU of a measured packing box with the ground truth of ``mesh`` posed at ``T_base_object``
    (:func:`truth_box`; LR-NBV paper, section 4.1, metric 1)."""
    return box_iou(measured, truth_box(transform_points(T_base_object, mesh.vertices), measured))


def _clip(subject: Array, clip: Array) -> Array:
    """Sutherland-Hodgman: the part of convex polygon ``subject`` (n, 2) inside convex polygon ``clip``
    (m, 2), both counter-clockwise; returns the vertices (k, 2), k = 0 when they do not overlap."""
    out = subject
    for i in range(clip.shape[0]):
        if out.shape[0] == 0:
            break
        a, b = clip[i], clip[(i + 1) % clip.shape[0]]
        edge = b - a
        # Signed area test: >= 0 on the left of a->b, i.e. inside a counter-clockwise polygon.
        side = edge[0] * (out[:, 1] - a[1]) - edge[1] * (out[:, 0] - a[0])
        kept: list[Array] = []
        for j in range(out.shape[0]):
            k = (j + 1) % out.shape[0]
            p, q, sp, sq = out[j], out[k], side[j], side[k]
            if sp >= 0.0:
                kept.append(p)
            if (sp >= 0.0) != (sq >= 0.0):
                kept.append(p + (q - p) * (sp / (sp - sq)))
        out = np.array(kept).reshape(-1, 2)
    return out


def _polygon_area(poly: Array) -> float:
    """Area (shoelace) of a simple polygon (n, 2); 0 for fewer than 3 vertices."""
    if poly.shape[0] < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def box_iou(a: PackingBox, b: PackingBox) -> float:
    """Intersection over union of two yaw-aligned boxes (volumes): footprint intersection area times the
    overlap of their height ranges, over the union of the volumes. 0 when either box is empty."""
    union_parts = a.volume + b.volume
    if a.volume <= 0.0 or b.volume <= 0.0:
        return 0.0
    dz = min(a.z_min + a.dims[2], b.z_min + b.dims[2]) - max(a.z_min, b.z_min)
    if dz <= 0.0:
        return 0.0
    inter = _polygon_area(_clip(a.footprint(), b.footprint())) * dz
    return float(inter / (union_parts - inter))
