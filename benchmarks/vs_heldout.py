"""VS-Local on ten shapes and placements that are not Table I's: scan time, path and coverage.

What the figures of ``benchmarks/vs_table.py`` become away from the eight objects at the station's centre,
for choosing the planners' parameters on the method rather than on those objects.

The cases: four primitive shapes built here with Open3D (metres, z up, base at z = 0, centred), each at
the station's centre or turned; the two shipped packing boxes, turned; four of Table I's objects moved
off the centre and turned. Each is one ``cell scan`` job (``config/sim-franka-rgbd.yaml`` by default, per
job seed); the figures are those of the online cloud (``result.json``; coverage within 2.5 mm of the
mesh, eq. 13), scan time and path as in Table I. The summary gives their means, beside the paper's mean
VS-Local scan time (42 s) for reference: the paper has no figures for these objects.

Prints one line per run, then as its last line JSON {"runs": [...], "summary": {...}}; ``--json`` also
writes it to a file. Runs go ``--jobs`` at a time (default 2), each in its own process.

Run: ``nice .venv/bin/python benchmarks/vs_heldout.py [--config F] [--seeds 0] [--out /tmp/vs_heldout]
[--json F]``
"""

from __future__ import annotations

import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from grid_report import jobs_parser, print_result, refuse_taken

from cell.config import load_config
from cell.evaluation.presets import write_heldout_shapes
from cell.jobs.runner import ScanRequest, run_scan

REPO = Path(__file__).resolve().parents[1]
PAPER_LOCAL_TIME_S = 42.0


# (label, object: a shape of ``write_heldout_shapes`` or a shipped name, pose (x [m], y [m], yaw [deg]))
CASES: tuple[tuple[str, str, tuple[float, float, float]], ...] = (
    ("cylinder", "cylinder", (0.0, 0.0, 0.0)),
    ("torus", "torus", (0.0, 0.0, 0.0)),
    ("cone", "cone", (0.0, 0.0, 0.0)),
    ("slab-30", "slab", (0.0, 0.0, 30.0)),
    ("hbox-20", "horizontal_box", (0.0, 0.0, 20.0)),
    ("vbox-m15", "vertical_box", (0.0, 0.0, -15.0)),
    ("bunny-moved", "bunny", (0.05, -0.04, 60.0)),
    ("mustard-moved", "mustard", (-0.04, 0.05, -40.0)),
    ("cube-30", "cube", (0.0, 0.0, 30.0)),
    ("teapot-moved", "teapot", (0.03, 0.03, 120.0)),
)


def run_one(config_path: Path, label: str, obj: str, pose: tuple[float, float, float], seed: int,
            folder: Path) -> dict[str, Any]:
    """One VS-Local scan job: its online metrics, scan time and path, and termination."""
    r = run_scan(ScanRequest(config=load_config(config_path), config_path=str(config_path), object=obj,
                             object_pose=pose, planner="vs-local", seed=seed, out=folder)).result
    m = r["metrics"] or {}
    return {"case": label, "object": obj, "pose": list(pose), "seed": seed, "status": r["status"],
            "termination": r["termination"], "coverage_pct": m.get("coverage_pct"),
            "chamfer_mm": m.get("chamfer_mm"), "scan_time_s": r["scan_time_s"],
            "path_length_m": r["scan_path_length_m"]}


def main() -> None:
    parser = jobs_parser(__doc__.splitlines()[0], REPO / "config" / "sim-franka-rgbd.yaml",
                         Path("/tmp/vs_heldout"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--jobs", type=int, default=2, help="scans run at the same time")
    args = parser.parse_args()
    grid = [(label, obj, pose, seed, args.out / f"{label}-s{seed}") for label, obj, pose in CASES
            for seed in args.seeds]
    refuse_taken(parser, [folder for *_, folder in grid])
    shapes = write_heldout_shapes(args.out / "shapes")
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = [pool.submit(run_one, args.config, label, str(shapes.get(obj, obj)), pose, seed, folder)
                   for label, obj, pose, seed, folder in grid]
        runs = []
        for future in futures:
            run = future.result()
            print(f"{run['case']:14} seed {run['seed']} {run['status']:10} {run['scan_time_s']:6.1f} s "
                  f"{run['path_length_m']:5.2f} m  coverage {run['coverage_pct']} %  "
                  f"Chamfer {run['chamfer_mm']} mm; {run['termination']}", flush=True)
            runs.append(run)
    done = [r for r in runs if r["status"] == "completed"]
    summary = {"n_runs": len(runs), "n_completed": len(done),
               "mean_time_s": round(float(np.mean([r["scan_time_s"] for r in done])), 2) if done else None,
               "mean_coverage_pct": (round(float(np.mean([r["coverage_pct"] or 0.0 for r in done])), 2)
                                     if done else None),
               "max_time_s": max((r["scan_time_s"] for r in done), default=None),
               "paper_mean_local_time_s": PAPER_LOCAL_TIME_S}
    print_result({"runs": runs, "summary": summary}, args.json)


if __name__ == "__main__":
    main()
