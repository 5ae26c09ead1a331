"""UR5e backend through ur-rtde (pinned: ``ur-rtde==1.6.5``, the ``ur5e`` extra).

Connections: RTDE receive (state), RTDE control (the control script ur-rtde uploads to port 30003 and
drives through its register handshake) and the dashboard server (remote control check, unlocking a
protective stop, power and brakes); RTDE IO (digital outputs) only while outputs are being set. ur-rtde's
IO interface writes to its socket in its destructor, and when the controller has dropped the connection
that write throws inside the destructor, which ends the whole process (``std::terminate``, exit 134), so
an IO interface is opened for each change of the outputs and closed while the controller still answers.
``connect`` first opens each controller port with ``connect_timeout_s`` so an unreachable controller fails
fast with its address, and asks the dashboard whether the pendant is in remote control.

Frames: ur-rtde reports and commands the TCP (``setTcp`` from the config); this backend converts to and
from the flange, which is what the :class:`~drivers.arm.base.Arm` interface speaks.

Motion:
- twists: clamped to the config's ceilings, turned into a TCP twist and sent with ``speedL`` (each call
  renews it); the RTDE watchdog (``watchdog_min_hz``) is armed for as long as the arm moves, and every
  command or ``state()`` call refreshes it, so a control loop that stops calling stops the arm.
- trajectories: a thread streams the joint samples with ``servoJ`` at ``servo_rate_hz``, interpolated at
  wall-clock time. The trajectory is in joint space and the guard checked those joints, so they go out
  as joints: ``servoL`` would let the controller's IK pick a configuration nobody checked.
- ``stop``: ``speedStop`` after velocity, ``servoStop`` after a trajectory, ``stopL`` otherwise, all with
  ``stop_deceleration_mps2``; then the watchdog is disarmed (frequency 0).

Faults, from the controller's safety status and the script's state: "protective stop", "emergency stop",
"safeguard stop", "safety fault", "power off", "control script not running", "disconnect". A command
while faulted, a command that returns False, or a lost connection raises ``RobotFault``.

A lost connection is latched as "disconnect" and nothing more is asked of the interfaces. ur-rtde 1.6.5
reconnects its control interface by itself, from its receive thread, and re-uploads the control script;
but that thread then keeps running beside the new receive thread it started, the two read the same
socket, and the process soon ends with a segmentation fault (reproduced against the RTDE peer, not
avoidable from outside the library). So the arm stays refused, and ``recover`` refuses to reconnect in
this process and asks for a restart of the program. The arm is stopped all the same: the RTDE watchdog,
armed whenever it moves, ends the control script when commands stop arriving.

``recover`` is the operator's action: close the safety popup and unlock the protective stop, power on and
release the brakes, re-upload the control script, re-send TCP and payload. An emergency stop that is still
pressed cannot be cleared from software.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable
from typing import Literal

import dashboard_client
import rtde_control
import rtde_io
import rtde_receive

from drivers.arm.base import ArmMode, ArmState, JointTrajectory
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
SAFETY_FAULT_WORDS = {3: "protective stop", 4: "safety recovery", 5: "safeguard stop", 6: "emergency stop",
                      7: "emergency stop", 8: "safety violation", 9: "safety fault", 12: "safeguard stop",
                      13: "safeguard stop"}
LOST_CONNECTION = "lost the connection to the controller"
# how long recovery steps may take on the controller before they count as failed [s]
RECOVERY_TIMEOUT_S = 10.0
N_DIGITAL = 8


class UR5eArm(HardwareArm):
    """A UR5e behind its controller (see the module docstring)."""

    name = "ur5e"

    def __init__(self, config: UR5eArmConfig, model: RobotModel) -> None:
        if model.name != "ur5e":
            raise ValueError(f"arm ur5e: needs the ur5e model, got {model.name!r}")
        self._config = config
        self._model = model
        self._device = f"arm ur5e at {config.host}"
        self._T_flange_tcp = ur_pose_to_T(config.tcp_offset)
        self._recv: rtde_receive.RTDEReceiveInterface | None = None
        self._ctl: rtde_control.RTDEControlInterface | None = None
        self._dash: dashboard_client.DashboardClient | None = None
        self._lock = threading.RLock()
        self._mode = ArmMode.IDLE
        self._watchdog_armed = False
        self._traj_thread: threading.Thread | None = None
        self._traj_cancel = threading.Event()
        self._traj_error: RobotFault | None = None
        self._lost = False  # the connection was lost (latched, see the module docstring)

    # ------------------------------------------------------------------ connection

    def connect(self) -> None:
        if self.is_connected:
            return
        cfg = self._config
        for what, port in PORTS.items():
            try:
                socket.create_connection((cfg.host, port), timeout=cfg.connect_timeout_s).close()
            except OSError as exc:
                raise DriverError(f"cannot reach the controller's {what} port {cfg.host}:{port} within "
                                  f"{cfg.connect_timeout_s:g} s ({exc}); check the address and that the "
                                  f"controller is on", device=self._device) from None
        try:
            dash = dashboard_client.DashboardClient(cfg.host)
            dash.connect(int(cfg.connect_timeout_s * 1000))
            if not dash.isInRemoteControl():
                dash.disconnect()
                raise DriverError("the controller is in local control: switch the teach pendant to Remote "
                                  "Control, then connect again", device=self._device)
            self._dash = dash
            self._recv = rtde_receive.RTDEReceiveInterface(cfg.host, cfg.rtde_frequency_hz, RECEIVE_VARIABLES)
            # a stopped robot cannot start the control script: connect to it for reading, so that its
            # fault shows; ``recover`` starts the script once the operator has cleared the stop
            if self._recv.getSafetyMode() not in SAFETY_FAULT_WORDS:
                self._start_control()
        except RuntimeError as exc:
            self._close_clients()
            raise DriverError(f"ur-rtde could not connect: {exc}", device=self._device) from None
        self._mode = ArmMode.IDLE

    def _start_control(self) -> None:
        """Open the control interface (ur-rtde uploads its control script) and send the tool."""
        cfg = self._config
        self._ctl = rtde_control.RTDEControlInterface(cfg.host, cfg.rtde_frequency_hz,
                                                      rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT)
        self._apply_tool()

    def _apply_tool(self) -> None:
        """Send TCP and payload from the config (the control script forgets them when it restarts)."""
        p = self._config.payload
        self._call("setTcp", lambda c: c.setTcp(self._config.tcp_offset))
        self._call("setPayload", lambda c: c.setPayload(p.mass_kg, list(p.cog_m)))

    def disconnect(self) -> None:
        """Stop, end the control script and close every connection. Safe to call twice."""
        if self._recv is None:
            return
        self._cancel_trajectory()
        if not self._lost and self._ctl is not None and self._ctl.isConnected() and not self._faults():
            self.stop()
            self._ctl.stopScript()
        self._close_clients()

    def _close_clients(self) -> None:
        for client in (self._ctl, self._recv, self._dash):
            if client is not None:
                # closing a socket the controller already dropped raises in ur-rtde; it is closed either way
                with contextlib.suppress(RuntimeError):
                    client.disconnect()
        self._ctl = self._recv = self._dash = None
        self._watchdog_armed = False
        self._lost = False

    @property
    def is_connected(self) -> bool:
        return self._recv is not None

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

    def _clients(self) -> tuple[rtde_receive.RTDEReceiveInterface, rtde_control.RTDEControlInterface | None]:
        """The receive interface and, once the control script could start, the control interface."""
        if self._recv is None:
            raise DriverError("not connected (call connect() first)", device=self._device)
        return self._recv, self._ctl

    # ------------------------------------------------------------------ state and faults

    def _connection_lost(self) -> RobotFault:
        """Latch a lost connection (module docstring) and say so."""
        self._lost = True
        return RobotFault(LOST_CONNECTION, device=self._device, fault="disconnect")

    def _faults(self) -> tuple[str, ...]:
        recv, ctl = self._clients()
        if self._lost:
            return ("disconnect",)  # nothing is asked of the interfaces any more
        if not recv.isConnected() or (ctl is not None and not ctl.isConnected()):
            self._connection_lost()
            return ("disconnect",)
        faults: list[str] = []
        safety = recv.getSafetyMode()
        if safety in SAFETY_FAULT_WORDS:
            faults.append(SAFETY_FAULT_WORDS[safety])
        robot_mode = recv.getRobotMode()
        if robot_mode != ROBOT_MODE_RUNNING:
            faults.append("power off" if robot_mode in (3, 4, 5)
                          else f"robot mode {ROBOT_MODES.get(robot_mode)}")
        if ctl is None or not ctl.isProgramRunning():
            faults.append("control script not running")
        if self._traj_error is not None and self._traj_error.fault not in faults:
            faults.append(self._traj_error.fault)
        return tuple(dict.fromkeys(faults))

    def _fault_error(self, what: str, faults: tuple[str, ...] | None = None) -> RobotFault:
        faults = self._faults() if faults is None else faults
        fault = faults[0] if faults else "command refused"
        words = ", ".join(faults) if faults else "the controller refused it"
        return RobotFault(f"{what}: {words}", device=self._device, fault=fault)

    def state(self) -> ArmState:
        recv, _ = self._clients()
        if self._lost or not recv.isConnected():
            raise self._connection_lost()
        q = checked_vector(recv.getActualQ(), 6, "actual_q", self._device)
        qd = checked_vector(recv.getActualQd(), 6, "actual_qd", self._device)
        T_tcp = ur_pose_to_T(checked_vector(recv.getActualTCPPose(), 6, "actual_TCP_pose", self._device))
        v_tcp = checked_vector(recv.getActualTCPSpeed(), 6, "actual_TCP_speed", self._device)
        T_flange = T_tcp @ inv_T(self._T_flange_tcp)
        faults = self._faults()
        streaming = self._traj_thread is not None and self._traj_thread.is_alive()
        if self._mode is ArmMode.TRAJECTORY and not streaming:
            self._mode = ArmMode.IDLE
        if self._watchdog_armed and not faults:
            with self._lock:
                self._ctl_call("kickWatchdog", lambda c: c.kickWatchdog())
        return ArmState(timestamp=recv.getTimestamp(), q=q, qd=qd, T_base_flange=T_flange,
                        v_base_flange=shift_twist(v_tcp, T_flange[:3, 3] - T_tcp[:3, 3]),
                        mode=ArmMode.FAULT if faults else self._mode, faults=faults)

    def controller_modes(self) -> dict[str, str]:
        recv, ctl = self._clients()
        return {
            "robot mode": ROBOT_MODES.get(recv.getRobotMode(), str(recv.getRobotMode())),
            "safety mode": SAFETY_MODES.get(recv.getSafetyMode(), str(recv.getSafetyMode())),
            "control script": "running" if ctl is not None and ctl.isProgramRunning() else "not running",
            "digital inputs": "".join("1" if b else "0" for b in self.digital_inputs()),
        }

    # ------------------------------------------------------------------ commands

    def _ctl_call(self, what: str, fn: Callable[[rtde_control.RTDEControlInterface], object]) -> object:
        """Call the control interface; a lost connection becomes a ``RobotFault``."""
        _, ctl = self._clients()
        if ctl is None:
            raise RobotFault(f"{what}: the control script never started", device=self._device,
                             fault="control script not running")
        try:
            return fn(ctl)
        except RuntimeError as exc:
            self._connection_lost()
            raise RobotFault(f"{what}: {exc}", device=self._device, fault="disconnect") from None

    def _call(self, what: str, fn: Callable[[rtde_control.RTDEControlInterface], object]) -> None:
        """A command that must succeed: refused while faulted, and a False answer is a fault."""
        with self._lock:
            faults = self._faults()
            if faults:
                raise self._fault_error(f"{what} refused", faults)
            if self._ctl_call(what, fn) is False:
                raise self._fault_error(f"{what} failed")

    def _arm_watchdog(self) -> None:
        if not self._watchdog_armed:
            self._call("setWatchdog", lambda c: c.setWatchdog(self._config.watchdog_min_hz))
            self._watchdog_armed = True

    def _command_twist(self, v_base_flange: Array) -> None:
        cfg = self._config
        v = clamp_twist(checked_vector(v_base_flange, 6, "twist", self._device), cfg.max_linear_mps,
                        cfg.max_angular_rps)
        self._cancel_trajectory()
        recv, _ = self._clients()
        T_tcp = ur_pose_to_T(checked_vector(recv.getActualTCPPose(), 6, "actual_TCP_pose", self._device))
        T_flange = T_tcp @ inv_T(self._T_flange_tcp)
        v_tcp = shift_twist(v, T_tcp[:3, 3] - T_flange[:3, 3])
        with self._lock:
            self._arm_watchdog()
            self._call("speedL", lambda c: c.speedL(v_tcp.tolist(), cfg.acceleration_mps2, 0.0))
            self._mode = ArmMode.VELOCITY

    def _execute_trajectory(self, trajectory: JointTrajectory) -> None:
        recv, _ = self._clients()
        q_now = checked_vector(recv.getActualQ(), 6, "actual_q", self._device)
        check_trajectory(trajectory, self._model, q_now, self._device)
        self._cancel_trajectory()
        with self._lock:
            faults = self._faults()
            if faults:
                raise self._fault_error("execute_trajectory() refused", faults)
            if self._mode is ArmMode.VELOCITY:
                self._call("speedStop", lambda c: c.speedStop(self._config.stop_deceleration_mps2))
            self._arm_watchdog()
            self._traj_error = None
            self._traj_cancel.clear()
            self._mode = ArmMode.TRAJECTORY
            self._traj_thread = threading.Thread(target=self._stream, args=(trajectory,), daemon=True,
                                                 name="ur5e-servoj")
            self._traj_thread.start()

    def _stream(self, trajectory: JointTrajectory) -> None:
        """Send the trajectory's joints with servoJ at ``servo_rate_hz`` until it ends or is cancelled."""
        cfg = self._config
        period = 1.0 / cfg.servo_rate_hz
        t0 = time.monotonic()
        tick = 0
        try:
            while not self._traj_cancel.is_set():
                t = time.monotonic() - t0
                q = interpolate(trajectory, min(t, trajectory.duration)).tolist()
                with self._lock:
                    self._call("servoJ", lambda c, q=q: c.servoJ(q, 0.0, 0.0, period, cfg.servo_lookahead_s,
                                                                 cfg.servo_gain))
                if t >= trajectory.duration:
                    break
                tick += 1
                time.sleep(max(0.0, t0 + tick * period - time.monotonic()))
            with self._lock:
                if not self._traj_cancel.is_set():
                    self._call("servoStop", lambda c: c.servoStop(cfg.stop_deceleration_mps2))
                    self._disarm_watchdog()
                    self._mode = ArmMode.IDLE
        except RobotFault as exc:
            self._traj_error = exc

    def _cancel_trajectory(self) -> None:
        thread = self._traj_thread
        if thread is not None and thread.is_alive() and thread is not threading.current_thread():
            self._traj_cancel.set()
            thread.join()
        self._traj_thread = None

    def _disarm_watchdog(self) -> None:
        if self._watchdog_armed:
            self._call("setWatchdog", lambda c: c.setWatchdog(0.0))
            self._watchdog_armed = False

    def stop(self) -> None:
        """Decelerate at ``stop_deceleration_mps2``. On a faulted arm the controller has stopped it already,
        so nothing is sent."""
        self._clients()
        self._cancel_trajectory()
        if self._faults():
            self._mode = ArmMode.IDLE
            return
        decel = self._config.stop_deceleration_mps2
        with self._lock:
            if self._mode is ArmMode.VELOCITY:
                self._call("speedStop", lambda c: c.speedStop(decel))
            elif self._mode is ArmMode.TRAJECTORY:
                self._call("servoStop", lambda c: c.servoStop(decel))
            else:
                self._call("stopL", lambda c: c.stopL(decel))
            self._disarm_watchdog()
            self._mode = ArmMode.IDLE

    # ------------------------------------------------------------------ recovery (operator action)

    def recover(self) -> None:
        recv, ctl = self._clients()
        dash = self._dash
        assert dash is not None
        if self._lost:
            raise RobotFault(f"{LOST_CONNECTION}; ur-rtde cannot reconnect safely in this process: restart "
                             "the program to connect again", device=self._device, fault="disconnect")
        self._cancel_trajectory()
        if recv.isEmergencyStopped():
            raise RobotFault("the emergency stop is pressed: release it on the robot, then recover again",
                             device=self._device, fault="emergency stop")
        if recv.isProtectiveStopped():
            dash.closeSafetyPopup()
            dash.unlockProtectiveStop()
            self._wait(lambda: not recv.isProtectiveStopped(), "unlocking the protective stop")
        if recv.getRobotMode() != ROBOT_MODE_RUNNING:
            dash.powerOn()
            dash.brakeRelease()
            self._wait(lambda: recv.getRobotMode() == ROBOT_MODE_RUNNING,
                       "powering on and releasing the brakes")
        self._traj_error = None
        self._watchdog_armed = False
        self._mode = ArmMode.IDLE
        if ctl is None:
            try:
                self._start_control()
            except RuntimeError as exc:
                raise self._fault_error(f"starting the control script: {exc}") from None
            return
        if not ctl.isProgramRunning():
            if not ctl.reuploadScript():
                raise self._fault_error("re-uploading the control script")
            self._wait(ctl.isProgramRunning, "restarting the control script")
        self._apply_tool()

    def _wait(self, done: Callable[[], bool], what: str) -> None:
        deadline = time.monotonic() + RECOVERY_TIMEOUT_S
        while not done():
            if time.monotonic() > deadline:
                raise self._fault_error(f"{what} did not finish within {RECOVERY_TIMEOUT_S:g} s")
            time.sleep(0.02)

    # ------------------------------------------------------------------ digital IO

    def digital_inputs(self) -> tuple[bool, ...]:
        """The eight standard digital inputs, DI0 first."""
        recv, _ = self._clients()
        bits = int(recv.getActualDigitalInputBits())
        return tuple(bool(bits >> i & 1) for i in range(N_DIGITAL))

    def trigger(self) -> bool:
        """The line trigger input's level; ``DriverError`` when the config wires none."""
        if self._config.trigger_input is None:
            raise DriverError("no trigger_input in the arm config", device=self._device)
        return self.digital_inputs()[self._config.trigger_input]

    def signal(self, state: Literal["busy", "done", "idle"]) -> None:
        """Drive the busy and done outputs for a packing line: busy while scanning, done when finished."""
        outputs = {self._config.busy_output: state == "busy", self._config.done_output: state == "done"}
        self._clients()
        try:
            io = rtde_io.RTDEIOInterface(self._config.host)  # see the module docstring
        except RuntimeError as exc:
            raise RobotFault(f"opening RTDE IO: {exc}", device=self._device, fault="disconnect") from None
        try:
            for index, level in outputs.items():
                if index is not None and not io.setStandardDigitalOut(index, level):
                    raise self._fault_error(f"setting digital output {index}")
        finally:
            with contextlib.suppress(RuntimeError):  # raises when the controller dropped the connection
                io.disconnect()
