"""Cost of what the sensor has seen standing on the table (``cell.perception.seen_obstacles``), on each
thread: perception's part per frame (``PerceptionPipeline.survey``: the returns kept on the grid, the cells
grown by their reach, their mesh and BVH built) and the control thread's part per update
(``CollisionWorld.set_seen``, which ``MotionGuard.set_seen`` calls from the tick that takes the update
in: the cells the arm stands in found and the body swapped in), for new cells and for the same cells
again (the body kept).

Each sim cell's sensor (the Franka's 640x480 RGB-D camera on the bunny, the UR5e's 8x8 ToF on the 30 cm
horizontal box) looks at its part from ``--frames`` views on a ring (``station_rig``) with no ROI found:
every cell of the part is an obstacle, the most a survey from home gives a part on the table. The
control thread's figures are printed beside its control period (``scan.control_rate_hz``): an update
taken in must not make its tick miss the deadline (1.5 periods).

Prints readable lines, then as its last line JSON {cell: {"cells": n, "perception_ms": median,
"control_new_ms": {"p50", "max"}, "control_same_ms": {"p50", "max"}, "control_period_ms": ...}}.

    .venv/bin/python benchmarks/seen_update.py [--frames 6] [--repeats 20]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from options import BenchmarkParser, count, first_paragraph

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from station_rig import StationRig

from cell.config import load_config
from cell.perception.seen_obstacles import SeenCells
from cell.safety.collision import CollisionWorld

REPO = Path(__file__).resolve().parents[1]
CELLS = (("rgbd", "sim-franka-rgbd.yaml", "bunny"), ("tof", "sim-ur5e-tof.yaml", "horizontal_box"))


def _ms(figures: list[float]) -> dict[str, float]:
    return {"p50": round(float(np.median(figures)), 3), "max": round(float(np.max(figures)), 3)}


def measure(config_name: str, object_name: str, n_frames: int, repeats: int) -> dict[str, Any]:
    """The figures of one cell (module docstring)."""
    cfg = load_config(REPO / "config" / config_name)
    rig = StationRig(cfg, object_name)
    perception_ms = []
    cells: SeenCells | None = None
    with rig.sensor:
        for k in range(n_frames):
            T = rig.view(180.0 + 360.0 * k / n_frames, 0.3)
            frame = rig.sensor.capture()
            t0 = time.perf_counter()
            cells = rig.pipeline.survey(frame, T)
            perception_ms.append((time.perf_counter() - t0) * 1e3)
    assert cells is not None and len(cells)
    world = CollisionWorld.for_cell(cfg)
    q = np.asarray(cfg.arm.home_joints_rad)
    # every other cell left out: a second set, so that each call alternating them builds a new body
    other = cells.without(np.arange(len(cells)) % 2 == 0)
    _ = other.body
    new, same = [], []
    for k in range(repeats):
        t0 = time.perf_counter()
        world.set_seen(other if k % 2 else cells, q_free=q)
        new.append((time.perf_counter() - t0) * 1e3)
    for _k in range(repeats):
        t0 = time.perf_counter()
        world.set_seen(cells, q_free=q)
        same.append((time.perf_counter() - t0) * 1e3)
    return {"cells": len(cells), "perception_ms": round(float(np.median(perception_ms)), 3),
            "control_new_ms": _ms(new), "control_same_ms": _ms(same),
            "control_period_ms": round(1e3 / cfg.scan.control_rate_hz, 3)}


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--frames", type=count, default=6)
    parser.add_argument("--repeats", type=count, default=20)
    args = parser.parse_args()
    figures = {}
    for name, config, obj in CELLS:
        f = measure(config, obj, args.frames, args.repeats)
        figures[name] = f
        print(f"{name}: {f['cells']} cells of {obj}; perception {f['perception_ms']} ms per frame; control "
              f"thread {f['control_new_ms']['p50']} ms (max {f['control_new_ms']['max']}) for new cells, "
              f"{f['control_same_ms']['p50']} ms (max {f['control_same_ms']['max']}) for the same; control "
              f"period {f['control_period_ms']} ms")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
