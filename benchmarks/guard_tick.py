"""Median cost of one guard tick per robot model: watchdog, fault read, speed and joint limits, barrier
projection, ruckig smoothing, and the FCL check of the joint path to the configuration predicted
``lookahead_s`` ahead.

Each model streams a slowly turning twist through ``MotionGuard.tick`` on its sim cell for 2000 control
periods; only the tick is timed (the simulated arm's own stepping is not). The safety issue's goal is at
most 1 ms per tick. The last line is JSON: ``{"ur5e_ms": ..., "panda_ms": ..., "goal_ms": 1.0}``.

    .venv/bin/python benchmarks/guard_tick.py
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from cell.config import load_config
from cell.safety.guard import MotionGuard
from drivers.arm.config import SimArmConfig
from drivers.arm.sim import SimArm
from drivers.clock import SimClock
from drivers.robots import get_robot_model

REPO = Path(__file__).resolve().parent.parent
CELLS = {"panda": REPO / "config/sim-franka-rgbd.yaml", "ur5e": REPO / "config/sim-ur5e-tof.yaml"}
TICKS = 2000


def median_tick_ms(model_name: str) -> float:
    cfg = load_config(CELLS[model_name])
    model = get_robot_model(model_name)
    clock = SimClock()
    assert isinstance(cfg.arm, SimArmConfig)  # the benchmark's cell files simulate the arm
    arm = SimArm(cfg.arm, model, clock)
    arm.connect()
    guard = MotionGuard.from_config(arm, model, cfg, clock)
    dt = 1.0 / cfg.scan.control_rate_hz
    times = []
    for k in range(TICKS):
        phase = 2.0 * np.pi * k / 400.0
        guard.command_twist(np.array([0.03 * np.cos(phase), 0.03 * np.sin(phase), 0.0, 0.0, 0.0, 0.1]))
        t0 = time.perf_counter()
        guard.tick()
        times.append(time.perf_counter() - t0)
        clock.sleep(dt)
    return float(np.median(times) * 1e3)


def main() -> None:
    figures = {f"{name}_ms": round(median_tick_ms(name), 4) for name in ("ur5e", "panda")}
    for name, ms in figures.items():
        print(f"{name:10s} {ms:8.3f} ms per guard tick (goal <= 1 ms)")
    print(json.dumps({**figures, "goal_ms": 1.0}))


if __name__ == "__main__":
    main()
