"""``cell arm``: commissioning commands for a cell's arm.

``status`` connects, prints the connection, the TCP pose (translation in metres, rotation as roll-pitch-
yaw in degrees, base frame), the joints, the modes and any fault in words, and disconnects.
``recover`` is the operator's action after a stop (see :meth:`drivers.arm.base.Arm.recover`).
``jog`` makes one small guarded move: a twist along or about a base-frame axis streamed through the cell's
motion guard (its speed, acceleration and joint limits, barrier planes, workspace and collision checks) at
the cell's control rate on the wall clock, ramped down to rest, then the status.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console
from scipy.spatial.transform import Rotation

from cell.cli.commands import command_group
from cell.cli.signals import interrupting
from cell.config import load_config
from cell.config.models import CellConfig
from cell.config.placeholders import require_arm_measured
from cell.safety.guard import MotionGuard
from drivers.arm.base import Arm
from drivers.arm.config import UR5eArmConfig
from drivers.arm.hardware import Array, HardwareArm
from drivers.arm.ur5e import UR5eArm
from drivers.clock import WallClock
from drivers.errors import CellError, DriverError, RobotFault, SafetyStop
from drivers.factory import make_arm
from drivers.robots import get_robot_model

arm_app = command_group(help="Commission a cell's arm: status, recovery, small guarded jog moves.",
                        no_args_is_help=True)
console = Console(soft_wrap=True)
err_console = Console(stderr=True)

AXES = {"x": 0, "y": 1, "z": 2, "rx": 3, "ry": 4, "rz": 5}
JOG_SPEED_FRACTION = 0.2  # a jog moves at this share of the cell's TCP limits
JOG_MAX_DISTANCE_M = 0.05  # the longest linear jog [m]
JOG_MAX_ANGLE_RAD = 0.2  # the largest rotation jog [rad]
# Within this much of the target [m, rad] a jog ends; the last stretch, covered at full speed in this
# time [s], is approached with a speed proportional to what remains.
JOG_TOLERANCE_M = 2e-4
JOG_TOLERANCE_RAD = 1e-3
JOG_APPROACH_S = 0.25
JOG_EXTRA_TIME_S = 3.0  # beyond the time at full speed, a jog may take this long [s], and as long to rest
REST_QD_RAD_S = 1e-3  # the arm is at rest when every joint is slower than this [rad/s]


@contextlib.contextmanager
def _connected_arm(config: Path, *, read_only: bool = False) -> Iterator[tuple[CellConfig, Arm]]:
    """The cell file's hardware arm, connected (a UR5e for reading only with ``read_only``), disconnected at
    the end; refused while the file's ``arm`` values are still marked ``# MEASURE:`` (its address would be
    the template's example); any ``CellError`` becomes a one-line error and exit code 1."""
    try:
        cfg = load_config(config)
        if cfg.arm.type == "sim":
            raise DriverError("commissioning commands are for hardware arms (arm.type ur5e or franka)",
                              device="arm sim")
        require_arm_measured(config, cfg.mode)
        model = get_robot_model(cfg.arm.model)
        arm = UR5eArm(cfg.arm, model, read_only=True) if read_only and isinstance(cfg.arm, UR5eArmConfig) \
            else make_arm(cfg.arm, model, None)
        arm.connect()
        try:
            yield cfg, arm
        finally:
            arm.disconnect()
    except CellError as exc:
        err_console.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(code=1) from None


def _print(text: str) -> None:
    console.print(text, markup=False, highlight=False)


def _print_status(arm: Arm) -> None:
    for line in _status_lines(arm):
        _print(line)


def _status_lines(arm: Arm) -> list[str]:
    lines = [f"arm {arm.name}: connected"]
    try:
        st = arm.state()
    except RobotFault as exc:
        return [*lines, f"fault: {exc.fault} ({exc})"]
    T_tcp = st.T_base_flange @ getattr(arm, "T_flange_tcp", np.eye(4))
    rpy = np.rad2deg(Rotation.from_matrix(T_tcp[:3, :3]).as_euler("xyz"))
    lines.append("tcp pose: " + " ".join(f"{a} {v:+.4f} m" for a, v in zip("xyz", T_tcp[:3, 3], strict=True))
                 + "  rpy " + " ".join(f"{v:+.1f}" for v in rpy) + " deg")
    lines.append("joints: " + " ".join(f"{q:+.4f}" for q in st.q) + " rad")
    modes = {"mode": st.mode.value}
    if isinstance(arm, HardwareArm):
        modes.update(arm.controller_modes())
    lines.append("; ".join(f"{k} {v}" for k, v in modes.items()))
    lines.append(f"faults: {', '.join(st.faults) if st.faults else 'none'}")
    return lines


@arm_app.command("status")
def status(config: Annotated[Path, typer.Option(help="cell file")]) -> None:
    """Connect, print pose, joints, modes and faults, disconnect.

    A UR5e is only read (RTDE and the dashboard): this works beside a running job, and starts no control
    script. A Franka takes one client: not while a job runs."""
    with _connected_arm(config, read_only=True) as (_, arm):
        _print_status(arm)


