"""Table I of the visual-servoing paper in simulation against the goal of issue 5: ``cell eval vs-table``
(its eight objects x VS-Local, VS-Global, VS-Hybrid on ``config/sim-franka-rgbd.yaml``, each job
re-processed at 1 mm as the paper measures Table I), then per strategy the objects whose mean coverage
over the seeds is at least Table I's and the mean over the objects of the scan time and the coverage.
The goal: per strategy at least 6 of the 8 objects at the paper's coverage, and a mean VS-Local scan time
of at most 42 s.

The report (results.csv, report.md with Table I beside ours, fig5.png with each scan's coverage and
Chamfer distance against scan time) is under ``--out``; running again skips the scans already done.
Options other than ``--out`` go to ``cell eval vs-table`` as they are (``--planners vs-local --seeds 0``,
``--jobs 2``, ``--executor ray``, ...). Prints JSON {"report": ..., "summary": {...}} as its last line.

Run: ``nice .venv/bin/python benchmarks/vs_table.py [--out /tmp/vs_table] [cell eval vs-table options]``
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from eval_preset import run_preset
from options import first_paragraph

from cell.evaluation import paper
from cell.evaluation.report import figures, groups
from cell.evaluation.results import Row

# Goal of issue 5.
MIN_OBJECTS_AT_PAPER = 6
MAX_LOCAL_TIME_S = 42.0


def summary(rows: Sequence[Row]) -> dict[str, Any]:
    """Per strategy: the objects of Table I at or above its coverage (mean over the seeds), the mean over
    the objects of each one's mean scan time and coverage; and whether the goal is met by the strategies
    that ran (at least one, each on all eight objects)."""
    out: dict[str, Any] = {}
    goal_met = True
    for planner in paper.VS_PLANNERS:
        # mean coverage and scan time per object of Table I that ran with this planner
        means = {g.object: (float(np.mean(figures(rs, "coverage_pct") or [0.0])),
                            float(np.mean(figures(rs, "scan_time_s") or [np.nan])))
                 for g in groups(rows)
                 if (rs := g.by_planner.get(planner)) and g.object in paper.TABLE_I_OBJECTS}
        if not means:  # a strategy not run (--planners): the goal is judged on those that ran
            continue
        below = [o for o, (c, _) in means.items() if c < (paper.table_i(planner, "coverage_pct", o) or 0.0)]
        mean_time = float(np.mean([t for _, t in means.values()]))
        out[planner] = {"objects": len(means), "at_or_above_paper": len(means) - len(below),
                        "below_paper": below, "mean_time_s": round(mean_time, 2),
                        "mean_coverage_pct": round(float(np.mean([c for c, _ in means.values()])), 2)}
        goal_met &= len(means) == len(paper.TABLE_I_OBJECTS)
        goal_met &= len(means) - len(below) >= MIN_OBJECTS_AT_PAPER
        if planner == "vs-local":
            goal_met &= mean_time <= MAX_LOCAL_TIME_S
    out["goal_met"] = goal_met and bool(out)
    return out


def main() -> None:
    report, rows = run_preset("vs-table", Path("/tmp/vs_table"), first_paragraph(__doc__))
    print(json.dumps({"report": str(report), "summary": summary(rows)}))


if __name__ == "__main__":
    main()
