"""Small SE(3) helpers on 4x4 homogeneous matrices (numpy, float64).

Naming follows the design guide: ``T_a_b`` is the pose of frame b expressed in frame a.
Rotations as roll-pitch-yaw are extrinsic x-y-z (R = Rz(yaw) Ry(pitch) Rx(roll)), angles in radians.
Quaternions are (x, y, z, w), scalar last.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

Array = NDArray[np.float64]


def make_T(R: NDArray[np.floating], p: NDArray[np.floating]) -> Array:
    """Homogeneous transform (float64) from a 3x3 rotation and a translation [m] of any float dtype."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def T_from_xyz_rpy(xyz: Array | Sequence[float], rpy: Array | Sequence[float]) -> Array:
    """Transform from a translation [m] and roll, pitch, yaw [rad] (extrinsic x-y-z)."""
    R = Rotation.from_euler("xyz", np.asarray(rpy, dtype=float)).as_matrix()
    return make_T(R, np.asarray(xyz, dtype=float))


def inv_T(T: Array) -> Array:
    """Inverse of a rigid transform."""
    R = T[:3, :3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def transform_points(T: Array, points: Array) -> Array:
    """Apply ``T`` to an (N, 3) array of points."""
    return points @ T[:3, :3].T + T[:3, 3]


def quat_xyzw(T: Array) -> Array:
    """Unit quaternion (x, y, z, w) of the rotation of ``T``, with w >= 0 for a unique sign."""
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return -q if q[3] < 0 else q


def rotvec(R: Array) -> Array:
    """Axis-angle vector [rad] of a rotation matrix."""
    return Rotation.from_matrix(R).as_rotvec()


def pose_error(T_current: Array, T_goal: Array) -> Array:
    """Twist-like error (dx, dy, dz, rx, ry, rz) from ``T_current`` to ``T_goal``, both in the same frame.

    The translation part is the position difference [m], the rotation part the axis-angle [rad] of
    R_goal R_current^T, both expressed in that common frame.
    """
    dp = T_goal[:3, 3] - T_current[:3, 3]
    dr = rotvec(T_goal[:3, :3] @ T_current[:3, :3].T)
    return np.concatenate([dp, dr])


def look_at(eye: Array, target: Array, up_hint: Array | None = None) -> Array:
    """Camera pose (z along the optical axis, x right, y down) at ``eye`` looking at ``target``.

    ``up_hint`` is the world direction that should appear "up" in the image (default +z); when the view
    is parallel to it, +x of the world is used instead.
    """
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    n = np.linalg.norm(z)
    if n < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z /= n
    up = np.array([0.0, 0.0, 1.0]) if up_hint is None else np.asarray(up_hint, dtype=float)
    if abs(float(np.dot(up, z))) > 1.0 - 1e-6:
        up = np.array([1.0, 0.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.column_stack([x, y, z]), eye)


def smallest_rotation(u: Array, v: Array) -> Array:
    """The rotation (3, 3) by the smallest angle that turns unit vector ``u`` (3,) onto unit ``v`` (3,),
    about their common normal; for opposite vectors, one of the half turns."""
    axis = np.cross(u, v)
    s = float(np.linalg.norm(axis))
    angle = float(np.arctan2(s, float(u @ v)))
    if s < 1e-12:
        if angle < np.pi / 2:
            return np.eye(3)
        axis = np.cross(u, np.eye(3)[int(np.argmin(np.abs(u)))])  # any normal of u
        s = float(np.linalg.norm(axis))
    return Rotation.from_rotvec(axis * (angle / s)).as_matrix()
