"""Table I of the visual-servoing paper in simulation: the eight objects x VS-Local, VS-Global and VS-Hybrid,
each a full ``cell scan`` job (``config/sim-franka-rgbd.yaml``, default noise, per job seed), beside the
paper's figures.

The paper's Table I is measured on clouds rebuilt offline from the scan's frames (section III-B: 1 mm
resolution, multiway registration), not on the online 2.5 mm cloud; each job is therefore re-processed
the same way (``cell reprocess``, ``cell.perception.reprocess``) and both are reported: the figures of
the paper's procedure first, the online cloud's after them.

Per run: coverage [%], Chamfer and Hausdorff [mm] (eq. 13), scan time [s of sim time, from the first frame
at the start view, as the paper's clocks; ``scan_time_s`` of result.json] and the sensor's path length
over the same span [m] (``scan_path_length_m``),
each with the paper's value for the same object and strategy (Table I; for time and path the paper gives
only the mean over objects: 42 / 57 / 67 s and 0.8 / 0.8 / 1.2 m). The summary checks the goal of issue 5
on the paper's procedure: per strategy, coverage at least the paper's on at least 6 of the 8 objects, and
a mean VS-Local scan time of at most 42 s.

``--seeds 0 1 2`` runs every object and strategy once per job seed (sensor noise and the planners'
random streams), as the paper ran each three times: Table I's figures are means of three runs (N = 3).
A scan's time depends strongly on small differences early on (VS-Local, seed 0 / 1 / 2: bunny 75 / 34 /
77 s, mustard 71 / 41 / 92 s), so one seed says little about a mean. With more than one seed the table
adds per object the mean and standard error over the seeds, as the paper reports them, and the summary
judges the mean coverage per object.

Re-processing also gives each run's eq. 13 figures as the scan went on (``timeline`` of
``result_hires.json``): the table adds the scan time at which a run first reached the paper's coverage for
its object and strategy, and ``<out>/fig5.png`` plots Chamfer distance and coverage against scan time, per
object, as the paper's Fig. 5 (bottom) does, a dot where each scan terminated.

Prints the table, then as its last line JSON {"runs": [...], "means": {...}, "summary": {...}};
``--json`` also writes that JSON to a file. Runs go ``--jobs`` at a time (default 2), each in its own process.

Run: ``nice .venv/bin/python benchmarks/vs_table.py [--planners vs-local] [--objects bunny cube]
[--seeds 0 1 2] [--object-pose 0.03 -0.02 40] [--out /tmp/vs_table] [--json table.json]``
"""

from __future__ import annotations

import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure  # not pyplot: a file only, no display

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from grid_report import grid_parser, print_result, refuse_taken

from cell.config import load_config
from cell.evaluation import paper
from cell.jobs.runner import ScanRequest, run_scan
from cell.perception.reprocess import reprocess_job

REPO = Path(__file__).resolve().parents[1]
OBJECTS = paper.TABLE_I_OBJECTS
PLANNERS = paper.VS_PLANNERS
PAPER_TIME_S = paper.MEAN_SCAN_TIME_S
PAPER_PATH_M = paper.MEAN_PATH_M
# Goal of issue 5.
MIN_OBJECTS_AT_PAPER = 6
MAX_LOCAL_TIME_S = 42.0


def job_folder(out: Path, obj: str, planner: str, seed: int) -> Path:
    """The folder of one scan job under ``out``."""
    return out / f"{obj}-{planner}-s{seed}"


