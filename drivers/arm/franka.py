"""Franka backend through franky-control (pinned: ``franky-control==2.0.0``, the ``franka`` extra).

A Cartesian velocity adapter: each twist becomes a franky ``CartesianVelocityMotion`` of
``velocity_hold_s`` in the base frame, queued asynchronously so that it takes over the running one
seamlessly; the control loop renews it at its rate, so the arm decelerates by itself within
``velocity_hold_s`` when the loop stops. Every motion is scaled by ``relative_dynamics_factor``.

Frames: franky reports and commands the end effector (EE, set in Desk); the Arm interface speaks the
flange, so poses go through ``F_T_EE`` and twists through the EE's lever arm.

Point-to-point: a synchronised rest-to-rest joint trajectory (what ``cell.control.trajectory`` plans) is
a straight segment in joint space, which franky's own time-optimal ``JointWaypointMotion`` to the last
sample also follows; the backend checks that the trajectory is such a segment and refuses anything
else, so the arm never leaves the path the guard checked.

Version check: before franky connects, the backend performs the research interface's connect handshake
itself (TCP port 1337: header ``<III`` command 0, command id, size; payload ``<HH`` version, UDP port)
and reads the server's answer (``<B`` status, ``<H`` version). A server that refuses the client's
version is refused with both versions named: the franky-control wheels speak version 10 (libfranka
0.21, FR3-era firmware); an older Panda needs a franky built against a matching libfranka.

Faults: the control unit aborts a running motion with a reason that libfranka raises as a
``ControlException`` (message ``Move command aborted: motion aborted by reflex! ["cartesian_reflex"]`` or
``... User Stop pressed!``); the robot has already stopped, holding its joints. The backend latches it as
a ``RobotFault`` whose ``fault`` is a word from libfranka's reason ("reflex", "user stop", otherwise
"control error"), and whose message carries the reason, the error flags the robot reports, the robot
mode and what the operator does next. A fault seen only in the robot's state (mode ``Reflex`` or
``UserStopped``, errors after a reflex outside a motion) refuses motion the same way; a lost connection
is "disconnect". ``recover`` is the operator's action: franky's automatic error recovery (refused by the
robot while the user stop is pressed), or a new connection after a disconnect.
"""

from __future__ import annotations

import contextlib
import json
import socket
import struct
import time
from importlib import metadata

import franky
import numpy as np

from drivers.arm.base import ArmMode, ArmState, JointTrajectory
from drivers.arm.claim import ArmClaim
from drivers.arm.config import FrankaArmConfig
from drivers.arm.hardware import (
    Array,
    HardwareArm,
    check_trajectory,
    checked_vector,
    clamp_twist,
    shift_twist,
)
from drivers.errors import DriverError, RobotFault
from drivers.hosts import recv_exact
from drivers.robots.model import RobotModel
from drivers.transforms import inv_T

COMMAND_PORT = 1337
# research-interface version spoken by each supported franky-control release
CLIENT_VERSIONS = {"2.0.0": 10}
CONNECT_HEADER = struct.Struct("<III")
CONNECT_REQUEST = struct.Struct("<HH")
CONNECT_REPLY = struct.Struct("<BH")
STATUS_INCOMPATIBLE = 1
# a trajectory whose samples stray further than this from the straight start-goal segment is refused [rad]
SEGMENT_TOL_RAD = 0.05
NETWORK_ERRORS = (franky.NetworkException, franky.ProtocolException)
# franky judges a recovery by the state it holds when the robot answers, which can still show the errors
# the recovery cleared (seen with a fresh connection): the state is read again for this long [s]
RECOVERY_STATE_LAG_S = 0.5
# what the operator does next, per fault word
NEXT_STEP = {
    "reflex": "find what the arm hit or which limit it reached and clear it, then recover (cell arm recover)",
    "user stop": "release the user stop, then recover (cell arm recover)",
    "control error": "check the motion and the network to the robot, then recover (cell arm recover)",
    "robot error": "read the errors in Desk, clear their cause, then recover (cell arm recover)",
    "disconnect": "check the network and that FCI is active in Desk, then recover (reconnects)",
}


def client_version() -> int:
    """The research-interface version of the installed franky-control."""
    installed = metadata.version("franky-control")
    if installed not in CLIENT_VERSIONS:
        raise DriverError(f"franky-control {installed} is installed, the cell is built for "
                          f"{', '.join(CLIENT_VERSIONS)}: pip install 'franky-control==2.0.0'",
                          device="arm franka")
    return CLIENT_VERSIONS[installed]


