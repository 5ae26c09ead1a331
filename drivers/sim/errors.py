"""The calibration error of a simulated cell: what a carefully calibrated real cell still gets wrong.

A real cell never knows exactly where its sensor is. Three errors remain after calibration, and the
simulated devices carry each, drawn once per job from the job's own generator (``draw_sim_errors``), so
that the same seed gives the same cell:

- **hand-eye**: the sensor really sits at ``mount @ T_error``, ``T_error`` a rotation with a
  N(0, ``hand_eye_std_deg``) angle about each sensor axis (the rotation vector's components) and a
  translation N(0, ``hand_eye_std_m``) per sensor axis [m];
- **kinematics**: the arm really moves with encoder zero offsets N(0, ``joint_offset_std_rad``) per joint
  and errors N(0, ``link_std_m``) on every DH length (``RobotModel.perturbed``), while it reports poses from
  its nominal model;
- **depth bias**: every range the sensor reports is off by one constant ``depth_offset_m``, drawn
  N(0, ``depth_offset_std_m``) [m] (the RGB-D camera's depth z, the ToF zone's distance).

The sizes (the shipped cells' files state them, with these reasons):

- Kinematics: a calibrated serial arm reaches an absolute position accuracy of a few tenths of a
  millimetre (Nubiola and Bonev 2013, an ABB IRB 1600 after laser-tracker calibration: a mean error of
  about 0.4 mm); the repeatability of the arms here is far below that (UR5e +-0.03 mm, Franka Panda
  +-0.1 mm, their datasheets), so the error is systematic. 0.2 mrad per joint (0.1 mm at 0.5 m of lever)
  and 0.2 mm per DH length give about 0.4 mm at the flange.
- Hand-eye: a board calibration of an RGB-D camera finds the mount to well under a millimetre in our sim
  (``benchmarks/calibration_accuracy.py``: 0.1 mm, 0.03 deg), but a real one also carries the camera's
  intrinsic error and the arm's accuracy in the calibration poses: 0.5 mm and 0.1 deg per axis. The ToF
  cell's shape calibration leaves 2 mm and 0.16 deg in sim at worst: 1.5 mm and 0.15 deg per axis.
- Depth bias: the RGB-D camera's depth after its own calibration, about 0.4 % of 0.25 m: 1 mm; the
  VL53L8CX's common offset after ``cell calibrate tof`` (its per-zone offsets are ``sensor.zone_bias``),
  whose mean zone error in sim is 1.0-1.4 mm: 2 mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.spatial.transform import Rotation

from drivers.config_base import StrictModel
from drivers.robots.model import RobotModel

Array = NDArray[np.float64]


class SimErrorConfig(StrictModel):
    """Standard deviations of the simulated calibration error (see the module docstring): hand-eye
    translation [m] and rotation [deg] per sensor axis, encoder zero offset per joint [rad], error per DH
    length [m], the sensor's common range offset [m]."""

    hand_eye_std_m: float = Field(default=0.0005, ge=0.0, le=0.01)
    hand_eye_std_deg: float = Field(default=0.1, ge=0.0, le=2.0)
    joint_offset_std_rad: float = Field(default=0.0002, ge=0.0, le=0.05)
    link_std_m: float = Field(default=0.0002, ge=0.0, le=0.01)
    depth_offset_std_m: float = Field(default=0.001, ge=0.0, le=0.02)


@dataclass(frozen=True)
class SimErrors:
    """One job's drawn error: ``T_mount_error`` (4x4, the true mount is ``mount @ T_mount_error``), the
    arm's true model (None: the nominal one), the sensor's range offset [m]."""

    T_mount_error: Array
    true_model: RobotModel | None
    depth_offset_m: float

    @staticmethod
    def none() -> SimErrors:
        """An exact cell (``sim.exact``)."""
        return SimErrors(np.eye(4), None, 0.0)

    def describe(self) -> str:
        """One line for the job's log: the hand-eye error's size, the depth offset, the kinematics."""
        angle = np.degrees(Rotation.from_matrix(self.T_mount_error[:3, :3]).magnitude())
        shift_mm = np.linalg.norm(self.T_mount_error[:3, 3]) * 1e3
        return (f"calibration error drawn: hand-eye {shift_mm:.2f} mm, {angle:.3f} deg; "
                f"depth offset {self.depth_offset_m * 1e3:+.2f} mm; "
                f"kinematics {'perturbed' if self.true_model is not None else 'exact'}")


def draw_sim_errors(config: SimErrorConfig, model: RobotModel, rng: np.random.Generator) -> SimErrors:
    """Draw a job's error from ``rng`` (a generator of its own: the draws do not shift the sensor's noise),
    in this order: hand-eye rotation vector (3) and translation (3), the depth offset, the arm's
    perturbation (``RobotModel.perturbed``)."""
    rotvec = rng.normal(0.0, np.deg2rad(config.hand_eye_std_deg), 3)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = rng.normal(0.0, config.hand_eye_std_m, 3)
    depth_offset = float(rng.normal(0.0, config.depth_offset_std_m))
    true_model = model.perturbed(rng, config.joint_offset_std_rad, config.link_std_m)
    return SimErrors(T, true_model, depth_offset)
