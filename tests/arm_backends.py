"""Arm backends for the tests, each against its real peer: the sim arm on a sim clock, the UR5e backend
against the RTDE controller peer, the Franka backend against franky-sim. Shared by the conformance suite
and the per-backend tests."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.arm.base import Arm, MotionToken
from drivers.arm.config import FrankaArmConfig, SimArmConfig, UR5eArmConfig
from drivers.arm.sim import SimArm
from drivers.clock import SimClock
from drivers.robots import get_robot_model
from tests.loopback import free_loopback
from tests.rtde_peer import ControllerPeer

# the fault the conformance suite injects into franky-sim: a collision reflex
REFLEX = "reflex cartesian_reflex"
PAYLOAD = {"mass_kg": 0.3, "cog_m": [0.0, 0.0, 0.03]}
# The RTDE watchdog for tests that stream commands for a while [Hz]: the test config's 5 Hz one ends the
# control script when the test process stalls for 0.2 s, which a loaded machine does now and then (the
# watchdog doing its job, not the behaviour under test); the watchdog's own tests keep 5 Hz.
STREAMING_WATCHDOG_HZ = 1.0


def ur5e_config(host: str, **overrides: object) -> UR5eArmConfig:
    """The UR5e config the tests use: 125 Hz RTDE (enough for a Python peer on a shared CI machine)."""
    data: dict[str, object] = {
        "type": "ur5e", "host": host, "tcp_offset": [0.0, 0.0, 0.05, 0.0, 0.0, 0.0], "payload": PAYLOAD,
        "max_linear_mps": 0.1, "max_angular_rps": 0.5, "acceleration_mps2": 0.5,
        "stop_deceleration_mps2": 1.0, "rtde_frequency_hz": 125.0, "servo_rate_hz": 125.0,
        "watchdog_min_hz": 5.0, "busy_output": 2, "done_output": 3, "trigger_input": 4,
        "connect_timeout_s": 2.0,
    }
    data.update(overrides)
    return UR5eArmConfig.model_validate(data)


def franka_config(host: str) -> FrankaArmConfig:
    return FrankaArmConfig.model_validate({
        "type": "franka", "host": host, "relative_dynamics_factor": 0.2, "velocity_hold_s": 0.1,
        "max_linear_mps": 0.1, "max_angular_rps": 0.5, "payload": PAYLOAD, "torque_threshold_nm": 20.0,
        "force_threshold_n": 30.0, "realtime": "ignore", "connect_timeout_s": 2.0})


class FrankySim:
    """franky-sim with injectable faults (tests/franky_fault_sim.py) on 127.0.0.N, port 1337, in its own
    process; ``q`` the robot's initial joints [rad] (franky-sim's default pose when None); ``host`` a
    given address (a robot that comes back), else a free one."""

    def __init__(self, q: Sequence[float] | None = None, host: str | None = None) -> None:
        self.host = host or free_loopback([1337], reuse_address=False)
        args = [sys.executable, "-m", "tests.franky_fault_sim", "--hostname", self.host]
        if q is not None:
            args += ["--q", ",".join(map(str, q))]
        self._proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, text=True, cwd=Path(__file__).parent.parent)
        if self._wait_for("Connect to the server") is None:
            raise RuntimeError("franky-sim did not start")

    def _wait_for(self, prefix: str) -> str | None:
        """The next line of the simulator's output that starts with ``prefix`` (None: it ended first)."""
        assert self._proc.stdout is not None
        for line in self._proc.stdout:
            if line.startswith(prefix):
                return line
        return None

    def inject(self, command: str) -> None:
        """A fault command (``reflex FLAG...``, ``user-stop``, ``release``); returns once it is applied."""
        assert self._proc.stdin is not None
        self._proc.stdin.write(command + "\n")
        self._proc.stdin.flush()
        if self._wait_for(f"done {command}") is None:
            raise RuntimeError(f"franky-sim ended before applying {command!r}")

    @property
    def alive(self) -> bool:
        return self._proc.poll() is None

    def kill(self) -> None:
        """The robot vanishes (power cut, cable pulled)."""
        self._proc.kill()
        self._proc.wait()
        for pipe in (self._proc.stdin, self._proc.stdout):
            if pipe is not None:
                pipe.close()


@dataclass
class Backend:
    """One backend under test: the connected arm, its motion token, how time passes, how a fault comes,
    and how long a twist holds without renewal on the arm's clock [s] (``None``: until the next command)."""

    name: str
    arm: Arm
    token: MotionToken
    advance: Callable[[float], None]
    inject_fault: Callable[[], None]
    recoverable: bool
    twist_hold_s: float | None = None

    def wait_until(self, predicate: Callable[[], bool], timeout_s: float = 20.0) -> None:
        """Let time pass until ``predicate()`` holds (a bound on waiting, not a timed assertion)."""
        waited = 0.0
        while not predicate():
            if waited > timeout_s:
                st = self.arm.state()
                raise AssertionError(f"{self.name}: condition not reached within {timeout_s} s (arm "
                                     f"{st.mode.name}, faults {st.faults}, joints {np.round(st.q, 4)}, "
                                     f"joint speeds {np.round(st.qd, 4)})")
            self.advance(0.02)
            waited += 0.02


@contextlib.contextmanager
def sim_backend() -> Iterator[Backend]:
    clock = SimClock()
    arm = SimArm(SimArmConfig(type="sim", model="ur5e"), get_robot_model("ur5e"), clock)

    def advance(seconds: float) -> None:
        for _ in range(max(1, round(seconds / 0.004))):
            clock.sleep(0.004)

    with arm:
        yield Backend("sim", arm, arm.claim_motion(), advance,
                      lambda: arm.inject_fault("protective stop"), recoverable=True)


@contextlib.contextmanager
def ur5e_backend(peer: ControllerPeer, **overrides: object) -> Iterator[Backend]:
    from drivers.arm.ur5e import UR5eArm

    arm = UR5eArm(ur5e_config(peer.host, **overrides), get_robot_model("ur5e"))
    arm.connect()
    try:
        yield Backend("ur5e", arm, arm.claim_motion(), time.sleep, peer.protective_stop, recoverable=True)
    finally:
        arm.disconnect()


@contextlib.contextmanager
def franka_backend(sim: FrankySim) -> Iterator[Backend]:
    from drivers.arm.franka import FrankaArm

    config = franka_config(sim.host)
    arm = FrankaArm(config, get_robot_model("panda"))
    arm.connect()
    try:
        yield Backend("franka", arm, arm.claim_motion(), time.sleep, lambda: sim.inject(REFLEX),
                      recoverable=True, twist_hold_s=config.velocity_hold_s)
    finally:
        if sim.alive:
            arm.disconnect()
