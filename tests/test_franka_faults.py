"""The Franka backend's fault paths against franky-sim with the control unit's faults injected
(tests/franky_fault_sim.py): what franky raises becomes a ``RobotFault`` with the reason, the robot's
errors and the next step; the arm is at rest; ``recover`` clears what the robot lets it clear; a lost
robot is a "disconnect" fault; a reflex during a scan ends the job with everything it recorded kept, and
``cell arm recover`` clears it. The conformance suite covers a reflex while idle."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from cell.cli.arm import arm_app
from cell.config import load_config
from cell.control.trajectory import joint_trajectory
from cell.jobs import session
from cell.jobs.progress import JobProgress
from cell.jobs.runner import ScanRequest, run_scan
from drivers.arm.base import ArmMode
from drivers.arm.franka import FrankaArm
from drivers.errors import DriverError, RobotFault, SafetyStop
from tests.arm_backends import Backend, FrankySim, franka_backend, franka_config
from tests.conftest import FRANKA

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


def at_rest(backend: Backend, window_s: float = 0.2) -> bool:
    """The arm's joints moved at under 1e-3 rad/s on average over ``window_s`` [s]: it has stopped.

    Not their speeds: franky-sim holds a stopped Panda with a PD law it integrates explicitly each 1 ms
    step, and at times the last joint is left chattering between two positions one step apart for good:
    its speed reads +-0.077 rad/s while it stays within 8e-5 rad (8 of 26 stops on a loaded machine)."""
    q_before = backend.arm.state().q
    backend.advance(window_s)
    return bool(np.max(np.abs(backend.arm.state().q - q_before)) < 1e-3 * window_s)


def test_a_reflex_during_a_move_stops_the_arm_names_its_errors_and_recovers(
        sim: FrankySim, franka: Backend) -> None:
    arm = franka.arm
    start_a_long_move(franka)
    sim.inject("reflex cartesian_reflex joint_velocity_violation")
    reflex = "reflex: joint_velocity_violation, cartesian_reflex"  # the robot's flags, in its order
    franka.wait_until(lambda: arm.state().faults == (reflex,) and at_rest(franka))
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


def test_a_vanished_robot_is_a_disconnect_recover_says_what_to_check_and_reconnects_once_it_is_back(
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
    back = FrankySim(host=sim.host)  # the robot is powered again: recover reconnects
    try:
        arm.recover()
        assert arm.state().faults == () and arm.state().mode is ArmMode.IDLE
        arm.command_twist(UP, franka.token)
        arm.stop()
    finally:
        back.kill()


def dry_run_cell(tmp_path: Path, host: str) -> Path:
    """The sim Franka cell as a dry run (the Franka backend, the simulated camera rendering from the pose
    the arm reports) against franky-sim at ``host``: a short raster, on the wall clock at 50 Hz with the
    dry run's lenient late-tick watchdog (a Python simulator shares the machine)."""
    data = yaml.safe_load(FRANKA.read_text())
    data["mode"] = "dry-run"
    home = data["arm"]["home_joints_rad"]
    data["arm"] = franka_config(host).model_dump(mode="json") | {"home_joints_rad": home}
    data["safety"]["watchdog"] |= {"deadline_factor": 5.0, "max_missed_deadlines": 5}
    data["scan"] |= {"planner": "raster", "control_rate_hz": 50.0}
    data["planners"]["raster"]["rings"] = [{"elevation_deg": 60.0, "n_views": 6}]
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_a_reflex_during_a_scan_ends_it_with_every_frame_kept_and_cell_arm_recover_clears_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # franky-sim, a Python simulator, runs slower than the wall clock on a loaded machine, and a move on
    # it with it: the job's deadline for a move (its planned duration + 2 s) is not what this test is about
    monkeypatch.setattr(session, "MOVE_TIMEOUT_MARGIN_S", 60.0)
    sim = FrankySim(q=load_config(FRANKA).arm.home_joints_rad)
    try:
        cell_file = dry_run_cell(tmp_path, sim.host)
        injected_at: list[int] = []

        def reflex_after_the_first_capture(progress: JobProgress) -> None:
            if progress.n_captures >= 1 and not injected_at:
                injected_at.append(progress.n_captures)
                sim.inject("reflex cartesian_reflex")  # a collision, as the arm moves on to the next view

        folder = tmp_path / "job"
        with pytest.raises(SafetyStop):  # raised once the folder is finished, as for any safety stop
            run_scan(ScanRequest(config=load_config(cell_file), config_path=str(cell_file), object="bunny",
                                 out=folder, max_time_s=120.0), on_progress=reflex_after_the_first_capture)
        result = json.loads((folder / "result.json").read_text())
        assert injected_at, "the scan ended before its first capture"
        assert result["status"] == "stopped"
        termination = result["termination"]
        assert "arm fault: reflex: cartesian_reflex" in termination, termination
        # nothing recorded before the fault is lost: every capture's frame, the cloud, the path, the log
        frames = sorted((folder / "frames").glob("*.npz"))
        assert result["n_captures"] == len(frames) >= injected_at[0]
        assert result["n_cloud_points"] > 0 and (folder / "cloud.ply").stat().st_size > 0
        assert len((folder / "trajectory.csv").read_text().splitlines()) > 2
        assert "reflex" in (folder / "log.txt").read_text()
        # the operator's way back: status shows the fault, recover clears it
        runner = CliRunner()
        status = runner.invoke(arm_app, ["status", "--config", str(cell_file)])
        assert status.exit_code == 0 and "faults: reflex: cartesian_reflex" in status.output, status.output
        recovered = runner.invoke(arm_app, ["recover", "--config", str(cell_file)])
        assert recovered.exit_code == 0 and "faults: none" in recovered.output, recovered.output
    finally:
        sim.kill()
