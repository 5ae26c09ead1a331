"""An emulated UR e-series controller that the real ur-rtde client talks to on loopback.

It listens on one address (``127.0.0.N``) on the controller's fixed ports:

- 30004 RTDE: protocol v2 negotiation, controller version, output recipes (a frequency and names) and
  input recipes, ids 1..N per connection; START is answered before the first data package; data packages
  go out at each output recipe's frequency; input data packages write the controller's input table.
- 29999 dashboard: the text commands ur-rtde and the cell use (remote control, PolyScope version, unlock
  protective stop, close safety popup, power on, brake release, robot and safety mode, stop, quit). As a
  real controller, it refuses to unlock a protective stop until ``UNLOCK_AFTER_S`` after it occurred,
  with the controller's answer (``UNLOCK_TOO_SOON``), and answers an unlock it accepts ("Protective stop
  releasing") before the release: the safety mode returns to normal ``RELEASE_S`` later.
- 30003 script: the uploaded program text. A ``def ...: ... end`` program starts "running": the peer
  then behaves as ur-rtde's control script does, through the register handshake: it reads the command
  from ``input_int_register_<off>`` and its arguments from the input int/double registers (``off`` is
  the register offset written into the uploaded script), answers 1 (ready) in
  ``output_int_register_<off>`` when idle, runs a regular command once and answers 2 (done) until the
  command register returns to 0; streaming commands (speedL, speedJ, servoJ, servoL) are taken at once
  and answered with 1. Command 255 ends the program.
- 30099 (peer only, not a UR port): a JSON-line control channel for tests and for people, which injects
  a protective stop, an emergency stop (and its release), a disconnect (every client socket closed),
  digital input changes and pulses timed on the controller's clock, and reports the state and the
  commands received.

Motion: a kinematic UR5e (the project's nominal model) integrated every tick over the wall-clock time
since the previous one (the cycle is 2 ms; a late one integrates what passed, up to ``MAX_STEP_S``):
speedL holds a TCP twist reached with the commanded acceleration, servoJ/servoL follow the target with
their lookahead time as a first-order lag (within joint speed limits), so the arm trails a streamed
trajectory as the controller's servo does, stops decelerate. A protective or emergency stop halts the
arm at once and ends the running program, like the controller. Releasing an emergency stop leaves the
robot powered off (robot mode POWER_OFF, safety mode NORMAL), as a UR does: the e-Series user manual has
the operator power the arm on and release the brakes again after a reset, and the dashboard's ``power on``
and ``brake release`` do that (here at once; a real arm passes through POWER_ON and IDLE before
RUNNING). An uploaded program runs only on a robot running normally (assumption: a UR does
not start a program on a powered-off or stopped robot, which is what ur-rtde's "Failed to start control
script" reports on one); the peer logs its refusal. The RTDE watchdog set by the script
(``set_watchdog``) ends the program when the command register is not refreshed at the set frequency.
The watchdog counts the controller's own time (``cycle_s``): a real controller's cycle never stops, but
this Python process can be descheduled on a loaded machine, and its own stall is not the client's
silence, so a late cycle counts at most ``MAX_WATCHDOG_STEP_S`` towards it.
"""

from __future__ import annotations

import contextlib
import json
import re
import socket
import struct
import threading
import time
import traceback
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from drivers.robots import get_robot_model
from drivers.transforms import inv_T, make_T
from tests.rtde_peer import protocol as proto

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003
CONTROL_PORT = 30099
PORTS = (RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT, CONTROL_PORT)

CONTROLLER_VERSION = (5, 15, 0, 0)
POLYSCOPE_VERSION = "URSoftware 5.15.0.0 (Jan 01 2024)"
SERIAL_NUMBER = "20235500001"

# robot modes and safety modes as RTDE reports them
ROBOT_MODE_POWER_OFF, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 5, 7
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP, SAFETY_ROBOT_EMERGENCY_STOP = 1, 3, 7
# A UR controller unlocks a protective stop only this long after it occurred [s], and answers earlier
# requests with this (the Dashboard Server's documented reply)
UNLOCK_AFTER_S = 5.0
# How long an accepted unlock takes to release the protective stop [s]: an assumption of this peer (the
# dashboard's answer says only that the release has begun), long enough for a client that does not wait
# for the release to act while the controller is still stopped.
RELEASE_S = 0.3
UNLOCK_TOO_SOON = ("Cannot unlock protective stop until 5s after occurrence. Always inspect cause of "
                   "protective stop before unlocking")
