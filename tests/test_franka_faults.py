"""The Franka backend's fault paths against franky-sim with the control unit's faults injected
(tests/franky_fault_sim.py): what franky raises becomes a ``RobotFault`` with the reason, the robot's
errors and the next step; the arm is at rest; ``recover`` clears what the robot lets it clear; a lost
robot is a "disconnect" fault. The conformance suite covers a reflex while idle."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from cell.control.trajectory import joint_trajectory
from drivers.arm.base import ArmMode
from drivers.arm.franka import FrankaArm
from drivers.errors import DriverError, RobotFault
from tests.arm_backends import Backend, FrankySim, franka_backend

UP = np.array([0.0, 0.0, 0.02, 0.0, 0.0, 0.0])  # a slow twist [m/s, rad/s]


@pytest.fixture
def sim() -> Iterator[FrankySim]:
    sim = FrankySim()
    yield sim
    if sim.alive:
        sim.kill()


@pytest.fixture
def franka(sim: FrankySim) -> Iterator[Backend]:
    with franka_backend(sim) as backend:
        yield backend


def start_a_long_move(backend: Backend) -> None:
    """A joint move of a few seconds, started and seen moving."""
    arm = backend.arm
    q0 = arm.state().q
    goal = q0.copy()
    goal[-1] += 1.0
    traj = joint_trajectory(arm.model, q0, goal, dt=0.01, velocity_scale=0.2,  # type: ignore[attr-defined]
                            acceleration_scale=0.2, jerk_scale=0.2)
    arm.execute_trajectory(traj, backend.token)
    backend.wait_until(lambda: bool(np.max(np.abs(arm.state().qd)) > 0.05))


def at_rest(backend: Backend) -> bool:
    return bool(np.max(np.abs(backend.arm.state().qd)) < 1e-3)


def test_a_reflex_during_a_move_stops_the_arm_names_its_errors_and_recovers(
        sim: FrankySim, franka: Backend) -> None:
    arm = franka.arm
    start_a_long_move(franka)
    sim.inject("reflex cartesian_reflex joint_velocity_violation")
    franka.wait_until(lambda: arm.state().faults == ("reflex",) and at_rest(franka))
    st = arm.state()
    assert st.mode is ArmMode.FAULT
    with pytest.raises(RobotFault) as refused:
        arm.command_twist(UP, franka.token)
    fault = refused.value
    assert fault.fault == "reflex"
    message = str(fault)
    # franky's reason, the robot's mode and flags, what to do
    assert "motion aborted by reflex" in message and "robot mode Reflex" in message
    assert '"joint_velocity_violation", "cartesian_reflex"' in message
    assert "then recover (cell arm recover)" in message
    q_faulted = st.q
    franka.advance(0.3)
    assert np.max(np.abs(arm.state().q - q_faulted)) < 1e-3  # the robot holds where it stopped
    arm.stop()  # anyone may stop a faulted arm; nothing is sent
    arm.recover()
    assert arm.state().faults == () and arm.state().mode is ArmMode.IDLE
    assert isinstance(arm, FrankaArm) and arm.controller_modes() == {"robot mode": "Idle", "errors": "none"}
    start_a_long_move(franka)  # moves again


def test_a_user_stop_cannot_be_recovered_until_it_is_released(sim: FrankySim, franka: Backend) -> None:
    arm = franka.arm
    for _ in range(5):  # a stream of twists, as the control loop sends them
        arm.command_twist(UP, franka.token)
        franka.advance(0.02)
    sim.inject("user-stop")
    franka.wait_until(lambda: "user stop" in arm.state().faults)
    with pytest.raises(RobotFault) as refused:
        arm.command_twist(UP, franka.token)
    assert refused.value.fault == "user stop" and "User Stop pressed" in str(refused.value)
    with pytest.raises(RobotFault) as still:
        arm.recover()
    assert still.value.fault == "user stop"
    assert "automatic error recovery failed" in str(still.value)
    assert "release the user stop, then recover" in str(still.value)
    sim.inject("release")
    arm.recover()
    assert arm.state().faults == ()
    arm.command_twist(UP, franka.token)
    arm.stop()


def test_a_vanished_robot_is_a_disconnect_and_recover_says_what_to_check(
        sim: FrankySim, franka: Backend) -> None:
    arm = franka.arm
    arm.command_twist(UP, franka.token)
    sim.kill()
    with pytest.raises(RobotFault) as lost:
        franka.wait_until(lambda: bool(arm.state().faults))
    assert lost.value.fault == "disconnect"
    assert "check the network and that FCI is active" in str(lost.value)
    with pytest.raises(RobotFault) as refused:
        arm.command_twist(UP, franka.token)
    assert refused.value.fault == "disconnect"
    with pytest.raises(DriverError, match="cannot reach the robot's control port"):
        arm.recover()
