"""Cost of one guard tick per robot model (UR5e, Panda): watchdog, fault read, speed and joint limits,
barrier projection, ruckig smoothing, and the check of the joint path to the configuration predicted
``lookahead_s`` ahead for collisions (``CollisionWorld.check_motion``). The safety issue's goal is at most
1 ms per tick: a deadline each tick has to keep, not an average, so it is judged on the p99.

Two motions per model, on its sim cell (config/sim-ur5e-tof.yaml, config/sim-franka-rgbd.yaml):

- ``steady``: a slowly turning twist (3 cm/s circling, 0.1 rad/s about z) streamed through
  ``MotionGuard.tick`` for ``--ticks`` control periods, no object ROI;
- ``scan``: every tick of a simulated vs-local scan of the bunny (``--scan-time`` s of sim time): the
  servo law's twists, the planner's moves, and an object ROI that perception replaces with each frame.

Only the tick is timed (not the simulated arm's stepping nor the scan's perception), in CPU time of the
calling thread (``time.thread_time``) and wall time (``time.perf_counter``). Ticks are told apart by what
the collision check did:

- ``fcl``: the way-ahead check measured at least one FCL distance. ``check_motion`` keeps, per pair of
  bodies, a lower bound on its distance and where it was measured, and measures again only the pairs
  whose bound, less how far they can have come closer since, no longer clears them: the first tick after
  a new ROI (each perception update replaces it, and every pair of it is measured again, most by their
  bounding spheres), a pair near the table or the ROI whose bound the path ahead uses up (about twice the
  path's length after each measurement), and the stretches of the path bisected for a pair close to it.
  On the steady twist that was 23 (UR5e) and 35 (Panda) ticks of 2000; in the Panda's scan about one
  checked tick in six (the output counts them);
- ``bound``: the check ran and every pair was cleared by its kept bound or its bounding spheres, with no
  FCL call (most ticks of a streamed twist);
- ``idle``: no streamed twist was checked: the arm follows a trajectory (checked whole before it
  started), has no target, or is settling after a stop.

Per kind: the number of ticks and the median, p99 and maximum [ms] of CPU and of wall time (on a shared
machine wall time also measures the other processes: the 1-min load average is printed), and whether the
goal is met, judged on the p99 of CPU time (a tick's deadline; the median would pass a kind whose
slowest hundredth overran it). The last line is JSON: ``{"models": {model: {motion: {kind:
{"n", "cpu_ms": {"p50", "p99", "max"}, "wall_ms": {...}, "goal_met"}}}}, "goal_ms": 1.0, "load_avg_1min":
[before, after]}``.

    .venv/bin/python benchmarks/guard_tick.py [--ticks 2000] [--scan-time 20]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from options import BenchmarkParser, count, positive

from cell.config import load_config
from cell.jobs.runner import ScanRequest, run_scan
from cell.safety.guard import MotionGuard
from drivers.arm.config import SimArmConfig
from drivers.arm.sim import SimArm
from drivers.clock import SimClock
from drivers.robots import get_robot_model

REPO = Path(__file__).resolve().parent.parent
CELLS = {"ur5e": REPO / "config/sim-ur5e-tof.yaml", "panda": REPO / "config/sim-franka-rgbd.yaml"}
KINDS = ("bound", "fcl", "idle")
GOAL_MS = 1.0


@dataclass(frozen=True)
class Tick:
    """One timed tick: CPU and wall time [s], and whether it checked the way ahead and measured FCL
    distances for it."""

    cpu_s: float
    wall_s: float
    checked: bool
    measured: bool

    @property
    def kind(self) -> str:
        return "fcl" if self.measured else "bound" if self.checked else "idle"


@contextmanager
def timed_ticks() -> Iterator[list[Tick]]:
    """Every ``MotionGuard.tick`` called inside the block, timed, in a list that it fills."""
    ticks: list[Tick] = []
    tick: Callable[..., None] = MotionGuard.tick

    def timed(guard: MotionGuard, *args: Any, **kwargs: Any) -> None:
        world = guard.collision
        checks, distances = world.n_motion_checks, world.n_distances
        c0, w0 = time.thread_time(), time.perf_counter()
        try:
            tick(guard, *args, **kwargs)
        finally:
            ticks.append(Tick(time.thread_time() - c0, time.perf_counter() - w0,
                              world.n_motion_checks > checks, world.n_distances > distances))

    setattr(MotionGuard, "tick", timed)  # noqa: B010 (mypy refuses assigning to a method)
    try:
        yield ticks
    finally:
        setattr(MotionGuard, "tick", tick)  # noqa: B010


def steady(model_name: str, n_ticks: int) -> list[Tick]:
    """``n_ticks`` ticks streaming a slowly turning twist on the model's sim cell."""
    cfg = load_config(CELLS[model_name])
    model = get_robot_model(model_name)
    clock = SimClock()
    assert isinstance(cfg.arm, SimArmConfig)  # the benchmark's cell files simulate the arm
    arm = SimArm(cfg.arm, model, clock)
    arm.connect()
    guard = MotionGuard.from_config(arm, model, cfg, clock)
    dt = 1.0 / cfg.scan.control_rate_hz
    with timed_ticks() as ticks:
        for k in range(n_ticks):
            phase = 2.0 * np.pi * k / 400.0
            guard.command_twist(np.array([0.03 * np.cos(phase), 0.03 * np.sin(phase), 0.0, 0.0, 0.0, 0.1]))
            guard.tick()
            clock.sleep(dt)
    return ticks


