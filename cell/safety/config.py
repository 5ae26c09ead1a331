"""The ``safety`` section of a cell file: limits, barrier planes, the collision world and the watchdog.

Units are SI (m, s, rad); frames: barrier planes, obstacles and the workspace box are in the robot base
frame, tool bodies in the flange frame. Safety values have no defaults: a cell file states them, as numbers
(strict: a quoted "475" is refused, not read; an integer is a number). The robot model's own maxima are
hard ceilings, checked when the cell file is loaded (``cell.config.load``).
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from drivers.config_base import (
    CELL_SIZE,
    IN_CELL,
    ONE_TURN,
    Bounds,
    Number,
    PositiveCount,
    PositiveNumber,
    StrictModel,
)
from drivers.transforms import T_from_xyz_rpy

Vec3 = tuple[Number, Number, Number]
Coordinate = Annotated[Number, IN_CELL]
"""[m] a coordinate of a place in the cell, written as a number (:data:`~drivers.config_base.CELL_EXTENT_M`:
a workspace or a barrier plane given in millimetres is no limit at all)."""
Point = tuple[Coordinate, Coordinate, Coordinate]
Angle = Annotated[Number, ONE_TURN]
"""[deg] an angle of a rotation, written as a number, within one turn."""
Size = Annotated[Number, CELL_SIZE]
"""[m] a size in the cell, written as a number (:data:`~drivers.config_base.CELL_EXTENT_M`)."""


class WorkspaceConfig(StrictModel):
    """Box in the base frame [m] that the sensor and the flange must stay inside; the guard treats its
    six faces as barrier planes."""

    min_m: Point
    max_m: Point

    @model_validator(mode="after")
    def _ordered(self) -> WorkspaceConfig:
        if not all(lo < hi for lo, hi in zip(self.min_m, self.max_m, strict=True)):
            raise ValueError(f"min_m {self.min_m} must be below max_m {self.max_m} on every axis")
        return self


class BarrierPlaneConfig(StrictModel):
    """A virtual barrier plane (visual-servoing paper section III-A, Fig. 3): a ``point`` on it [m] and its
    ``normal`` pointing into the allowed side, both in the base frame. ``name`` appears in the logs."""

    point: Point
    """[m] a point on the plane, in the base frame."""
    normal: Vec3
    """[1] the direction into the allowed side, in the base frame (any length but zero)."""
    name: str | None = None

    @field_validator("normal")
    @classmethod
    def _nonzero(cls, n: Vec3) -> Vec3:
        if float(np.linalg.norm(n)) < 1e-9:
            raise ValueError("normal must not be the zero vector")
        return n


class BodyPose(StrictModel):
    """Pose of a body's centre: translation ``xyz_m`` [m], extrinsic roll-pitch-yaw ``rpy_deg`` [deg]."""

    xyz_m: Point
    rpy_deg: tuple[Angle, Angle, Angle] = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        return T_from_xyz_rpy(self.xyz_m, np.deg2rad(self.rpy_deg))


class BoxBody(StrictModel):
    """A box of edge lengths ``size_m`` centred on its pose."""

    shape: Literal["box"]
    name: str
    size_m: tuple[Size, Size, Size]
    pose: BodyPose


class CylinderBody(StrictModel):
    """A cylinder of ``radius_m`` and ``length_m`` along its pose's z axis, centred on the pose."""

    shape: Literal["cylinder"]
    name: str
    radius_m: Size
    length_m: Size
    pose: BodyPose


class MeshBody(StrictModel):
    """A triangle mesh in metres (any format Open3D reads; a relative ``path`` is taken from the working
    directory) placed at its pose."""

    shape: Literal["mesh"]
    name: str
    path: str
    pose: BodyPose


Body = Annotated[BoxBody | CylinderBody | MeshBody, Field(discriminator="shape")]


