"""Configuration of each arm backend, selected by ``type:`` (a pydantic discriminated union)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, PositiveFloat

from drivers.config_base import StrictModel

RobotModelName = Literal["panda", "ur5e"]


class PoseErrorConfig(StrictModel):
    """Simulated calibration and kinematic error, drawn once per job from the job's generator.

    The simulated arm moves with perturbed kinematics but reports poses from the nominal model, so the
    poses a job sees are off by a few millimetres like a real arm's, and registration has something to
    correct. ``joint_offset_std_rad``: encoder zero offset per joint; ``link_std_m``: error on every
    DH length (a and d).
    """

    joint_offset_std_rad: float = Field(ge=0.0, le=0.05)
    link_std_m: float = Field(ge=0.0, le=0.01)


class SimArmConfig(StrictModel):
    """The simulated arm: integrates commanded twists through the model's differential IK."""

    type: Literal["sim"]
    model: RobotModelName
    home_joints_rad: list[float] | None = None
    pose_error: PoseErrorConfig | None = None


class UR5eArmConfig(StrictModel):
    """A UR5e controller reached through ur-rtde (hardware backend)."""

    type: Literal["ur5e"]
    model: Literal["ur5e"] = "ur5e"
    host: str
    home_joints_rad: list[float] | None = None
    connect_timeout_s: PositiveFloat = 5.0


class FrankaArmConfig(StrictModel):
    """A Franka arm reached through franky (hardware backend)."""

    type: Literal["franka"]
    model: Literal["panda"] = "panda"
    host: str
    home_joints_rad: list[float] | None = None
    relative_dynamics_factor: float = Field(default=0.1, gt=0.0, le=1.0)


ArmConfig = Annotated[SimArmConfig | UR5eArmConfig | FrankaArmConfig, Field(discriminator="type")]
