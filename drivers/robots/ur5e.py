"""Universal Robots UR5e: standard DH kinematics, limits and a capsule collision model.

Sources
-------
- DH parameters: Universal Robots, "DH parameters for calculations of kinematics and dynamics"
  (UR support article), UR5e row: a = [0, -0.425, -0.3922, 0, 0, 0] m,
  d = [0.1625, 0, 0, 0.1333, 0.0997, 0.0996] m, alpha = [pi/2, 0, 0, pi/2, -pi/2, 0] rad. Standard
  (distal) convention; the last link frame is the tool flange (no separate flange element).
- Joint ranges: +-360 deg on every joint (UR5e user manual, technical specifications), except the elbow
  (joint 3), limited here to +-pi: the shoulder-lift link physically blocks the elbow at about +-180 deg,
  so positions beyond +-pi cannot be reached without self-collision (Universal Robots' own ROS
  description limits ``elbow_joint`` to +-pi for the same reason), and planning through them only wastes
  effort.
- Joint speed: 180 deg/s (pi rad/s) on every joint (UR5e datasheet).
- Joint acceleration: UR publishes no joint acceleration limit (the drives are torque limited); we use
  10 rad/s^2, the conservative ceiling Universal Robots' ROS MoveIt configuration uses for time
  parametrisation. Jerk: not published either; 1000 rad/s^3 (a ramp from 0 to the acceleration ceiling in
  10 ms) is our choice for trajectory generation.
- TCP ceilings: linear 1.0 m/s (UR safety-configuration default for the tool speed limit); angular
  pi rad/s (our choice: what one wrist joint alone reaches at full speed); accelerations 5 m/s^2 and
  10 rad/s^2 (our choice, comfortably below what speedL accepts, for a camera-carrying arm); jerks
  500 m/s^3 and 1000 rad/s^3 (not published; our choice: the acceleration ceiling reached in 10 ms).
- Capsule radii are estimated from the UR5e datasheet drawing (base mount diameter 149 mm, wrist joint
  housings about 90 mm) and rounded up so that each capsule encloses its link; the lateral offsets of the
  upper arm (138 mm along the shoulder axis) and of the forearm (138 - 131 = 7 mm) are those of Universal
  Robots' URDF description. The figures are in frame coordinates of ``fk_all`` (see
  :mod:`drivers.robots.model`).
"""

from __future__ import annotations

import numpy as np

from drivers.robots.model import CapsuleSpec, RobotModel

PI = float(np.pi)

UR5E_A = [0.0, -0.425, -0.3922, 0.0, 0.0, 0.0]
UR5E_D = [0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996]
UR5E_ALPHA = [PI / 2, 0.0, 0.0, PI / 2, -PI / 2, 0.0]

# Ready pose: upper arm vertical, forearm horizontal towards base -x, wrist down. The flange is at
# (-0.492, -0.133, 0.488) m in the base frame with its z axis pointing straight down (checked in the tests).
UR5E_Q_HOME = [0.0, -PI / 2, PI / 2, -PI / 2, -PI / 2, 0.0]

_SHOULDER_OFFSET = 0.138  # upper-arm tube offset along the shoulder-lift axis [m]
_FOREARM_OFFSET = 0.138 - 0.131  # forearm tube offset along the elbow axis [m]

UR5E_CAPSULES = (
    # frame 0 (base): pedestal and shoulder-pan drive, bottom of the capsule at z = 0.
    CapsuleSpec("base", 0, (0.0, 0.0, 0.075), (0.0, 0.0, 0.1625), 0.075),
    # frame 1: shoulder-lift drive housing, along the shoulder axis z1.
    CapsuleSpec("shoulder", 1, (0.0, 0.0, 0.0), (0.0, 0.0, _SHOULDER_OFFSET), 0.075),
    # frame 2 (at the elbow axis): upper-arm tube from the shoulder to the elbow, then the elbow drive.
    CapsuleSpec("upper_arm", 2, (0.425, 0.0, _SHOULDER_OFFSET), (0.0, 0.0, _SHOULDER_OFFSET), 0.060),
    CapsuleSpec("elbow", 2, (0.0, 0.0, _SHOULDER_OFFSET), (0.0, 0.0, _FOREARM_OFFSET), 0.060),
    # frame 3 (at the wrist-1 axis): forearm tube, then the wrist-1 drive up to the wrist-2 axis.
    CapsuleSpec("forearm", 3, (0.3922, 0.0, _FOREARM_OFFSET), (0.0, 0.0, _FOREARM_OFFSET), 0.050),
    CapsuleSpec("wrist1", 3, (0.0, 0.0, _FOREARM_OFFSET), (0.0, 0.0, 0.1333), 0.046),
    # frames 4 and 5: wrist-2 and wrist-3 drives, the last one ending at the flange.
    CapsuleSpec("wrist2", 4, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0997), 0.046),
    CapsuleSpec("wrist3", 5, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0996), 0.046),
)


def ur5e_model() -> RobotModel:
    """The nominal UR5e model (standard DH, flange = link 6 frame)."""
    return RobotModel(
        name="ur5e",
        convention="standard",
        a=np.array(UR5E_A),
        d=np.array(UR5E_D),
        alpha=np.array(UR5E_ALPHA),
        q_min=np.array([-2 * PI, -2 * PI, -PI, -2 * PI, -2 * PI, -2 * PI]),
        q_max=np.array([2 * PI, 2 * PI, PI, 2 * PI, 2 * PI, 2 * PI]),
        qd_max=np.full(6, PI),
        qdd_max=np.full(6, 10.0),
        qddd_max=np.full(6, 1000.0),
        q_home=np.array(UR5E_Q_HOME),
        tcp_max_linear_mps=1.0,
        tcp_max_angular_rps=PI,
        tcp_max_linear_acc=5.0,
        tcp_max_angular_acc=10.0,
        tcp_max_linear_jerk=500.0,
        tcp_max_angular_jerk=1000.0,
        capsule_specs=UR5E_CAPSULES,
        flange=None,
    )
