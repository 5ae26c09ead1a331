"""The guard on its own, for both robot models in sim: property-based twist streams and random targets
never cross a barrier plane, never collide, never exceed a limit; ruckig trajectories respect the limits;
the pieces (projection, collision world, watchdog, smoothing) against hand-made cases."""

from __future__ import annotations

import contextlib

import numpy as np
import open3d as o3d
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cell.config import load_config
from cell.control.trajectory import joint_trajectory
from cell.safety.barriers import BarrierPlane, Barriers, approach_speed, project_onto_halfspaces
from cell.safety.collision import CollisionWorld
from cell.safety.config import WatchdogConfig
from cell.safety.guard import TwistRefused
from cell.safety.smoothing import TwistSmoother
from cell.safety.watchdog import Watchdog
from drivers.arm.base import ArmMode, JointTrajectory
from drivers.errors import SafetyStop
from drivers.robots import get_robot_model

from .conftest import PANDA_AT_REACH, UR5E
from .safety_rig import CELLS, Rig

PROPERTY = settings(max_examples=5, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow])


twists = st.lists(st.tuples(st.lists(st.floats(-0.6, 0.6), min_size=3, max_size=3),
                            st.lists(st.floats(-1.5, 1.5), min_size=3, max_size=3),
                            st.integers(10, 60)), min_size=1, max_size=4)


@pytest.mark.parametrize("model_name", ["panda", "ur5e"])
@PROPERTY
@given(stream=twists)
def test_random_twist_streams_stay_safe(model_name, stream):
    rig = Rig.of(model_name)
    try:
        for lin, ang, ticks in stream:
            rig.guard.command_twist(np.array(lin + ang))
            rig.tick(ticks)
        rig.guard.hold()
        rig.tick(60)
    except SafetyStop:
        # A refusal (a collision predicted ahead) stops the arm: it must come to rest safely too.
        for _ in range(100):
            rig.step()
        assert rig.arm.state().mode is ArmMode.IDLE
    rig.assert_safe()
    assert rig.judge.cell_limits["joint_velocity_share"] == 0
    rig.check_sent()


@pytest.mark.parametrize("axis", [0, 4])
def test_a_twist_cut_after_smoothing_is_still_commanded_within_every_configured_limit(axis):
    """Twice the speed limits backwards along an axis (with a sideways drift) from the Panda at its reach:
    the smoothed twist asks a joint for more than its share as the arm turns, and the guard cuts it down
    after smoothing (``smoothed_twist``). Every twist it sends keeps the cell file's TCP speed,
    acceleration and jerk limits and each joint's share of its speed limit (``Rig.check_sent``): the cut
    may not be a jump (it was: a jerk of 5 to 19 times the limit in the soak)."""
    rig = Rig.of("panda", PANDA_AT_REACH)
    sf = rig.cfg.safety
    v = np.zeros(6)
    v[axis] = -2.0 * (sf.tcp_max_linear_mps if axis < 3 else sf.tcp_max_angular_rps)
    v[:3] += 0.3 * sf.tcp_max_linear_mps * np.array([1.0, -1.0, 0.5])
    rig.guard.command_twist(v)
    with contextlib.suppress(TwistRefused):
        rig.tick(80)
    assert rig.guard.log.clamps["smoothed_twist"] > 0
    rig.check_sent()
    rig.settle()
    rig.assert_safe()


@pytest.mark.parametrize("model_name", ["panda", "ur5e"])
@PROPERTY
@given(fractions=st.lists(st.floats(0.0, 1.0), min_size=7, max_size=7))
def test_random_targets_are_refused_or_executed_safely(model_name, fractions):
    rig = Rig.of(model_name)
    m = rig.model
    lo = m.q_min + rig.cfg.safety.joint_position_margin_rad
    hi = m.q_max - rig.cfg.safety.joint_position_margin_rad
    q_goal = lo + (hi - lo) * np.array(fractions[:m.n_joints])
    sf = rig.cfg.safety
    traj = joint_trajectory(m, rig.arm.state().q, q_goal, dt=rig.dt, velocity_scale=sf.joint_velocity_scale,
                            acceleration_scale=sf.joint_acceleration_scale, jerk_scale=sf.joint_jerk_scale)
    _, refusal = rig.guard.check_trajectory(traj)
    if refusal is not None:
        assert refusal.kind in {"collision", "barrier", "joint margin"}
        return
    started = rig.guard.execute_trajectory(traj)
    rig.tick(int(started.duration / rig.dt) + 5)
    np.testing.assert_allclose(rig.arm.state().q, q_goal, atol=1e-9)
    rig.assert_safe()


