"""Backends from configuration: one registry per hardware kind, keyed by the config's ``type:``.

Registration is explicit (a dict below), so a type is known whether or not its module was imported.
Hardware backends import their client library only when built.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from drivers.arm.base import Arm
from drivers.arm.config import ArmConfig, FrankaArmConfig, ReplayArmConfig, SimArmConfig, UR5eArmConfig
from drivers.arm.hardware import require_module
from drivers.arm.replay import ReplayArm
from drivers.arm.sim import SimArm
from drivers.clock import Clock, SimClock, WallClock
from drivers.depth.base import DepthSensor
from drivers.depth.config import (
    DepthConfig,
    RealSenseConfig,
    ReplayConfig,
    SimRGBDConfig,
    SimToFConfig,
    VL53L8CXConfig,
)
from drivers.depth.replay import JobRecording, PlaybackClock, ReplaySensor
from drivers.depth.sim_rgbd import SimRGBD
from drivers.depth.sim_tof import SimToF
from drivers.errors import DriverError
from drivers.robots.model import RobotModel
from drivers.sim.errors import SimErrors
from drivers.sim.scene import SimScene

Array = NDArray[np.float64]


@dataclass
class SimWorld:
    """What simulated backends share: the job's clock, random generator and scene. The clock is the
    simulated one in sim mode; in a dry run (a hardware arm with a simulated sensor) it is the wall clock,
    and the simulated arm, which needs the simulated clock, is not part of it. A replayed job plays on the
    simulated clock and has no scene. ``errors``: the calibration error the simulated arm and sensor
    really have (``drivers.sim.errors``; none by default)."""

    clock: Clock
    rng: np.random.Generator
    scene: SimScene | None
    errors: SimErrors = field(default_factory=SimErrors.none)


def _need_sim(sim: SimWorld | None, kind: str) -> SimWorld:
    if sim is None:
        raise DriverError("a simulated backend needs a simulated world (mode: sim or dry-run)", device=kind)
    return sim


def _need_scene(sim: SimWorld | None, kind: str) -> SimScene:
    scene = _need_sim(sim, kind).scene
    if scene is None:
        raise DriverError("a simulated sensor needs a simulated scene (mode: sim or dry-run)", device=kind)
    return scene


def _sim_arm(cfg: ArmConfig, model: RobotModel, sim: SimWorld | None) -> Arm:
    assert isinstance(cfg, SimArmConfig)
    world = _need_sim(sim, "arm sim")
    if not isinstance(world.clock, SimClock):
        raise DriverError("the simulated arm needs the simulated clock (mode: sim)", device="arm sim")
    return SimArm(cfg, model, world.clock, world.errors.true_model)


def _ur5e_arm(cfg: ArmConfig, model: RobotModel, sim: SimWorld | None) -> Arm:
    assert isinstance(cfg, UR5eArmConfig)
    require_module("rtde_control", "ur-rtde==1.6.5", "arm ur5e")
    from drivers.arm.ur5e import UR5eArm

    return UR5eArm(cfg, model)


def _franka_arm(cfg: ArmConfig, model: RobotModel, sim: SimWorld | None) -> Arm:
    assert isinstance(cfg, FrankaArmConfig)
    require_module("franky", "franky-control==2.0.0", "arm franka")
    from drivers.arm.franka import FrankaArm

    return FrankaArm(cfg, model)


def _replay_arm(cfg: ArmConfig, model: RobotModel, sim: SimWorld | None) -> Arm:
    assert isinstance(cfg, ReplayArmConfig)
    recording = JobRecording(cfg.job_dir)
    return ReplayArm(recording, model, _replay_clock(sim, recording))


ARM_BACKENDS: dict[str, Callable[[ArmConfig, RobotModel, SimWorld | None], Arm]] = {
    "sim": _sim_arm,
    "ur5e": _ur5e_arm,
    "franka": _franka_arm,
    "replay": _replay_arm,
}


def make_arm(cfg: ArmConfig, model: RobotModel, sim: SimWorld | None) -> Arm:
    """The arm backend named by ``cfg.type``."""
    return ARM_BACKENDS[cfg.type](cfg, model, sim)


PoseSource = Callable[[], Array]


def _sim_rgbd(cfg: DepthConfig, sim: SimWorld | None, pose: PoseSource) -> DepthSensor:
    assert isinstance(cfg, SimRGBDConfig)
    world = _need_sim(sim, "depth sim-rgbd")
    return SimRGBD(cfg, _need_scene(sim, "depth sim-rgbd"), pose, world.clock, world.rng,
                   depth_offset_m=world.errors.depth_offset_m)


def _sim_tof(cfg: DepthConfig, sim: SimWorld | None, pose: PoseSource) -> DepthSensor:
    assert isinstance(cfg, SimToFConfig)
    world = _need_sim(sim, "depth sim-tof")
    return SimToF(cfg, _need_scene(sim, "depth sim-tof"), pose, world.clock, world.rng,
                  depth_offset_m=world.errors.depth_offset_m)


def _job_clock(sim: SimWorld | None) -> Clock:
    """The clock hardware and replay backends stamp frames with: the job's sim clock, else the wall clock."""
    return sim.clock if sim is not None else WallClock()