@arm_app.command("recover")
def recover(config: Annotated[Path, typer.Option(help="cell file")]) -> None:
    """Clear the arm's fault, once the cause of the stop is found and cleared.

    UR: close the safety popup, unlock the protective stop (the controller allows it from 5 s after the
    stop), power on, release the brakes, restart the control script; Franka: automatic error recovery.
    Then print the status. An emergency stop must be released on the robot first."""
    with _connected_arm(config) as (_, arm):
        arm.recover()
        _print_status(arm)


def _progress(T_start: Array, T_now: Array, axis: int) -> float:
    """How far the flange has moved from ``T_start`` to ``T_now`` (4x4, base frame) along base axis ``axis``
    (0-2, [m]) or turned about it (3-5, [rad])."""
    if axis < 3:
        return float(T_now[axis, 3] - T_start[axis, 3])
    return float(Rotation.from_matrix(T_now[:3, :3] @ T_start[:3, :3].T).as_rotvec()[axis - 3])


def _jog(guard: MotionGuard, clock: WallClock, axis: int, distance: float, speed: float,
         period_s: float) -> None:
    """Move the flange by ``distance`` [m, or rad for axes 3-5] along or about base axis ``axis`` through
    ``guard``, at most at ``speed`` [m/s or rad/s], ticking once per control period ``period_s`` [s] on
    the wall clock; then ramp down, wait for the arm to report rest and end the motion.

    The jog closes the loop on the pose the arm reports: the commanded speed is ``speed`` until the
    remaining distance is ``speed * JOG_APPROACH_S``, then proportional to it (backwards after an
    overshoot), until the arm is within the tolerance and nearly still, so it settles on the target whatever
    the loop's or the controller's delays (the guard's ramps smooth every change). A jog
    that does not get there in time (e.g. slowed or blocked by a barrier plane or a joint margin) is
    stopped and raises ``SafetyStop``; so does any fault or refusal, after the guard stopped the arm.
    """
    tolerance = JOG_TOLERANCE_RAD if axis >= 3 else JOG_TOLERANCE_M
    T_start = guard.state().T_base_flange
    give_up = clock.now() + abs(distance) / speed + JOG_EXTRA_TIME_S
    next_tick = clock.now()
    twist = np.zeros(6)
    while True:
        state = guard.state()
        remaining = distance - _progress(T_start, state.T_base_flange, axis)
        # there and (nearly) still: an arm that lags behind the commands may still be coasting past it
        if abs(remaining) <= tolerance and abs(state.v_base_flange[axis]) <= tolerance / JOG_APPROACH_S:
            break
        if clock.now() > give_up:
            guard.stop("jog: target not reached in time")
            nominal = abs(distance) / speed
            raise SafetyStop(f"jog: {abs(remaining):.4f} short of the target after {nominal:.1f} s + "
                             f"{JOG_EXTRA_TIME_S:g} s; a limit or a barrier plane may slow or block it")
        twist[axis] = float(np.clip(remaining / JOG_APPROACH_S, -speed, speed))
        guard.command_twist(twist)
        guard.tick()
        next_tick += period_s
        clock.sleep(next_tick - clock.now())
    guard.hold()
    rest_by = clock.now() + JOG_EXTRA_TIME_S
    while np.any(np.abs(guard.state().qd) > REST_QD_RAD_S):
        if clock.now() > rest_by:
            guard.stop("jog: the arm did not come to rest")
            raise SafetyStop(f"jog: the arm was still moving {JOG_EXTRA_TIME_S:g} s after the ramp down")
        guard.tick()
        next_tick += period_s
        clock.sleep(next_tick - clock.now())
    guard.finish()


@arm_app.command("jog")
def jog(
    config: Annotated[Path, typer.Option(help="cell file")],
    axis: Annotated[str, typer.Option(help="x, y, z (base frame, metres) or rx, ry, rz (radians)")],
    distance: Annotated[float, typer.Option(help=f"signed distance [m] or angle [rad], at most "
                                                 f"{JOG_MAX_DISTANCE_M} / {JOG_MAX_ANGLE_RAD}")],
) -> None:
    """One small guarded move of the flange along or about a base-frame axis.

    Then stop and print the status."""
    if axis not in AXES:
        raise typer.BadParameter(f"axis must be one of {', '.join(AXES)}")
    rotation = AXES[axis] >= 3
    limit = JOG_MAX_ANGLE_RAD if rotation else JOG_MAX_DISTANCE_M
    if not 0.0 < abs(distance) <= limit:
        raise typer.BadParameter(f"distance must be non-zero and at most {limit} for a jog")
    with _connected_arm(config) as (cfg, arm):
        clock = WallClock()
        guard = MotionGuard.from_config(arm, get_robot_model(cfg.arm.model), cfg, clock)
        try:
            s = cfg.safety
            speed = JOG_SPEED_FRACTION * (s.tcp_max_angular_rps if rotation else s.tcp_max_linear_mps)
            with interrupting():  # as Ctrl-C: the guard and the disconnect stop the arm
                _jog(guard, clock, AXES[axis], distance, speed, 1.0 / cfg.scan.control_rate_hz)
        finally:
            guard.release()
        _print_status(arm)
