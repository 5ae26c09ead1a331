"""``cell eval``'s executors on this machine: the same 16-scan grid on the local process pool and on a
local Ray instance of the same size; wall time of each, their ratio (issue 23's goal: Ray at least 0.9x
the pool's throughput) and whether their results.csv are byte-identical. Also the mean wall time of one
scan of the grid.

The grid: 4 packing objects x lr-nbv and heu x seeds 0 1 on ``config/sim-ur5e-tof.yaml`` with the cell's
own time budget (the packing preset's; ``--max-time`` to shorten it), no coverage limit.

Both wall times count everything a user waits for: the pool starts its worker processes, Ray its
instance (``ray.init``: GCS, raylet, agents, the pre-started workers), and the workers of both import
the scan's modules before their first scan. ``--repeats`` runs pool and Ray that many times each,
interleaved, the order reversed from one repeat to the next (pool then Ray, Ray then pool:
``benchmarks/interleaved.py``) so that a change of the machine's load falls on both, and reports the
median of each and the median and range of the per-repeat ratios. ``--attached`` also times Ray on an
instance started beforehand (what a user with a running cluster, ``--ray-address``, waits for), which
shows Ray's start-up apart; it takes its turn with the others (pool, Ray, attached; then attached, Ray,
pool), so that it and the pool run first alike. Only completed scans are timed: a run with a scan
whose status in results.csv is not ``completed`` (a budget too short, a refused scan) ends the benchmark
with the first of them named and exit code 1.

Prints JSON. Run: ``nice .venv/bin/python benchmarks/eval_executors.py [--jobs 2] [--repeats 2]
[--max-time S] [--attached]``
"""

from __future__ import annotations

import io
import json
import tempfile
import time
from pathlib import Path

from interleaved import compared, in_turn
from options import BenchmarkParser, count, first_paragraph, positive

from cell.evaluation import paper
from cell.evaluation.executors import Executor, LocalPool, RayExecutor
from cell.evaluation.grid import RESULTS_CSV, run_grid
from cell.evaluation.results import read_csv
from cell.evaluation.spec import ScanSpec, cross

REPO = Path(__file__).resolve().parents[1]


def timed(executor: Executor, specs: list[ScanSpec], out: Path) -> float:
    """Wall time [s] of the grid into the empty folder ``out``."""
    start = time.perf_counter()
    run_grid(specs, out, executor, stream=io.StringIO())
    return time.perf_counter() - start


def not_completed(out: Path) -> str | None:
    """Which scans of the grid run into ``out`` did not complete (their status in results.csv), or None:
    a failed scan ends early, so its grid's wall time would not be the executor's."""
    rows = read_csv(out / RESULTS_CSV)
    failed = [r for r in rows if r["status"] != "completed"]
    if not failed:
        return None
    first = failed[0]
    return (f"{len(failed)} of {len(rows)} scans did not complete, so their wall time measures no executor "
            f"(the first: {first['object']} {first['planner']} seed {first['seed']}, {first['status']}: "
            f"{first['termination']})")


def timed_attached(jobs: int, specs: list[ScanSpec], out: Path) -> tuple[float, float]:
    """(seconds to start a local Ray instance of ``jobs`` CPUs, seconds of the grid on it)."""
    import ray

    start = time.perf_counter()
    ray.init(num_cpus=jobs, include_dashboard=False, log_to_driver=False)
    try:
        return time.perf_counter() - start, timed(RayExecutor(jobs=jobs), specs, out)
    finally:
        ray.shutdown()


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--jobs", type=count, default=2)
    parser.add_argument("--max-time", type=positive, default=None,
                        help="scan budget [s] (default: the cell's)")
    parser.add_argument("--repeats", type=count, default=2)
    parser.add_argument("--attached", action="store_true", help="also Ray on an instance started before")
    args = parser.parse_args()
    cases = [(o, (0.0, 0.0, 0.0)) for o in paper.PACKING_OBJECTS]
    specs = cross(str(REPO / "config" / "sim-ur5e-tof.yaml"), cases, ["lr-nbv", "heu"], [0, 1], args.max_time)
    pool_s: list[float] = []
    ray_s: list[float] = []
    attached: list[tuple[float, float]] = []
    identical = True
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeats):
            root = Path(tmp) / str(k)
            for kind in in_turn(k, ("pool", "ray", *(("attached",) if args.attached else ()))):
                if kind == "pool":
                    pool_s.append(timed(LocalPool(args.jobs), specs, root / kind))
                elif kind == "ray":
                    ray_s.append(timed(RayExecutor(jobs=args.jobs), specs, root / kind))
                else:
                    attached.append(timed_attached(args.jobs, specs, root / kind))
                if problem := not_completed(root / kind):
                    parser.error(f"{kind}: {problem}")
            reference = (root / "pool" / RESULTS_CSV).read_bytes()
            identical &= all((root / kind / RESULTS_CSV).read_bytes() == reference
                             for kind in ("ray", "attached") if (root / kind).exists())
        results = (Path(tmp) / "0" / "pool").glob("scans/*/result.json")
        scan_s = [json.loads(p.read_text())["wall_time_s"] for p in results]
    mean_scan_s = sum(scan_s) / len(scan_s)
    throughput = compared(pool_s, ray_s)  # pool's time / Ray's: Ray's throughput against the pool's
    report = {
        "n_scans": len(specs), "jobs": args.jobs, "max_time_s": args.max_time, "repeats": args.repeats,
        "pool_wall_s": [round(s, 2) for s in pool_s], "ray_wall_s": [round(s, 2) for s in ray_s],
        "pool_wall_median_s": round(throughput.this, 2), "ray_wall_median_s": round(throughput.reference, 2),
        "ray_throughput_vs_pool": round(throughput.ratio, 3),
        "ray_throughput_vs_pool_range": throughput.ratios()["ratio_range"],
        "results_csv_identical": identical,
        "mean_scan_wall_s": round(mean_scan_s, 3),
    }
    if attached:
        report["ray_start_s"] = [round(start, 2) for start, _ in attached]
        report["ray_attached_wall_s"] = [round(wall, 2) for _, wall in attached]
        attached_throughput = compared(pool_s, [wall for _, wall in attached])
        report["ray_attached_throughput_vs_pool"] = round(attached_throughput.ratio, 3)
        report["ray_attached_throughput_vs_pool_range"] = attached_throughput.ratios()["ratio_range"]
    print(json.dumps(report))


if __name__ == "__main__":
    main()
