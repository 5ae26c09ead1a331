"""Each safety function of the guard, shown to act where it must, judged by the motion the simulated arm
really made (``tests.safety_rig.MotionJudge``, which shares no code with the guard). Each test fails when
its function is taken out of the guard (``benchmarks/safety_mutants.py`` checks that): the barrier
projection of streamed twists and the barrier check of moves, the collision check of both, the joint
margin clamp of both, and the watchdog's late-loop and stale-perception stops. ``benchmarks/safety_soak.py``
runs the same judge over 10^5 random commands per robot; the defects it found are kept here as tests."""

from __future__ import annotations

import numpy as np
import pytest

from cell.control.trajectory import joint_trajectory
from cell.safety.guard import TwistRefused
from drivers.arm.base import ArmMode, JointTrajectory
from drivers.errors import SafetyStop
from drivers.robots import get_robot_model

from .safety_rig import Rig, cell_config

ROBOTS = ["panda", "ur5e"]


def _plane_below(model_name: str, depth_m: float) -> dict[str, object]:
    """A horizontal barrier plane ``depth_m`` below the lower of the TCP and the sensor at the home pose."""
    rig = Rig.of(model_name)
    z = rig.judge.guarded_points(rig.arm.state().T_base_flange)[:, 2].min()
    return {"name": "shelf", "point": [0.0, 0.0, float(z) - depth_m], "normal": [0.0, 0.0, 1.0]}


def _move(rig: Rig, q_goal: np.ndarray) -> JointTrajectory:
    """A ruckig move from the arm's joints to ``q_goal`` [rad], planned as a job plans it."""
    sf = rig.cfg.safety
    return joint_trajectory(rig.model, rig.arm.state().q, q_goal, dt=rig.dt,
                            velocity_scale=sf.joint_velocity_scale,
                            acceleration_scale=sf.joint_acceleration_scale, jerk_scale=sf.joint_jerk_scale)


def _lowered(rig: Rig, drop_m: float) -> np.ndarray:
    """Joints [rad] that put the flange ``drop_m`` straight below where it is, same orientation."""
    T = rig.arm.state().T_base_flange.copy()
    T[2, 3] -= drop_m
    return rig.model.ik_pose(T, rig.arm.state().q)


def _wrist_near_its_limit(model_name: str, room_rad: float) -> Rig:
    """The home pose with the last joint ``room_rad`` below the upper edge of its margin."""
    base = cell_config(model_name)
    q0 = np.array(base.arm.home_joints_rad)
    q0[-1] = get_robot_model(model_name).q_max[-1] - base.safety.joint_position_margin_rad - room_rad
    return Rig(cell_config(model_name, home_joints_rad=q0))


def _roll_wrist(rig: Rig, rate_rps: float, ticks: int) -> None:
    """Stream a turn of the flange about its own z axis (the last joint alone), re-aimed every tick."""
    for _ in range(ticks):
        z = rig.arm.state().T_base_flange[:3, 2]
        rig.guard.command_twist(np.concatenate([np.zeros(3), rate_rps * z]))
        rig.tick()


@pytest.mark.parametrize("model_name", ROBOTS)
def test_a_streamed_twist_into_a_plane_stops_at_its_margin_and_slides_along_it(model_name):
    rig = Rig(cell_config(model_name, barrier_planes=[_plane_below(model_name, 0.08)]))
    start = rig.arm.state().T_base_flange[:3, 3].copy()
    rig.guard.command_twist(np.array([0.0, 0.04, -0.1, 0.0, 0.0, 0.0]))
    rig.tick(250)  # 2.5 s: without the plane the arm would go 25 cm down
    rig.assert_safe()
    margin = rig.cfg.safety.barrier_margin_m
    assert margin - 1e-3 < rig.judge.clearance(rig.arm.state().q) < margin + 2e-3  # it reached the plane
    moved = rig.arm.state().T_base_flange[:3, 3] - start
    assert moved[1] > 0.09  # and kept sliding sideways along it
    assert rig.guard.log.clamps["barrier shelf"] > 0


@pytest.mark.parametrize("model_name", ROBOTS)
def test_a_move_through_a_plane_is_refused_as_a_barrier(model_name):
    rig = Rig(cell_config(model_name, barrier_planes=[_plane_below(model_name, 0.03)]))
    traj = _move(rig, _lowered(rig, 0.08))
    _, refusal = rig.guard.check_trajectory(traj)
    assert refusal is not None and refusal.kind == "barrier" and "shelf" in refusal.message
    with pytest.raises(SafetyStop, match="refused"):
        rig.guard.execute_trajectory(traj)
    rig.settle()
    rig.assert_safe()