def run_one(config_path: Path, obj: str, planner: str, seed: int, pose: tuple[float, float, float],
            out: Path) -> dict[str, Any]:
    """One scan job, re-processed: the metrics of the paper's procedure and of the online cloud (``online``),
    sim time, path length, termination and the wall time [s] of the scan and of the re-processing."""
    cfg = load_config(config_path)
    wall = time.perf_counter()
    folder = job_folder(out, obj, planner, seed)
    r = run_scan(ScanRequest(config=cfg, config_path=str(config_path), object=obj, object_pose=pose,
                             planner=planner, seed=seed, out=folder)).result
    scan_wall = time.perf_counter() - wall
    hires = reprocess_job(folder)
    m = hires["metrics"] or {}
    return {"object": obj, "planner": planner, "seed": seed, "status": r["status"],
            "termination": r["termination"], "coverage_pct": m.get("coverage_pct"),
            "chamfer_mm": m.get("chamfer_mm"), "hausdorff_mm": m.get("hausdorff_mm"),
            "online": r["metrics"], "scan_time_s": r["scan_time_s"], "sim_time_s": r["sim_time_s"],
            "path_length_m": r["scan_path_length_m"],
            "time_to_paper_coverage_s": time_to_coverage(hires["timeline"],
                                                         paper_value(planner, "coverage_pct", obj)),
            "timeline": hires["timeline"],
            "n_captures": r["n_captures"], "wall_s": round(scan_wall, 2),
            "reprocess_wall_s": round(time.perf_counter() - wall - scan_wall, 2)}


def time_to_coverage(timeline: dict[str, list[float | None]] | None, coverage_pct: float | None
                     ) -> float | None:
    """Scan time [s] of the first frame whose cloud, with the frames before it, reaches ``coverage_pct``
    (re-processing's timeline); None if it never does, or nothing is known to compare."""
    if timeline is None or coverage_pct is None:
        return None
    return next((t for t, c in zip(timeline["t_s"], timeline["coverage_pct"], strict=True)
                 if t is not None and c is not None and c >= coverage_pct), None)


paper_value = paper.table_i


def _pair(value: float | None, paper: float | None, digits: int) -> str:
    ours = "-" if value is None else f"{value:.{digits}f}"
    return ours if paper is None else f"{ours} ({paper:.{digits}f})"


def table(runs: list[dict[str, Any]]) -> list[str]:
    """One line per run, ours (paper's) side by side."""
    lines = [f"{'planner':9} {'object':9} {'seed':>4} {'coverage %':>14} {'Chamfer mm':>12} "
             f"{'Hausdorff mm':>14} {'time s':>12} {'to paper cov. s':>15} {'path m':>11}  "
             f"{'online: cov % / Ch / Hd':>24}  termination"]
    for r in runs:
        p, o = r["planner"], r["object"]
        online = r["online"] or {}
        online_text = " / ".join("-" if online.get(k) is None else f"{online[k]:.1f}"
                                 for k in ("coverage_pct", "chamfer_mm", "hausdorff_mm"))
        lines.append(
            f"{p:9} {o:9} {r['seed']:>4} "
            f"{_pair(r['coverage_pct'], paper_value(p, 'coverage_pct', o), 1):>14} "
            f"{_pair(r['chamfer_mm'], paper_value(p, 'chamfer_mm', o), 1):>12} "
            f"{_pair(r['hausdorff_mm'], paper_value(p, 'hausdorff_mm', o), 1):>14} "
            f"{_pair(r['scan_time_s'], PAPER_TIME_S.get(p), 1):>12} "
            f"{_pair(r['time_to_paper_coverage_s'], None, 1):>15} "
            f"{_pair(r['path_length_m'], PAPER_PATH_M.get(p), 2):>11}  {online_text:>24}  "
            f"{r['termination'][:60]}")
    return lines


MEAN_KEYS = ("coverage_pct", "chamfer_mm", "hausdorff_mm", "scan_time_s", "path_length_m",
             "online_coverage_pct")


def _mean_se(values: list[float]) -> dict[str, float | None]:
    """Mean and standard error of the mean (None for one value), as Table I's "± standard error"."""
    se = float(np.std(values, ddof=1) / np.sqrt(len(values))) if len(values) > 1 else None
    return {"mean": float(np.mean(values)), "se": se}


def _figure(run: dict[str, Any], key: str) -> float:
    """One of ``MEAN_KEYS`` of a run; 0 where it has none (e.g. no ground truth)."""
    value = (run["online"] or {}).get("coverage_pct") if key == "online_coverage_pct" else run.get(key)
    return float(value or 0.0)


