"""``cell arm status`` and ``cell arm jog`` against the RTDE controller peer, with the UR5e hardware
template (config/ur5e-vl53l8cx.yaml) pointed at the peer."""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from cell.cli.arm import AXES, arm_app
from drivers.arm.hardware import ur_pose_to_T
from tests.conftest import CONFIG_DIR
from tests.rtde_peer import REPO, ControllerPeer

TEMPLATE = CONFIG_DIR / "ur5e-vl53l8cx.yaml"
POSE_LINE = re.compile(r"tcp pose: x ([-+.\d]+) m y ([-+.\d]+) m z ([-+.\d]+) m")


def peer_cell_file(template: Path, host: str, folder: Path) -> Path:
    """``template`` with the arm pointed at a peer on ``host``, with timing a Python peer and a control loop
    on a loaded test machine keep up with: RTDE at 125 Hz, a 50 Hz control loop, the RTDE watchdog at
    1 Hz (as in ``test_real_mode``; at 2 Hz the peer's control script once stopped a jog when the three
    processes, test, ur-rtde child and peer, stalled on two loaded cores), and a late-loop watchdog that
    tolerates scheduling hiccups (5 periods, 5 in a row). The limits, workspace and planes are the
    template's."""
    data = yaml.safe_load(template.read_text())
    data["arm"].update(host=host, rtde_frequency_hz=125.0, connect_timeout_s=2.0, watchdog_min_hz=1.0)
    data["scan"]["control_rate_hz"] = 50.0
    data["safety"]["watchdog"].update(deadline_factor=5.0, max_missed_deadlines=5)
    path = folder / f"peer-{template.name}"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture
def peer() -> Iterator[ControllerPeer]:
    home = yaml.safe_load(TEMPLATE.read_text())["arm"]["home_joints_rad"]
    p = ControllerPeer(q=home)
    yield p
    p.stop()


@pytest.fixture
def cell_file(peer: ControllerPeer, tmp_path: Path) -> Path:
    return peer_cell_file(TEMPLATE, peer.host, tmp_path)


def tcp_position(output: str) -> np.ndarray:
    match = POSE_LINE.search(output)
    assert match is not None, output
    return np.array([float(v) for v in match.groups()])


def cell_tcp_position(peer: ControllerPeer, cell_file: Path) -> np.ndarray:
    """Where the cell's TCP (its file's ``arm.tcp_offset``) is at the peer's joints [m, base frame], whatever
    TCP the controller has active (another program's, none)."""
    offset = yaml.safe_load(cell_file.read_text())["arm"]["tcp_offset"]
    return (ur_pose_to_T(peer.state()["flange_pose"]) @ ur_pose_to_T(offset))[:3, 3]


def run_ok(command: str, cell_file: Path) -> str:
    """The output of ``cell arm <command> --config <cell_file>``, which must succeed."""
    result = CliRunner().invoke(arm_app, [command, "--config", str(cell_file)])
    assert result.exit_code == 0, result.output
    return result.output


def _status_then_recover(peer: ControllerPeer, cell_file: Path, faulted: tuple[str, ...],
                         recovered: tuple[str, ...]) -> None:
    """``cell arm status`` shows the ``faulted`` words with the pose of the cell's TCP (not the controller's
    active one: none here), then ``cell arm recover`` the ``recovered`` ones."""
    output = run_ok("status", cell_file)
    assert all(words in output for words in faulted), output
    assert np.allclose(tcp_position(output), cell_tcp_position(peer, cell_file), atol=1e-4)
    output = run_ok("recover", cell_file)
    assert all(words in output for words in recovered), output


def test_status_prints_the_tcp_pose_then_a_protective_stop_until_recovered(peer: ControllerPeer,
                                                                           cell_file: Path) -> None:
    output = run_ok("status", cell_file)
    assert "arm ur5e: connected" in output and "faults: none" in output
    assert np.allclose(tcp_position(output), cell_tcp_position(peer, cell_file), atol=1e-4)

    peer.protective_stop()
    _status_then_recover(peer, cell_file, ("protective stop", "safety mode PROTECTIVE_STOP"),
                         ("faults: none", "safety mode NORMAL"))
    assert any("unlocked" in e for e in peer.state()["events"])