@pytest.mark.parametrize("model_name", ROBOTS)
def test_a_move_may_graze_a_margin_as_deep_as_a_stop_may_and_no_deeper(model_name):
    """A move's samples may enter a plane's margin by the share a streamed twist's stop may use (the
    straight joint line of a retrace along a path that slid on the margin bends into it), not further."""
    margin = cell_config(model_name).safety.barrier_margin_m
    depth = 0.08
    for into_m, refused in ((0.4 * margin, False), (0.6 * margin, True)):
        rig = Rig(cell_config(model_name, barrier_planes=[_plane_below(model_name, depth)]))
        traj = _move(rig, _lowered(rig, depth - margin + into_m))
        _, refusal = rig.guard.check_trajectory(traj)
        assert (refusal is not None) == refused, (into_m, refusal)
        if refused:
            assert refusal is not None and refusal.kind == "barrier" and "shelf" in refusal.message
        else:
            rig.guard.execute_trajectory(traj)
            rig.settle()
            rig.assert_safe()
            assert -0.5 * margin < rig.judge.clearance(rig.arm.state().q) - margin < -0.3 * margin


@pytest.mark.parametrize("model_name", ROBOTS)
def test_a_move_through_the_object_is_refused_as_a_collision(model_name):
    rig = Rig.of(model_name)
    flange = rig.arm.state().T_base_flange[:3, 3]
    # The tool reaches 5 cm below the flange at most and the guard inflates the box by 2 cm: 3 cm clear.
    rig.set_roi(flange - np.array([0.05, 0.05, 0.20]), flange - np.array([-0.05, -0.05, 0.10]))
    assert rig.guard.collision.check(rig.arm.state().q) is None
    _, refusal = rig.guard.check_trajectory(_move(rig, _lowered(rig, 0.15)))
    assert refusal is not None and refusal.kind == "collision" and "ROI" in refusal.message


@pytest.mark.parametrize("model_name", ROBOTS)
def test_a_streamed_wrist_roll_stops_at_the_joint_margin(model_name):
    rig = _wrist_near_its_limit(model_name, 0.15)
    _roll_wrist(rig, 0.15, 250)  # 2.5 s: without the margin the joint would turn 0.375 rad
    rig.assert_safe()
    assert rig.judge.cell_limits["joint_margin"] == 0
    room = rig.guard.joint_bounds[1][-1] - rig.arm.state().q[-1]
    assert 0.0 <= room < 0.02  # it came close, and stopped
    assert rig.guard.log.clamps["joint_position_margin"] > 0


@pytest.mark.parametrize("model_name", ROBOTS)
def test_a_move_into_the_joint_margin_is_refused(model_name):
    rig = _wrist_near_its_limit(model_name, 0.15)
    q_goal = rig.arm.state().q.copy()
    q_goal[-1] = rig.model.q_max[-1] - 0.02  # inside the margin, short of the joint's limit
    _, refusal = rig.guard.check_trajectory(_move(rig, q_goal))
    assert refusal is not None and refusal.kind == "joint margin"


@pytest.mark.parametrize("model_name", ROBOTS)
def test_a_joint_moving_faster_than_the_ik_predicts_is_stopped_before_its_limit(model_name):
    # Near a singularity the differential IK that the braking check predicts with falls short of what the
    # joints do; the arm's measured joint speeds must still stop it. Here the wrist, at the edge of its
    # margin, reports a speed towards its limit that no twist the guard sent would give: one from which the
    # arm's own stop ends three quarters of the way into the margin, past the half the guard allows.
    rig = _wrist_near_its_limit(model_name, 0.0)
    dt, qdd = rig.dt, float(rig.model.qdd_max[-1])
    travel = 0.75 * rig.cfg.safety.joint_position_margin_rad
    speed = qdd * (-dt + np.sqrt(dt * dt + 2.0 * travel / qdd))  # speed * (dt + speed / (2 qdd)) = travel
    rig.guard.command_twist(np.zeros(6))
    rig.arm._qd = np.zeros(rig.model.n_joints)
    rig.arm._qd[-1] = speed
    with pytest.raises(TwistRefused, match=rf"joint {rig.model.n_joints} at \+{speed:.3f} rad/s") as refused:
        rig.guard.tick()
    assert refused.value.refusal.kind == "joint limit"
    rig.settle()
    assert rig.arm.state().q[-1] < rig.model.q_max[-1] - 0.2 * rig.cfg.safety.joint_position_margin_rad


def test_late_control_ticks_stop_the_arm():
    rig = Rig.of("ur5e")
    rig.guard.command_twist(np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0]))
    rig.tick(20)
    allowed = rig.cfg.safety.watchdog.max_missed_deadlines
    with pytest.raises(SafetyStop, match="watchdog: control loop missed its deadline"):
        for _ in range(allowed + 1):
            rig.clock.sleep(2.0 * rig.dt)  # each tick a period late
            rig.guard.tick()
    assert rig.guard.watchdog.missed_in_a_row == allowed
    assert rig.arm.state().mode is ArmMode.STOPPING