def object_means(runs: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, Any]]]:
    """Per strategy and object, over its runs (one per seed): ``n`` and the mean and standard error of
    each of ``MEAN_KEYS``."""
    grouped: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for r in runs:
        grouped.setdefault(r["planner"], {}).setdefault(r["object"], []).append(r)
    return {planner: {obj: {"n": len(rs), **{k: _mean_se([_figure(r, k) for r in rs]) for k in MEAN_KEYS}}
                      for obj, rs in per_object.items()}
            for planner, per_object in grouped.items()}


def means_table(means: dict[str, dict[str, dict[str, Any]]]) -> list[str]:
    """Table I's layout: per strategy and object the mean ± standard error over the seeds, the paper's
    figure in brackets."""
    def cell(m: dict[str, float | None], paper: float | None, digits: int) -> str:
        se = "" if m["se"] is None else f" ± {m['se']:.{digits}f}"
        return f"{m['mean']:.{digits}f}{se}" + ("" if paper is None else f" ({paper:.{digits}f})")

    lines = [f"{'planner':9} {'object':9} {'n':>2} {'coverage %':>21} {'Chamfer mm':>18} "
             f"{'Hausdorff mm':>20} {'time s':>19}"]
    for planner, per_object in means.items():
        for obj, m in per_object.items():
            lines.append(
                f"{planner:9} {obj:9} {m['n']:>2} "
                f"{cell(m['coverage_pct'], paper_value(planner, 'coverage_pct', obj), 1):>21} "
                f"{cell(m['chamfer_mm'], paper_value(planner, 'chamfer_mm', obj), 1):>18} "
                f"{cell(m['hausdorff_mm'], paper_value(planner, 'hausdorff_mm', obj), 1):>20} "
                f"{cell(m['scan_time_s'], None, 1):>19}")
    return lines


def summary(runs: list[dict[str, Any]], means: dict[str, dict[str, dict[str, Any]]]) -> dict[str, Any]:
    """Per strategy: objects whose mean coverage over the seeds is at or above the paper's (of those in
    Table I that ran; with the paper's procedure, and with the online cloud), the mean over objects of
    each object's mean time and path, each run's time to the paper's coverage; and the goal of issue 5
    where all eight objects ran. ``means``: ``object_means(runs)``."""
    out: dict[str, Any] = {}
    goal_met = True
    for planner, per_object in means.items():
        # (object, its means, Table I's coverage) of the objects in Table I
        judged = [(obj, m, paper) for obj, m in per_object.items()
                  if (paper := paper_value(planner, "coverage_pct", obj)) is not None]
        at_paper = [obj for obj, m, paper in judged if m["coverage_pct"]["mean"] >= paper]
        online = [obj for obj, m, paper in judged if m["online_coverage_pct"]["mean"] >= paper]
        rs = [r for r in runs if r["planner"] == planner]
        objects = per_object.values()
        entry: dict[str, Any] = {
            "n_runs": len(rs), "seeds": sorted({r["seed"] for r in rs}),
            "at_or_above_paper": len(at_paper), "of": len(judged),
            "below_paper": [obj for obj, _, _ in judged if obj not in at_paper],
            "at_or_above_paper_online": len(online),
            "mean_coverage_pct": round(float(np.mean([m["coverage_pct"]["mean"] for m in objects])), 2),
            "mean_time_s": round(float(np.mean([m["scan_time_s"]["mean"] for m in objects])), 2),
            "time_to_paper_coverage_s": {obj: [r["time_to_paper_coverage_s"] for r in rs
                                               if r["object"] == obj] for obj, _, _ in judged},
            "mean_path_m": round(float(np.mean([m["path_length_m"]["mean"] for m in objects])), 3),
        }
        out[planner] = entry
        if {obj for obj, _, _ in judged} == set(OBJECTS):
            goal_met &= len(at_paper) >= MIN_OBJECTS_AT_PAPER
            if planner == "vs-local":
                goal_met &= entry["mean_time_s"] <= MAX_LOCAL_TIME_S
        else:
            goal_met = False
    out["goal_met"] = goal_met and set(PLANNERS) <= set(out)
    return out