def _replay_clock(sim: SimWorld | None, recording: JobRecording) -> Clock:
    """The clock a recording plays on: the job's, else the wall clock from the recording's first frame
    (real time, without waiting for the moments before it)."""
    return sim.clock if sim is not None else PlaybackClock(recording.frames[0].timestamp)


def _vl53l8cx(cfg: DepthConfig, sim: SimWorld | None, pose: PoseSource) -> DepthSensor:
    assert isinstance(cfg, VL53L8CXConfig)
    if cfg.i2c is not None:
        from drivers.depth.vl53l8cx.i2c import VL53L8CXI2C  # needs the optional i2c extra when connecting

        return VL53L8CXI2C(cfg, _job_clock(sim))
    from drivers.depth.vl53l8cx.serial_driver import VL53L8CXSerial  # pyserial is imported on connect

    return VL53L8CXSerial(cfg, _job_clock(sim))


def _realsense(cfg: DepthConfig, sim: SimWorld | None, pose: PoseSource) -> DepthSensor:
    assert isinstance(cfg, RealSenseConfig)
    from drivers.depth.realsense import RealSense

    return RealSense(cfg, _job_clock(sim))


def _replay(cfg: DepthConfig, sim: SimWorld | None, pose: PoseSource) -> DepthSensor:
    assert isinstance(cfg, ReplayConfig)
    recording = JobRecording(cfg.job_dir)
    return ReplaySensor(recording, _replay_clock(sim, recording), (cfg.range_min_m, cfg.range_max_m))


SENSOR_BACKENDS: dict[str, Callable[[DepthConfig, SimWorld | None, PoseSource], DepthSensor]] = {
    "sim-rgbd": _sim_rgbd,
    "sim-tof": _sim_tof,
    "vl53l8cx": _vl53l8cx,
    "realsense": _realsense,
    "replay": _replay,
}


def make_sensor(cfg: DepthConfig, sim: SimWorld | None, true_sensor_pose: PoseSource) -> DepthSensor:
    """The depth backend named by ``cfg.type``. ``true_sensor_pose`` gives where the sensor really is
    (simulated sensors render from it)."""
    return SENSOR_BACKENDS[cfg.type](cfg, sim, true_sensor_pose)


def true_flange_pose(arm: Arm) -> PoseSource:
    """Where the flange really is: the simulated arm's true pose (which differs from the reported one
    under its pose-error model); for a hardware arm, the pose it reports."""
    if isinstance(arm, SimArm):
        return arm.true_flange_pose
    return lambda: arm.state().T_base_flange
