"""``cell eval``'s executors on this machine: the same 16-scan grid on the local process pool and on a
local Ray instance of the same size; wall time of each, their ratio (issue 23's goal: Ray at least 0.9x
the pool's throughput) and whether their results.csv are byte-identical. Also the mean wall time of one
scan, from which ``--table-i-seeds`` scans of Table I (8 objects x 3 strategies) on ``--nodes`` nodes of
``--cores`` cores are estimated (full budgets: pass ``--max-time`` 0 to keep the cell's).

The grid: 4 packing objects x lr-nbv and heu x seeds 0 1 on ``config/sim-ur5e-tof.yaml`` with a short
budget (``--max-time``, default 20 s of sim time), no coverage limit.

Prints JSON. Run: ``nice .venv/bin/python benchmarks/eval_executors.py [--jobs 2] [--max-time 20]``
"""

from __future__ import annotations

import argparse
import io
import json
import tempfile
import time
from pathlib import Path

from cell.evaluation import paper
from cell.evaluation.executors import Executor, LocalPool, RayExecutor
from cell.evaluation.grid import RESULTS_CSV, run_grid
from cell.evaluation.spec import cross

REPO = Path(__file__).resolve().parents[1]


def timed(executor: Executor, specs: list, out: Path) -> float:
    start = time.perf_counter()
    run_grid(specs, out, executor, stream=io.StringIO())
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--max-time", type=float, default=20.0)
    parser.add_argument("--nodes", type=int, default=10)
    parser.add_argument("--cores", type=int, default=16)
    parser.add_argument("--table-i-seeds", type=int, default=10)
    args = parser.parse_args()
    cases = [(o, (0.0, 0.0, 0.0)) for o in paper.PACKING_OBJECTS]
    specs = cross(str(REPO / "config" / "sim-ur5e-tof.yaml"), cases, ["lr-nbv", "heu"], [0, 1],
                  args.max_time or None)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        pool_s = timed(LocalPool(args.jobs), specs, root / "pool")
        ray_s = timed(RayExecutor(jobs=args.jobs), specs, root / "ray")
        identical = (root / "pool" / RESULTS_CSV).read_bytes() == (root / "ray" / RESULTS_CSV).read_bytes()
        results = (root / "pool").glob("scans/*/result.json")
        scan_s = [json.loads(p.read_text())["wall_time_s"] for p in results]
    mean_scan_s = sum(scan_s) / len(scan_s)
    n_table_i = len(paper.TABLE_I_OBJECTS) * len(paper.VS_PLANNERS) * args.table_i_seeds
    print(json.dumps({
        "n_scans": len(specs), "jobs": args.jobs, "max_time_s": args.max_time,
        "pool_wall_s": round(pool_s, 2), "ray_wall_s": round(ray_s, 2),
        "ray_throughput_vs_pool": round(pool_s / ray_s, 3), "results_csv_identical": identical,
        "mean_scan_wall_s": round(mean_scan_s, 3), "table_i_scans": n_table_i,
    }))


if __name__ == "__main__":
    main()
