"""Small SE(3) helpers on 4x4 homogeneous matrices (numpy, float64).

Naming follows the design guide: ``T_a_b`` is the pose of frame b expressed in frame a.
Rotations as roll-pitch-yaw are extrinsic x-y-z (R = Rz(yaw) Ry(pitch) Rx(roll)), angles in radians.
Quaternions are (x, y, z, w), scalar last.
"""

from __future__ import annotations

import math
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
    """Unit quaternion (x, y, z, w) of the rotation of ``T`` (4x4, or a 3x3 rotation), with w >= 0 for a
    unique sign.

    In closed form from whichever of the trace and the three diagonal entries is largest (Shepperd 1978,
    the choice SciPy's ``Rotation.from_matrix`` makes too): the component it gives is at least 1/2, so
    dividing by it is well conditioned at every angle. For one matrix this is some 20 times faster than
    building a ``Rotation``, and the control loop and the IK call it every tick and every iteration.
    """
    R = T[:3, :3]
    r00, r11, r22 = float(R[0, 0]), float(R[1, 1]), float(R[2, 2])
    trace = r00 + r11 + r22
    i = 0 if r00 >= r11 and r00 >= r22 else (1 if r11 >= r22 else 2)
    if trace > float(R[i, i]):
        q = [float(R[2, 1] - R[1, 2]), float(R[0, 2] - R[2, 0]), float(R[1, 0] - R[0, 1]), 1.0 + trace]
    else:
        j, k = (i + 1) % 3, (i + 2) % 3
        q = [0.0, 0.0, 0.0, float(R[k, j] - R[j, k])]
        q[i] = 1.0 - trace + 2.0 * float(R[i, i])
        q[j] = float(R[j, i] + R[i, j])
        q[k] = float(R[k, i] + R[i, k])
    out = np.array(q) / math.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)
    return -out if out[3] < 0.0 else out


def rotvec(R: Array) -> Array:
    """Axis-angle vector [rad] of a rotation matrix (3, 3), its angle in [0, pi]: twice the angle of
    :func:`quat_xyzw`'s quaternion, about its vector part."""
    q = quat_xyzw(R)
    s = math.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2)
    if s == 0.0:
        return np.zeros(3)
    return q[:3] * (2.0 * math.atan2(s, q[3]) / s)


def rotation_from_rotvec(r: Array | Sequence[float]) -> Array:
    """The rotation matrix (3, 3) of an axis-angle vector ``r`` [rad] (Rodrigues' formula, its second
    coefficient (1 - cos a) / a^2 written with the half angle, so that it loses no digits at small angles)."""
    rx, ry, rz = (float(v) for v in r)
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle == 0.0:
        return np.eye(3)
    half = 0.5 * angle
    a = math.sin(angle) / angle
    b = 0.5 * (math.sin(half) / half) ** 2
    # I + a K + b K^2 with K = [r]x, and K^2 = r r^T - |r|^2 I
    c = 1.0 - b * angle * angle
    return np.array([[c + b * rx * rx, b * rx * ry - a * rz, b * rx * rz + a * ry],
                     [b * rx * ry + a * rz, c + b * ry * ry, b * ry * rz - a * rx],
                     [b * rx * rz - a * ry, b * ry * rz + a * rx, c + b * rz * rz]])


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
    return rotation_from_rotvec(axis * (angle / s))