def test_stale_perception_stops_the_arm():
    rig = Rig.of("panda")
    rig.guard.command_twist(np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0]))
    max_age = rig.cfg.safety.watchdog.perception_max_age_s
    rig.tick(20)
    rig.guard.tick(perception_time_s=rig.clock.now() - 0.9 * max_age)
    rig.step()
    with pytest.raises(SafetyStop, match="watchdog: perception data are"):
        rig.guard.tick(perception_time_s=rig.clock.now() - 1.1 * max_age)
    assert rig.arm.state().mode is ArmMode.STOPPING


# The soak's findings: a guard that shaped the twist it was asked for but assumed the flange or a joint could
# brake harder and sooner than the jerk-limited, phase-synchronised smoothing after it let them overshot a
# plane at full speed (more so while the smoother also ramped a turn) and a joint margin in a fast wrist roll.

@pytest.mark.parametrize("turn_rps", [0.0, 1.0])
def test_a_full_speed_twist_into_a_plane_stops_before_it(turn_rps):
    rig = Rig(cell_config("ur5e", barrier_planes=[_plane_below("ur5e", 0.10)]))
    rig.guard.command_twist(np.array([0.0, 0.0, -0.25, 0.0, 0.0, 0.0]))
    rig.tick(30)
    rig.guard.command_twist(np.array([0.0, 0.0, -0.25, turn_rps, 0.0, 0.0]))
    rig.tick(150)
    rig.assert_safe()


def test_a_wrist_roll_at_half_the_angular_limit_stops_before_the_joint_limit():
    rig = _wrist_near_its_limit("ur5e", 0.15)
    _roll_wrist(rig, 0.5 * rig.cfg.safety.tcp_max_angular_rps, 150)
    rig.assert_safe()



# The soak's Panda move whose camera clipped a corner of an obstacle between two trajectory samples 6 mrad
# apart (episode 444 at seed 0): both samples are clear, a configuration between them is not.
CLIPPED_MOVE_RAD = np.array([
    [-1.167074392953996, -1.2075228186016285, 2.0583127764039957, -0.4692569815403904, -1.7861427082940624,
     0.7187804278168044, -1.4329491091891482],
    [-1.1734675606719847, -1.2114249419303993, 2.06294724120488, -0.4676316499730932, -1.7891880097079849,
     0.7183273754710752, -1.4317828086890534]])
CLIPPED_OBSTACLE = {"shape": "box", "name": "random obstacle",
                    "size_m": [0.1501869745180332, 0.10695310120325563, 0.1408453732136572],
                    "pose": {"xyz_m": [0.13023988259255723, 0.6236337732070906, 0.7078193987754317]}}


def test_a_move_that_clips_an_obstacle_between_its_samples_is_refused():
    rig = Rig(cell_config("panda", home_joints_rad=CLIPPED_MOVE_RAD[0], obstacles=[CLIPPED_OBSTACLE]))
    a, b = CLIPPED_MOVE_RAD
    assert rig.judge.contact(a) is None and rig.judge.contact(b) is None
    assert rig.judge.contact((a + b) / 2.0) == "camera touches random obstacle"
    move = JointTrajectory(t=np.array([0.0, rig.dt]), q=CLIPPED_MOVE_RAD.copy())
    _, refusal = rig.guard.check_trajectory(move)
    assert refusal is not None and refusal.kind == "collision"
    assert "camera would touch random obstacle" in refusal.message


def test_a_twist_streamed_near_the_wrist_singularity_never_asks_a_joint_for_more_than_its_acceleration():
    # The soak's UR5e twists whose jerk passed the robot's limit: near a singularity the joint velocities of a
    # smoothly changing twist change faster than the robot can accelerate; the arm saturated at its limit and,
    # when it caught up, its acceleration leapt by more than the jerk limit allows in one period.
    base = cell_config("ur5e")
    q0 = np.array(base.arm.home_joints_rad)
    q0[4] = -0.13  # the wrist 7.4 degrees from its singularity
    rig = Rig(cell_config("ur5e", home_joints_rad=q0))
    twist = np.array([-0.16, 0.12, -0.04, 0.34, 0.0, -0.34])
    for sign in (1.0, -1.0):
        rig.guard.command_twist(sign * twist)
        rig.tick(40)
    rig.assert_safe()
    assert rig.judge.worst["joint_acceleration"] < 0.99  # never at the arm's own limit
    assert rig.guard.log.clamps["joint_acceleration"] > 0