def test_refused_trajectory_names_the_bodies_and_stops():
    rig = Rig.of("ur5e")
    q0 = rig.arm.state().q
    q_goal = q0.copy()
    q_goal[1] += 1.2  # shoulder down: the upper arm swings into the table
    sf = rig.cfg.safety
    traj = joint_trajectory(rig.model, q0, q_goal, dt=rig.dt, velocity_scale=sf.joint_velocity_scale,
                            acceleration_scale=sf.joint_acceleration_scale, jerk_scale=sf.joint_jerk_scale)
    _, refusal = rig.guard.check_trajectory(traj)
    assert refusal is not None and refusal.kind in {"collision", "barrier"}
    with pytest.raises(SafetyStop, match="refused"):
        rig.guard.execute_trajectory(traj)
    log = rig.guard.log.as_dict()
    assert log["refusals"] and log["stops"][0]["reason"].startswith("refused")


def test_a_planners_move_is_checked_once_and_a_refusal_is_an_answer(monkeypatch):
    """``try_trajectory``: a move the guard refuses comes back as the refusal, with the arm neither moved
    nor stopped (the next move goes); one it accepts is started after one check of its path."""
    rig = Rig.of("ur5e")
    q0 = rig.arm.state().q
    sf = rig.cfg.safety
    scales = {"velocity_scale": sf.joint_velocity_scale, "acceleration_scale": sf.joint_acceleration_scale,
              "jerk_scale": sf.joint_jerk_scale}
    into_table = q0 + np.eye(rig.model.n_joints)[1] * 1.2  # shoulder down: the upper arm into the table
    _, refusal = rig.guard.try_trajectory(joint_trajectory(rig.model, q0, into_table, dt=rig.dt, **scales))
    assert refusal is not None and refusal.kind in {"collision", "barrier"}
    assert not rig.guard.following and not rig.guard.log.as_dict()["stops"]
    np.testing.assert_array_equal(rig.arm.state().q, q0)
    checks = []
    check_path = rig.guard.collision.check_path
    monkeypatch.setattr(rig.guard.collision, "check_path", lambda *a: checks.append(1) or check_path(*a))
    q_goal = q0 + np.array([0.1, -0.05, 0.05, 0.0, 0.1, 0.0])
    started, refusal = rig.guard.try_trajectory(joint_trajectory(rig.model, q0, q_goal, dt=rig.dt, **scales))
    assert refusal is None and rig.guard.following and len(checks) == 1
    rig.tick(int(started.duration / rig.dt) + 5)
    np.testing.assert_allclose(rig.arm.state().q, q_goal, atol=1e-9)
    rig.assert_safe()


@pytest.mark.parametrize("model_name", ["panda", "ur5e"])
def test_ruckig_trajectories_respect_the_configured_limits(model_name):
    cfg = load_config(CELLS[model_name])
    m = get_robot_model(model_name)
    sf = cfg.safety
    rng = np.random.default_rng(5)
    dt = 0.002
    for _ in range(5):
        q0, q1 = rng.uniform(m.q_min, m.q_max), rng.uniform(m.q_min, m.q_max)
        traj = joint_trajectory(m, q0, q1, dt=dt, velocity_scale=sf.joint_velocity_scale,
                                acceleration_scale=sf.joint_acceleration_scale,
                                jerk_scale=sf.joint_jerk_scale)
        assert traj.qd is not None
        assert np.all(np.abs(traj.qd) <= m.qd_max * sf.joint_velocity_scale * (1 + 1e-6))
        qdd = np.diff(traj.qd, axis=0) / np.diff(traj.t)[:, None]
        assert np.all(np.abs(qdd) <= m.qdd_max * sf.joint_acceleration_scale * 1.01 + 1e-6)
        np.testing.assert_array_equal(traj.q[-1], q1)


