"""An evaluation: run a grid (``cell.evaluation.grid``), compute each object's coverage limit
(``cell.evaluation.limit``, cached in ``limits.json`` by its inputs) and write the report
(``cell.evaluation.report``), all under one output folder."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TextIO

from cell.config import load_config
from cell.evaluation.executors import Executor, TaskFailure
from cell.evaluation.grid import run_grid, timelines
from cell.evaluation.limit import ROLL_STEP_DEG, cell_coverage_limit
from cell.evaluation.report import Limits, write_report
from cell.evaluation.spec import ScanSpec, input_digest
from cell.evaluation.task import ScanTask, TaskOutput, run_scan_task
from drivers.sim.objects import load_object

LIMITS_JSON = "limits.json"


def run_limit_task(task: tuple[ScanSpec, int]) -> float:
    """The coverage limit [%] of a scan's object at its placement on its cell, over the given number of
    view directions per hemisphere (in a worker of the grid's executor)."""
    spec, n_directions = task
    mesh = load_object(spec.object, spec.object_scale)
    return cell_coverage_limit(load_config(spec.config), mesh, spec.placement, n_directions).coverage_pct


def coverage_limits(specs: Sequence[ScanSpec], out: Path, n_directions: int, executor: Executor,
                    stream: TextIO | None = None) -> Limits:
    """The coverage limit [%] of each object and placement of ``specs`` on its cell, by (object,
    placement) as results.csv writes them; computed once per set of inputs, the new ones side by side on
    ``executor`` (each is minutes of inverse kinematics on one core), and kept in ``limits.json``. A limit
    whose computation failed is left out (the report shows none), and why is written to ``stream``
    (default stderr)."""
    cache_path = out / LIMITS_JSON
    cache: dict[str, float] = json.loads(cache_path.read_text()) if cache_path.is_file() else {}
    keys = [input_digest(spec.config, spec.object, placement=spec.placement, scale=spec.object_scale,
                         n_directions=n_directions, roll_step_deg=ROLL_STEP_DEG) for spec in specs]
    todo = {key: spec for key, spec in zip(keys, specs, strict=True) if key not in cache}
    pending = list(todo)

    def on_done(index: int, value: float | TaskFailure) -> None:
        if isinstance(value, TaskFailure):
            spec = todo[pending[index]]
            print(f"eval: no coverage limit of {spec.object} at {spec.placement}: {value.reason}",
                  file=stream if stream is not None else sys.stderr, flush=True)
        else:
            cache[pending[index]] = value

    if todo:
        executor.run(run_limit_task, [(todo[key], n_directions) for key in pending], on_done)
    cache_path.write_text(json.dumps(cache, indent=1, sort_keys=True) + "\n")
    return {(spec.object_label, spec.placement_text): cache[key]
            for spec, key in zip(specs, keys, strict=True) if key in cache}


def evaluate(specs: Sequence[ScanSpec], out: Path, executor: Executor, *, limit_directions: int | None,
             task: Callable[[ScanTask], TaskOutput] = run_scan_task, stream: TextIO | None = None,
             title_lines: Sequence[str] = ()) -> Path:
    """Run the grid, then the coverage limits on the same executor (``limit_directions`` directions per
    hemisphere; None: none), and the report; returns report.md's path."""
    rows = run_grid(specs, out, executor, task, stream)
    limits = coverage_limits(specs, out, limit_directions, executor, stream) if limit_directions else {}
    return write_report(rows, out, limits, title_lines, timelines(specs, out))