def scan(model_name: str, time_s: float, out: Path) -> list[Tick]:
    """The ticks of a simulated vs-local scan of the bunny, ``time_s`` [s] of sim time, on the model's
    sim cell; its folder in ``out``."""
    path = CELLS[model_name]
    request = ScanRequest(config=load_config(path), config_path=str(path), object="bunny", planner="vs-local",
                          max_time_s=time_s, out=out / model_name)
    with timed_ticks() as ticks:
        run_scan(request)
    return ticks


def spread_ms(times_s: list[float]) -> dict[str, float]:
    """Median, p99 (interpolated) and maximum [ms] of ``times_s`` [s]."""
    t = np.asarray(times_s) * 1e3
    return {"p50": round(float(np.median(t)), 4), "p99": round(float(np.percentile(t, 99)), 4),
            "max": round(float(t.max()), 4)}


def figures(ticks: list[Tick]) -> dict[str, dict[str, Any]]:
    """Per kind of tick present: its count, the spread of its CPU and wall time [ms], and whether the p99
    of its CPU time keeps the goal's deadline."""
    out: dict[str, dict[str, Any]] = {}
    for kind in KINDS:
        some = [t for t in ticks if t.kind == kind]
        if some:
            cpu_ms = spread_ms([t.cpu_s for t in some])
            out[kind] = {"n": len(some), "cpu_ms": cpu_ms, "wall_ms": spread_ms([t.wall_s for t in some]),
                         "goal_met": cpu_ms["p99"] <= GOAL_MS}
    return out


def main() -> None:
    parser = BenchmarkParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ticks", type=count, default=2000, help="ticks of the steady twist per model")
    parser.add_argument("--scan-time", type=positive, default=20.0, help="sim time of each model's scan [s]")
    args = parser.parse_args()
    load_before = os.getloadavg()[0]
    results: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="guard-tick-") as tmp:
        for name in CELLS:
            results[name] = {"steady": figures(steady(name, args.ticks)),
                             "scan": figures(scan(name, args.scan_time, Path(tmp)))}
    load_after = os.getloadavg()[0]
    print(f"load average (1 min) {load_before:.2f} before, {load_after:.2f} after; goal <= {GOAL_MS:g} ms "
          "per tick (CPU p99)")
    print("model  motion kind       n    CPU ms p50 / p99 / max       wall ms p50 / p99 / max    goal")
    for name, motions in results.items():
        for motion, kinds in motions.items():
            for kind, f in kinds.items():
                c, w = f["cpu_ms"], f["wall_ms"]
                print(f"{name:6s} {motion:6s} {kind:5s} {f['n']:6d}   {c['p50']:7.3f} {c['p99']:7.3f} "
                      f"{c['max']:7.3f}      {w['p50']:7.3f} {w['p99']:7.3f} {w['max']:7.3f}    "
                      f"{'met' if f['goal_met'] else 'NOT met'}")
    print(json.dumps({"models": results, "goal_ms": GOAL_MS,
                      "load_avg_1min": [round(load_before, 2), round(load_after, 2)]}))


if __name__ == "__main__":
    main()
