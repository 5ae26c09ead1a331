"""The simulated arm's contact with what stands in the cell: the object as the sim placed it, and the table.

A real arm that hits the part stops: a UR5e's controller goes into a protective stop (its collision
detection), a Franka into a reflex. The simulated arm does the same. After the arm has moved in a sim step
(every ``clock.sleep``: one control period in a job), :class:`SimContact` tests the arm's bodies where it
really is (the true model's forward kinematics, :meth:`SimArm.true_frames`) with python-fcl against a BVH
of the placed object's triangles (built once per job) and against the table's slab; the first body in
contact faults the arm through :meth:`SimArm.inject_fault`, as the ``sim.faults`` schedule does
(:mod:`drivers.sim.faults`), with the kind the real arm would report (:data:`CONTACT_FAULTS`) and what
touched what where [m, base frame], e.g. ``protective stop: contact: forearm touched the object (box) at
(0.297, -0.210, 0.300) m``. The guard stops the job on it (``arm fault: ...``) as on any arm fault.

The bodies are the ones the safety layer checks its motions with (the robot model's link capsules and the
cell file's ``safety.collision.tool`` bodies: ``cell.safety.collision.CollisionWorld.arm_bodies``), so
the sim faults on what the guard would have refused had it known the object's true shape. The links that
stand on the table (the base and the first joint's housing, ``ArmBody.on_base``) are not checked against
it.

The check is discrete, at the end of each step that moved the joints, and an FCL test of a mesh finds
where a body crosses the object's surface (a body wholly inside the object touches none of its
triangles). A body gets inside only by crossing the surface, and in a step of a job it moves millimetres
(streamed twists) to a couple of centimetres (the fastest point-to-point moves): less than the bodies'
own sizes (4 cm and more), so the crossing is caught on the step it happens. A body that went wholly
through a wall thinner than a step's motion less its own size, between two checks, would be missed.

Cost: nothing is checked while the joints have not moved or once the arm is faulted; a body whose
bounding sphere does not reach the object's (or the table's) axis-aligned box is not looked at closer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import fcl
import numpy as np
from numpy.typing import NDArray

from drivers.fcl_bodies import ArmBody, fcl_transform, mesh_bvh

if TYPE_CHECKING:  # the devices it watches
    from drivers.arm.sim import SimArm
    from drivers.clock import SimClock
    from drivers.sim.scene import SimScene

Array = NDArray[np.float64]

CONTACT_FAULTS: dict[str, str] = {"ur5e": "protective stop", "panda": "reflex"}
"""The fault each robot model's controller reports when the arm hits something (by model name)."""


@dataclass(frozen=True)
class Contact:
    """A body of the arm touching ``what`` (``"the object"``, ``"the table"``) at ``point_base``
    [m, base frame]; ``str`` says so for a fault."""

    body: str
    what: str
    point_base: Array

    def __str__(self) -> str:
        x, y, z = self.point_base
        return f"contact: {self.body} touched {self.what} at ({x:.3f}, {y:.3f}, {z:.3f}) m"


@dataclass
class _Static:
    name: str
    obj: fcl.CollisionObject
    lo: Array
    hi: Array


def _aabb_static(name: str, geometry: fcl.CollisionGeometry, T: Array, lo: Array, hi: Array) -> _Static:
    """A static body and its axis-aligned box ``lo``..``hi`` [m, base frame]."""
    return _Static(name, fcl.CollisionObject(geometry, fcl_transform(T)), lo, hi)


class SimContact:
    """Faults ``arm`` when one of its ``bodies`` touches the object or the table of ``scene`` (see the
    module docstring); registered as a clock stepper after the arm, so it sees where each step left the
    arm."""

    def __init__(self, clock: SimClock, arm: SimArm, scene: SimScene, bodies: list[ArmBody]) -> None:
        name = arm.model.name
        if name not in CONTACT_FAULTS:
            raise ValueError(f"sim contact: no contact fault for robot model {name!r} (known: "
                             f"{', '.join(CONTACT_FAULTS)})")
        self._fault = CONTACT_FAULTS[name]
        self._arm = arm
        self._bodies = bodies
        self._objs = [fcl.CollisionObject(b.geometry) for b in bodies]
        self._frames = np.array([b.frame for b in bodies], dtype=int)
        self._local = np.array([b.T_frame_body for b in bodies])
        self._radii = np.array([b.radius for b in bodies])
        self._request = fcl.CollisionRequest(num_max_contacts=1, enable_contact=True)
        self._statics: list[tuple[_Static, NDArray[np.bool_]]] = []
        vertices, triangles = scene.object_vertices_base, scene.object_triangles
        if triangles.shape[0]:
            bvh = mesh_bvh(vertices, triangles)
            what = "the object" if scene.object_name is None else f"the object ({scene.object_name})"
            self._statics.append((_aabb_static(what, bvh, np.eye(4), vertices.min(axis=0),
                                               vertices.max(axis=0)), np.ones(len(bodies), dtype=bool)))
        lo, hi = scene.table_box
        slab = np.eye(4)
        slab[:3, 3] = (lo + hi) / 2.0
        self._statics.append((_aabb_static("the table", fcl.Box(*(hi - lo)), slab, lo, hi),
                              ~np.array([b.on_base for b in bodies], dtype=bool)))
        self._q_checked: Array | None = None
        clock.add_stepper(self._step)

    def contact(self, T_frames: Array) -> Contact | None:
        """The first body of the arm in contact with the object or the table when the arm's frames are at
        ``T_frames`` (``fk_all``'s (n + 2, 4, 4), base frame), or None."""
        T = T_frames[self._frames] @ self._local
        centers = T[:, :3, 3]
        for st, checked in self._statics:
            # a sphere reaches a box when the box's nearest point to its centre lies within its radius
            gap = np.linalg.norm(centers - np.clip(centers, st.lo, st.hi), axis=1)
            for i in np.nonzero(checked & (gap <= self._radii))[0]:
                obj = self._objs[i]
                obj.setTransform(fcl_transform(T[i]))
                result = fcl.CollisionResult()
                if fcl.collide(obj, st.obj, self._request, result) > 0:
                    where = result.contacts[0].pos if result.contacts else centers[i]
                    return Contact(self._bodies[i].name, st.name, np.asarray(where, dtype=float))
        return None

    def _step(self, dt: float) -> None:
        arm = self._arm
        if arm.fault is not None:
            return
        q = arm.joints
        if self._q_checked is not None and np.array_equal(q, self._q_checked):
            return
        self._q_checked = q
        hit = self.contact(arm.true_frames())
        if hit is not None:
            arm.inject_fault(self._fault, detail=str(hit))
