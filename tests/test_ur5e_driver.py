"""The UR5e backend against the RTDE controller peer: what the driver sends (clamped twists, TCP, payload,
watchdog, digital outputs) and what it does on protective stops, emergency stops, dropped connections and
a crash of the process that holds the ur-rtde clients."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cell.config import load_config
from cell.jobs.runner import ScanRequest, prepare_scan
from drivers.arm.base import ArmMode, JointTrajectory
from drivers.arm.hardware import ur_pose_to_T
from drivers.arm.ur5e import REPLY_TIMEOUT_S, SILENT_PERIODS, UR5eArm
from drivers.errors import DriverError, RobotFault
from drivers.robots import get_robot_model
from tests.arm_backends import STREAMING_WATCHDOG_HZ, Backend, ur5e_backend, ur5e_config
from tests.conftest import CONFIG_DIR
from tests.rtde_peer import REPO, ControllerPeer
from tests.rtde_peer.broken import BrokenController
from tests.rtde_peer.controller import UNLOCK_AFTER_S


@pytest.fixture
def peer() -> Iterator[ControllerPeer]:
    p = ControllerPeer()
    yield p
    p.stop()


@pytest.fixture
def ur(peer: ControllerPeer) -> Iterator[Backend]:
    with ur5e_backend(peer) as b:
        yield b


@pytest.fixture
def streaming_ur(peer: ControllerPeer) -> Iterator[Backend]:
    """``ur`` with the RTDE watchdog for tests that stream for a while (tests/arm_backends.py)."""
    with ur5e_backend(peer, watchdog_min_hz=STREAMING_WATCHDOG_HZ) as b:
        yield b


def test_connect_sends_tcp_and_payload_from_the_config(peer: ControllerPeer, ur: Backend) -> None:
    st = peer.state()
    assert st["program_running"] and st["scripts_uploaded"] == 1
    assert np.allclose(st["tcp_offset"], [0, 0, 0.05, 0, 0, 0]) and st["payload_kg"] == pytest.approx(0.3)
    # the driver speaks the flange: the reported flange is the TCP minus the offset
    flange = ur.arm.state().T_base_flange
    assert np.allclose(flange[:3, 3], peer.state()["flange_pose"][:3], atol=1e-6)


def test_the_flange_is_reported_whatever_tcp_the_controller_has(peer: ControllerPeer) -> None:
    """``cell arm status`` connects for reading only (no control script, no setTcp) and took the flange as
    the controller's TCP pose less the config's TCP, whatever TCP the controller had: the same joints gave
    poses 40 / 30 mm apart before and after a jog had set the cell's TCP. A program with another TCP drives
    the arm (then has ended, its TCP left on the controller): the reader reports the flange all the same,
    and so does the program's own driver."""
    other = [0.1, -0.05, 0.2, 0.0, 0.3, 0.0]
    reader = UR5eArm(ur5e_config(peer.host), get_robot_model("ur5e"), read_only=True)
    with ur5e_backend(peer, tcp_offset=other) as owner:
        assert np.allclose(peer.state()["tcp_offset"], other)
        flange = ur_pose_to_T(peer.state()["flange_pose"])
        assert np.allclose(owner.arm.state().T_base_flange, flange, atol=1e-6)
        reader.connect()
        try:
            assert np.allclose(reader.state().T_base_flange, flange, atol=1e-6)
        finally:
            reader.disconnect()
    assert np.allclose(peer.state()["tcp_offset"], other)
    reader.connect()
    try:
        assert np.allclose(reader.state().T_base_flange, flange, atol=1e-6)
    finally:
        reader.disconnect()


