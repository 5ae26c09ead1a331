"""UR5e backend through ur-rtde (pinned: ``ur-rtde==1.6.5``, the ``ur5e`` extra).

Connections: RTDE receive (state), RTDE control (the control script ur-rtde uploads to port 30003 and
drives through its register handshake) and the dashboard server (remote control check, unlocking a
protective stop, power and brakes); a packing line's digital outputs have a link of their own
(:mod:`drivers.arm.ur_io`). The driver's live in a child process that it owns
(:mod:`drivers.arm.ur_rtde_process`, :mod:`drivers.arm.ur_rtde_child`): ur-rtde 1.6.5 misbehaves after
a dropped connection (its control interface reconnects by itself and then runs two receive threads on
one socket, which crashes the process; its IO interface's destructor aborts the process), and in a
child that is a fault, not the end of the program. ``connect`` first opens each controller port with
``connect_timeout_s`` so an unreachable controller fails fast with its address, and asks the dashboard
whether the pendant is in remote control.
It starts the control script only on a robot that runs normally: a stopped or powered-off one (robot mode
POWER_OFF after an emergency stop is released, or at boot) is connected for reading, shows its fault, and
``recover`` powers it on and starts the script.
A port that accepts the connection but then closes it or never answers (another device at that address,
a controller still booting, a service disabled in PolyScope) fails with the port, what happened and what
to check, not ur-rtde's bare "Operation canceled" or "End of file".

Frames: ur-rtde reports and commands the TCP (``setTcp`` from the config); this backend converts to and
from the flange, which is what the :class:`~drivers.arm.base.Arm` interface speaks. The controller's TCP
is the config's only while this driver's control script runs with the tool it sent: connected for
reading (``read_only``, ``cell arm status``), or with the script stopped, the active TCP is another
program's or the installation's, and RTDE (ur-rtde 1.6.5) does not report it. The flange is then the
robot model's forward kinematics of the measured joints (nominal kinematics: it differs from the
controller's calibrated pose by the robot's calibration, about a millimetre), so that the same joints give
the same pose whatever TCP the controller has.

Motion:
- twists: clamped to the config's ceilings, turned into a TCP twist and sent with ``speedL`` (each call
  renews it); the RTDE watchdog (``watchdog_min_hz``) is armed for as long as the arm moves, and every
  command or ``state()`` call refreshes it, so a control loop that stops calling stops the arm. A control
  tick (``state()`` then ``command_twist``) is two round trips to the child: ``command_twist`` checks
  faults and takes the TCP pose from the state read less than one RTDE period (``rtde_frequency_hz``)
  ago when there is one, since the receive interface has nothing newer before its next data package;
  ``benchmarks/ur_rtde_tick.py`` measures the tick.
- trajectories: a thread streams the joint samples with ``servoJ`` at ``servo_rate_hz``, interpolated at
  wall-clock time. The trajectory is in joint space and the guard checked those joints, so they go out
  as joints: ``servoL`` would let the controller's IK pick a configuration nobody checked. The last
  sample is held until the joints are within ``settle_tolerance_rad`` of it, and only then comes
  ``servoStop``: servoJ's lookahead leaves the arm behind its setpoint, and a stop in the same controller
  cycle as the last servoJ would discard that servoJ. Joints not there after ``settle_timeout_s`` are a
  fault ("trajectory end not reached").
- ``stop``: ``speedStop`` after velocity, ``servoStop`` after a trajectory, ``stopL`` otherwise, all with
  ``stop_deceleration_mps2``; then the watchdog is disarmed (frequency 0).

Faults, from the controller's safety status and the script's state: "protective stop", "emergency stop",
"safeguard stop", "safety fault", "power off", "control script not running", "disconnect". A command
while faulted, a command that returns False, or a lost connection raises ``RobotFault``.

A lost connection ("disconnect") is the controller closing it, the controller going silent with the
connection open (its RTDE timestamp not advancing for ``SILENT_PERIODS`` RTDE periods: stopped, hung, or a
network path that no longer delivers), the child process ending for any other reason (a crash), an error
from ur-rtde on a command, or the child not answering within ``REPLY_TIMEOUT_S``. The child is then gone:
it ends itself as soon as it sees the controller's drop (before ur-rtde's own reconnection could send
anything), and the driver kills it in every other case, so nothing in this process can resume motion
nor send to a silent controller commands that it would run at once on resuming. The fault is latched:
``state()`` and every command raise it until the operator recovers. The arm is stopped all the same: the
RTDE watchdog, armed whenever it moves, ends the control script when commands stop arriving.

``recover`` is the operator's action: after a lost connection, start a fresh child and connect again
(control script, TCP and payload); then close the safety popup and unlock the protective stop (the one the
state shows, or the dashboard's: the state can lag it), power on and release the brakes, re-upload the
control script, re-send TCP and payload. An emergency stop that is still pressed cannot be cleared from
software.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.arm.base import ArmMode, ArmState, JointTrajectory
from drivers.arm.claim import ArmClaim
from drivers.arm.config import UR5eArmConfig
from drivers.arm.hardware import (
    Array,
    HardwareArm,
    check_trajectory,
    checked_vector,
    clamp_twist,
    interpolate,
    shift_twist,
    ur_pose_to_T,
)
from drivers.arm.ur_rtde_process import ClientError, ClientGone, RTDEProcess
from drivers.errors import DriverError, RobotFault
from drivers.robots.model import RobotModel
from drivers.transforms import inv_T

PORTS = {"RTDE": 30004, "dashboard": 29999, "script": 30003}
RECEIVE_VARIABLES = ["timestamp", "actual_q", "actual_qd", "actual_TCP_pose", "actual_TCP_speed",
                     "robot_mode", "safety_mode", "safety_status_bits", "robot_status_bits", "runtime_state",
                     "actual_digital_input_bits", "actual_digital_output_bits"]
ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
               4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
SAFETY_MODES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
                10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
                13: "SYSTEM_THREE_POSITION_ENABLING_STOP"}
ROBOT_MODE_RUNNING = 7
SAFETY_PROTECTIVE_STOP = 3
SAFETY_FAULT_WORDS = {3: "protective stop", 4: "safety recovery", 5: "safeguard stop", 6: "emergency stop",
                      7: "emergency stop", 8: "safety violation", 9: "safety fault", 12: "safeguard stop",
                      13: "safeguard stop"}
# how long recovery steps may take on the controller before they count as failed [s]
RECOVERY_TIMEOUT_S = 10.0
# A UR controller refuses to unlock a protective stop until 5 s after it occurred, answering with this
# (Dashboard Server e-Series, "unlock protective stop"); recover asks again this often until it may [s]
UNLOCK_TOO_SOON = "Cannot unlock protective stop until 5s after occurrence"
UNLOCK_RETRY_S = 0.25
# how long a command or a state read in the child may take before the child counts as hung [s]; the
# slowest are the stops (speedStop waits for the deceleration) and script re-uploads
REPLY_TIMEOUT_S = 5.0
# State whose controller timestamp has not advanced for this many RTDE periods (1 / rtde_frequency_hz) is a
# controller gone silent with the connection open. A controller sends every period from its real-time
# cycle, so the gaps come from the client's side: the ur-rtde process or the network delayed on a
# non-real-time PC. 25 periods (50 ms at 500 Hz, 200 ms at the 125 Hz the test configs use) clear those
# (none over 50 ms seen on the shared 2-core test machine with eight busy processes, the test peer in the
# real-time class as a controller; in the normal class that peer itself fell silent for up to 0.25 s), and
# still end blind motion long before ur-rtde's own control interface gives up on a silent controller
# (about 2.5 s, then it reconnects by itself).
SILENT_PERIODS = 25
# ur-rtde's control interface gives up on a control script that does not start after 5 s
CONTROL_START_TIMEOUT_S = 5.0
N_DIGITAL = 8
# what ur-rtde's (boost.asio's) errors mean during a connection's handshake
HANDSHAKE_ERRORS = {"Operation canceled": "no answer within {timeout:g} s (connect_timeout_s)",
                    "End of file": "the controller closed the connection",
                    "Connection reset by peer": "the controller reset the connection"}


class UR5eArm(HardwareArm):
    """A UR5e behind its controller (see the module docstring)."""

    name = "ur5e"

    def __init__(self, config: UR5eArmConfig, model: RobotModel, *, read_only: bool = False) -> None:
        """``read_only``: connect to read the arm's state only (RTDE receive and the dashboard), beside a
        program that drives it: no control script is started, the arm is not claimed, and the script's
        state is that program's, not a fault; every command then raises."""
        if model.name != "ur5e":
            raise ValueError(f"arm ur5e: needs the ur5e model, got {model.name!r}")
        self._config = config
        self._model = model
        self._read_only = read_only
        self._device = f"arm ur5e at {config.host}"
        self._T_flange_tcp = ur_pose_to_T(config.tcp_offset)
        self._proc: RTDEProcess | None = None
        self._connected = False
        self._control = False  # the control interface is open in the child
        self._tool_sent = False  # the config's TCP went to the control script now open (``_apply_tool``)
        self._lost: RobotFault | None = None  # latched until the operator recovers (module docstring)
        self._lock = threading.RLock()  # one exchange with the child at a time, and what depends on it
        self._mode = ArmMode.IDLE
        self._watchdog_armed = False
        self._traj_thread: threading.Thread | None = None
        self._traj_cancel = threading.Event()
        self._traj_error: RobotFault | None = None
        self._last_snapshot: tuple[float, dict[str, Any]] | None = None  # (time.monotonic(), snapshot)
        # the controller's latest RTDE timestamp [s] and the time.monotonic() it first arrived at [s]
        self._newest_data: tuple[float, float] | None = None
        self._claim = ArmClaim("ur5e", config.host)

    # ------------------------------------------------------------------ connection

    def connect(self) -> None:
        if self._connected:
            return
        cfg = self._config
        for what, port in PORTS.items():
            try:
                socket.create_connection((cfg.host, port), timeout=cfg.connect_timeout_s).close()
            except OSError as exc:
                raise DriverError(f"cannot reach the controller's {what} port {cfg.host}:{port} within "
                                  f"{cfg.connect_timeout_s:g} s ({exc}); check the address and that the "
                                  f"controller is on", device=self._device) from None
        if not self._read_only:
            self._claim.take()
        try:
            self._open()
        except DriverError:
            self._lost = None  # a failed connect latches nothing: the next connect starts afresh
            self._claim.release()
            raise
        self._connected = True

    def _open(self) -> None:
        """Start a child process and connect its clients; the control script only when the robot runs
        normally: a stopped robot, or one powered off (robot mode POWER_OFF, as after an emergency stop is
        released or at boot) does not start it, and ur-rtde would wait out its 5 s for it and fail as if
        the script port were at fault. Connect for reading instead, so that the fault shows, and let
        ``recover`` start the script once the operator has cleared the stop or powered the arm on."""
        cfg = self._config
        self._proc = RTDEProcess()
        self._proc.start()
        self._control = False
        self._tool_sent = False
        self._watchdog_armed = False
        self._mode = ArmMode.IDLE
        # a stream's error belongs to the connection it ran on: one that ended with a lost connection
        # would otherwise refuse the new connection's first commands (TCP and payload) as "disconnect"
        self._traj_error = None
        timeout = cfg.connect_timeout_s + REPLY_TIMEOUT_S
        step = "dashboard"
        try:
            self._proc.call("dashboard_connect", cfg.host, int(cfg.connect_timeout_s * 1000),
                            timeout_s=timeout)
            if not self._proc.call("dashboard", "isInRemoteControl", timeout_s=REPLY_TIMEOUT_S):
                raise DriverError("the controller is in local control: switch the teach pendant to Remote "
                                  "Control, then connect again", device=self._device)
            step = "RTDE"
            self._proc.call("receive_connect", cfg.host, cfg.rtde_frequency_hz, RECEIVE_VARIABLES,
                            timeout_s=timeout)
            snap = self._snapshot()
            if not self._read_only and snap["safety_mode"] not in SAFETY_FAULT_WORDS \
                    and snap["robot_mode"] == ROBOT_MODE_RUNNING:
                step = "script"
                self._start_control()
        except (ClientError, ClientGone) as exc:
            self._close_process()
            raise self._handshake_error(step, exc) from None
        except DriverError:
            self._close_process()
            raise

    def _handshake_error(self, step: str, exc: Exception) -> DriverError:
        """The failure of a connection that the controller's ``step`` port (a key of ``PORTS``) accepted:
        what was tried, what happened, and what to check."""
        cfg = self._config
        said = str(exc)
        meaning = HANDSHAKE_ERRORS.get(said.rsplit(": ", 1)[-1])  # ur-rtde may say "read: End of file"
        if meaning is not None:
            said = f"{meaning.format(timeout=cfg.connect_timeout_s)} (ur-rtde: {said})"
        tried = {"dashboard": "the dashboard server's handshake", "RTDE": "the RTDE protocol handshake",
                 "script": "uploading ur-rtde's control script and starting it"}[step]
        return DriverError(
            f"the controller's {step} port {cfg.host}:{PORTS[step]} accepted the connection, but {tried} "
            f"failed: {said}; check that {cfg.host} is the UR controller and not another device, that it "
            "has finished booting, that the Dashboard Server and RTDE are enabled (PolyScope: Settings > "
            "Security > Services) and that no other program holds the connection", device=self._device)

    def _start_control(self) -> None:
        """Open the control interface (ur-rtde uploads its control script) and send the tool. Raises
        ``ClientError`` / ``ClientGone`` from the child as they come."""
        cfg = self._config
        with self._lock:
            assert self._proc is not None
            self._proc.call("control_connect", cfg.host, cfg.rtde_frequency_hz,
                            timeout_s=CONTROL_START_TIMEOUT_S + cfg.connect_timeout_s + REPLY_TIMEOUT_S)
            self._control = True
        self._apply_tool()

    def _apply_tool(self) -> None:
        """Send TCP and payload from the config (the control script forgets them when it restarts)."""
        p = self._config.payload
        self._tool_sent = False
        self._call("setTcp", list(self._config.tcp_offset))
        self._tool_sent = True
        self._call("setPayload", p.mass_kg, list(p.cog_m))

    def disconnect(self) -> None:
        """Stop, end the control script and close every connection (the child ends). Safe to call twice."""
        if not self._connected:
            return
        self._cancel_trajectory()
        try:
            if self._lost is None and self._control and not self._faults(self._snapshot()):
                self.stop()
                self._send("stopScript")
        except RobotFault as exc:
            if exc.fault != "disconnect":
                raise  # a lost connection leaves nothing to stop: the watchdog stops the arm
        finally:
            self._close_process()
            self._claim.release()
            self._connected = False
            self._lost = None

    def _close_process(self) -> None:
        with self._lock:
            if self._proc is not None:
                self._proc.close()
            self._proc = None
            self._last_snapshot = None
            self._newest_data = None
            self._control = False
            self._tool_sent = False
            self._watchdog_armed = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    @property
    def client_pid(self) -> int | None:
        """The process id of the child that holds the ur-rtde connections, while it runs."""
        return self._proc.pid if self._proc is not None else None

    @property
    def T_flange_tcp(self) -> Array:
        """The TCP in the flange frame (4x4), from the config."""
        return self._T_flange_tcp.copy()

    @property
    def n_joints(self) -> int:
        return 6

    @property
    def model(self) -> RobotModel:
        return self._model

    # ------------------------------------------------------------------ the child process

    def _request(self, op: str, *args: object, timeout_s: float = REPLY_TIMEOUT_S) -> Any:
        """Run ``op`` in the child. A latched loss is raised again; a child that ended or hung becomes a
        latched loss. ``ClientError`` (ur-rtde raised) is left to the caller."""
        with self._lock:
            if self._lost is not None:
                raise self._lost
            if self._proc is None:
                raise DriverError("not connected (call connect() first)", device=self._device)
            try:
                return self._proc.call(op, *args, timeout_s=timeout_s)
            except ClientGone as exc:
                raise self._lose(str(exc)) from None

    def _lose(self, why: str) -> RobotFault:
        """Latch a lost connection: the child is killed (if it still runs) and every later request raises
        the returned fault until ``recover``."""
        with self._lock:
            if self._proc is not None:
                self._proc.kill()
            self._last_snapshot = None
            self._lost = RobotFault(f"lost the connection to the controller: {why}", device=self._device,
                                    fault="disconnect")
            return self._lost

    def _snapshot(self, kick: bool = False) -> dict[str, Any]:
        """The controller's state as the child reads it (see ``Clients.snapshot`` in the child)."""
        try:
            snap: dict[str, Any] = self._request("snapshot", kick)
        except ClientError as exc:
            raise self._lose(f"reading the state: {exc}") from None
        now = time.monotonic()
        self._check_data_flows(snap["timestamp"], now)
        self._last_snapshot = (now, snap)
        return snap

    def _check_data_flows(self, timestamp: float, now: float) -> None:
        """Latch a lost connection when the controller's RTDE ``timestamp`` [s] has stayed the same for
        more than ``SILENT_PERIODS`` RTDE periods up to ``now`` (``time.monotonic()``) [s]. The silence is
        counted from when that timestamp first reached this driver, so a driver that itself paused between
        reads does not count its own pause. The child is killed: ur-rtde would otherwise queue every
        command for a controller that reads none, and a controller that resumes would run them at once."""
        newest = self._newest_data
        if newest is None or timestamp != newest[0]:
            self._newest_data = (timestamp, now)
            return
        silent_s = now - newest[1]
        limit_s = SILENT_PERIODS / self._config.rtde_frequency_hz
        if silent_s > limit_s:
            raise self._lose(f"no data from the controller for {silent_s:.3f} s although the connection is "
                             f"open (its RTDE timestamp stayed at {timestamp:.3f} s; at "
                             f"{self._config.rtde_frequency_hz:g} Hz the limit is {limit_s:g} s); nothing "
                             "more is sent to it")

    def _recent_snapshot(self) -> dict[str, Any]:
        """The last snapshot if it is younger than one RTDE period (a new read would return the same
        data package), else a new one."""
        last = self._last_snapshot
        if last is not None and self._lost is None and \
                time.monotonic() - last[0] < 1.0 / self._config.rtde_frequency_hz:
            return last[1]
        return self._snapshot()

    def _send(self, name: str, *args: object) -> None:
        """Send a control-interface command; an error from ur-rtde is a lost connection, and a False
        answer a fault."""
        try:
            answer = self._request("control", name, args)
        except ClientError as exc:
            raise self._lose(f"{name}: {exc}") from None
        if answer is False:
            raise self._fault_error(f"{name} failed")

    def _call(self, name: str, *args: object) -> None:
        """A command that must succeed: refused while faulted (``_send`` otherwise)."""
        with self._lock:
            faults = self._faults(self._snapshot())
            if faults:
                raise self._fault_error(f"{name} refused", faults)
            self._send(name, *args)

    def _dashboard(self, name: str) -> object:
        try:
            return self._request("dashboard", name)
        except ClientError as exc:
            raise self._lose(f"dashboard {name}: {exc}") from None

    # ------------------------------------------------------------------ state and faults

    def _faults(self, snap: dict[str, Any]) -> tuple[str, ...]:
        faults: list[str] = []
        safety = snap["safety_mode"]
        if safety in SAFETY_FAULT_WORDS:
            faults.append(SAFETY_FAULT_WORDS[safety])
        robot_mode = snap["robot_mode"]
        if robot_mode != ROBOT_MODE_RUNNING:
            faults.append("power off" if robot_mode in (3, 4, 5)
                          else f"robot mode {ROBOT_MODES.get(robot_mode)}")
        if not snap["program_running"] and not self._read_only:
            faults.append("control script not running")
        if self._traj_error is not None and self._traj_error.fault not in faults:
            faults.append(self._traj_error.fault)
        return tuple(dict.fromkeys(faults))

    def _fault_error(self, what: str, faults: tuple[str, ...] | None = None) -> RobotFault:
        faults = self._faults(self._snapshot()) if faults is None else faults
        fault = faults[0] if faults else "command refused"
        words = ", ".join(faults) if faults else "the controller refused it"
        return RobotFault(f"{what}: {words}", device=self._device, fault=fault)

    def state(self) -> ArmState:
        snap = self._snapshot(kick=self._watchdog_armed)
        q = checked_vector(snap["q"], 6, "actual_q", self._device)
        qd = checked_vector(snap["qd"], 6, "actual_qd", self._device)
        T_tcp = ur_pose_to_T(checked_vector(snap["tcp_pose"], 6, "actual_TCP_pose", self._device))
        v_tcp = checked_vector(snap["tcp_speed"], 6, "actual_TCP_speed", self._device)
        T_flange = self._flange_pose(snap, q, T_tcp)
        faults = self._faults(snap)
        streaming = self._traj_thread is not None and self._traj_thread.is_alive()
        if self._mode is ArmMode.TRAJECTORY and not streaming:
            self._mode = ArmMode.IDLE
        return ArmState(timestamp=snap["timestamp"], q=q, qd=qd, T_base_flange=T_flange,
                        v_base_flange=shift_twist(v_tcp, T_flange[:3, 3] - T_tcp[:3, 3]),
                        mode=ArmMode.FAULT if faults else self._mode, faults=faults)

    def _flange_pose(self, snap: dict[str, Any], q: Array, T_tcp: Array) -> Array:
        """T_base_flange (4x4) [m]: the controller's TCP pose ``T_tcp`` less the config's TCP while this
        driver's control script runs with that TCP, else the model's forward kinematics of the joints
        ``q`` [rad] (the controller's active TCP is then not the config's; module docstring)."""
        if self._tool_sent and self._control and snap["program_running"]:
            return T_tcp @ inv_T(self._T_flange_tcp)
        return self._model.fk(q)

    def controller_modes(self) -> dict[str, str]:
        snap = self._snapshot()
        robot_mode, safety_mode = snap["robot_mode"], snap["safety_mode"]
        return {
            "robot mode": ROBOT_MODES.get(robot_mode, str(robot_mode)),
            "safety mode": SAFETY_MODES.get(safety_mode, str(safety_mode)),
            "control script": "running" if snap["program_running"] else "not running",
            "digital inputs": "".join("1" if b else "0" for b in bits(snap["digital_inputs"])),
        }

    # ------------------------------------------------------------------ commands

    def _arm_watchdog(self) -> None:
        if not self._watchdog_armed:
            self._call("setWatchdog", self._config.watchdog_min_hz)
            self._watchdog_armed = True

    def _command_twist(self, v_base_flange: Array) -> None:
        cfg = self._config
        v = clamp_twist(checked_vector(v_base_flange, 6, "twist", self._device), cfg.max_linear_mps,
                        cfg.max_angular_rps)
        self._cancel_trajectory()
        with self._lock:
            snap = self._recent_snapshot()
            faults = self._faults(snap)
            if faults:
                raise self._fault_error("speedL refused", faults)
            T_tcp = ur_pose_to_T(checked_vector(snap["tcp_pose"], 6, "actual_TCP_pose", self._device))
            T_flange = T_tcp @ inv_T(self._T_flange_tcp)
            v_tcp = shift_twist(v, T_tcp[:3, 3] - T_flange[:3, 3])
            self._arm_watchdog()
            self._send("speedL", v_tcp.tolist(), cfg.acceleration_mps2, 0.0)
            self._mode = ArmMode.VELOCITY

    def _execute_trajectory(self, trajectory: JointTrajectory) -> None:
        q_now = checked_vector(self._snapshot()["q"], 6, "actual_q", self._device)
        check_trajectory(trajectory, self._model, q_now, self._device)
        self._cancel_trajectory()
        with self._lock:
            faults = self._faults(self._snapshot())
            if faults:
                raise self._fault_error("execute_trajectory() refused", faults)
            if self._mode is ArmMode.VELOCITY:
                self._send("speedStop", self._config.stop_deceleration_mps2)
            self._arm_watchdog()
            self._traj_error = None
            self._traj_cancel.clear()
            self._mode = ArmMode.TRAJECTORY
            self._traj_thread = threading.Thread(target=self._stream, args=(trajectory,), daemon=True,
                                                 name="ur5e-servoj")
            self._traj_thread.start()

    def _stream(self, trajectory: JointTrajectory) -> None:
        """Send the trajectory's joints with servoJ at ``servo_rate_hz`` until it ends or is cancelled,
        holding the last sample until the joints settle on it (module docstring)."""
        cfg = self._config
        period = 1.0 / cfg.servo_rate_hz
        t0 = time.monotonic()
        tick = 0
        unsettled: RobotFault | None = None
        try:
            while not self._traj_cancel.is_set():
                t = time.monotonic() - t0
                q = interpolate(trajectory, min(t, trajectory.duration)).tolist()
                self._call("servoJ", q, 0.0, 0.0, period, cfg.servo_lookahead_s, cfg.servo_gain)
                if t >= trajectory.duration:
                    error = self._end_error(trajectory.q[-1])
                    if error <= cfg.settle_tolerance_rad:
                        break
                    if t - trajectory.duration > cfg.settle_timeout_s:
                        unsettled = RobotFault(
                            f"trajectory end not reached: a joint is {error:.4f} rad from it "
                            f"{t - trajectory.duration:.2f} s after the end", device=self._device,
                            fault="trajectory end not reached")
                        break
                tick += 1
                time.sleep(max(0.0, t0 + tick * period - time.monotonic()))
            with self._lock:
                if not self._traj_cancel.is_set():
                    self._call("servoStop", cfg.stop_deceleration_mps2)
                    self._disarm_watchdog()
                    self._mode = ArmMode.IDLE
            self._traj_error = unsettled
        except RobotFault as exc:
            self._traj_error = exc

    def _end_error(self, q_end: Array) -> float:
        """The largest joint distance [rad] from ``q_end``, as read just before the last command."""
        assert self._last_snapshot is not None  # _call has just read one
        q = checked_vector(self._last_snapshot[1]["q"], 6, "actual_q", self._device)
        return float(np.max(np.abs(q - q_end)))

    def _cancel_trajectory(self) -> None:
        thread = self._traj_thread
        if thread is not None and thread.is_alive() and thread is not threading.current_thread():
            self._traj_cancel.set()
            thread.join()
        self._traj_thread = None

    def _disarm_watchdog(self) -> None:
        if self._watchdog_armed:
            self._call("setWatchdog", 0.0)
            self._watchdog_armed = False

    def stop(self) -> None:
        """Decelerate at ``stop_deceleration_mps2``. On a faulted arm the controller has stopped it already,
        and after a lost connection the RTDE watchdog stops it, so nothing is sent."""
        if not self._connected:
            raise DriverError("not connected (call connect() first)", device=self._device)
        self._cancel_trajectory()
        decel = self._config.stop_deceleration_mps2
        with self._lock:
            if self._lost is not None or self._faults(self._snapshot()):
                self._mode = ArmMode.IDLE
                return
            if self._mode is ArmMode.VELOCITY:
                self._call("speedStop", decel)
            elif self._mode is ArmMode.TRAJECTORY:
                self._call("servoStop", decel)
            else:
                self._call("stopL", decel)
            self._disarm_watchdog()
            self._mode = ArmMode.IDLE

    # ------------------------------------------------------------------ recovery (operator action)

    def recover(self) -> None:
        if not self._connected:
            raise DriverError("not connected (call connect() first)", device=self._device)
        self._cancel_trajectory()
        if self._lost is not None:
            self._reconnect()
        snap = self._snapshot()
        if snap["emergency_stopped"]:
            raise RobotFault("the emergency stop is pressed: release it on the robot, then recover again",
                             device=self._device, fault="emergency stop")
        if snap["protective_stopped"] or self._dashboard_says_protective_stop():
            self._dashboard("closeSafetyPopup")
            self._unlock_protective_stop()
            self._wait(lambda: not self._dashboard_says_protective_stop()
                       and not self._snapshot()["protective_stopped"], "unlocking the protective stop")
        if snap["robot_mode"] != ROBOT_MODE_RUNNING:
            self._dashboard("powerOn")
            self._dashboard("brakeRelease")
            self._wait(lambda: self._snapshot()["robot_mode"] == ROBOT_MODE_RUNNING,
                       "powering on and releasing the brakes")
        self._traj_error = None
        self._watchdog_armed = False
        self._mode = ArmMode.IDLE
        if not self._control:
            try:
                self._start_control()
            except ClientError as exc:
                raise self._fault_error(f"starting the control script: {exc}") from None
            except ClientGone as exc:
                raise self._lose(str(exc)) from None
            return
        if not self._snapshot()["program_running"]:
            self._send("reuploadScript")
            self._wait(lambda: self._snapshot()["program_running"], "restarting the control script")
        self._apply_tool()

    def _unlock_protective_stop(self) -> None:
        """Ask the controller to unlock its protective stop. It refuses until 5 s after the stop occurred
        (ur-rtde raises with the controller's answer, :data:`UNLOCK_TOO_SOON`), so an operator's recovery
        right after a stop asks again until it may, within ``RECOVERY_TIMEOUT_S``; any other refusal is a
        fault naming the controller's answer."""
        deadline = time.monotonic() + RECOVERY_TIMEOUT_S
        while True:
            try:
                self._request("dashboard", "unlockProtectiveStop")
                return
            except ClientError as exc:
                if UNLOCK_TOO_SOON not in str(exc) or time.monotonic() > deadline:
                    raise RobotFault(f"unlocking the protective stop: {exc}", device=self._device,
                                     fault="protective stop") from None
            time.sleep(UNLOCK_RETRY_S)

    def _dashboard_says_protective_stop(self) -> bool:
        """Whether the controller itself, asked on the dashboard, is in a protective stop. The receive
        interface and the control interface read two RTDE streams, so the script's end can reach the driver
        before the protective stop that ended it: seen on a loaded machine, recover skipped the unlock and
        waited out its timeout for a script the controller would not run. The release after an unlock is
        awaited here too: the dashboard answers the unlock when the release begins, and a receive stream
        that lags would let the script's re-upload reach a controller still stopped, which does not run
        it (recover then waits for the receive stream as well, so that the state read after it agrees)."""
        return f"Safetystatus: {SAFETY_MODES[SAFETY_PROTECTIVE_STOP]}" in str(self._dashboard("safetystatus"))

    def _reconnect(self) -> None:
        """After a lost connection: a fresh child connects again (the lost one was killed). Stays latched
        as lost when that fails."""
        lost = self._lost
        self._close_process()
        self._lost = None
        try:
            self._open()
        except DriverError:
            self._lost = self._lost or lost
            raise

    def _wait(self, done: Callable[[], bool], what: str) -> None:
        deadline = time.monotonic() + RECOVERY_TIMEOUT_S
        while not done():
            if time.monotonic() > deadline:
                raise self._fault_error(f"{what} did not finish within {RECOVERY_TIMEOUT_S:g} s")
            time.sleep(0.02)

    # ------------------------------------------------------------------ digital IO

    def digital_inputs(self) -> tuple[bool, ...]:
        """The eight standard digital inputs, DI0 first."""
        return bits(self._snapshot()["digital_inputs"])


def bits(value: int) -> tuple[bool, ...]:
    """The ``N_DIGITAL`` lowest bits of ``value``, bit 0 first."""
    return tuple(bool(value >> i & 1) for i in range(N_DIGITAL))