ROBOT_MODE_NAMES = {3: "POWER_OFF", 5: "IDLE", 7: "RUNNING"}
SAFETY_MODE_NAMES = {1: "NORMAL", 3: "PROTECTIVE_STOP", 7: "ROBOT_EMERGENCY_STOP"}

# control-script commands (ur-rtde's RobotCommand types) the peer acts on
CMD_SPEEDJ, CMD_SPEEDL, CMD_SERVOJ, CMD_SERVOL = 9, 10, 11, 24
CMD_SPEED_STOP, CMD_SERVO_STOP, CMD_SET_PAYLOAD, CMD_SET_TCP = 15, 16, 17, 29
CMD_PROTECTIVE_STOP, CMD_STOPL, CMD_STOPJ, CMD_SET_WATCHDOG, CMD_STOP_SCRIPT = 31, 33, 34, 35, 255
STREAMING = {CMD_SPEEDJ, CMD_SPEEDL, CMD_SERVOJ, CMD_SERVOL, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}
COMMAND_NAMES = {CMD_SPEEDJ: "speedJ", CMD_SPEEDL: "speedL", CMD_SERVOJ: "servoJ", CMD_SERVOL: "servoL",
                 CMD_SPEED_STOP: "speedStop", CMD_SERVO_STOP: "servoStop", CMD_SET_PAYLOAD: "setPayload",
                 CMD_SET_TCP: "setTcp", CMD_PROTECTIVE_STOP: "triggerProtectiveStop", CMD_STOPL: "stopL",
                 CMD_STOPJ: "stopJ", CMD_SET_WATCHDOG: "setWatchdog", CMD_STOP_SCRIPT: "stopScript"}

TICK_S = 0.002  # the controller's 500 Hz cycle
# A late cycle integrates the time that really passed (motion keeps wall-clock pace on a loaded machine,
# as a real controller's does), but at most this much [s], so that a long stall does not teleport the arm.
MAX_STEP_S = 0.25
# The most a late cycle counts towards the RTDE watchdog [s]: ten cycles. Longer gaps between cycles are
# the peer's own stalls (up to 117 ms seen in a loaded test run, where the ticks are otherwise 2-20 ms).
MAX_WATCHDOG_STEP_S = 10 * TICK_S
MAX_RECORDS = 5000
HOME_Q = [0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0]


def pose_to_T(pose: list[float] | np.ndarray) -> np.ndarray:
    """UR pose (x, y, z, rx, ry, rz) [m, axis-angle rad] to 4x4."""
    p = np.asarray(pose, dtype=float)
    return make_T(Rotation.from_rotvec(p[3:]).as_matrix(), p[:3])


def T_to_pose(T: np.ndarray) -> list[float]:
    return [*T[:3, 3].tolist(), *Rotation.from_matrix(T[:3, :3]).as_rotvec().tolist()]


@dataclass
class Record:
    """A command the emulated control script received."""

    t: float
    cmd: int
    name: str
    doubles: list[float]
    ints: list[int]


