"""Franka Emika Panda: modified (Craig) DH kinematics, libfranka limits and a capsule collision model.

Sources
-------
- DH parameters: Franka Control Interface documentation, "Robot and interface specifications",
  Denavit-Hartenberg parameters (modified convention, Craig):
  a = [0, 0, 0, 0.0825, -0.0825, 0, 0.088] m, d = [0.333, 0, 0.316, 0, 0.384, 0, 0] m,
  alpha = [0, -pi/2, pi/2, pi/2, -pi/2, pi/2, pi/2] rad, then the flange: d = 0.107 m, a = 0, alpha = 0,
  no joint. The link frames are those of Franka's URDF (``panda_link1`` .. ``panda_link8``).
- Limits: libfranka documentation, "Limits for Panda": q_max, q_min [rad], dq_max [rad/s],
  ddq_max [rad/s^2], dddq_max [rad/s^3]; Cartesian: 1.7 m/s, 2.5 rad/s, 13 m/s^2, 25 rad/s^2,
  6500 m/s^3, 12500 rad/s^3.
- Ready pose: libfranka's example start pose [0, -pi/4, 0, -3pi/4, 0, pi/2, pi/4].
- Redundancy: the seventh joint's self-motion serves joint-limit avoidance (``PANDA_LIMIT_AVOIDANCE_GAIN``).
- Capsules: radii from the published link dimensions (drive housings of 120 to 130 mm diameter on
  joints 1-4, about 110 mm on the forearm and wrist, flange 63 mm), rounded up so that each capsule encloses
  its link; placed along the link frames of Franka's URDF. The figures are in frame coordinates of
  ``fk_all`` (index i = link frame i, 0 = base). Pairs (link5, link7) are additionally treated as adjacent
  because the wrist drives of link 5 and link 7 touch at the joint-6 fold, as in Franka's own collision
  filtering.
"""

from __future__ import annotations

import numpy as np

from drivers.robots.model import CapsuleSpec, RobotModel

PI = float(np.pi)

PANDA_A = [0.0, 0.0, 0.0, 0.0825, -0.0825, 0.0, 0.088]
PANDA_D = [0.333, 0.0, 0.316, 0.0, 0.384, 0.0, 0.0]
PANDA_ALPHA = [0.0, -PI / 2, PI / 2, PI / 2, -PI / 2, PI / 2, PI / 2]
PANDA_FLANGE_D = 0.107

PANDA_Q_MAX = [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]
PANDA_Q_MIN = [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973]
PANDA_DQ_MAX = [2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61]
PANDA_DDQ_MAX = [15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0]
PANDA_DDDQ_MAX = [7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0]
PANDA_Q_HOME = [0.0, -PI / 4, 0.0, -3 * PI / 4, 0.0, PI / 2, PI / 4]
# Null-space joint-limit avoidance gain k [rad] (drivers.robots.model, "Redundancy"). Not a Franka figure:
# at 3 the self-motion is about as fast as the task's own joint motion for a joint 90 % of the way to its
# limit, enough to unwind the shoulder-elbow twist of a sideways view within a few centimetres of camera
# travel (at 1 the base joint still reached its margin in a bunny scan).
PANDA_LIMIT_AVOIDANCE_GAIN = 3.0

PANDA_CAPSULES = (
    # frame 0: base, bottom of the capsule at z = 0.
    CapsuleSpec("link0", 0, (0.0, 0.0, 0.08), (0.0, 0.0, 0.14), 0.080),
    # frame 1 (at the joint-2 axis, 0.333 m up): the column of link 1.
    CapsuleSpec("link1", 1, (0.0, 0.0, -0.193), (0.0, 0.0, 0.0), 0.070),
    # frame 2: joint-2 housing along z2, then the upper arm towards joint 3 (along -y2).
    CapsuleSpec("link2", 2, (0.0, 0.0, -0.065), (0.0, 0.0, 0.065), 0.065),
    CapsuleSpec("link2b", 2, (0.0, 0.0, 0.0), (0.0, -0.20, 0.0), 0.065),
    # frame 3: upper arm up to the elbow, then the elbow offset (0.0825 along x3).
    CapsuleSpec("link3", 3, (0.0, 0.0, -0.116), (0.0, 0.0, 0.0), 0.065),
    CapsuleSpec("link3b", 3, (0.0, 0.0, 0.0), (0.0825, 0.065, 0.0), 0.060),
    # frame 4: joint-4 housing along z4, then the step back towards the forearm axis.
    CapsuleSpec("link4", 4, (0.0, 0.0, -0.065), (0.0, 0.0, 0.065), 0.060),
    CapsuleSpec("link4b", 4, (0.0, 0.0, 0.0), (-0.0825, 0.134, 0.0), 0.060),
    # frame 5 (at the wrist): forearm along z5, then its narrower part offset along +y5.
    CapsuleSpec("link5", 5, (0.0, 0.0, -0.25), (0.0, 0.0, -0.17), 0.060),
    CapsuleSpec("link5b", 5, (0.0, 0.075, -0.18), (0.0, 0.075, -0.02), 0.045),
    # frame 6: joint-6 housing reaching out to the joint-7 axis (0.088 along x6).
    CapsuleSpec("link6", 6, (0.0, 0.0, 0.0), (0.088, 0.0, 0.0), 0.055),
    # frame 7: joint-7 drive up to the flange (z = 0.107), the flange disc (r 31.5 mm) inside.
    CapsuleSpec("link7", 7, (0.0, 0.0, -0.03), (0.0, 0.0, 0.07), 0.050),
)


def panda_model() -> RobotModel:
    """The nominal Panda model (modified DH, flange 0.107 m past link 7)."""
    return RobotModel(
        name="panda",
        convention="modified",
        a=np.array(PANDA_A),
        d=np.array(PANDA_D),
        alpha=np.array(PANDA_ALPHA),
        q_min=np.array(PANDA_Q_MIN),
        q_max=np.array(PANDA_Q_MAX),
        qd_max=np.array(PANDA_DQ_MAX),
        qdd_max=np.array(PANDA_DDQ_MAX),
        qddd_max=np.array(PANDA_DDDQ_MAX),
        q_home=np.array(PANDA_Q_HOME),
        tcp_max_linear_mps=1.7,
        tcp_max_angular_rps=2.5,
        tcp_max_linear_acc=13.0,
        tcp_max_angular_acc=25.0,
        tcp_max_linear_jerk=6500.0,
        tcp_max_angular_jerk=12500.0,
        capsule_specs=PANDA_CAPSULES,
        extra_adjacent_pairs=(("link5", "link7"), ("link5b", "link7")),
        flange=(0.0, PANDA_FLANGE_D, 0.0),
        limit_avoidance_gain=PANDA_LIMIT_AVOIDANCE_GAIN,
    )