def plot_timelines(runs: list[dict[str, Any]], path: Path) -> None:
    """The paper's Fig. 5 (bottom) for these runs: per object, Chamfer distance [mm] (top panel) and
    coverage [%] (bottom, Table I's figure per strategy dashed) against scan time [s], a line per
    strategy and seed, a dot where the scan terminated."""
    objects = list(dict.fromkeys(r["object"] for r in runs))
    cols = min(4, len(objects))
    rows = -(-len(objects) // cols)
    fig = Figure(figsize=(4.0 * cols, 5.0 * rows))
    axes = fig.subplots(2 * rows, cols, squeeze=False)
    colours = dict(zip(PLANNERS, ("tab:blue", "tab:orange", "tab:green"), strict=True))
    for i, obj in enumerate(objects):
        top, bottom = axes[2 * (i // cols), i % cols], axes[2 * (i // cols) + 1, i % cols]
        labelled: set[str] = set()
        for r in (r for r in runs if r["object"] == obj and r["timeline"] is not None):
            tl, colour = r["timeline"], colours.get(r["planner"], "tab:gray")
            label = None if r["planner"] in labelled else r["planner"]
            labelled.add(r["planner"])
            for ax, key in ((top, "chamfer_mm"), (bottom, "coverage_pct")):
                ax.plot(tl["t_s"], tl[key], color=colour, label=label)
                ax.plot([r["scan_time_s"]], [tl[key][-1]], "o", color=colour)
            paper = paper_value(r["planner"], "coverage_pct", obj)
            if paper is not None:
                bottom.axhline(paper, color=colour, linestyle="--", linewidth=0.8)
        top.set_title(obj)
        top.set_ylabel("Chamfer [mm]")
        top.set_ylim(bottom=0.0)
        bottom.set_ylabel("coverage [%]")
        bottom.set_xlabel("scan time [s]")
        top.legend(fontsize="small")
    for j in range(len(objects), rows * cols):
        axes[2 * (j // cols), j % cols].set_visible(False)
        axes[2 * (j // cols) + 1, j % cols].set_visible(False)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = grid_parser(__doc__.splitlines()[0], REPO / "config" / "sim-franka-rgbd.yaml", OBJECTS, PLANNERS,
                         Path("/tmp/vs_table"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0],
                        help="job seeds; every scan runs once per seed")
    parser.add_argument("--jobs", type=int, default=2, help="scans run at the same time")
    args = parser.parse_args()
    grid = [(p, o, s) for p in args.planners for o in args.objects for s in args.seeds]
    refuse_taken(parser, [job_folder(args.out, o, p, s) for p, o, s in grid])
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = [pool.submit(run_one, args.config, o, p, s, tuple(args.object_pose), args.out)
                   for p, o, s in grid]
        runs = []
        for future in futures:
            run = future.result()
            online = (run["online"] or {}).get("coverage_pct")
            print(f"{run['planner']:9} {run['object']:9} seed {run['seed']} coverage {run['coverage_pct']} % "
                  f"(online {online} %), {run['scan_time_s']} s, {run['wall_s']} s wall + "
                  f"{run['reprocess_wall_s']} s re-processing; {run['termination']}", flush=True)
            runs.append(run)
    print("\n".join(table(runs)))
    means = object_means(runs)
    if len(args.seeds) > 1:
        print("\n".join(means_table(means)))
    plot_timelines(runs, args.out / "fig5.png")
    print(f"Fig. 5 (Chamfer and coverage against scan time): {args.out / 'fig5.png'}")
    result = {"runs": runs, "means": means, "summary": summary(runs, means)}
    print_result(result, args.json)


if __name__ == "__main__":
    main()