def server_version(host: str, timeout_s: float) -> tuple[bool, int]:
    """Offer the client's version to the robot at ``host``; returns (accepted, the server's version)."""
    # the robot streams its state to the UDP port a client names, so name a real one for the handshake
    with socket.create_connection((host, COMMAND_PORT), timeout=timeout_s) as sock, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.bind((sock.getsockname()[0], 0))
        request = CONNECT_REQUEST.pack(client_version(), udp.getsockname()[1])
        sock.sendall(CONNECT_HEADER.pack(0, 0, CONNECT_HEADER.size + len(request)) + request)
        header = recv_exact(sock, CONNECT_HEADER.size)
        _, _, size = CONNECT_HEADER.unpack(header)
        payload = recv_exact(sock, size - CONNECT_HEADER.size)
    status, version = CONNECT_REPLY.unpack(payload[:CONNECT_REPLY.size])
    return status != STATUS_INCOMPATIBLE, version


def aborted_fault(exc: franky.ControlException) -> str:
    """The fault word for a motion the robot aborted, from libfranka's fixed wording of the reason."""
    text = str(exc)
    if "User Stop" in text:
        return "user stop"
    return "reflex" if "reflex" in text else "control error"


class FrankaArm(HardwareArm):
    """A Franka Panda / FR3 behind its control unit (see the module docstring)."""

    name = "franka"

    def __init__(self, config: FrankaArmConfig, model: RobotModel) -> None:
        if model.name != "panda":
            raise ValueError(f"arm franka: needs the panda model, got {model.name!r}")
        self._config = config
        self._model = model
        self._device = f"arm franka at {config.host}"
        self._claim = ArmClaim("franka", config.host)
        self._robot: franky.Robot | None = None
        self._mode = ArmMode.IDLE
        self._fault: RobotFault | None = None

    # ------------------------------------------------------------------ connection

    def connect(self) -> None:
        if self._robot is not None:
            return
        cfg = self._config
        try:
            accepted, version = server_version(cfg.host, cfg.connect_timeout_s)
        except (OSError, ConnectionError) as exc:
            raise DriverError(f"cannot reach the robot's control port {cfg.host}:{COMMAND_PORT} within "
                              f"{cfg.connect_timeout_s:g} s ({exc}); check the address, that FCI is "
                              "activated in Desk and that the brakes are open", device=self._device) from None
        if not accepted:
            raise DriverError(f"the robot's server speaks research-interface version {version}, this client "
                              f"(franky-control {metadata.version('franky-control')}) speaks "
                              f"{client_version()}: FR3-era firmware is needed, or a franky built "
                              "against the libfranka that matches the robot's system version",
                              device=self._device)
        realtime = (franky.RealtimeConfig.Enforce if cfg.realtime == "enforce"
                    else franky.RealtimeConfig.Ignore)
        self._claim.take()
        try:
            robot = franky.Robot(cfg.host, relative_dynamics_factor=cfg.relative_dynamics_factor,
                                 default_torque_threshold=cfg.torque_threshold_nm,
                                 default_force_threshold=cfg.force_threshold_n, realtime_config=realtime)
            robot.set_load(cfg.payload.mass_kg, list(cfg.payload.cog_m), [0.0] * 9)
        except (franky.IncompatibleVersionException, *NETWORK_ERRORS, franky.RealtimeException,
                franky.CommandException) as exc:
            self._claim.release()
            raise DriverError(f"franky could not connect: {exc}", device=self._device) from None
        self._robot = robot
        self._mode = ArmMode.IDLE
        self._fault = None

    def disconnect(self) -> None:
        """Stop and drop the connection (franky closes it with the Robot object). Safe to call twice."""
        if self._robot is None:
            return
        try:
            if self._fault is None:
                self.stop()
        finally:
            self._robot = None
            self._claim.release()

    @property
    def is_connected(self) -> bool:
        return self._robot is not None

    @property
    def n_joints(self) -> int:
        return 7

    @property
    def model(self) -> RobotModel:
        return self._model

    def _require(self) -> franky.Robot:
        if self._robot is None:
            raise DriverError("not connected (call connect() first)", device=self._device)
        return self._robot

    # ------------------------------------------------------------------ state and faults

    def _fault_error(self, fault: str, what: str, robot: franky.Robot | None = None) -> RobotFault:
        """A fault with the facts: ``what`` happened, the robot's mode and errors (when it answers), and
        the operator's next step."""
        facts = [what.replace("\n", "; ")]
        if robot is not None:
            with contextlib.suppress(*NETWORK_ERRORS):
                st = robot.state
                facts.append(f"robot mode {st.robot_mode.name}")
                if robot.has_errors:
                    facts.append(f"errors {st.current_errors}")
                elif fault != "user stop":
                    facts.append(f"last motion's errors {st.last_motion_errors}")
        facts.append(NEXT_STEP[fault])
        return RobotFault("; ".join(facts), device=self._device, fault=fault)

    def _latch(self, exc: Exception, robot: franky.Robot, what: str) -> RobotFault:
        """Latch what franky raised about a motion as the arm's fault, until ``recover``."""
        if isinstance(exc, franky.ControlException):
            self._fault = self._fault_error(aborted_fault(exc), f"{what}: {exc}", robot)
        elif isinstance(exc, NETWORK_ERRORS):
            self._fault = self._fault_error("disconnect", f"{what}: lost the connection: {exc}")
        else:  # a command the robot refused: its state says why
            faults = self._fault_kinds(robot, robot.state)
            self._fault = self._fault_error(faults[0] if faults else "control error", f"{what}: {exc}", robot)
        return self._fault

    def _poll(self, robot: franky.Robot) -> None:
        """Surface what a running motion raised as a fault."""
        try:
            robot.poll_motion()
        except (franky.ControlException, *NETWORK_ERRORS) as exc:
            self._latch(exc, robot, "the robot stopped the motion")

    def _fault_kinds(self, robot: franky.Robot, state: franky.RobotState) -> tuple[str, ...]:
        """The faults' kinds (keys of ``NEXT_STEP``): the latched one, then what the robot's state says."""
        faults: list[str] = [self._fault.fault] if self._fault is not None else []
        if state.robot_mode == franky.RobotMode.Reflex:
            faults.append("reflex")
        if state.robot_mode == franky.RobotMode.UserStopped:
            faults.append("user stop")
        if robot.has_errors and not faults:
            faults.append("robot error")
        return tuple(dict.fromkeys(faults))

    @staticmethod
    def _described(kinds: tuple[str, ...], robot: franky.Robot, state: franky.RobotState) -> tuple[str, ...]:
        """The faults for people (``ArmState.faults``): a reflex, an error or an aborted motion with the
        robot's error flags (its current errors, else the last motion's): ``reflex: cartesian_reflex``."""
        errors = state.current_errors if robot.has_errors else state.last_motion_errors
        flags = ", ".join(json.loads(str(errors)))
        flagged = ("reflex", "robot error", "control error")
        return tuple(f"{kind}: {flags}" if flags and kind in flagged else kind for kind in kinds)

    def _read(self) -> tuple[franky.Robot, franky.RobotState]:
        robot = self._require()
        self._poll(robot)
        if self._fault is not None and self._fault.fault == "disconnect":
            raise self._fault
        try:
            return robot, robot.state
        except NETWORK_ERRORS as exc:
            raise self._latch(exc, robot, "reading the state") from None

    def state(self) -> ArmState:
        robot, st = self._read()
        T_ee = np.asarray(st.O_T_EE.matrix, dtype=float)
        T_flange = T_ee @ inv_T(np.asarray(st.F_T_EE.matrix, dtype=float))
        twist = st.O_dP_EE_est if st.O_dP_EE_est is not None else st.O_dP_EE_d
        v_ee = np.concatenate([np.asarray(twist.linear), np.asarray(twist.angular)])
        faults = self._described(self._fault_kinds(robot, st), robot, st)
        if self._mode is not ArmMode.IDLE and not robot.is_in_control:
            self._mode = ArmMode.IDLE
        return ArmState(timestamp=st.time.to_sec(),
                        q=np.asarray(st.q, dtype=float), qd=np.asarray(st.dq, dtype=float),
                        T_base_flange=T_flange,
                        v_base_flange=shift_twist(v_ee, T_flange[:3, 3] - T_ee[:3, 3]),
                        mode=ArmMode.FAULT if faults else self._mode, faults=faults)

    def controller_modes(self) -> dict[str, str]:
        robot, st = self._read()
        errors = str(st.current_errors) if robot.has_errors else "none"
        return {"robot mode": st.robot_mode.name, "errors": errors}

    def _refuse_if_faulted(self, what: str) -> franky.Robot:
        robot, st = self._read()
        kinds = self._fault_kinds(robot, st)
        if kinds:
            latched = f" ({self._fault})" if self._fault is not None else ""
            faults = ", ".join(self._described(kinds, robot, st))
            raise self._fault_error(kinds[0], f"{what} refused: {faults}{latched}", robot)
        return robot

    def _move(self, what: str, motion: object) -> None:
        robot = self._refuse_if_faulted(what)
        try:
            robot.move(motion, asynchronous=True)
        except (franky.ControlException, franky.CommandException, *NETWORK_ERRORS) as exc:
            raise self._latch(exc, robot, what) from None

    # ------------------------------------------------------------------ commands

    def _command_twist(self, v_base_flange: Array) -> None:
        cfg = self._config
        v = clamp_twist(checked_vector(v_base_flange, 6, "twist", self._device), cfg.max_linear_mps,
                        cfg.max_angular_rps)
        _, st = self._read()
        T_ee = np.asarray(st.O_T_EE.matrix, dtype=float)
        T_flange = T_ee @ inv_T(np.asarray(st.F_T_EE.matrix, dtype=float))
        v_ee = shift_twist(v, T_ee[:3, 3] - T_flange[:3, 3])
        hold = franky.Duration(max(1, round(cfg.velocity_hold_s * 1000)))
        motion = franky.CartesianVelocityMotion(franky.Twist(v_ee[:3], v_ee[3:]), duration=hold,
                                                relative_dynamics_factor=cfg.relative_dynamics_factor)
        self._move("command_twist()", motion)
        self._mode = ArmMode.VELOCITY

    def _execute_trajectory(self, trajectory: JointTrajectory) -> None:
        _, st = self._read()
        check_trajectory(trajectory, self._model, np.asarray(st.q, dtype=float), self._device)
        q0, q1 = trajectory.q[0], trajectory.q[-1]
        seg = q1 - q0
        length2 = float(seg @ seg)
        s = (np.clip((trajectory.q - q0) @ seg / length2, 0.0, 1.0) if length2 > 0
             else np.zeros(len(trajectory.t)))
        off = float(np.max(np.abs(trajectory.q - (q0 + s[:, None] * seg))))
        if off > SEGMENT_TOL_RAD:
            raise ValueError(f"{self._device}: the trajectory leaves the straight joint segment by "
                             f"{off:.4f} rad; this backend executes rest-to-rest joint segments only")
        motion = franky.JointWaypointMotion([franky.JointWaypoint(q1.tolist())],
                                            relative_dynamics_factor=self._config.relative_dynamics_factor)
        self._move("execute_trajectory()", motion)
        self._mode = ArmMode.TRAJECTORY

    def stop(self) -> None:
        """Decelerate within the relative dynamics factor; a faulted arm has been stopped by the robot."""
        robot = self._require()
        self._poll(robot)
        if self._fault is not None or self._mode is ArmMode.IDLE:
            self._mode = ArmMode.IDLE
            return
        if self._mode is ArmMode.STOPPING:
            return  # a stop motion is under way (franky refuses a stop of the other kind meanwhile)
        rdf = self._config.relative_dynamics_factor
        stop_motion = (franky.CartesianVelocityStopMotion(rdf) if self._mode is ArmMode.VELOCITY
                       else franky.JointStopMotion(rdf))
        self._move("stop()", stop_motion)
        self._mode = ArmMode.STOPPING

    @staticmethod
    def _errors_clear_within(robot: franky.Robot, timeout_s: float) -> bool:
        """Whether the robot's state shows no errors within ``timeout_s`` [s] (read every 10 ms)."""
        deadline = time.monotonic() + timeout_s
        while robot.has_errors:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
        return True

    def recover(self) -> None:
        """Operator action: franky's automatic error recovery; a lost connection is re-opened."""
        robot = self._require()
        if self._fault is not None and self._fault.fault == "disconnect":
            self._robot = None
            try:
                self.connect()
            except DriverError:
                self._robot = robot  # still latched as lost: the operator's next recover tries again
                raise
            return
        try:
            ok = robot.recover_from_errors() or self._errors_clear_within(robot, RECOVERY_STATE_LAG_S)
        except (franky.CommandException, *NETWORK_ERRORS) as exc:
            faults = self._fault_kinds(robot, robot.state) if isinstance(exc, franky.CommandException) else ()
            raise self._fault_error(faults[0] if faults else "disconnect",
                                    f"the automatic error recovery failed: {exc}", robot) from None
        if not ok:
            raise self._fault_error("robot error", "the robot still reports errors after the automatic "
                                    "error recovery", robot)
        self._fault = None
        self._mode = ArmMode.IDLE