# The soak's UR5e twists that turned the forearm into a corner of an obstacle (episode 121 at seed 0): from
# rest next to it, a twist and then a turn; every configuration predicted ahead of the arm was clear, but
# the arm's way bent off the lines to them and into the corner.
TURN_START_RAD = [3.60876244304158, 5.37057717043888, -1.228811513311022, 4.700343488188488,
                  0.06029129185400769, -0.35000450611175127]
TURN_TWISTS = np.array([
    [0.12749711018155616, -0.037918294455657905, -0.0905331743686652, 0.11822092426281426,
     -0.08553862292228254, -0.22329735317968283],
    [-0.02799054350998415, -0.003675371077657719, -0.008943716901939285, 1.4365664135416782,
     -0.5890831662736534, 0.39655249595916786]])
CORNER_OBSTACLE = {"shape": "box", "name": "random obstacle",
                   "size_m": [0.1693682910030958, 0.19357351526407934, 0.10854120879428275],
                   "pose": {"xyz_m": [0.1832482707988733, -0.0179117165298196, 0.8908961367745728]}}


def test_a_streamed_twist_that_turns_into_an_obstacle_is_refused_before_it_touches():
    rig = Rig(cell_config("ur5e", home_joints_rad=TURN_START_RAD, obstacles=[CORNER_OBSTACLE]))
    with pytest.raises(TwistRefused) as refused:
        for twist in TURN_TWISTS:
            rig.guard.command_twist(twist)
            rig.tick(24)
    assert refused.value.refusal.kind == "collision"
    assert "forearm would touch random obstacle" in refused.value.refusal.message
    rig.settle()
    rig.assert_safe()


# A streamed twist that bends the arm's way: along x, then along y and back a little.
BEND_TWISTS = (np.array([0.25, 0.0, 0.0, 0.0, 0.0, 0.0]), np.array([-0.1, 0.25, 0.0, 0.0, 0.0, 0.0]))
BEND_TICKS = (30, 40)
CUBE_M = 0.01


def _stream_the_bend(rig: Rig) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Stream ``BEND_TWISTS``; returns the joints [rad] the arm reached after each tick and the configuration
    each tick predicted ``lookahead_s`` ahead at the twist it sent (the end of the path the guard checks)."""
    lookahead = rig.cfg.safety.collision.lookahead_s
    reached, predicted = [], []
    for twist, ticks in zip(BEND_TWISTS, BEND_TICKS, strict=True):
        rig.guard.command_twist(twist)
        for _ in range(ticks):
            q = rig.arm.state().q
            rig.tick()
            predicted.append(q + rig.model.velocity_map(q)(rig.sent[-1]) * lookahead)
            reached.append(rig.arm.state().q)
    return reached, predicted


def _cube_beside_the_predictions(model_name: str) -> np.ndarray:
    """The centre [m] of a cube of side ``CUBE_M`` that the arm reaches on its way round the bend while no
    configuration predicted until then touches it: inside the bend, where the arm's way turns off the lines
    to the predictions (found on a free run, with the judge's bodies)."""
    rig = Rig.of(model_name)
    reached, predicted = _stream_the_bend(rig)
    flange = np.array([rig.model.fk(q)[:3, 3] for q in reached])
    k = BEND_TICKS[0] + BEND_TICKS[1] // 3
    along = flange[k + 1] - flange[k - 1]
    bend = flange[k + 3] - 2.0 * flange[k] + flange[k - 3]
    inward = bend - (bend @ along) / (along @ along) * along
    inward /= np.linalg.norm(inward)

    def touches(centre: np.ndarray, q: np.ndarray) -> bool:
        rig.judge.set_roi(centre - CUBE_M / 2.0, centre + CUBE_M / 2.0)
        return rig.judge.contact(q) is not None

    steps = np.arange(0.0, 0.2, 0.0005)
    surface = next(s for s in steps if not touches(flange[k] + s * inward, reached[k]))
    for depth in steps[1:10]:
        centre = flange[k] + (surface - depth) * inward
        first = next((j for j, q in enumerate(reached) if touches(centre, q)), None)
        if first is not None and not any(touches(centre, q) for q in predicted[:first + 1]):
            return centre
    raise AssertionError(f"no cube on the {model_name}'s way round the bend lies beside every prediction")


@pytest.mark.parametrize("model_name", ROBOTS)
def test_a_streamed_twist_that_bends_is_refused_before_a_cube_beside_its_predictions(model_name):
    centre = _cube_beside_the_predictions(model_name)
    cube = {"shape": "box", "name": "cube", "size_m": [CUBE_M] * 3, "pose": {"xyz_m": centre.tolist()}}
    rig = Rig(cell_config(model_name, obstacles=[cube]))
    with pytest.raises(TwistRefused) as refused:
        _stream_the_bend(rig)
    assert refused.value.refusal.kind == "collision"
    rig.settle()
    rig.assert_safe()