def test_twists_are_clamped_and_sent_with_speedl_under_a_watchdog(peer: ControllerPeer, ur: Backend) -> None:
    ur.arm.command_twist(np.array([0.0, 0.0, 0.5, 0.0, 0.0, 0.0]), ur.token)  # 0.5 m/s > the 0.1 ceiling
    # speedL streams: ur-rtde returns once it is sent, the peer takes it from the socket a little later
    peer.wait_for(lambda s: s["counts"].get("speedL", 0) > 0, what="speedL")
    speedl = peer.records("speedL")[-1]["doubles"]
    assert np.linalg.norm(speedl[:3]) == pytest.approx(0.1) and speedl[2] > 0
    assert speedl[6] == pytest.approx(0.5)  # acceleration from the config
    watchdog = peer.records("setWatchdog")
    assert watchdog and watchdog[0]["doubles"][0] == pytest.approx(5.0)
    ur.arm.stop()
    assert peer.records("speedStop")[-1]["doubles"][0] == pytest.approx(1.0)
    assert peer.records("setWatchdog")[-1]["doubles"][0] == 0.0  # disarmed at rest


def test_the_watchdog_stops_the_arm_when_the_loop_stops_calling(peer: ControllerPeer, ur: Backend) -> None:
    ur.arm.command_twist(np.array([0.0, 0.0, 0.02, 0.0, 0.0, 0.0]), ur.token)
    peer.wait_for(lambda s: not s["program_running"], what="the watchdog ending the script")
    assert any("watchdog" in e for e in peer.state()["events"])
    # the client learns it from the next data package
    ur.wait_until(lambda: "control script not running" in ur.arm.state().faults)
    with pytest.raises(RobotFault, match="control script not running") as refused:
        ur.arm.command_twist(np.zeros(6), ur.token)
    assert refused.value.fault == "control script not running"
    ur.arm.recover()
    assert peer.state()["scripts_uploaded"] == 2 and ur.arm.state().faults == ()


def test_protective_stop_is_a_fault_until_the_operator_recovers(peer: ControllerPeer, ur: Backend) -> None:
    peer.protective_stop()
    ur.wait_until(lambda: "protective stop" in ur.arm.state().faults)
    assert _ur(ur).controller_modes()["safety mode"] == "PROTECTIVE_STOP"
    with pytest.raises(RobotFault) as refused:
        ur.arm.command_twist(np.zeros(6), ur.token)
    assert refused.value.fault == "protective stop"
    ur.arm.recover()
    assert peer.state()["safety_mode"] == "NORMAL" and peer.state()["program_running"]
    assert np.allclose(peer.state()["tcp_offset"], [0, 0, 0.05, 0, 0, 0])  # re-sent after the restart
    # the controller refuses an unlock until 5 s after the stop: recover, asked at once, waited for it
    # rather than taking the refusal for a lost connection
    times = {text: float(t) for t, text in (e.split(" ", 1) for e in peer.state()["events"])}
    assert times["protective stop unlocked (dashboard)"] - times["protective stop"] >= UNLOCK_AFTER_S


def test_recover_unlocks_a_protective_stop_the_receive_stream_does_not_show_yet(
        peer: ControllerPeer, ur: Backend, monkeypatch: pytest.MonkeyPatch) -> None:
    """The receive and control interfaces read two RTDE streams, so the script's end can reach the driver
    before the protective stop that ended it (seen on a loaded machine): recover asks the dashboard."""
    arm = _ur(ur)
    peer.protective_stop()
    ur.wait_until(lambda: "protective stop" in arm.state().faults)
    read = arm._snapshot
    stale = [True]  # recover's first read: from before the stop

    def snapshot(kick: bool = False) -> dict[str, Any]:
        snap = read(kick)
        if stale:
            stale.clear()
            return {**snap, "protective_stopped": False, "safety_mode": 1}
        return snap

    monkeypatch.setattr(arm, "_snapshot", snapshot)
    arm.recover()
    assert not stale
    assert peer.state()["safety_mode"] == "NORMAL" and peer.state()["program_running"]