@dataclass
class Controller:
    """The controller's state, shared by every connection thread (guarded by ``lock``)."""

    remote_control: bool = True
    q: np.ndarray = field(default_factory=lambda: np.array(HOME_Q))
    lock: threading.RLock = field(default_factory=threading.RLock)

    def __post_init__(self) -> None:
        self.model = get_robot_model("ur5e")
        self.t0 = time.monotonic()
        self.qd = np.zeros(6)
        self.twist = np.zeros(6)  # current TCP twist under speedL, base frame
        self.twist_target = np.zeros(6)
        self.accel = 0.5
        self.q_target: np.ndarray | None = None
        self.motion = "idle"  # idle | speedl | speedj | servo | stopping
        self.servo_lookahead = 0.1  # the servo's time constant [s]
        self.T_flange_tcp = np.eye(4)
        self.payload_kg = 0.0
        self.payload_cog = [0.0, 0.0, 0.0]
        self.inputs: dict[str, Any] = {}
        self.input_updated: dict[str, float] = {}  # controller time of each input's last write [s]
        self.cycle_s = 0.0  # the controller's time as its cycles count it (module docstring) [s]
        self.digital_in = 0
        self.pulse_ends: dict[int, float] = {}  # input index -> when its pulse falls [s, now()'s clock]
        self.digital_out = 0
        self.robot_mode = ROBOT_MODE_RUNNING
        self.safety_mode = SAFETY_NORMAL
        self.estop_pressed = False
        self.protective_stop_at = 0.0  # when the last protective stop occurred [s]
        self.release_at: float | None = None  # when an accepted unlock releases the stop [s]
        self.program_running = False
        self.reg_int_offset = 0
        self.reg_float_offset = 0
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.executing = False
        self.watchdog_hz = 0.0
        self.records: list[Record] = []
        self.counts: dict[str, int] = {}
        self.events: list[str] = []
        self.scripts_uploaded = 0
        self.connections: list[socket.socket] = []
        self.dropped_at: float | None = None  # when every client connection was last dropped [s]

    # ------------------------------------------------------------------ helpers

    def now(self) -> float:
        return time.monotonic() - self.t0

    def event(self, text: str) -> None:
        self.events.append(f"{self.now():.3f} {text}")

    def in_int(self, i: int) -> int:
        return int(self.inputs.get(f"input_int_register_{i + self.reg_int_offset}", 0))

    def in_double(self, i: int) -> float:
        return float(self.inputs.get(f"input_double_register_{i + self.reg_float_offset}", 0.0))

    def doubles(self, n: int) -> list[float]:
        return [self.in_double(i) for i in range(n)]

    def tcp_T(self) -> np.ndarray:
        return self.model.fk(self.q) @ self.T_flange_tcp

    def faulted(self) -> bool:
        return self.safety_mode != SAFETY_NORMAL or self.robot_mode != ROBOT_MODE_RUNNING

    def halt(self) -> None:
        self.qd = np.zeros(6)
        self.twist = np.zeros(6)
        self.twist_target = np.zeros(6)
        self.q_target = None
        self.motion = "idle"

    def end_program(self, why: str) -> None:
        if self.program_running:
            self.event(f"program ended: {why}")
        self.program_running = False
        self.executing = False
        self.watchdog_hz = 0.0
        self.out_int[self.reg_int_offset] = 0

    # ------------------------------------------------------------------ inputs and the script

    def write_inputs(self, names: list[str], values: list[object]) -> None:
        with self.lock:
            for name, value in zip(names, values, strict=True):
                self.inputs[name] = value
                self.input_updated[name] = self.cycle_s
            if f"input_int_register_{self.reg_int_offset}" in names and self.in_int(0) != 0:
                self._record(self.in_int(0))
            if "standard_digital_output_mask" in self.inputs and "standard_digital_output" in names:
                mask = int(self.inputs["standard_digital_output_mask"])
                value = int(self.inputs["standard_digital_output"])
                self.digital_out = (self.digital_out & ~mask) | (value & mask)

    def start_program(self, text: str) -> None:
        with self.lock:
            self.scripts_uploaded += 1
            self.reg_int_offset = _script_offset(text, "reg_offset_int")
            self.reg_float_offset = _script_offset(text, "reg_offset_float")
            if self.faulted():
                self.event("program refused: the robot is not running normally")
                return
            self.program_running = True
            self.executing = False
            self.out_int[self.reg_int_offset] = 1
            self.event(f"program started (register offsets {self.reg_int_offset}/{self.reg_float_offset})")

    def _record(self, cmd: int) -> None:
        """Keep a command package as it arrived (streaming commands are re-read every tick, not re-kept)."""
        name = COMMAND_NAMES.get(cmd, f"cmd{cmd}")
        self.counts[name] = self.counts.get(name, 0) + 1
        if len(self.records) < MAX_RECORDS:
            ints = [self.in_int(i) for i in range(8)]
            self.records.append(Record(self.now(), cmd, name, self.doubles(12), ints))

    def _process(self, cmd: int) -> None:
        """Run one command as the control script's ``process_cmd`` would."""
        d = self.doubles(12)
        if cmd == CMD_SPEEDL:
            self.twist_target = np.array(d[:6])
            self.accel = max(d[6], 1e-3)
            self.motion = "speedl"
        elif cmd == CMD_SPEEDJ:
            self.qd = np.array(d[:6])
            self.motion = "speedj"
        elif cmd == CMD_SERVOJ:
            self.q_target = np.array(d[:6])
            self.servo_lookahead = d[9]
            self.motion = "servo"
        elif cmd == CMD_SERVOL:
            T_flange = pose_to_T(d[:6]) @ inv_T(self.T_flange_tcp)
            self.q_target = self.model.ik_pose(T_flange, self.q)
            self.servo_lookahead = d[9]
            self.motion = "servo"
        elif cmd in (CMD_SPEED_STOP, CMD_SERVO_STOP, CMD_STOPL, CMD_STOPJ):
            self.twist_target = np.zeros(6)
            self.accel = max(d[0], 1e-3)
            self.q_target = None
            self.motion = "stopping"
        elif cmd == CMD_SET_TCP:
            self.T_flange_tcp = pose_to_T(d[:6])
        elif cmd == CMD_SET_PAYLOAD:
            self.payload_kg, self.payload_cog = d[0], d[1:4]
        elif cmd == CMD_SET_WATCHDOG:
            self.watchdog_hz = d[0]
            self.event(f"watchdog set to {d[0]:g} Hz")
        elif cmd == CMD_PROTECTIVE_STOP:
            self.protective_stop()
        elif cmd == CMD_STOP_SCRIPT:
            self.halt()
            self.end_program("stop script command")

    def _script_tick(self) -> None:
        if not self.program_running:
            return
        reg = f"input_int_register_{self.reg_int_offset}"
        silent_s = self.cycle_s - self.input_updated.get(reg, 0.0)
        if self.watchdog_hz > 0.0 and silent_s > 1.0 / self.watchdog_hz:
            self.halt()
            self.end_program(f"RTDE watchdog expired: no command for {silent_s:.3f} s of controller time "
                             f"at {self.watchdog_hz:g} Hz")
            return
        cmd = self.in_int(0)
        out = self.reg_int_offset
        if cmd in STREAMING:
            self._process(cmd)
            self.out_int[out] = 1
        elif cmd == 0:
            self.executing = False
            self.out_int[out] = 1
        elif not self.executing:
            self.executing = True
            self._process(cmd)
            if self.program_running:
                self.out_int[out] = 2

    # ------------------------------------------------------------------ motion

    def _step_motion(self, dt: float) -> None:
        m = self.model
        if self.faulted():
            self.halt()
            return
        if self.motion in ("speedl", "stopping") and self.q_target is None:
            dv = self.twist_target - self.twist
            norm = float(np.linalg.norm(dv))
            step = self.accel * dt
            self.twist = self.twist_target.copy() if norm <= step else self.twist + dv * (step / norm)
            if self.motion == "stopping" and not np.any(self.twist):
                self.motion = "idle"
            # the TCP twist is the flange twist plus the lever of the TCP offset
            T_f = m.fk(self.q)
            lever = (T_f @ self.T_flange_tcp)[:3, 3] - T_f[:3, 3]
            v_flange = self.twist.copy()
            v_flange[:3] -= np.cross(self.twist[3:], lever)
            self.qd = m.ik_velocity(self.q, v_flange, dt)
        elif self.motion == "servo" and self.q_target is not None:
            err = self.q_target - self.q
            self.qd = np.clip(err / max(self.servo_lookahead, dt), -m.qd_max, m.qd_max)
        elif self.motion == "stopping":
            self.q_target = None
            self.qd = np.zeros(6)
            self.motion = "idle"
        elif self.motion != "speedj":
            self.qd = np.zeros(6)
        self.q = np.clip(self.q + self.qd * dt, m.q_min, m.q_max)

    def tick(self, dt: float) -> None:
        with self.lock:
            self._end_pulses()
            self.cycle_s += min(dt, MAX_WATCHDOG_STEP_S)
            if self.release_at is not None and self.now() >= self.release_at:
                self.release_at = None
                self.safety_mode = SAFETY_NORMAL
                self.event("protective stop unlocked (dashboard)")
            self._script_tick()
            self._step_motion(dt)

    # ------------------------------------------------------------------ injected events

    def protective_stop(self) -> None:
        with self.lock:
            self.safety_mode = SAFETY_PROTECTIVE_STOP
            self.protective_stop_at = self.now()
            self.release_at = None
            self.halt()
            self.end_program("protective stop")
            self.event("protective stop")

    def emergency_stop(self) -> None:
        with self.lock:
            self.safety_mode = SAFETY_ROBOT_EMERGENCY_STOP
            self.release_at = None
            self.robot_mode = ROBOT_MODE_POWER_OFF
            self.estop_pressed = True
            self.halt()
            self.end_program("emergency stop")
            self.event("emergency stop pressed")

    def release_emergency_stop(self) -> None:
        with self.lock:
            self.estop_pressed = False
            self.safety_mode = SAFETY_NORMAL
            self.event("emergency stop released (robot powered off)")

    def set_digital_input(self, index: int, value: bool) -> None:
        with self.lock:
            self.pulse_ends.pop(index, None)
            self._set_input(index, value)

    def pulse_digital_input(self, index: int, duration_s: float) -> float:
        """Raise input ``index`` now and let it fall ``duration_s`` later, on this controller's clock (the
        RTDE ``timestamp``, ``now()``): a test process descheduled meanwhile does not stretch the pulse.
        Returns when it falls [s, that clock]."""
        with self.lock:
            self._set_input(index, True)
            self.pulse_ends[index] = self.now() + duration_s
            return self.pulse_ends[index]

    def _set_input(self, index: int, value: bool) -> None:
        bit = 1 << index
        self.digital_in = (self.digital_in | bit) if value else (self.digital_in & ~bit)

    def _end_pulses(self) -> None:
        """Let each pulse whose time is up fall (with the lock held): before every cycle and every data
        package, so that no package stamped after a pulse's end shows it high."""
        now = self.now()
        for index, end in list(self.pulse_ends.items()):
            if now >= end:
                del self.pulse_ends[index]
                self._set_input(index, False)

    # ------------------------------------------------------------------ outputs

    def output_values(self, names: list[str]) -> list[object]:
        with self.lock:
            self._end_pulses()
            T = self.tcp_T()
            J = self.model.jacobian(self.q)
            v_flange = J @ self.qd
            lever = T[:3, 3] - self.model.fk(self.q)[:3, 3]
            v_tcp = v_flange.copy()
            v_tcp[:3] += np.cross(v_flange[3:], lever)
            safety_bits = {SAFETY_NORMAL: 1, SAFETY_PROTECTIVE_STOP: (1 << 2) | (1 << 10),
                           SAFETY_ROBOT_EMERGENCY_STOP: (1 << 6) | (1 << 7) | (1 << 10)}[self.safety_mode]
            powered = 1 if self.robot_mode >= ROBOT_MODE_IDLE else 0
            status_bits = powered | (2 if self.program_running else 0)
            known: dict[str, object] = {
                "timestamp": self.now(), "actual_q": self.q.tolist(), "target_q": self.q.tolist(),
                "actual_qd": self.qd.tolist(), "target_qd": self.qd.tolist(),
                "actual_TCP_pose": T_to_pose(T), "target_TCP_pose": T_to_pose(T),
                "actual_TCP_speed": v_tcp.tolist(), "target_TCP_speed": v_tcp.tolist(),
                "robot_mode": self.robot_mode, "safety_mode": self.safety_mode,
                "safety_status": self.safety_mode, "safety_status_bits": safety_bits,
                "robot_status_bits": status_bits, "runtime_state": 2 if self.program_running else 1,
                "actual_digital_input_bits": self.digital_in, "actual_digital_output_bits": self.digital_out,
                "speed_scaling": 1.0, "target_speed_fraction": 1.0, "payload": self.payload_kg,
                "payload_cog": list(self.payload_cog), "joint_mode": [253] * 6,
            }
            out: list[object] = []
            for name in names:
                if name in known:
                    out.append(known[name])
                elif name.startswith("output_int_register_"):
                    out.append(self.out_int[int(name.rsplit("_", 1)[1])])
                elif name.startswith("output_double_register_"):
                    out.append(self.out_double[int(name.rsplit("_", 1)[1])])
                elif name.startswith("input_"):
                    out.append(self.inputs.get(name, 0))
                else:
                    out.append(_zero(proto.variable_type(name, "output")))
            return out

    def report(self) -> dict[str, Any]:
        with self.lock:
            return {
                "q": self.q.tolist(), "qd": self.qd.tolist(), "tcp_pose": T_to_pose(self.tcp_T()),
                "flange_pose": T_to_pose(self.model.fk(self.q)), "tcp_offset": T_to_pose(self.T_flange_tcp),
                "payload_kg": self.payload_kg, "payload_cog": list(self.payload_cog),
                "motion": self.motion, "twist": self.twist.tolist(),
                "robot_mode": ROBOT_MODE_NAMES[self.robot_mode],
                "safety_mode": SAFETY_MODE_NAMES[self.safety_mode], "program_running": self.program_running,
                "watchdog_hz": self.watchdog_hz, "scripts_uploaded": self.scripts_uploaded,
                "digital_in": self.digital_in, "digital_out": self.digital_out,
                "counts": dict(self.counts), "events": list(self.events),
                "connections": len(self.connections), "dropped_at": self.dropped_at,
            }


