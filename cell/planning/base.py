"""What a planner is, and the session it drives.

A planner decides where the sensor goes next and when to capture; it talks to the cell only through a
``ScanSession`` (implemented by ``cell.jobs``), which routes every motion through the safety guard.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from cell.config.models import CellConfig
from cell.perception.pipeline import PerceptionPipeline, PerceptionUpdate
from drivers.depth.base import SensorModel

Array = NDArray[np.float64]


class ScanSession(Protocol):
    """The services a planner may use during a scan. Poses are 4x4 in the robot base frame."""

    config: CellConfig
    rng: np.random.Generator
    """The job's generator for a planner's random draws (a stream of the job's ``--seed`` of its own, so
    planning never changes the noise the simulated devices see)."""
    perception: PerceptionPipeline
    """The job's perception pipeline, to read (never to feed): its occupancy map (``perception.map``, e.g.
    for an NBV objective) and accumulated cloud; ``latest_perception`` is its newest update. While
    continuous capture runs on the wall clock the pipeline is written on another thread: read the map of
    the newest update (``latest_perception().map``) instead, a copy nothing writes."""

    def log(self, message: str) -> None:
        """Add a line to the job's log, stamped with job time."""
        ...

    def now(self) -> float:
        """Job time [s] (sim time in sim mode)."""
        ...

    def sensor_pose(self) -> Array:
        """T_base_sensor as reported by the arm and the hand-eye transform."""
        ...

    def sensor_model(self) -> SensorModel:
        """The connected sensor's viewing geometry (field of view, pixels or zones, range)."""
        ...

    def move_to_sensor_pose(self, T_base_sensor: Array) -> bool:
        """Move so that the sensor reaches ``T_base_sensor`` (joint-space, guarded, blocking in job time):
        straight to the joints solved from the current ones or from home, or by way of home when the
        guard refuses the straight move, else the same way to the pose rolled about the sensor's optical
        axis where the roll sees the same (a sensor's captures hold the pose they were taken from).
        Returns False, and records and counts why, when the pose has no reachable joint solution or the
        safety layer would refuse every one of those moves (collision, barrier plane, joint margin)."""
        ...

    def retrace(self, duration_s: float) -> bool:
        """After the guard stopped a streamed twist: once the arm is at rest, move it back (joint space,
        guarded, blocking in job time) to the joints it had ``duration_s`` [s] before, along the path it
        came. Returns False, without moving, when the arm reports no joints or the guard would refuse
        the move."""
        ...

    def wait(self, dt: float) -> None:
        """Let ``dt`` [s] pass with the arm doing what it was told. Raises ``TwistRefused``
        (``cell.safety.guard``) when the guard refused a streamed twist: the arm has been stopped and the
        refusal counted; the planner may command another twist (back off) or let it end the job."""
        ...

    def capture(self) -> int:
        """Capture one frame at the current pose and run it through the perception pipeline; returns the
        number of points it kept."""
        ...

    def set_continuous_capture(self, on: bool) -> None:
        """Capture at the configured perception rate while moving (as the servo planners do), or not.
        While it is on, the watchdog stops the arm when perception data grow too old."""
        ...

    def command_sensor_twist(self, v_sensor: Array) -> Array:
        """Stream a twist of the sensor frame expressed in the sensor frame (v [m/s], w [rad/s]; the
        papers' camera twist) through the guard until the next command or ``hold``; ``wait`` lets it act.
        Returns the twist the limits and barrier planes allow now, sensor frame."""
        ...

    def hold(self) -> None:
        """Ramp a streamed twist down to rest (within the acceleration limits)."""
        ...

    def joint_limit_twists(self, activation_rad: float) -> Array:
        """Rows a (m, 6), one per joint closer than ``activation_rad`` [rad] to its position margin: a
        sensor twist v (sensor frame) moves that joint towards the margin at a . v [rad/s] (first order),
        so that a planner can keep its motion from pressing into a joint limit (as barrier planes)."""
        ...

    def singularity_twists(self, activation: float) -> Array:
        """Rows a (0 or 1, 6): while the smallest singular value of the arm's Jacobian is below
        ``activation``, a sensor twist v (sensor frame) lowers it at a . v (first order), so that a
        planner can keep its motion from driving the arm into a singularity (as barrier planes)."""
        ...

    def feasible_sensor_velocity(self, v_sensor: Array, activation_m: float) -> Array:
        """Project a desired sensor velocity or direction (3,), sensor frame, into the set the barrier
        planes allow: the component into any plane closer than ``activation_m`` is removed so the motion
        slides along it (visual-servoing paper Fig. 3)."""
        ...

    def sensor_pose_allowed(self, T_base_sensor: Array) -> bool:
        """Whether a candidate sensor pose keeps the TCP and the sensor inside every barrier plane and the
        workspace box (e.g. to reject global goal candidates)."""
        ...

    def sensor_poses_allowed(self, T_base_sensor: Array, from_here: bool = False) -> NDArray[np.bool_]:
        """``sensor_pose_allowed`` of each of the poses (K, 4, 4); ``from_here``: as far into a plane's
        margin as a motion from the current pose may go (a camera sliding along a plane is inside its
        margin, and so is every view at its height)."""
        ...

    def sensor_path_reachable(self, T_base_sensor: Array, min_singular_value: float = 0.0) -> bool:
        """Whether the arm follows sensor poses (K, 4, 4) in turn from where it is (K = 1: reaches one
        pose): inverse kinematics seeded from the current joints, then from each solution for the next
        pose (a servo travels continuously, so the solutions near the present configuration are the ones
        that count), every solution with each joint inside its position margin, free of collision and
        with the smallest singular value of the arm's Jacobian at least ``min_singular_value`` (clear of
        the edge of its reach), and no joint jumping between consecutive poses (a change of
        configuration the servo cannot make)."""
        ...

    def sensor_view_reachable(self, T_base_sensor: Array) -> bool:
        """Whether ``move_to_sensor_pose`` finds joints for the view (4, 4) that the arm may take (inside
        every joint's position margin, free of collision): among the inverse-kinematics solutions a move
        tries (seeded from the current joints and from home: a point-to-point move may change the arm's
        configuration) at the pose or at a roll about the optical axis after which the sensor sees the
        same. The move checks its path as well."""
        ...

    def latest_perception(self) -> PerceptionUpdate | None:
        """The newest perception update (pose, object, ROI, H_ROI), None before the first frame."""
        ...


class Planner(ABC):
    """A scan strategy. ``run`` drives the session until done and returns why it ended, in words. A job
    finds it by the name, with the description, that :mod:`cell.planning.registry` gives it."""

    def __init__(self, config: CellConfig) -> None:
        self.config = config

    @abstractmethod
    def run(self, session: ScanSession) -> str: ...

    def search_views(self) -> list[Array]:
        """The sensor poses T_base_sensor (4x4, base frame [m]) from which the planner looks for the object
        before it has found one, in the order it tries them: a placement none of them sees ends in
        ``no_object`` (``cell.jobs.placement.check_in_view``). Empty when it does not say (no placement is
        refused then)."""
        return []

    def figures(self) -> dict[str, float | int | str | None]:
        """The planner's own figures of the scan so far, for progress reports (names carry units);
        none by default."""
        return {}