def test_recover_waits_for_the_controller_to_release_the_stop_before_restarting_the_script(
        peer: ControllerPeer, ur: Backend, monkeypatch: pytest.MonkeyPatch) -> None:
    """The dashboard answers an unlock before the controller has released the stop, and a script sent
    before the release does not run: recover waits for the release as the dashboard reports it, not as
    a receive stream that lags behind it (here, one that never showed the stop)."""
    arm = _ur(ur)
    peer.protective_stop()
    ur.wait_until(lambda: not arm._snapshot()["program_running"])
    read = arm._snapshot

    def snapshot(kick: bool = False) -> dict[str, Any]:
        return {**read(kick), "protective_stopped": False, "safety_mode": 1}

    monkeypatch.setattr(arm, "_snapshot", snapshot)
    arm.recover()
    state = peer.state()
    assert state["safety_mode"] == "NORMAL" and state["program_running"]
    assert not any("program refused" in e for e in state["events"])


def test_emergency_stop_cannot_be_cleared_from_software(peer: ControllerPeer, ur: Backend) -> None:
    peer.emergency_stop()
    ur.wait_until(lambda: "emergency stop" in ur.arm.state().faults)
    with pytest.raises(RobotFault, match="release it"):
        ur.arm.recover()
    peer.release_emergency_stop()
    ur.wait_until(lambda: "emergency stop" not in ur.arm.state().faults)
    assert "power off" in ur.arm.state().faults
    ur.arm.recover()  # power on, brake release, script re-upload
    assert ur.arm.state().faults == () and peer.state()["robot_mode"] == "RUNNING"


def test_an_arm_powered_off_after_a_released_emergency_stop_connects_and_recover_powers_it_on(
        peer: ControllerPeer) -> None:
    """A released emergency stop leaves the robot powered off (robot mode POWER_OFF, safety NORMAL), as at
    boot: connecting reads the state and does not upload a control script the controller would not run,
    and recover powers the arm on, releases the brakes and starts the script."""
    peer.emergency_stop()
    peer.release_emergency_stop()
    with ur5e_backend(peer) as ur:
        arm = _ur(ur)
        assert "power off" in arm.state().faults and arm.controller_modes()["robot mode"] == "POWER_OFF"
        state = peer.state()
        assert state["scripts_uploaded"] == 0 and not any("program refused" in e for e in state["events"])
        arm.recover()
        assert arm.state().faults == () and peer.state()["robot_mode"] == "RUNNING"
        assert peer.state()["program_running"] and peer.state()["scripts_uploaded"] == 1
        assert np.allclose(peer.state()["tcp_offset"], [0, 0, 0.05, 0, 0, 0])
        _twist_moves_the_flange_up(peer, ur)


def test_digital_inputs(peer: ControllerPeer, ur: Backend) -> None:
    """The arm driver reads the inputs; a line's handshake sets the outputs through a link of its own
    (``drivers.arm.ur_io``, tested with the line)."""
    arm = ur.arm
    assert isinstance(arm, UR5eArm)
    peer.set_digital_input(4, True)
    ur.wait_until(lambda: arm.digital_inputs()[4])
    assert arm.controller_modes()["digital inputs"] == "00001000"


def test_a_trajectory_is_streamed_with_servoj(peer: ControllerPeer, ur: Backend) -> None:
    from cell.control.trajectory import joint_trajectory

    q0 = ur.arm.state().q
    goal = q0 + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.1])
    traj = joint_trajectory(get_robot_model("ur5e"), q0, goal, dt=0.008, velocity_scale=0.3,
                            acceleration_scale=0.3, jerk_scale=0.3)
    ur.arm.execute_trajectory(traj, ur.token)
    ur.wait_until(lambda: ur.arm.state().mode is ArmMode.IDLE)
    servoj = peer.records("servoJ")
    assert len(servoj) > 10 and np.allclose(servoj[-1]["doubles"][:6], goal, atol=1e-9)
    assert peer.records("servoStop")


