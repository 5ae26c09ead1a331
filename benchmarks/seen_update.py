"""Cost of what the sensor has seen standing on the table (``cell.perception.seen_obstacles``), on each
thread: perception's part per frame (``PerceptionPipeline.survey``: the returns kept on the grid, the cells
grown by their reach, their mesh and BVH built; from a view already taken, most blocks hold the cells they
held and keep their bodies) and the control thread's part per update (``CollisionWorld.set_seen``, which
``MotionGuard.set_seen`` calls from the tick that takes the update in: the cells the arm stands in found
and the bodies swapped in), for new cells (their bodies built by perception, as an update brings them),
for the same cells again (the bodies kept), and for new cells some of which the arm stands in (a column of
cells from the flange down: the blocks holding them built again on the control thread).

Each sim cell's sensor (the Franka's 640x480 RGB-D camera on the bunny, the UR5e's 8x8 ToF on the 30 cm
horizontal box) looks at its part from ``--frames`` views on a ring (``station_rig``) with no ROI found,
then from the same views again (new captures): every cell of the part is an obstacle, the most a survey
from home gives a part on the table. The control thread's figures (for the first lap's cells) are printed
beside its control period (``scan.control_rate_hz``): an update taken in must not make its tick miss the
deadline (1.5 periods).

Prints readable lines, then as its last line JSON {cell: {"cells": n, "perception_ms": median,
"perception_again_ms": median, "control_new_ms": {"p50", "max"}, "control_same_ms": {...},
"control_at_arm_ms": {...}, "control_period_ms": ...}}.

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
from cell.perception.seen_obstacles import SeenCells, SeenObstacles
from cell.safety.collision import CollisionWorld
from drivers.robots import get_robot_model

REPO = Path(__file__).resolve().parents[1]
CELLS = (("rgbd", "sim-franka-rgbd.yaml", "bunny"), ("tof", "sim-ur5e-tof.yaml", "horizontal_box"))


def _ms(figures: list[float]) -> dict[str, float]:
    return {"p50": round(float(np.median(figures)), 3), "max": round(float(np.max(figures)), 3)}


def measure(config_name: str, object_name: str, n_frames: int, repeats: int) -> dict[str, Any]:
    """The figures of one cell (module docstring)."""
    cfg = load_config(REPO / "config" / config_name)
    rig = StationRig(cfg, object_name)
    perception_ms: list[list[float]] = [[], []]
    laps: list[SeenCells] = []
    with rig.sensor:
        for lap in perception_ms:
            for k in range(n_frames):
                T = rig.view(180.0 + 360.0 * k / n_frames, 0.3)
                frame = rig.sensor.capture()
                t0 = time.perf_counter()
                seen = rig.pipeline.survey(frame, T)
                lap.append((time.perf_counter() - t0) * 1e3)
            laps.append(seen)
    cells = laps[0]
    assert len(cells)
    world = CollisionWorld.for_cell(cfg)
    q = np.asarray(cfg.arm.home_joints_rad)
    flange = world.arm_bodies()[-1]
    below = get_robot_model(cfg.arm.model).fk_all(q)[flange.frame][:3, 3] \
        - np.column_stack([np.zeros((30, 2)), np.linspace(0.0, 0.3, 30)])

    def with_points(points: np.ndarray) -> SeenCells:
        """``cells`` and the cells of ``points`` (base frame), their bodies built as perception does."""
        seen = SeenObstacles(cells.voxel_m, table_z_m=-1.0, table_band_m=0.0)
        seen.add(np.vstack([cells.centers(), points]), np.eye(4), pitch_rad=0.0)
        return seen.outside(None)

    # every other cell left out: a second set, so that calls alternating them swap in other bodies
    variants = {"new": (cells, cells.without(np.arange(len(cells)) % 2 == 0)), "same": (cells, cells),
                "at_arm": (with_points(below), with_points(below + np.array([0.01, 0.0, 0.0])))}
    figures: dict[str, Any] = {"cells": len(cells),
                               "perception_ms": round(float(np.median(perception_ms[0])), 3),
                               "perception_again_ms": round(float(np.median(perception_ms[1])), 3)}
    for name, (a, b) in variants.items():
        for chunk, _ in b.chunks:
            _ = chunk.body
        taken = []
        for k in range(repeats):
            t0 = time.perf_counter()
            world.set_seen(b if k % 2 else a, q_free=q)
            taken.append((time.perf_counter() - t0) * 1e3)
        figures[f"control_{name}_ms"] = _ms(taken)
    figures["control_period_ms"] = round(1e3 / cfg.scan.control_rate_hz, 3)
    return figures


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--frames", type=count, default=6)
    parser.add_argument("--repeats", type=count, default=20)
    args = parser.parse_args()
    figures = {}
    for name, config, obj in CELLS:
        f = measure(config, obj, args.frames, args.repeats)
        figures[name] = f
        control = "; ".join(f"{what} {f[key]['p50']}, {f[key]['max']}" for what, key in (
            ("new cells", "control_new_ms"), ("the same", "control_same_ms"),
            ("some at the arm", "control_at_arm_ms")))
        print(f"{name}: {f['cells']} cells of {obj}; perception {f['perception_ms']} ms per frame, "
              f"{f['perception_again_ms']} ms from a view already taken; control "
              f"thread (median, max [ms]): {control}; control period {f['control_period_ms']} ms")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