def test_a_twist_into_a_plane_slides_along_it():
    plane = BarrierPlane.make("wall", [0.5, 0.0, 0.0], [-1.0, 0.0, 0.0])
    b = Barriers([plane], margin_m=0.0, acc=1.0, jerk=10.0, latency_s=0.01, time_constant_s=0.1)
    at_wall = np.array([[0.5, 0.0, 0.3]])
    v, active = b.project_twist(np.array([0.2, 0.1, 0.0, 0.0, 0.0, 0.0]), at_wall[0], at_wall, 1.0)
    np.testing.assert_allclose(v, [0.0, 0.1, 0.0, 0.0, 0.0, 0.0], atol=1e-12)
    assert active == ["wall"]
    away, _ = b.project_twist(np.array([-0.2, 0.1, 0.0, 0.0, 0.0, 0.0]), at_wall[0], at_wall, 1.0)
    np.testing.assert_allclose(away[:3], [-0.2, 0.1, 0.0])
    # Far from the plane, the twist passes unchanged.
    far = np.array([[0.0, 0.0, 0.3]])
    same, none = b.project_twist(np.array([0.2, 0.1, 0.0, 0.0, 0.0, 0.0]), far[0], far, 0.25)
    np.testing.assert_allclose(same[:3], [0.2, 0.1, 0.0])
    assert none == []


def test_two_planes_at_once_leave_the_edge_direction():
    planes = [BarrierPlane.make("x", [0.5, 0, 0], [-1, 0, 0]),
              BarrierPlane.make("floor", [0, 0, 0.1], [0, 0, 1])]
    b = Barriers(planes, margin_m=0.0, acc=1.0, jerk=10.0, latency_s=0.01, time_constant_s=0.1)
    corner = np.array([0.5, 0.0, 0.1])
    v = b.project_velocity(corner, np.array([0.3, 0.2, -0.4]), activation_m=0.01)
    np.testing.assert_allclose(v, [0.0, 0.2, 0.0], atol=1e-12)


def test_the_halfspace_projection_is_the_closest_feasible_point():
    rng = np.random.default_rng(3)
    for _ in range(200):
        m = int(rng.integers(1, 5))
        A, b = rng.normal(size=(m, 3)), rng.normal(size=m) * 0.1 - 0.3
        x_d = rng.normal(size=3)
        x, _ = project_onto_halfspaces(x_d, A, b, np.ones(3))
        assert np.min(A @ x - b) >= -1e-9
        # No feasible point among many random ones is closer.
        cand = x + rng.normal(size=(2000, 3)) * 0.05
        ok = np.all(cand @ A.T - b >= 0.0, axis=1)
        assert np.all(np.linalg.norm(cand[ok] - x_d, axis=1) >= np.linalg.norm(x - x_d) - 1e-9)


def test_approach_speed_lets_a_braking_motion_stop_before_the_plane():
    acc, jerk, latency = 1.0, 10.0, 0.01
    for d in (0.001, 0.01, 0.05, 0.3):
        v = float(approach_speed(np.array(d), acc=acc, jerk=jerk, latency_s=latency, time_constant_s=1e-9))
        t = latency + acc / jerk
        assert v * t + v * v / (2 * acc) == pytest.approx(d, rel=1e-9)
    assert float(approach_speed(np.array(-0.01), acc=acc, jerk=jerk, latency_s=latency,
                                time_constant_s=0.1)) == 0.0


@pytest.mark.parametrize("model_name", ["panda", "ur5e"])
def test_collision_world_names_the_bodies(model_name):
    cfg = load_config(CELLS[model_name])
    m = get_robot_model(model_name)
    world = CollisionWorld.for_cell(cfg)
    assert world.moving_names[-len(cfg.safety.collision.tool):] == [b.name for b in cfg.safety.collision.tool]
    q_home = np.asarray(cfg.arm.home_joints_rad)
    assert world.check(q_home) is None
    flange = m.fk(q_home)[:3, 3]
    world.set_roi(flange - 0.05, flange + 0.05)
    hit = world.check(q_home)
    assert hit is not None and hit.body_b == "object ROI"
    world.set_roi(None, None)
    assert world.check(q_home) is None


def _vertical_move_refusal(rig: Rig, dz: float):
    """Why the guard would refuse moving the flange straight up by ``dz`` [m] (down when negative), or
    None."""
    q0 = rig.arm.state().q
    T = rig.model.fk(q0)
    T[2, 3] += dz
    sf = rig.cfg.safety
    traj = joint_trajectory(rig.model, q0, rig.model.ik_pose(T, q0), dt=rig.dt,
                            velocity_scale=sf.joint_velocity_scale,
                            acceleration_scale=sf.joint_acceleration_scale, jerk_scale=sf.joint_jerk_scale)
    return rig.guard.check_trajectory(traj)[1]