class TableConfig(StrictModel):
    """The table slab: its top at ``station.table_z_m``, centre ``center_xy_m`` and ``size_m`` [m] in the
    base frame, ``thickness_m`` below the top. The arm's moving bodies keep ``clearance_m`` [m] above the
    top: the guard knows the tool where the arm's model and calibration put it, and a calibrated cell's
    tool is still off by millimetres (the sim's errors: hand-eye 1.5 mm and 0.15 deg, joint offsets 0.2
    mrad, links 0.2 mm; a camera's corner 0.1 m from the flange moves 0.3 mm per 0.15 deg). With no
    clearance a Franka camera body came to 1 mm over the table by the job's model and touched it in the
    sim; the barrier planes keep the sensor as far from theirs (``barrier_margin_m``, 5 mm)."""

    center_xy_m: tuple[Coordinate, Coordinate]
    size_m: tuple[Size, Size]
    thickness_m: Size = 0.05
    clearance_m: Annotated[Number, Bounds(0.0, 0.05, "m", "a clearance over the table is at most 5 cm")] \
        = 0.005


class CollisionConfig(StrictModel):
    """The collision world checked with python-fcl.

    ``lookahead_s``: each control tick checks the joint path to the configuration predicted this far
    ahead at the commanded velocity, continuously (``CollisionWorld.check_motion``).
    ``trajectory_step_rad``: the joint paths of point-to-point moves are cut into stretches no longer than
    this in any joint, each checked continuously (``CollisionWorld.check_path``).
    ``roi_margin_m``: the object's ROI box is inflated by this much on each side. ``tool``: bodies carried
    by the flange (the sensor and its bracket), posed in the flange frame.
    ``obstacles``: static bodies in the base frame.
    """

    lookahead_s: Number = Field(gt=0.0, le=1.0)
    trajectory_step_rad: Number = Field(gt=0.0, le=0.2)
    roi_margin_m: Annotated[Number, Bounds(0.0, 0.5, "m", "a margin around the object is at most 0.5 m")]
    table: TableConfig
    tool: list[Body] = Field(min_length=1)
    obstacles: list[Body]


class WatchdogConfig(StrictModel):
    """When the control loop or perception is late, the arm stops.

    A control tick misses its deadline when it comes more than ``deadline_factor`` control periods after
    the previous one; ``max_missed_deadlines`` misses in a row stop the arm. While a planner streams
    motion from perception (continuous capture), perception older than ``perception_max_age_s`` [s]
    stops the arm.
    """

    deadline_factor: Number = Field(gt=1.0)
    """[1] control periods after the previous tick beyond which a tick has missed its deadline."""
    max_missed_deadlines: PositiveCount
    perception_max_age_s: PositiveNumber


class SafetyConfig(StrictModel):
    """Motion limits of the cell (safety issue, items 1-5).

    TCP (flange) limits: ``tcp_max_linear_mps`` [m/s], ``tcp_max_angular_rps`` [rad/s], accelerations
    ``tcp_max_linear_acc_mps2`` [m/s^2], ``tcp_max_angular_acc_rps2`` [rad/s^2] and jerks
    ``tcp_max_linear_jerk_mps3`` [m/s^3], ``tcp_max_angular_jerk_rps3`` [rad/s^3] (ruckig smoothing of
    streamed twists). Joint limits: ``joint_velocity_scale``, ``joint_acceleration_scale``,
    ``joint_jerk_scale`` are the shares (0, 1] of each joint's maxima that motion may use;
    ``joint_position_margin_rad`` keeps joints this far inside their limits. ``barrier_margin_m``: the
    TCP and the sensor keep this distance from every barrier plane and workspace face, so that the arm's
    tracking lag never takes them across.
    """

    tcp_max_linear_mps: PositiveNumber
    tcp_max_angular_rps: PositiveNumber
    tcp_max_linear_acc_mps2: PositiveNumber
    tcp_max_angular_acc_rps2: PositiveNumber
    tcp_max_linear_jerk_mps3: PositiveNumber
    tcp_max_angular_jerk_rps3: PositiveNumber
    joint_velocity_scale: Number = Field(gt=0.0, le=1.0)
    """[1] the share of each joint's maximum velocity that motion may use."""
    joint_acceleration_scale: Number = Field(gt=0.0, le=1.0)
    """[1] the share of each joint's maximum acceleration that motion may use."""
    joint_jerk_scale: Number = Field(gt=0.0, le=1.0)
    """[1] the share of each joint's maximum jerk that motion may use."""
    joint_position_margin_rad: Number = Field(ge=0.0, le=0.5)
    workspace: WorkspaceConfig
    barrier_planes: list[BarrierPlaneConfig]
    barrier_margin_m: Number = Field(ge=0.0, le=0.1)
    collision: CollisionConfig
    watchdog: WatchdogConfig