def _script_offset(text: str, name: str) -> int:
    """The register offset ur-rtde wrote into the uploaded script. ur-rtde 1.6.5 writes the number after
    the template's trailing comment, i.e. at the start of the next line, so both places are accepted."""
    m = re.search(rf"global {name}\s*=\s*(?:#[^\n]*\n)?\s*(\d+)", text)
    if m is None:
        raise ValueError(f"uploaded script sets no {name}")
    return int(m.group(1))


def _zero(rtde_type: str) -> object:
    code = proto.TYPE_CODES[rtde_type]
    if code[0].isdigit():
        return [0.0 if code[-1] == "d" else 0] * int(code[0])
    return 0.0 if code == "d" else (False if code == "?" else 0)


# ---------------------------------------------------------------------- connections


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    data = bytearray()
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("client closed the connection")
        data.extend(chunk)
    return bytes(data)


@dataclass
class _OutputRecipe:
    names: list[str]
    types: list[str]
    period_s: float
    next_t: float = 0.0


class RTDESession:
    """One RTDE client connection: recipes, START/PAUSE, data both ways.

    Output and input recipes are numbered 1..N each, per connection: ur-rtde's control interface sends
    its commands with input recipe ids counted from 1 after its one output recipe."""

    def __init__(self, ctl: Controller, sock: socket.socket) -> None:
        self.ctl = ctl
        self.sock = sock
        self.send_lock = threading.Lock()
        self.outputs: dict[int, _OutputRecipe] = {}
        self.inputs: dict[int, tuple[list[str], list[str]]] = {}
        self.started = False
        # set when the controller drops the connection: what was read from it but not yet taken is
        # discarded, as a controller that closed a connection takes nothing more from it
        self.dropped = False

    def send(self, kind: int, payload: bytes = b"") -> None:
        with self.send_lock:
            self.sock.sendall(proto.message(kind, payload))

    def serve(self) -> None:
        while True:
            size, kind = proto.HEADER.unpack(_recv_exact(self.sock, proto.HEADER.size))
            payload = _recv_exact(self.sock, size - proto.HEADER.size)
            self.handle(kind, payload)

    def handle(self, kind: int, payload: bytes) -> None:
        if kind == proto.REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            self.send(kind, struct.pack(">B", 1 if version in (1, 2) else 0))
        elif kind == proto.GET_URCONTROL_VERSION:
            self.send(kind, struct.pack(">IIII", *CONTROLLER_VERSION))
        elif kind == proto.SETUP_OUTPUTS:
            (frequency,) = struct.unpack(">d", payload[:8])
            names = [n for n in payload[8:].decode().split(",") if n]
            types = [proto.variable_type(n, "output") for n in names]
            rid = len(self.outputs) + 1
            if "NOT_FOUND" not in types:
                self.outputs[rid] = _OutputRecipe(names, types, 1.0 / max(min(frequency, 500.0), 1.0))
            self.send(kind, struct.pack(">B", rid) + ",".join(types).encode())
        elif kind == proto.SETUP_INPUTS:
            names = [n for n in payload.decode().split(",") if n]
            types = [proto.variable_type(n, "input") for n in names]
            rid = len(self.inputs) + 1
            if "NOT_FOUND" not in types:
                self.inputs[rid] = (names, types)
            self.send(kind, struct.pack(">B", rid) + ",".join(types).encode())
        elif kind == proto.START:
            self.send(kind, struct.pack(">B", 1))
            self.started = True
        elif kind == proto.PAUSE:
            self.started = False
            self.send(kind, struct.pack(">B", 1))
        elif kind == proto.DATA_PACKAGE:
            rid = payload[0]
            if rid in self.inputs:
                names, types = self.inputs[rid]
                flat = proto.recipe_struct(types).unpack(payload[1:])
                with self.ctl.lock:
                    if not self.dropped:
                        self.ctl.write_inputs(names, proto.group(types, flat))

    def publish(self, t: float) -> None:
        """Send the data packages that are due at time ``t``."""
        if not self.started:
            return
        for rid, recipe in self.outputs.items():
            if t + 1e-6 < recipe.next_t:
                continue
            recipe.next_t = max(recipe.next_t + recipe.period_s, t)
            values = proto.flatten(self.ctl.output_values(recipe.names))
            data = proto.recipe_struct(recipe.types).pack(*values)
            self.send(proto.DATA_PACKAGE, struct.pack(">B", rid) + data)