def test_a_roi_margin_reaching_the_arm_where_it_stands_is_shrunk_on_that_face():
    """An object's box 5.5 cm under the flange: its margin would reach the wrist where the arm stands, and
    every move would be refused at its first sample. The space the arm takes is free of the object, so the
    guard shrinks the margin of the face towards the arm only: a move away passes, a move into the object's
    box is still refused."""
    rig = Rig.of("ur5e")
    q0 = rig.arm.state().q
    p = rig.model.fk(q0)[:3, 3]
    lo, hi = p + np.array([-0.05, -0.05, -0.30]), p + np.array([0.05, 0.05, -0.055])
    cfg = rig.cfg.safety.collision
    world = CollisionWorld(rig.model, cfg, rig.cfg.station.table_z_m)
    world.set_roi(lo, hi)
    hit = world.check(q0)
    assert hit is not None and hit.body_b == "object ROI"
    margins = world.set_roi(lo, hi, q_free=q0)
    assert margins is not None and world.check(q0) is None
    np.testing.assert_array_equal(margins[:5], cfg.roi_margin_m)
    assert 0.0 < margins[5] < cfg.roi_margin_m

    rig.guard.set_roi(lo, hi)  # before any tick the guard has not read the joints: the full margin
    assert "roi_margin_at_arm" not in rig.guard.log.clamps
    rig.guard.tick()  # as a job's control loop, which reads the joints the ROI is shrunk for
    rig.guard.set_roi(lo, hi)
    assert rig.guard.log.clamps["roi_margin_at_arm"] == 1
    assert _vertical_move_refusal(rig, 0.10) is None
    refusal = _vertical_move_refusal(rig, -0.10)
    assert refusal is not None and "object ROI" in refusal.message


def test_a_roi_whose_own_box_reaches_the_arm_keeps_its_margin():
    rig = Rig.of("ur5e")
    q0 = rig.arm.state().q
    p = rig.model.fk(q0)[:3, 3]
    rig.guard.set_roi(p - 0.05, p + 0.05)
    assert rig.guard.log.clamps["roi_margin_at_arm"] == 0
    refusal = _vertical_move_refusal(rig, 0.10)
    assert refusal is not None and refusal.message.startswith("trajectory sample 0:")


def test_obstacles_of_every_shape_are_checked(tmp_path):
    cfg = load_config(UR5E)
    m = get_robot_model("ur5e")
    q_home = np.asarray(cfg.arm.home_joints_rad)
    flange = m.fk(q_home)[:3, 3]
    mesh_path = tmp_path / "block.ply"
    o3d.io.write_triangle_mesh(str(mesh_path), o3d.geometry.TriangleMesh.create_box(0.1, 0.1, 0.1))
    shapes = [
        {"shape": "box", "name": "crate", "size_m": [0.1, 0.1, 0.1]},
        {"shape": "cylinder", "name": "pillar", "radius_m": 0.05, "length_m": 0.2},
        {"shape": "mesh", "name": "block", "path": str(mesh_path)},
    ]
    for shape in shapes:
        at = flange - (0.05 if shape["shape"] == "mesh" else 0.0)
        data = cfg.safety.collision.model_dump(mode="json")
        data["obstacles"] = [{**shape, "pose": {"xyz_m": at.tolist()}}]
        collision = type(cfg.safety.collision).model_validate(data)
        hit = CollisionWorld(m, collision, cfg.station.table_z_m).check(q_home)
        assert hit is not None and hit.body_b == shape["name"]


def test_self_collision_is_found_and_adjacent_links_are_not():
    cfg = load_config(UR5E)
    m = get_robot_model("ur5e")
    world = CollisionWorld(m, cfg.safety.collision, cfg.station.table_z_m)
    q = np.asarray(cfg.arm.home_joints_rad).copy()
    q[2] = 3.05  # elbow folded back onto the upper arm
    hit = world.check(q)
    assert hit is not None and {hit.body_a, hit.body_b} <= set(world.moving_names)
    assert not m.are_adjacent(hit.body_a, hit.body_b)


