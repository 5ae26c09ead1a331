"""One conformance suite for the Arm interface, passed by every backend against its real peer:
the sim arm, the UR5e backend (ur-rtde against the RTDE controller peer) and the Franka backend (franky
against franky-sim)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from cell.control.trajectory import joint_trajectory
from drivers.arm.base import ArmMode, MotionToken
from drivers.errors import DriverError, RobotFault
from tests.arm_backends import (
    STREAMING_WATCHDOG_HZ,
    Backend,
    FrankySim,
    franka_backend,
    sim_backend,
    ur5e_backend,
)
from tests.rtde_peer import ControllerPeer

TWIST_MOTION_S = 0.5  # how long the twist test commands motion, on the arm's own clock [s]


@pytest.fixture(scope="module")
def franky_sim() -> Iterator[FrankySim]:
    """One franky-sim for the module (the fault test injects a reflex and recovers from it)."""
    sim = FrankySim()
    yield sim
    sim.kill()


@pytest.fixture(params=["sim", "ur5e", "franka"])
def backend(request: pytest.FixtureRequest, franky_sim: FrankySim) -> Iterator[Backend]:
    if request.param == "sim":
        with sim_backend() as b:
            yield b
    elif request.param == "ur5e":
        peer = ControllerPeer()
        try:
            with ur5e_backend(peer, watchdog_min_hz=STREAMING_WATCHDOG_HZ) as b:
                yield b
        finally:
            peer.stop()
    else:
        with franka_backend(franky_sim) as b:
            yield b


def test_state_reports_joints_pose_and_idle(backend: Backend) -> None:
    st = backend.arm.state()
    assert backend.arm.is_connected
    assert st.q.shape == (backend.arm.n_joints,) and st.qd.shape == (backend.arm.n_joints,)
    R = st.T_base_flange[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.allclose(st.T_base_flange[3], [0, 0, 0, 1])
    assert st.mode is ArmMode.IDLE and st.faults == ()


def test_motion_needs_the_guard_token(backend: Backend) -> None:
    with pytest.raises(DriverError, match="safety guard"):
        backend.arm.command_twist(np.zeros(6), MotionToken())


def test_malformed_twist_is_refused_before_anything_is_sent(backend: Backend) -> None:
    with pytest.raises(ValueError, match="twist"):
        backend.arm.command_twist(np.zeros(5), backend.token)
    with pytest.raises(ValueError, match="non-finite"):
        backend.arm.command_twist(np.array([0.01, 0, 0, 0, np.nan, 0]), backend.token)
    assert backend.arm.state().mode is ArmMode.IDLE


def test_twist_moves_the_flange_as_commanded_and_stop_brings_it_to_rest(backend: Backend) -> None:
    """The control loop renews a twist at 50 Hz until the arm's own clock (``ArmState.timestamp``) has
    seen ``TWIST_MOTION_S`` of commanded motion since the arm first reported moving; the flange must
    cover at least half of speed x that time (the rest is the acceleration ramp). The arm's clock, not
    the test's: a simulator on a loaded machine (franky-sim) runs slower than the wall clock. A twist
    holds until renewed, or for ``backend.twist_hold_s`` of the arm's time (Franka), which bounds each
    renewal's share of the motion time."""
    arm = backend.arm
    st = arm.state()
    p0 = st.T_base_flange[:3, 3]
    speed = 0.04
    v = np.array([0.0, 0.0, speed, 0.0, 0.0, 0.0])
    hold = backend.twist_hold_s if backend.twist_hold_s is not None else np.inf
    motion_s = 0.0
    moving = False
    last_command_t = st.timestamp
    arm.command_twist(v, backend.token)
    for _ in range(1000):  # a bound on waiting, 20 s of the test's time
        backend.advance(0.02)
        st = arm.state()
        # counted from the arm's first report of motion: on a loaded machine the first command can reach
        # the controller late (a fresh-clone run once saw the RTDE peer's arm still in 0.7 s of its clock)
        if moving:
            motion_s += min(st.timestamp - last_command_t, hold)
            if motion_s >= TWIST_MOTION_S:
                break
        moving = moving or bool(np.linalg.norm(st.v_base_flange[:3]) > 0.0)
        last_command_t = st.timestamp
        arm.command_twist(v, backend.token)
    assert st.mode is ArmMode.VELOCITY
    moved = st.T_base_flange[:3, 3] - p0
    assert motion_s >= TWIST_MOTION_S, f"{backend.name}: only {motion_s:.3f} s of motion on the arm's clock"
    assert moved[2] > 0.5 * speed * motion_s, f"{backend.name}: flange moved {moved} in {motion_s:.3f} s"
    assert np.linalg.norm(moved[:2]) < 0.3 * moved[2]
    arm.stop()
    backend.wait_until(lambda: arm.state().mode is ArmMode.IDLE
                       and bool(np.linalg.norm(arm.state().v_base_flange[:3]) < 1e-3))


def test_trajectory_ends_at_its_last_sample(backend: Backend) -> None:
    arm = backend.arm
    model = arm.model  # type: ignore[attr-defined]
    q0 = arm.state().q
    goal = q0.copy()
    goal[-1] += 0.2
    goal[-2] -= 0.1
    traj = joint_trajectory(model, q0, goal, dt=0.01, velocity_scale=0.3, acceleration_scale=0.3,
                            jerk_scale=0.3)
    arm.execute_trajectory(traj, backend.token)
    # franky-sim's joints settle on the goal after franky's motion has finished, so wait for both
    backend.wait_until(lambda: arm.state().mode is ArmMode.IDLE
                       and np.max(np.abs(arm.state().q - goal)) < 5e-3)


def test_a_fault_surfaces_and_refuses_motion(backend: Backend) -> None:
    arm = backend.arm
    backend.inject_fault()
    with pytest.raises(RobotFault) as refused:
        backend.wait_until(lambda: bool(arm.state().faults))
        arm.command_twist(np.array([0.0, 0.0, 0.01, 0, 0, 0]), backend.token)
    assert refused.value.fault
    if backend.recoverable:
        st = arm.state()
        assert st.mode is ArmMode.FAULT
        arm.stop()  # anyone may stop a faulted arm
        arm.recover()
        assert arm.state().faults == ()
        arm.command_twist(np.array([0.0, 0.0, 0.01, 0, 0, 0]), backend.token)
        arm.stop()