def _dashboard_reply(ctl: Controller, line: str) -> str | None:
    """The dashboard server's answer to one command line, or ``None`` to close the connection."""
    cmd = line.strip()
    low = cmd.lower()
    with ctl.lock:
        if low == "quit":
            return None
        if low == "is in remote control":
            return "true" if ctl.remote_control else "false"
        if low == "polyscopeversion":
            return POLYSCOPE_VERSION
        if low == "get serial number":
            return SERIAL_NUMBER
        if low == "get robot model":
            return "UR5"
        if low == "robotmode":
            return f"Robotmode: {ROBOT_MODE_NAMES[ctl.robot_mode]}"
        if low == "safetystatus" or low == "safetymode":
            return f"Safetystatus: {SAFETY_MODE_NAMES[ctl.safety_mode]}"
        if low == "running":
            return f"Program running: {'true' if ctl.program_running else 'false'}"
        if low == "programstate":
            return "PLAYING rtde_control" if ctl.program_running else "STOPPED <unnamed>"
        if low == "close safety popup":
            return "closing safety popup"
        if low == "unlock protective stop":
            if ctl.safety_mode == SAFETY_PROTECTIVE_STOP:
                if ctl.now() - ctl.protective_stop_at < UNLOCK_AFTER_S:
                    return UNLOCK_TOO_SOON
                if ctl.release_at is None:
                    ctl.release_at = ctl.now() + RELEASE_S
            return "Protective stop releasing"
        if low == "power on":
            if ctl.estop_pressed:
                return "Cannot power on: emergency stop pressed"
            if ctl.robot_mode == ROBOT_MODE_POWER_OFF:
                ctl.robot_mode = ROBOT_MODE_IDLE
            return "Powering on"
        if low == "brake release":
            if ctl.robot_mode == ROBOT_MODE_IDLE:
                ctl.robot_mode = ROBOT_MODE_RUNNING
            return "Brake releasing"
        if low == "stop":
            ctl.halt()
            ctl.end_program("dashboard stop")
            return "Stopped"
    return f"could not understand: '{cmd}'"