def test_trajectory_check_is_dense():
    cfg = load_config(UR5E)
    m = get_robot_model("ur5e")
    world = CollisionWorld(m, cfg.safety.collision, cfg.station.table_z_m)
    q0 = np.asarray(cfg.arm.home_joints_rad)
    q_mid = q0.copy()
    q_mid[1] += 1.2
    assert world.check(q_mid) is not None
    # Two collision-free end points whose straight joint path passes through q_mid.
    q_end = q0.copy()
    q_end[1] += 2.4
    path = np.vstack([q0, q_end])
    hit = world.check_path(path, 0.02)
    assert hit is not None and hit[0] == 1


@pytest.mark.parametrize("model_name", ["ur5e", "panda"])
def test_no_point_of_a_body_moves_further_than_its_sweep_bound(model_name):
    # The path check's soundness rests on this bound: points on the surface of every link capsule and the
    # corners of the tool, along random straight joint moves from random configurations.
    cfg = load_config(CELLS[model_name])
    m = get_robot_model(model_name)
    world = CollisionWorld(m, cfg.safety.collision, cfg.station.table_z_m)
    offsets = np.vstack([np.zeros(3), np.eye(3), -np.eye(3)])
    points = [(c.frame, np.vstack([np.asarray(end) + c.radius * offsets for end in (c.a, c.b)]))
              for c in m.capsule_specs]
    flange = m.n_joints + 1
    for body in cfg.safety.collision.tool:
        corners = np.array(np.meshgrid(*[[-0.5, 0.5]] * 3)).reshape(3, -1).T * np.asarray(body.size_m)
        points.append((flange, corners @ body.pose.matrix()[:3, :3].T + body.pose.matrix()[:3, 3]))
    rng = np.random.default_rng(7)
    for _ in range(40):
        q0 = rng.uniform(m.q_min, m.q_max)
        dq = rng.uniform(-0.5, 0.5, m.n_joints)
        bound = world.sweep_bound(dq)
        start = m.fk_all(q0)
        for s in np.linspace(0.0, 1.0, 9)[1:]:
            F = m.fk_all(q0 + s * dq)
            for k, (frame, local) in enumerate(points):
                moved = (local @ F[frame, :3, :3].T + F[frame, :3, 3]) - (local @ start[frame, :3, :3].T
                                                                          + start[frame, :3, 3])
                assert np.max(np.linalg.norm(moved, axis=1)) <= s * bound[k] + 1e-12


def test_watchdog_counts_late_ticks_in_a_row():
    dog = Watchdog(WatchdogConfig(deadline_factor=1.5, max_missed_deadlines=3, perception_max_age_s=2.0),
                   period_s=0.01)
    assert dog.tick(0.0) is None
    assert dog.tick(0.02) is None and dog.tick(0.04) is None  # two late ticks
    assert dog.tick(0.05) is None and dog.missed_in_a_row == 0  # on time again: the count restarts
    assert dog.tick(0.07) is None and dog.tick(0.09) is None
    reason = dog.tick(0.11)
    assert reason is not None and "3 times in a row" in reason
    assert dog.perception(5.0, None) is None and dog.perception(5.0, 3.5) is None
    assert "2.50 s old" in (dog.perception(5.0, 2.5) or "")


def test_smoother_keeps_direction_and_limits():
    sm = TwistSmoother(0.01, (1.0, 2.0), (10.0, 20.0))
    target = np.array([0.2, -0.1, 0.05, 0.0, 0.3, 0.0])
    out = [sm.step(target) for _ in range(200)]
    v = np.array(out)
    lin = v[:, :3]
    # Intermediate linear velocities point along the target (phase synchronisation; ruckig ends the ramp
    # within a couple of degrees of it).
    cos = (lin @ target[:3]) / (np.linalg.norm(lin, axis=1) * np.linalg.norm(target[:3]) + 1e-15)
    assert np.all(cos[np.linalg.norm(lin, axis=1) > 1e-6] > 0.999)
    assert np.all(np.linalg.norm(np.diff(v[:, :3], axis=0), axis=1) / 0.01 <= 1.0 + 1e-6)
    np.testing.assert_allclose(v[-1], target, atol=1e-9)