def test_a_trajectory_end_not_reached_in_time_is_a_fault(peer: ControllerPeer) -> None:
    """The servo's lag decays exponentially, so no arm gets within 1e-9 rad of the end in 50 ms: the
    arm is stopped and reports the fault, and the operator's recover clears it."""
    from cell.control.trajectory import joint_trajectory

    with ur5e_backend(peer, settle_tolerance_rad=1e-9, settle_timeout_s=0.05) as ur:
        q0 = ur.arm.state().q
        traj = joint_trajectory(get_robot_model("ur5e"), q0, q0 + np.array([0.0, 0, 0, 0, 0, 0.1]),
                                dt=0.008, velocity_scale=0.3, acceleration_scale=0.3, jerk_scale=0.3)
        ur.arm.execute_trajectory(traj, ur.token)
        ur.wait_until(lambda: bool(ur.arm.state().faults))
        assert ur.arm.state().faults == ("trajectory end not reached",)
        assert ur.arm.state().mode is ArmMode.FAULT and peer.records("servoStop")
        with pytest.raises(RobotFault, match="trajectory end not reached"):
            ur.arm.command_twist(np.zeros(6), ur.token)
        ur.arm.recover()
        assert ur.arm.state().faults == () and ur.arm.state().mode is ArmMode.IDLE


def test_refuses_a_controller_in_local_control() -> None:
    peer = ControllerPeer(remote_control=False)
    try:
        arm = UR5eArm(ur5e_config(peer.host), get_robot_model("ur5e"))
        with pytest.raises(DriverError, match="Remote Control"):
            arm.connect()
        assert not arm.is_connected
    finally:
        peer.stop()


def test_an_unreachable_controller_fails_fast_with_its_address() -> None:
    arm = UR5eArm(ur5e_config("127.0.0.254", connect_timeout_s=0.5), get_robot_model("ur5e"))
    with pytest.raises(DriverError, match=r"127\.0\.0\.254:30004"):
        arm.connect()


@pytest.mark.parametrize("behaviour, dashboard_ok, port, tried, what", [
    ("close", False, "dashboard port {host}:29999", "the dashboard server's handshake",
     r"the controller closed the connection \(ur-rtde: End of file\)"),
    ("hang", False, "dashboard port {host}:29999", "the dashboard server's handshake",
     r"no answer within 0\.5 s \(connect_timeout_s\) \(ur-rtde: Operation canceled\)"),
    # the RTDE client reads as the socket closes: an end of file or a reset, by the timing
    ("close", True, "RTDE port {host}:30004", "the RTDE protocol handshake",
     r"the controller (closed|reset) the connection "
     r"\(ur-rtde: read: (End of file|Connection reset by peer)\)"),
])
def test_a_handshake_that_fails_says_what_was_tried_and_what_to_check(behaviour, dashboard_ok, port, tried,
                                                                     what) -> None:
    controller = BrokenController(behaviour, dashboard_ok=dashboard_ok)
    try:
        arm = UR5eArm(ur5e_config(controller.host, connect_timeout_s=0.5), get_robot_model("ur5e"))
        with pytest.raises(DriverError) as failed:
            arm.connect()
        text = str(failed.value)
        assert f"the controller's {port.format(host=controller.host)} accepted the connection, but {tried} " \
               f"failed: " in text
        assert re.search(what, text)
        assert f"check that {controller.host} is the UR controller" in text and "Settings > Security" in text
        assert not arm.is_connected
    finally:
        controller.stop()


