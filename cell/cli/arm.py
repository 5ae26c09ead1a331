"""``cell arm``: commissioning commands for a cell's arm.

``status`` connects, prints the connection, the TCP pose (translation in metres, rotation as roll-pitch-
yaw in degrees, base frame), the joints, the modes and any fault in words, and disconnects.
``jog`` makes small guarded moves: each step is a short twist through the cell's motion guard (its limits
and workspace), then a stop.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console
from scipy.spatial.transform import Rotation

from cell.config import load_config
from cell.config.models import CellConfig
from drivers.arm.base import Arm
from drivers.arm.hardware import HardwareArm
from drivers.clock import WallClock
from drivers.errors import CellError, DriverError, RobotFault
from drivers.factory import make_arm
from drivers.robots import get_robot_model

arm_app = typer.Typer(help="Commission a cell's arm: status, small guarded jog moves.", no_args_is_help=True)
console = Console(soft_wrap=True)
err_console = Console(stderr=True)

AXES = {"x": 0, "y": 1, "z": 2, "rx": 3, "ry": 4, "rz": 5}
JOG_SPEED_FRACTION = 0.2  # a jog moves at this share of the cell's TCP limits


def _open_arm(config: Path) -> tuple[CellConfig, Arm]:
    cfg = load_config(config)
    if cfg.arm.type == "sim":
        raise DriverError("commissioning commands are for hardware arms (arm.type ur5e or franka)",
                          device="arm sim")
    arm = make_arm(cfg.arm, get_robot_model(cfg.arm.model), None)
    arm.connect()
    return cfg, arm


def _print(text: str) -> None:
    console.print(text, markup=False, highlight=False)


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
    """Connect, print pose, joints, modes and faults, disconnect."""
    try:
        _, arm = _open_arm(config)
        try:
            for line in _status_lines(arm):
                _print(line)
        finally:
            arm.disconnect()
    except CellError as exc:
        err_console.print(f"error: {exc}", markup=False, highlight=False)
        raise typer.Exit(code=1) from None


@arm_app.command("jog")
def jog(
    config: Annotated[Path, typer.Option(help="cell file")],
    axis: Annotated[str, typer.Option(help="x, y, z (base frame, metres) or rx, ry, rz (radians)")],
    distance: Annotated[float, typer.Option(help="signed distance [m] or angle [rad], at most 0.05 / 0.2")],
) -> None:
    """One small guarded move of the flange along or about a base-frame axis, then stop."""
    from cell.safety.guard import MotionGuard

    if axis not in AXES:
        raise typer.BadParameter(f"axis must be one of {', '.join(AXES)}")
    limit = 0.05 if AXES[axis] < 3 else 0.2
    if not 0.0 < abs(distance) <= limit:
        raise typer.BadParameter(f"distance must be non-zero and at most {limit} for a jog")
    try:
        cfg, arm = _open_arm(config)
        try:
            clock = WallClock()
            guard = MotionGuard.from_config(arm, get_robot_model(cfg.arm.model), cfg, clock)
            s = cfg.safety
            speed = JOG_SPEED_FRACTION * (s.tcp_max_linear_mps if AXES[axis] < 3 else s.tcp_max_angular_rps)
            twist = np.zeros(6)
            twist[AXES[axis]] = np.sign(distance) * speed
            period = 1.0 / cfg.scan.control_rate_hz
            end = clock.now() + abs(distance) / speed
            while clock.now() < end:
                guard.state()
                guard.command_twist(twist)
                time.sleep(period)
            guard.stop("jog finished")
            for line in _status_lines(arm):
                _print(line)
        finally:
            arm.disconnect()
    except CellError as exc:
        err_console.print(f"error: {exc}", markup=False, highlight=False)
        raise typer.Exit(code=1) from None