def test_guard_refuses_bad_twists_and_conflicting_motion():
    rig = Rig.of("panda")
    with pytest.raises(SafetyStop, match="6 finite values"):
        rig.guard.command_twist(np.array([0.0, np.nan, 0, 0, 0, 0]))
    rig2 = Rig.of("ur5e")
    rig2.guard.command_twist(np.array([0.01, 0, 0, 0, 0, 0]))
    q = rig2.arm.state().q
    with pytest.raises(SafetyStop, match="while a twist is being streamed"):
        rig2.guard.execute_trajectory(JointTrajectory(t=np.array([0.0, 1.0]), q=np.vstack([q, q])))
    # a trajectory starts where the arm is: one from elsewhere would have the arm jump to its start
    rig3 = Rig.of("ur5e")
    q = rig3.arm.state().q
    elsewhere = q + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.05])
    with pytest.raises(SafetyStop, match=r"starts 0\.0500 rad away from the arm's joints"):
        rig3.guard.execute_trajectory(JointTrajectory(t=np.array([0.0, 1.0]), q=np.vstack([elsewhere, q])))
    assert rig3.arm.state().mode is not ArmMode.TRAJECTORY
    # and nothing streams over a trajectory being followed
    rig4 = Rig.of("ur5e")
    q = rig4.arm.state().q
    rig4.guard.execute_trajectory(JointTrajectory(t=np.array([0.0, 2.0]), q=np.vstack([q, q + 0.02])))
    with pytest.raises(SafetyStop, match="while a trajectory is being followed"):
        rig4.guard.command_twist(np.array([0.01, 0, 0, 0, 0, 0]))


def test_a_trajectory_faster_than_the_limits_is_slowed_down_along_its_path():
    """A planner's trajectory that asks a joint or the TCP for more speed than the cell allows is stretched
    in time, its path kept, before the arm gets it."""
    rig = Rig.of("ur5e")
    q0 = rig.arm.state().q
    q = np.linspace(q0, q0 + np.array([0.2, -0.1, 0.1, 0.0, 0.0, 0.1]), 11)
    executed = rig.guard.execute_trajectory(JointTrajectory(t=np.linspace(0.0, 0.05, 11), q=q))
    np.testing.assert_array_equal(executed.q, q)
    sf, m = rig.cfg.safety, rig.model
    qd = np.abs(np.diff(executed.q, axis=0)) / np.diff(executed.t)[:, None]
    assert np.all(qd <= m.qd_max * sf.joint_velocity_scale * 1.02 + 1e-9)  # the guard's 2 % tolerance
    flange = np.array([m.fk(qk)[:3, 3] for qk in executed.q])
    assert np.all(np.linalg.norm(np.diff(flange, axis=0), axis=1) / np.diff(executed.t)
                  <= sf.tcp_max_linear_mps * 1.02 + 1e-9)
    assert rig.guard.log.as_dict()["clamps"]["trajectory_time_scaled"] == 1


def test_fault_stop_leaves_the_arm_recoverable():
    rig = Rig.of("panda")
    rig.guard.command_twist(np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0]))
    rig.tick(30)
    rig.arm.inject_fault("reflex")
    with pytest.raises(SafetyStop, match="arm fault: reflex"):
        rig.guard.tick()
    for _ in range(50):
        rig.step()
    rig.arm.recover()
    rig.guard.command_twist(np.array([0.0, 0.02, 0.0, 0.0, 0.0, 0.0]))
    rig.tick(20)
    assert rig.arm.state().mode is ArmMode.VELOCITY


def test_a_streamed_twist_into_the_object_is_refused_as_a_twist_refusal():
    rig = Rig.of("panda")
    p = rig.arm.state().T_base_flange[:3, 3]
    rig.set_roi(p + np.array([-0.1, -0.1, -0.30]), p + np.array([0.1, 0.1, -0.20]))
    rig.guard.command_twist(np.array([0.0, 0.0, -0.1, 0.0, 0.0, 0.0]))
    with pytest.raises(TwistRefused) as refused:
        rig.tick(400)
    assert isinstance(refused.value, SafetyStop) and refused.value.refusal.kind == "collision"
    assert "ROI" in refused.value.refusal.message or "roi" in refused.value.refusal.message.lower()
    log = rig.guard.log.as_dict()
    assert len(log["refusals"]) == 1 and log["stops"][0]["reason"].startswith("refused")
    for _ in range(100):
        rig.step()
    assert rig.arm.state().mode is ArmMode.IDLE
    rig.guard.command_twist(np.array([0.0, 0.0, 0.05, 0.0, 0.0, 0.0]))  # backing off is allowed
    rig.tick(20)
    assert rig.arm.state().mode is ArmMode.VELOCITY
    rig.assert_safe()