def _running(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie nobody has reaped yet does not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _ur(backend: Backend) -> UR5eArm:
    assert isinstance(backend.arm, UR5eArm)
    return backend.arm


def _until_lost(ur: Backend, action: Callable[[], None]) -> RobotFault:
    """Repeat ``action`` every 20 ms until it raises the "disconnect" fault (another fault first, e.g. the
    control script ended by the drop, is not it yet); a bound on waiting: 20 s."""
    for _ in range(1000):
        try:
            action()
        except RobotFault as exc:
            if exc.fault == "disconnect":
                return exc
        ur.advance(0.02)
    raise AssertionError("the lost connection never surfaced")


def _slow_trajectory(arm: UR5eArm) -> JointTrajectory:
    """A turn of the last joint by 1 rad from where the arm is, slow enough to take over 5 s: it is still
    being streamed when the tests that use it are done waiting (5 s at the most)."""
    from cell.control.trajectory import joint_trajectory

    q0 = arm.state().q
    traj = joint_trajectory(get_robot_model("ur5e"), q0, q0 + np.array([0.0, 0, 0, 0, 0, 1.0]), dt=0.008,
                            velocity_scale=0.05, acceleration_scale=0.3, jerk_scale=0.3)
    assert traj.duration > 5.0
    return traj


def _twist_moves_the_flange_up(peer: ControllerPeer, ur: Backend) -> None:
    """A twist streamed at 50 Hz for 0.5 s moves the peer's flange up."""
    z0 = peer.state()["flange_pose"][2]
    for _ in range(25):
        ur.arm.command_twist(np.array([0.0, 0.0, 0.02, 0.0, 0.0, 0.0]), ur.token)
        ur.advance(0.02)
    ur.arm.stop()
    assert peer.state()["flange_pose"][2] > z0


def test_a_dropped_connection_ends_the_client_process_until_the_operator_reconnects(
        peer: ControllerPeer, streaming_ur: Backend) -> None:
    ur = streaming_ur
    arm = _ur(ur)
    first = arm.client_pid
    assert first is not None and _running(first)
    v = np.array([0.0, 0.0, 0.02, 0.0, 0.0, 0.0])
    arm.command_twist(v, ur.token)
    peer.drop_clients()
    lost = _until_lost(ur, lambda: arm.command_twist(v, ur.token))  # the control loop keeps commanding
    assert "controller closed the connection" in str(lost)
    assert arm.client_pid is None and not _running(first)
    q_after_drop = peer.state()["q"]
    # latched: state and motion raise, stop sends nothing, until the operator recovers
    with pytest.raises(RobotFault, match="lost the connection"):
        arm.state()
    with pytest.raises(RobotFault, match="lost the connection"):
        arm.command_twist(v, ur.token)
    arm.stop()
    dropped_at = peer.state()["dropped_at"]
    assert [r for r in peer.records() if r["t"] > dropped_at] == []  # nothing reached the controller
    assert np.allclose(peer.state()["q"], q_after_drop) and peer.state()["motion"] == "idle"

    arm.recover()  # the operator's action: a fresh process connects again
    second = arm.client_pid
    assert second is not None and second != first
    assert arm.state().faults == () and arm.state().mode is ArmMode.IDLE
    assert np.allclose(peer.state()["tcp_offset"], [0, 0, 0.05, 0, 0, 0])  # the tool is sent again
    _twist_moves_the_flange_up(peer, ur)


def test_recover_after_a_connection_lost_during_a_trajectory(peer: ControllerPeer,
                                                            streaming_ur: Backend) -> None:
    """The servoJ stream ends with the lost connection's fault; recover's new connection is not refused
    for it (it once refused to send the TCP: "setTcp refused: disconnect")."""
    ur = streaming_ur
    arm = _ur(ur)
    arm.execute_trajectory(_slow_trajectory(arm), ur.token)
    peer.wait_for(lambda s: s["counts"].get("servoJ", 0) > 10, what="servoJ")
    peer.drop_clients()
    ur.wait_until(lambda: arm.client_pid is None)  # the child ends itself at the drop
    # which comes first is a race inside ur-rtde: the child's monitor seeing the drop (it exits, "the
    # controller closed the connection"), or the servoJ stream's failed send reconnecting in its own
    # thread, which on a loaded machine crashes the child first ("killed by signal 11 (Segmentation fault)")
    either = (r"lost the connection to the controller: (the controller closed the connection|the ur-rtde "
              r"process was killed by signal 11 \(Segmentation fault\))")
    with pytest.raises(RobotFault, match=either) as lost:
        arm.state()
    assert lost.value.fault == "disconnect"
    arm.recover()
    assert arm.state().faults == () and arm.state().mode is ArmMode.IDLE
    _twist_moves_the_flange_up(peer, ur)


def test_a_crashed_client_process_is_a_fault_and_the_watchdog_stops_the_arm(
        peer: ControllerPeer, streaming_ur: Backend) -> None:
    ur = streaming_ur
    arm = _ur(ur)
    pid = arm.client_pid
    assert pid is not None
    arm.command_twist(np.array([0.0, 0.0, 0.02, 0.0, 0.0, 0.0]), ur.token)
    os.kill(pid, signal.SIGKILL)
    with pytest.raises(RobotFault, match="killed by signal 9") as lost:
        arm.state()
    assert lost.value.fault == "disconnect"
    # nobody renews the twist: the RTDE watchdog armed for the motion ends the script and halts the arm
    peer.wait_for(lambda s: not s["program_running"], what="the watchdog ending the script")
    assert any("watchdog" in e for e in peer.state()["events"])
    arm.recover()
    assert arm.state().faults == ()
    _twist_moves_the_flange_up(peer, ur)


def test_a_hung_client_process_is_killed_and_a_fault(peer: ControllerPeer, streaming_ur: Backend) -> None:
    """The child stops answering (SIGSTOP): after the reply timeout the driver kills it and faults."""
    arm = _ur(streaming_ur)
    pid = arm.client_pid
    assert pid is not None
    os.kill(pid, signal.SIGSTOP)
    with pytest.raises(RobotFault, match=f"did not answer snapshot within {REPLY_TIMEOUT_S:g} s") as lost:
        arm.state()
    assert lost.value.fault == "disconnect" and arm.client_pid is None and not _running(pid)
    arm.recover()
    assert arm.state().faults == ()


def _silence_fault(ur: Backend, peer: ControllerPeer) -> RobotFault:
    """The fault the arm reports after the controller went silent, once the resumed peer has read what
    the ur-rtde process sent before it was ended (its connections closed)."""
    peer.wait_for(lambda s: s["connections"] == 1, what="the ur-rtde process's connections closed")
    with pytest.raises(RobotFault, match="no data from the controller for") as lost:
        ur.arm.state()
    assert lost.value.fault == "disconnect"
    silent_s = float(re.search(r"no data from the controller for ([\d.]+) s", str(lost.value)).group(1))
    # a bound on the detection: SILENT_PERIODS periods at the test config's 125 Hz are 0.2 s
    assert SILENT_PERIODS / ur5e_config(peer.host).rtde_frequency_hz <= silent_s < 1.0
    return lost.value


def test_a_controller_that_goes_silent_is_a_fault_and_receives_no_command_after_it(
        peer: ControllerPeer, streaming_ur: Backend) -> None:
    """The controller stops with its connections open: ur-rtde reports the last state it received, and
    every command waits in the socket for a controller that reads none. A control loop's next reads find
    the controller's timestamp stuck: the driver latches a disconnect naming the silence and ends the
    ur-rtde process, so the resumed controller receives exactly the commands sent before the fault."""
    ur = streaming_ur
    arm = _ur(ur)
    v = np.array([0.0, 0.0, 0.02, 0.0, 0.0, 0.0])
    arm.command_twist(v, ur.token)
    peer.wait_for(lambda s: s["counts"].get("speedL", 0) == 1, what="the first speedL")
    sent = 1
    with peer.frozen():
        with pytest.raises(RobotFault):
            for _ in range(500):  # the control loop at 50 Hz; a bound on waiting: 10 s
                arm.state()
                arm.command_twist(v, ur.token)
                sent += 1
                ur.advance(0.02)
        assert arm.client_pid is None
    _silence_fault(ur, peer)
    assert peer.state()["counts"]["speedL"] == sent
    arm.recover()  # the operator's action: a fresh process connects again
    assert arm.state().faults == ()
    _twist_moves_the_flange_up(peer, ur)


def test_a_trajectory_stream_stops_when_the_controller_goes_silent(peer: ControllerPeer,
                                                                  streaming_ur: Backend) -> None:
    """The servoJ stream reads the state before each sample: it ends with the fault, not seconds later
    when ur-rtde gives up on the silent controller (about 2.5 s: some 300 samples at 125 Hz)."""
    ur = streaming_ur
    arm = _ur(ur)
    arm.execute_trajectory(_slow_trajectory(arm), ur.token)
    before = peer.wait_for(lambda s: s["counts"].get("servoJ", 0) > 10, what="servoJ")["counts"]["servoJ"]
    with peer.frozen():
        ur.wait_until(lambda: arm.client_pid is None, timeout_s=5.0)  # without reading the state
    _silence_fault(ur, peer)
    # what was sent while the controller was silent: about 0.2 s of samples at 125 Hz, and any sent
    # between the count above and the stop
    assert peer.state()["counts"]["servoJ"] - before < 100
    arm.recover()
    assert arm.state().faults == ()


def test_the_client_process_ends_with_the_program_that_owns_the_driver(peer: ControllerPeer) -> None:
    """The driver's process is killed outright (no clean-up runs): its client process ends by itself."""
    owner = subprocess.Popen([sys.executable, "-m", "tests.test_ur5e_driver", peer.host], cwd=REPO,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert owner.stdout is not None
        pid = int(owner.stdout.readline())
        assert _running(pid)
    finally:
        owner.kill()
        owner.wait()
        if owner.stdout is not None:
            owner.stdout.close()
    deadline = time.monotonic() + 20.0  # a bound on waiting
    while _running(pid):
        assert time.monotonic() < deadline, f"client process {pid} outlived its driver"
        time.sleep(0.05)


def test_a_second_program_of_this_machine_is_refused_the_arm_until_the_first_has_gone(
        peer: ControllerPeer, tmp_path: Path) -> None:
    """A second control script would end the first program's (a scan started beside the service's job);
    the claim goes with its holder however that ends."""
    owner = subprocess.Popen([sys.executable, "-m", "tests.test_ur5e_driver", peer.host], cwd=REPO,
                             stdout=subprocess.PIPE, text=True)
    second = UR5eArm(ur5e_config(peer.host), get_robot_model("ur5e"))
    try:
        assert owner.stdout is not None
        owner.stdout.readline()  # connected
        started = [e for e in peer.state()["events"] if "program started" in e]
        refusal = rf"driven by another program of this machine \(pid {owner.pid}:"
        with pytest.raises(DriverError, match=refusal):
            second.connect()
        assert [e for e in peer.state()["events"] if "program started" in e] == started  # no second script
        dry_run = load_config(CONFIG_DIR / "dryrun-ur5e-peer.yaml")
        dry_run = dry_run.model_copy(update={"arm": dry_run.arm.model_copy(update={"host": peer.host})})
        with pytest.raises(DriverError, match=refusal):  # a scan refuses before it makes its folder
            prepare_scan(ScanRequest(config=dry_run, config_path="dry-run", object="horizontal_box",
                                     out=tmp_path / "job"))
        assert not (tmp_path / "job").exists()
    finally:
        owner.kill()
        owner.wait()
        if owner.stdout is not None:
            owner.stdout.close()
    second.connect()  # the kernel released the claim of the killed program
    second.disconnect()


def _own_a_connected_arm(host: str) -> None:
    """The driver's process in the test above: connects, prints the client process id, waits to be
    killed."""
    arm = UR5eArm(ur5e_config(host), get_robot_model("ur5e"))
    arm.connect()
    print(arm.client_pid, flush=True)
    time.sleep(600)


if __name__ == "__main__":
    _own_a_connected_arm(sys.argv[1])