def test_status_and_recover_after_a_released_emergency_stop(peer: ControllerPeer, cell_file: Path) -> None:
    """After an emergency stop is released the robot is powered off: status says so (not that the script
    port failed) and recover powers it on and releases the brakes."""
    peer.emergency_stop()
    peer.release_emergency_stop()
    _status_then_recover(peer, cell_file, ("robot mode POWER_OFF", "faults: power off"),
                         ("faults: none", "robot mode RUNNING"))
    assert peer.state()["robot_mode"] == "RUNNING"
    assert not any("program refused" in e for e in peer.state()["events"])


def test_status_reads_the_arm_beside_a_program_that_drives_it(peer: ControllerPeer, cell_file: Path) -> None:
    """An operator looks at the arm while a job drives it: no second control script, no refusal; the pose
    is the cell's TCP, not the TCP the program sent (0.05 m along the flange's z, the cell's is at y 0.04 m,
    z 0.03 m)."""
    owner = subprocess.Popen([sys.executable, "-m", "tests.test_ur5e_driver", peer.host], cwd=REPO,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert owner.stdout is not None
        owner.stdout.readline()  # connected, its control script running
        started = [e for e in peer.state()["events"] if "program started" in e]
        output = run_ok("status", cell_file)
        assert "faults: none" in output
        assert np.allclose(tcp_position(output), cell_tcp_position(peer, cell_file), atol=1e-4)
        assert [e for e in peer.state()["events"] if "program started" in e] == started
        assert peer.state()["program_running"]
    finally:
        owner.kill()
        owner.wait()
        if owner.stdout is not None:
            owner.stdout.close()


def flange_motion(before: list[float], after: list[float]) -> np.ndarray:
    """The flange's motion between two UR poses: translation [m] and rotation vector [rad], base frame."""
    R0, R1 = (Rotation.from_rotvec(p[3:]) for p in (before, after))
    return np.concatenate([np.subtract(after[:3], before[:3]), (R1 * R0.inv()).as_rotvec()])


@pytest.mark.parametrize(("axis", "distance"), [("z", 0.02), ("y", -0.01), ("rz", 0.1)])
def test_jog_moves_the_flange_by_the_distance(peer: ControllerPeer, cell_file: Path, axis: str,
                                              distance: float) -> None:
    # the flange, not the TCP: the TCP offset changes when the driver connects and sends it
    before = peer.state()["flange_pose"]
    result = CliRunner().invoke(arm_app, ["jog", "--config", str(cell_file), "--axis", axis,
                                          "--distance", str(distance)])
    assert result.exit_code == 0, result.output
    moved = flange_motion(before, peer.state()["flange_pose"])
    expected = np.zeros(6)
    expected[AXES[axis]] = distance
    assert np.allclose(moved, expected, atol=1e-3), moved
    # streamed with speedL through the guard, ended with speedStop, the watchdog disarmed at rest
    assert peer.records("speedL") and peer.records("speedStop")
    assert peer.state()["watchdog_hz"] == 0.0 and peer.state()["motion"] == "idle"
    assert np.allclose(tcp_position(result.output), cell_tcp_position(peer, cell_file), atol=1e-4)


def test_jog_refuses_a_protectively_stopped_arm(peer: ControllerPeer, cell_file: Path) -> None:
    peer.protective_stop()
    result = CliRunner().invoke(arm_app, ["jog", "--config", str(cell_file), "--axis", "z",
                                          "--distance", "0.01"])
    assert result.exit_code == 1
    assert "protective stop" in result.output
    assert not peer.records("speedL")


def test_jog_refuses_a_long_move_before_connecting(cell_file: Path) -> None:
    result = CliRunner().invoke(arm_app, ["jog", "--config", str(cell_file), "--axis", "x",
                                          "--distance", "0.2"])
    assert result.exit_code == 1 and "at most 0.05" in result.output
