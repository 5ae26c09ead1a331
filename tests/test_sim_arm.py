"""SimArm: twist following, trajectories, stopping, limits, the pose-error model and input checks."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.arm.base import ArmMode, JointTrajectory, MotionToken
from drivers.arm.config import SimArmConfig
from drivers.arm.sim import SimArm
from drivers.clock import SimClock
from drivers.errors import DriverError, RobotFault
from drivers.robots import ROBOT_MODEL_NAMES, get_robot_model
from drivers.transforms import pose_error

DT = 0.004  # 250 Hz


_TOKENS: dict[int, MotionToken] = {}


def tok(arm: SimArm) -> MotionToken:
    """The motion token these tests claimed for ``arm`` (the safety guard holds it in a job)."""
    return _TOKENS[id(arm)]


def make_arm(name: str = "panda", seed: int = 0, error: tuple[float, float] | None = None,
             **cfg: object) -> tuple[SimArm, SimClock]:
    """A connected sim arm; ``error`` (joint offset std [rad], DH length std [m]) perturbs its true model."""
    clock = SimClock()
    config = SimArmConfig(type="sim", model=name, **cfg)  # type: ignore[arg-type]
    model = get_robot_model(name)
    true_model = None if error is None else model.perturbed(np.random.default_rng(seed), *error)
    arm = SimArm(config, model, clock, true_model)
    arm.connect()
    _TOKENS[id(arm)] = arm.claim_motion()
    return arm, clock


def run(clock: SimClock, seconds: float) -> None:
    for _ in range(round(seconds / DT)):
        clock.sleep(DT)


@pytest.mark.parametrize("name", ROBOT_MODEL_NAMES)
def test_constant_twist_moves_flange_at_commanded_velocity(name: str) -> None:
    arm, clock = make_arm(name)
    v = np.array([0.05, -0.03, 0.04, 0.0, 0.0, 0.1])
    arm.command_twist(v, tok(arm))
    run(clock, 0.2)  # let the acceleration ramp settle
    s0 = arm.state()
    assert s0.mode is ArmMode.VELOCITY
    run(clock, 1.0)
    s1 = arm.state()
    dp = (s1.T_base_flange[:3, 3] - s0.T_base_flange[:3, 3]) / (s1.timestamp - s0.timestamp)
    np.testing.assert_allclose(dp, v[:3], atol=2e-3)
    w = pose_error(s0.T_base_flange, s1.T_base_flange)[3:] / (s1.timestamp - s0.timestamp)
    np.testing.assert_allclose(w, v[3:], atol=5e-3)
    np.testing.assert_allclose(s1.v_base_flange, v, atol=2e-3)
    assert s1.timestamp == pytest.approx(1.2)


def test_trajectory_is_followed_then_idle() -> None:
    arm, clock = make_arm("ur5e")
    q0 = arm.state().q
    t = np.linspace(0.0, 2.0, 21)
    q = q0 + np.outer(np.sin(np.pi * t / 4.0), [0.3, -0.2, 0.25, 0.1, -0.1, 0.2])
    arm.execute_trajectory(JointTrajectory(t=t, q=q), tok(arm))
    assert arm.state().mode is ArmMode.TRAJECTORY
    run(clock, 1.0)
    s = arm.state()
    expect = np.array([np.interp(1.0, t, q[:, j]) for j in range(6)])
    np.testing.assert_allclose(s.q, expect, atol=1e-9)
    assert s.mode is ArmMode.TRAJECTORY
    assert np.linalg.norm(s.qd) > 0.0
    run(clock, 1.2)
    s = arm.state()
    np.testing.assert_allclose(s.q, q[-1], atol=1e-12)
    assert s.mode is ArmMode.IDLE
    np.testing.assert_array_equal(s.qd, 0.0)


def test_trajectory_must_start_at_current_q() -> None:
    arm, _ = make_arm("panda")
    q0 = arm.state().q
    t = np.array([0.0, 1.0])
    with pytest.raises(ValueError, match="rad away"):
        arm.execute_trajectory(JointTrajectory(t=t, q=np.vstack([q0 + 0.01, q0 + 0.1])), tok(arm))
    with pytest.raises(ValueError, match="joints"):
        arm.execute_trajectory(JointTrajectory(t=t, q=np.zeros((2, 6))), tok(arm))


@pytest.mark.parametrize("name", ROBOT_MODEL_NAMES)
def test_stop_decelerates_within_limits(name: str) -> None:
    arm, clock = make_arm(name)
    m = arm.model
    arm.command_twist(np.array([0.0, 0.0, -0.3, 0.0, 0.0, 0.0]), tok(arm))
    run(clock, 0.3)
    qd_prev = arm.state().qd
    assert np.linalg.norm(qd_prev) > 0.1
    arm.stop()
    assert arm.state().mode is ArmMode.STOPPING
    for _ in range(500):
        clock.sleep(DT)
        s = arm.state()
        assert np.all(np.abs(s.qd - qd_prev) <= m.qdd_max * DT * (1 + 1e-9))
        # deceleration keeps the joint-space direction
        if np.linalg.norm(s.qd) > 0:
            cos = s.qd @ qd_prev / np.linalg.norm(s.qd) / np.linalg.norm(qd_prev)
            assert cos == pytest.approx(1.0, abs=1e-9)
        qd_prev = s.qd
        if s.mode is ArmMode.IDLE:
            break
    assert arm.state().mode is ArmMode.IDLE
    np.testing.assert_array_equal(arm.state().qd, 0.0)


@pytest.mark.parametrize("name", ROBOT_MODEL_NAMES)
def test_joint_limits_hold(name: str) -> None:
    arm, clock = make_arm(name)
    m = arm.model
    # push hard in one direction for long: the arm runs into its workspace boundary / joint limits
    for v in ([1.0, 0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, 3.0]):
        arm.command_twist(np.array(v), tok(arm))
        for _ in range(1000):
            clock.sleep(0.01)
            s = arm.state()
            assert np.all(s.q >= m.q_min) and np.all(s.q <= m.q_max)
            assert np.all(np.abs(s.qd) <= m.qd_max * (1 + 1e-9))


def test_pose_error_model() -> None:
    pe = (0.002, 0.001)
    arm, clock = make_arm("panda", seed=11, error=pe)
    diff = arm.true_flange_pose()[:3, 3] - arm.state().T_base_flange[:3, 3]
    assert 3e-4 < np.linalg.norm(diff) < 2e-2
    arm2, _ = make_arm("panda", seed=11, error=pe)
    np.testing.assert_array_equal(arm.true_flange_pose(), arm2.true_flange_pose())
    arm3, _ = make_arm("panda", seed=12, error=pe)
    assert not np.array_equal(arm.true_flange_pose(), arm3.true_flange_pose())
    # the error stays mm-level while moving, and the true pose moves with the reported one
    T_true0 = arm.true_flange_pose()
    arm.command_twist(np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0]), tok(arm))
    run(clock, 0.5)
    diff = arm.true_flange_pose()[:3, 3] - arm.state().T_base_flange[:3, 3]
    assert 3e-4 < np.linalg.norm(diff) < 2e-2
    assert np.linalg.norm(arm.true_flange_pose()[:3, 3] - T_true0[:3, 3]) > 0.015
    # without pose error both agree
    plain, _ = make_arm("panda")
    np.testing.assert_array_equal(plain.true_flange_pose(), plain.state().T_base_flange)


def test_home_joints_from_config_and_validation() -> None:
    q_home = [0.1, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7]
    arm, _ = make_arm("panda", home_joints_rad=q_home)
    np.testing.assert_array_equal(arm.state().q, q_home)
    with pytest.raises(ValueError, match="7 finite values"):
        make_arm("panda", home_joints_rad=[0.0] * 6)
    with pytest.raises(ValueError, match=r"home_joints_rad\[3\]"):
        make_arm("panda", home_joints_rad=[0.0] * 7)  # joint 4 must be below -0.0698
    clock = SimClock()
    with pytest.raises(ValueError, match="model"):
        SimArm(SimArmConfig(type="sim", model="ur5e"), get_robot_model("panda"), clock)


def test_bad_twist_raises() -> None:
    arm, _ = make_arm("ur5e")
    with pytest.raises(ValueError, match="shape"):
        arm.command_twist(np.zeros(3), tok(arm))
    with pytest.raises(ValueError, match="non-finite"):
        arm.command_twist(np.array([0, 0, np.nan, 0, 0, 0]), tok(arm))


def test_disconnected_raises_and_context_manager() -> None:
    clock = SimClock()
    arm = SimArm(SimArmConfig(type="sim", model="ur5e"), get_robot_model("ur5e"), clock)
    assert not arm.is_connected
    _TOKENS[id(arm)] = arm.claim_motion()
    for call in (arm.state, arm.stop, lambda: arm.command_twist(np.zeros(6), tok(arm))):
        with pytest.raises(DriverError, match="arm sim"):
            call()
    with arm:
        assert arm.is_connected
        arm.command_twist(np.array([0.0, 0.0, 0.05, 0.0, 0.0, 0.0]), tok(arm))
        clock.sleep(0.1)
    assert not arm.is_connected
    arm.disconnect()  # twice is fine
    q = arm.true_flange_pose()
    clock.sleep(0.1)  # no motion while disconnected
    np.testing.assert_array_equal(arm.true_flange_pose(), q)


def test_deterministic_run() -> None:
    def once() -> np.ndarray:
        arm, clock = make_arm("ur5e", seed=3, error=(0.001, 0.0005))
        arm.command_twist(np.array([0.02, 0.01, -0.03, 0.05, 0.0, 0.0]), tok(arm))
        run(clock, 0.5)
        arm.stop()
        run(clock, 0.5)
        return np.concatenate([arm.state().q, arm.true_flange_pose().ravel()])

    np.testing.assert_array_equal(once(), once())


def test_motion_needs_the_claimed_token() -> None:
    arm, _ = make_arm("panda")
    with pytest.raises(DriverError, match="through the safety guard"):
        arm.command_twist(np.zeros(6), MotionToken())
    with pytest.raises(DriverError, match="already owned"):
        arm.claim_motion()
    arm.release_motion(tok(arm))
    with pytest.raises(DriverError, match="through the safety guard"):
        arm.command_twist(np.zeros(6), tok(arm))


def test_injected_fault_brakes_refuses_motion_until_recovered() -> None:
    arm, clock = make_arm("ur5e")
    arm.command_twist(np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]), tok(arm))
    run(clock, 0.5)
    arm.inject_fault("protective stop")
    s = arm.state()
    assert s.mode is ArmMode.FAULT and s.faults == ("protective stop",)
    with pytest.raises(RobotFault, match="protective stop"):
        arm.command_twist(np.zeros(6), tok(arm))
    with pytest.raises(RobotFault, match="at rest"):
        arm.recover()
    run(clock, 1.0)
    assert np.all(arm.state().qd == 0.0) and arm.state().mode is ArmMode.FAULT
    arm.recover()
    assert arm.state().mode is ArmMode.IDLE and arm.state().faults == ()
    arm.command_twist(np.zeros(6), tok(arm))


def test_disconnect_fault_and_non_recoverable_fault() -> None:
    arm, _ = make_arm("panda")
    arm.inject_fault("disconnect")
    with pytest.raises(RobotFault, match="disconnected"):
        arm.state()
    arm.recover()
    assert arm.state().faults == ()
    arm.inject_fault("emergency stop", recoverable=False)
    with pytest.raises(RobotFault, match="cannot be cleared"):
        arm.recover()
    arm.release_fault()
    arm.recover()
    assert arm.state().mode is ArmMode.IDLE
