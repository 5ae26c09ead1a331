"""Benchmark of the simulated depth sensors: frame time of SimRGBD (640x480) and SimToF (8x8, 4x4 subrays).

Scene: the bunny on the table at (0.5, 0, 0) [m, base frame]; each sensor ~0.3 m from the object's centre,
looking at it from 45 deg elevation. Renders ``--frames`` frames per sensor after a warm-up and prints one
line per figure, then as its last line JSON {"rgbd_frame_ms": median, "tof_frame_ms": median}.

Run: ``.venv/bin/python benchmarks/sim_render.py [--frames 30]``

On a 2-core machine the RGB-D figure is dominated by Open3D's ``cast_rays`` (~25 ms for 307,200 rays
against the bunny); OpenBLAS worker threads left spinning by the per-frame ray rotation compete with
Embree's threads, so ``OPENBLAS_NUM_THREADS=1`` gives a lower, steadier figure there.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from options import BenchmarkParser, count, first_paragraph

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.clock import SimClock
from drivers.depth.config import SimRGBDConfig, SimToFConfig
from drivers.depth.sim_rgbd import SimRGBD
from drivers.depth.sim_tof import SimToF
from drivers.sim.objects import load_object
from drivers.sim.scene import SimScene
from drivers.transforms import look_at, make_T


def time_frames(sensor, n: int, warmup: int = 3) -> tuple[list[float], int]:
    for _ in range(warmup):
        sensor.capture()
    times = []
    n_points = 0
    for _ in range(n):
        t0 = time.perf_counter()
        frame = sensor.capture()
        times.append((time.perf_counter() - t0) * 1e3)
        n_points = len(frame.points)
    return times, n_points


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--frames", type=count, default=30)
    args = parser.parse_args()

    obj = load_object("bunny")
    centre = np.array([0.5, 0.0, 0.0])
    t0 = time.perf_counter()
    scene = SimScene(obj, make_T(np.eye(3), centre))
    build_ms = (time.perf_counter() - t0) * 1e3
    target = centre + np.array([0.0, 0.0, obj.extents_m[2] / 2.0])
    d = 0.3
    eye = target + d * np.array([-np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4)])
    T_base_sensor = look_at(eye, target)
    clock = SimClock()

    rgbd_cfg = SimRGBDConfig(type="sim-rgbd", width=640, height=480, fx=460.0, fy=460.0, cx=319.5, cy=239.5,
                             range_min_m=0.1, range_max_m=1.5,
                             noise={"sigma0_m": 0.0005, "k_per_m": 0.002})
    tof_cfg = SimToFConfig(type="sim-tof", resolution=8, fov_deg=45.0, subrays=4, range_min_m=0.02,
                           range_max_m=4.0, noise={"sigma0_m": 0.005, "k_per_m": 0.0})
    rgbd = SimRGBD(rgbd_cfg, scene, lambda: T_base_sensor, clock, np.random.default_rng(0))
    tof = SimToF(tof_cfg, scene, lambda: T_base_sensor, clock, np.random.default_rng(0))

    results = {}
    with rgbd, tof:
        for key, sensor in (("rgbd_frame_ms", rgbd), ("tof_frame_ms", tof)):
            times, n_points = time_frames(sensor, args.frames)
            med = float(np.median(times))
            results[key] = round(med, 3)
            print(f"{sensor.name:9s} {args.frames} frames: median {med:8.3f} ms, min {min(times):8.3f} ms, "
                  f"max {max(times):8.3f} ms, {n_points} points in the last frame")
    print(f"scene build (bunny, {len(obj.triangles)} triangles + table): {build_ms:.1f} ms")
    print(json.dumps(results))


if __name__ == "__main__":
    main()