class PeerServer:
    """The listening sockets, the 500 Hz controller cycle, and the connection threads."""

    def __init__(self, host: str, ctl: Controller) -> None:
        self.host = host
        self.ctl = ctl
        self.sessions: list[RTDESession] = []
        self.stop_event = threading.Event()
        self.listeners: dict[int, socket.socket] = {}
        for port in PORTS:
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, port))
            s.listen(8)
            self.listeners[port] = s

    def run(self) -> None:
        handlers = {RTDE_PORT: self._rtde, DASHBOARD_PORT: self._dashboard, SCRIPT_PORT: self._script,
                    CONTROL_PORT: self._control}
        for port, handler in handlers.items():
            threading.Thread(target=self._accept, args=(self.listeners[port], handler), daemon=True).start()
        next_t = last = time.monotonic()
        while not self.stop_event.is_set():
            now = time.monotonic()
            self.ctl.tick(min(max(now - last, 1e-6), MAX_STEP_S))
            last = now
            t = self.ctl.now()
            for session in list(self.sessions):
                try:
                    session.publish(t)
                except OSError:
                    self._forget(session)
            next_t += TICK_S
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_t = time.monotonic()

    def _forget(self, session: RTDESession) -> None:
        if session in self.sessions:
            self.sessions.remove(session)

    def _accept(self, listener: socket.socket, handler: Any) -> None:
        while not self.stop_event.is_set():
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            threading.Thread(target=self._guarded, args=(handler, conn), daemon=True).start()

    def _guarded(self, handler: Any, conn: socket.socket) -> None:
        with self.ctl.lock:
            self.ctl.connections.append(conn)
        try:
            handler(conn)
        except (OSError, ConnectionError):
            pass  # the client went away, or a disconnect was injected
        except Exception:
            traceback.print_exc()  # a peer bug or a malformed message: show it, drop the connection
        finally:
            with self.ctl.lock:
                if conn in self.ctl.connections:
                    self.ctl.connections.remove(conn)
            conn.close()

    def _rtde(self, conn: socket.socket) -> None:
        session = RTDESession(self.ctl, conn)
        self.sessions.append(session)
        try:
            session.serve()
        finally:
            self._forget(session)

    def _dashboard(self, conn: socket.socket) -> None:
        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        buffer = b""
        while True:
            chunk = conn.recv(4096)
            if not chunk:
                return
            buffer += chunk
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                reply = _dashboard_reply(self.ctl, line.decode(errors="replace"))
                if reply is None:
                    conn.sendall(b"Disconnected\n")
                    return
                conn.sendall(reply.encode() + b"\n")

    def _script(self, conn: socket.socket) -> None:
        buffer = ""
        while True:
            chunk = conn.recv(65536)
            if not chunk:
                return
            buffer += chunk.decode(errors="replace")
            stripped = buffer.rstrip()
            if stripped.startswith("def ") and stripped.endswith("\nend"):
                self.ctl.start_program(buffer)
                buffer = ""

    def _control(self, conn: socket.socket) -> None:
        reader = conn.makefile("r")
        for line in reader:
            request = json.loads(line)
            conn.sendall((json.dumps(self._control_reply(request)) + "\n").encode())

    def _control_reply(self, req: dict[str, Any]) -> dict[str, Any]:
        op = req.get("op")
        ctl = self.ctl
        if op == "state":
            return ctl.report()
        if op == "records":
            with ctl.lock:
                return {"records": [r.__dict__ for r in ctl.records]}
        if op == "protective_stop":
            ctl.protective_stop()
        elif op == "emergency_stop":
            ctl.emergency_stop()
        elif op == "release_emergency_stop":
            ctl.release_emergency_stop()
        elif op == "digital_input":
            ctl.set_digital_input(int(req["index"]), bool(req["value"]))
        elif op == "digital_pulse":
            ends_s = ctl.pulse_digital_input(int(req["index"]), float(req["duration_s"]))
            return {"ok": True, "ends_s": ends_s}
        elif op == "remote_control":
            with ctl.lock:
                ctl.remote_control = bool(req["value"])
        elif op == "disconnect":
            self.drop_clients()
        elif op == "shutdown":
            self.shutdown()
        else:
            return {"error": f"unknown op {op!r}"}
        return {"ok": True}

    def drop_clients(self) -> None:
        """Close every client socket (RTDE, dashboard, script), as a controller that reboots would."""
        with self.ctl.lock:
            self.ctl.event("disconnect: every client connection closed")
            self.ctl.dropped_at = self.ctl.now()
            self.ctl.halt()
            self.ctl.end_program("clients disconnected")
            for session in self.sessions:
                session.dropped = True
            for conn in list(self.ctl.connections):
                if conn.getsockname()[1] == CONTROL_PORT:
                    continue
                with contextlib.suppress(OSError):  # the client may have closed it already
                    conn.shutdown(socket.SHUT_RDWR)

    def shutdown(self) -> None:
        self.stop_event.set()
        for s in self.listeners.values():
            s.close()
