"""Rigid bodies for python-fcl shared by the safety layer's collision world (``cell.safety.collision``)
and the simulated cell's contact check (:mod:`drivers.sim.contact`): poses as FCL transforms, triangle
meshes as BVHs, and the bodies an arm carries. Base frame, metres."""

from __future__ import annotations

from dataclasses import dataclass

import fcl
import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def fcl_transform(T: Array) -> fcl.Transform:
    """The FCL transform of a pose (4x4)."""
    return fcl.Transform(np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]))


def mesh_bvh(vertices: Array, triangles: NDArray[np.int32]) -> fcl.BVHModel:
    """A BVH of a triangle mesh: ``vertices`` (V, 3) [m] and ``triangles`` (F, 3) indices into them."""
    bvh = fcl.BVHModel()
    bvh.beginModel(vertices.shape[0], triangles.shape[0])
    bvh.addSubModel(np.ascontiguousarray(vertices, dtype=float),
                    np.ascontiguousarray(triangles, dtype=np.int32))
    bvh.endModel()
    return bvh


@dataclass(frozen=True)
class ArmBody:
    """A body carried by one of the arm's frames: ``frame`` indexes the robot model's ``fk_all``,
    ``T_frame_body`` (4x4) is the body's pose in that frame [m], ``geometry`` its FCL shape about that
    pose; ``bounds`` (2, 3) the lower and upper corners of a box in the body's frame [m] that holds it;
    ``levers`` (n_joints,) [m/rad] bound how far any of its points moves per radian of each joint, in any
    configuration (``cell.safety.collision.CollisionWorld.sweep_bound``); ``on_base``: it stands on the
    table (not checked against it)."""

    name: str
    frame: int
    T_frame_body: Array
    geometry: fcl.CollisionGeometry
    bounds: Array
    levers: Array
    on_base: bool
