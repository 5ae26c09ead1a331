"""An evaluation: run a grid (``cell.evaluation.grid``), compute each object's coverage limit
(``cell.evaluation.limit``, cached in ``limits.json`` by its inputs) and write the report
(``cell.evaluation.report``), all under one output folder."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TextIO

from cell.config import load_config
from cell.evaluation.executors import Executor
from cell.evaluation.grid import run_grid, timelines
from cell.evaluation.limit import ROLL_STEP_DEG, cell_coverage_limit
from cell.evaluation.report import Limits, write_report
from cell.evaluation.spec import ScanSpec, input_digest
from cell.evaluation.task import ScanTask, TaskOutput, run_scan_task
from drivers.sim.objects import load_object

LIMITS_JSON = "limits.json"


def coverage_limits(specs: Sequence[ScanSpec], out: Path, n_directions: int) -> Limits:
    """The coverage limit [%] of each object and placement of ``specs`` on its cell, by (object,
    placement) as results.csv writes them; computed once per set of inputs and kept in ``limits.json``."""
    cache_path = out / LIMITS_JSON
    cache: dict[str, float] = json.loads(cache_path.read_text()) if cache_path.is_file() else {}
    limits: Limits = {}
    for spec in specs:
        key = input_digest(spec.config, spec.object, placement=spec.placement, scale=spec.object_scale,
                           n_directions=n_directions, roll_step_deg=ROLL_STEP_DEG)
        if key not in cache:
            mesh = load_object(spec.object, spec.object_scale)
            cache[key] = cell_coverage_limit(load_config(spec.config), mesh, spec.placement,
                                             n_directions).coverage_pct
        limits[(spec.object_label, spec.placement_text)] = cache[key]
    cache_path.write_text(json.dumps(cache, indent=1, sort_keys=True) + "\n")
    return limits


def evaluate(specs: Sequence[ScanSpec], out: Path, executor: Executor, *, limit_directions: int | None,
             task: Callable[[ScanTask], TaskOutput] = run_scan_task, stream: TextIO | None = None,
             title_lines: Sequence[str] = ()) -> Path:
    """Run the grid, the coverage limits (``limit_directions`` directions per hemisphere; None: none)
    and the report; returns report.md's path."""
    rows = run_grid(specs, out, executor, task, stream)
    limits = coverage_limits(specs, out, limit_directions) if limit_directions else {}
    return write_report(rows, out, limits, title_lines, timelines(specs, out))
