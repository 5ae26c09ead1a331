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

Cost: nothing is checked once the arm is faulted, nor while the joints have not moved far enough since
the last check to bring any body as far as the clearance it found (:meth:`SimContact._step`); a body
whose box does not reach the object's (or the table's) axis-aligned box is not looked at closer
(:meth:`SimContact.check`).
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

LEVER_SLACK = 0.01
"""[m/rad] added to each body's levers: they come from the nominal model, the arm moves with the true one,
whose links differ by fractions of a millimetre (``drivers.sim.errors``)."""

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
    """A static body: its axis-aligned box ``lo``..``hi`` [m, base frame] as an FCL ``box``, and its
    ``mesh`` when it is not that box itself (the object)."""

    name: str
    lo: Array
    hi: Array
    box: fcl.CollisionObject
    mesh: fcl.CollisionObject | None


def _static(name: str, lo: Array, hi: Array, mesh: fcl.CollisionGeometry | None) -> _Static:
    """The static body of the box ``lo``..``hi`` [m, base frame] and, if not that box, its ``mesh``
    (base frame)."""
    T = np.eye(4)
    T[:3, 3] = (lo + hi) / 2.0
    box = fcl.CollisionObject(fcl.Box(*(hi - lo)), fcl_transform(T))
    return _Static(name, lo, hi, box, None if mesh is None else fcl.CollisionObject(mesh))


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
        # the corners (k, 4, 8) of each body's box, homogeneous, in the body's frame
        lo_hi = np.array([b.bounds for b in bodies])
        corners = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), axis=-1).reshape(8, 3)
        self._corners = np.concatenate([lo_hi[:, corners, [0, 1, 2]], np.ones((len(bodies), 8, 1))],
                                       axis=2).transpose(0, 2, 1)
        self._levers = np.array([b.levers for b in bodies]) + LEVER_SLACK
        self._request = fcl.CollisionRequest(num_max_contacts=1, enable_contact=True)
        self._distance_request = fcl.DistanceRequest()
        self._statics: list[tuple[_Static, NDArray[np.bool_]]] = []
        vertices, triangles = scene.object_vertices_base, scene.object_triangles
        if triangles.shape[0]:
            what = "the object" if scene.object_name is None else f"the object ({scene.object_name})"
            self._statics.append((_static(what, vertices.min(axis=0), vertices.max(axis=0),
                                          mesh_bvh(vertices, triangles)), np.ones(len(bodies), dtype=bool)))
        self._statics.append((_static("the table", *scene.table_box, None),
                              ~np.array([b.on_base for b in bodies], dtype=bool)))
        self._q_checked: Array | None = None
        self._clearance = np.zeros(len(bodies))
        clock.add_stepper(self._step)

    def check(self, T_frames: Array) -> tuple[Contact | None, Array]:
        """The first body of the arm in contact with the object or the table when the arm's frames are at
        ``T_frames`` (``fk_all``'s (n + 2, 4, 4), base frame), or None; and lower bounds (k,) [m] on the
        distance of each body from them (zero after a contact).

        A body whose axis-aligned box (that of its ``bounds`` box where it is) stays clear of a static
        body's is at least the boxes' gap away from it. The others are measured with FCL against the
        static body's box: its distance when they are apart (the table is that box; the object lies within
        it); when they touch, the table is touched, and the object is tested with its mesh (a contact and
        where, or no clearance known)."""
        T = T_frames[self._frames] @ self._local
        points = (T @ self._corners)[:, :3, :]
        lo, hi = points.min(axis=2), points.max(axis=2)
        clearance = np.full(len(self._bodies), np.inf)
        for st, checked in self._statics:
            gap = np.linalg.norm(np.maximum(np.maximum(st.lo - hi, lo - st.hi), 0.0), axis=1)
            near = checked & (gap <= 0.0)
            clearance = np.where(checked & ~near, np.minimum(clearance, gap), clearance)
            for i in np.nonzero(near)[0]:
                obj = self._objs[i]
                obj.setTransform(fcl_transform(T[i]))
                distance = float(fcl.distance(obj, st.box, self._distance_request, fcl.DistanceResult()))
                if distance > 0.0:
                    clearance[i] = min(clearance[i], distance)
                    continue
                clearance[i] = 0.0
                result = fcl.CollisionResult()
                if not fcl.collide(obj, st.box if st.mesh is None else st.mesh, self._request, result) \
                        and st.mesh is not None:
                    continue
                where = result.contacts[0].pos if result.contacts else T[i, :3, 3]
                return Contact(self._bodies[i].name, st.name, np.asarray(where, dtype=float)), \
                    np.zeros(len(self._bodies))
        return None, clearance

    def _step(self, dt: float) -> None:
        """After the arm's step: check it where it is now, unless no body can have come as far as its
        clearance since it was last checked. Between joints q0 and q, a body's points move by at most
        ``levers @ |q - q0|`` (:class:`ArmBody`), so while that stays below the body's clearance at q0 for
        every body, nothing can touch."""
        arm = self._arm
        if arm.fault is not None:
            return
        q = arm.joints
        if self._q_checked is not None and \
                np.all(self._levers @ np.abs(q - self._q_checked) < self._clearance):
            return
        hit, self._clearance = self.check(arm.true_frames())
        self._q_checked = q
        if hit is not None:
            arm.inject_fault(self._fault, detail=str(hit))