def test_a_twist_streamed_while_a_stop_brakes_the_arm_starts_once_it_is_at_rest():
    """A planner backs off at once after a refusal, while the arm's stop still brakes it: the twist waits
    for the arm to come to rest and then moves it, instead of being refused (smoothed from a rest the
    joints were not at, it needed a joint to change speed faster than the robot can)."""
    rig = Rig.of("panda")
    p = rig.arm.state().T_base_flange[:3, 3]
    rig.set_roi(p + np.array([0.30, -0.1, -0.2]), p + np.array([0.5, 0.1, 0.2]))
    rig.guard.command_twist(np.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.0]))
    with pytest.raises(TwistRefused):
        rig.tick(400)
    assert np.max(np.abs(rig.arm.state().qd)) > 0.1  # still braking
    rig.guard.command_twist(np.array([-0.05, 0.0, 0.0, 0.0, 0.0, 0.0]))
    rig.tick(150)
    state = rig.arm.state()
    assert state.mode is ArmMode.VELOCITY
    assert state.v_base_flange[0] < -0.045  # backing off at the commanded speed
    rig.assert_safe()


def test_a_commanded_twist_comes_back_as_the_arm_realizes_it():
    """Damped least squares falls short of a twist along a near-singular direction: the returned twist
    says so (the servo scan judges a camera held by the arm's reach by it)."""
    rig = Rig.of("panda")
    outward = np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.0])
    free = rig.guard.command_twist(outward)
    assert np.allclose(free, outward, atol=5e-4)
    rig.guard.hold()

    stretched = Rig.of("panda", PANDA_AT_REACH)
    realized = stretched.guard.command_twist(outward)
    assert np.linalg.norm(realized[:3]) < 0.15 * np.linalg.norm(outward[:3])
    up = np.array([0.0, 0.0, 0.02, 0.0, 0.0, 0.0])
    assert np.allclose(stretched.guard.command_twist(up), up, atol=5e-4)


def test_a_twist_too_fast_comes_back_within_the_limits():
    """A planner asking for more than the cell allows is told what the arm will do: its twist within the
    TCP's speed limits and, through the arm's joints, theirs (each tick limits the streamed twist again)."""
    rig = Rig.of("ur5e")
    sf, m = rig.cfg.safety, rig.model
    for asked in (np.array([2.0, 0.0, 0.0, 0.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 0.0, 0.0, 5.0])):
        realized = rig.guard.command_twist(asked)
        assert np.linalg.norm(realized[:3]) <= sf.tcp_max_linear_mps + 1e-9
        assert np.linalg.norm(realized[3:]) <= sf.tcp_max_angular_rps + 1e-9
        qd = m.velocity_map(rig.arm.state().q)(realized)
        assert np.all(np.abs(qd) <= m.qd_max * sf.joint_velocity_scale * (1 + 1e-6))
        rig.guard.hold()


def test_a_pose_as_deep_in_a_plane_margin_as_a_motion_from_here_may_go_is_allowed_from_here():
    """A camera sliding along a plane sits inside its margin, as deep as a streamed twist may take it:
    from there the poses at its own depth are within reach (``from_here``), deeper ones are not, and
    without ``from_here`` neither is."""
    rig = Rig.of("ur5e")
    rig.guard.tick()
    T = rig.model.fk(rig.arm.state().q)
    margin = 0.01
    lowest = float(np.min(rig.guard.guarded_points(T)[:, 2]))
    floor = BarrierPlane.make("floor", [0.0, 0.0, lowest - 0.6 * margin], [0.0, 0.0, 1.0])
    rig.guard.barriers = Barriers([floor], margin_m=margin, acc=1.0, jerk=10.0, latency_s=0.01,
                                  time_constant_s=0.1)
    level = T.copy()
    level[:2, 3] += 0.05  # elsewhere at the same height
    assert rig.guard.barrier_violation(level) is not None
    assert rig.guard.barrier_violation(level, rig.guard.motion_floor()) is None
    deeper = level.copy()
    deeper[2, 3] -= 0.2 * margin
    assert rig.guard.barrier_violation(deeper, rig.guard.motion_floor()) is not None
