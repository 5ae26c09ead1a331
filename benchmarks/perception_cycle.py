"""Benchmark of one full perception cycle (filter, register, integrate, segment) per frame.

RGB-D: the Franka cell's pipeline (config/sim-franka-rgbd.yaml) on 640x480 frames of the bunny taken
from views 20 degrees apart on a ring at Z* = 0.25 m; ToF: the UR5e cell's pipeline on 8x8 frames of the
horizontal box. Rendering is not timed. The first frames build the target and the map; the median is
taken over the following ``--frames``. Prints readable lines (with the median wall / CPU time of each
stage, ``PerceptionPipeline.stage_times``), then as its last line JSON {"rgbd_ms": median,
"tof_ms": median, "rgbd_cpu_ms": ..., "tof_cpu_ms": ..., "rgbd_stages_cpu_ms": {stage: median}, ...}.
Goals (issue 3): rgbd_ms <= 100, tof_ms <= 5 (wall time on an otherwise idle machine). The ``_cpu_ms``
figures are the process's CPU time per cycle: on a machine shared with other work they move far less
than the wall time does.

Run: ``.venv/bin/python benchmarks/perception_cycle.py [--frames 12]``
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from options import BenchmarkParser, count, first_paragraph

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from station_rig import StationRig

from cell.config import load_config

REPO = Path(__file__).resolve().parents[1]


def cycle_times(config_name: str, object_name: str, standoff_m: float, n_frames: int, warmup: int = 3,
                ) -> tuple[list[float], list[float], dict[str, list[tuple[float, float]]]]:
    """Wall and CPU time [ms] of each timed cycle, and the (wall, CPU) [ms] of each stage per cycle."""
    rig = StationRig(load_config(REPO / "config" / config_name), object_name)
    times, cpu = [], []
    stages: dict[str, list[tuple[float, float]]] = {}
    with rig.sensor:
        for k in range(warmup + n_frames):
            T = rig.view(180.0 + 20.0 * k, standoff_m)
            frame = rig.sensor.capture()
            t0, c0 = time.perf_counter(), time.process_time()
            rig.pipeline.process(frame, T)
            if k >= warmup:
                times.append((time.perf_counter() - t0) * 1e3)
                cpu.append((time.process_time() - c0) * 1e3)
                for stage, figures in rig.pipeline.stage_times.last.items():
                    stages.setdefault(stage, []).append(figures)
    return times, cpu, stages


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--frames", type=count, default=12)
    args = parser.parse_args()
    figures: dict[str, object] = {}
    for name, config, obj, standoff, goal in (("rgbd", "sim-franka-rgbd.yaml", "bunny", 0.25, 100.0),
                                              ("tof", "sim-ur5e-tof.yaml", "horizontal_box", 0.4, 5.0)):
        t, cpu, stages = cycle_times(config, obj, standoff, args.frames)
        figures[f"{name}_ms"] = round(float(np.median(t)), 3)
        figures[f"{name}_cpu_ms"] = round(float(np.median(cpu)), 3)
        figures[f"{name}_stages_cpu_ms"] = {s: round(float(np.median([c for _, c in v])), 3)
                                            for s, v in stages.items()}
        print(f"{name:5s} {len(t)} cycles: median {np.median(t):8.2f} ms (goal <= {goal:g} ms), "
              f"min {min(t):8.2f}, max {max(t):8.2f}; CPU time median {np.median(cpu):8.2f} ms")
        for stage, v in stages.items():
            print(f"      {stage:10s} wall {np.median([w for w, _ in v]):8.2f} ms, "
                  f"CPU {np.median([c for _, c in v]):8.2f} ms (medians)")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
