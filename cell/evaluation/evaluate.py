"""An evaluation: run a grid (``cell.evaluation.grid``), compute each object's coverage limit
(``cell.evaluation.limit``, cached in ``limits.json`` by its inputs) and write the report
(``cell.evaluation.report``), all under one output folder.

Shared by every run on the folder (the shards of a grid, ``cell.evaluation.grid.Shard``): each limit is
added to ``limits.json`` as it is computed (an interrupted run keeps those it finished), and
``results.csv`` and the report are rebuilt from every finished scan, by one writer at a time
(``cell.evaluation.grid.writers``), each file written whole. A shard computes its part of the limits.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from cell.config import load_config
from cell.evaluation.executors import Executor, TaskFailure
from cell.evaluation.grid import (
    WHOLE,
    Shard,
    ran_on,
    run_grid,
    running,
    timelines,
    write_results,
    writers,
)
from cell.evaluation.limit import ROLL_STEP_DEG, cell_coverage_limit
from cell.evaluation.report import Limits, write_report
from cell.evaluation.results import Row, identity, row_id
from cell.evaluation.spec import ScanSpec, input_digest, scan_key
from cell.evaluation.task import ScanTask, TaskOutput, run_scan_task
from cell.packing.result import surface_coverage_radius_m
from drivers.atomic_file import write_text_atomic
from drivers.sim.objects import load_object

LIMITS_JSON = "limits.json"


def run_limit_task(task: tuple[ScanTask, int]) -> float:
    """The coverage limit [%] of a scan's object at its placement on its cell, over the given number of
    view directions per hemisphere (in a worker of the grid's executor, from the task's copies of the
    cell file, the files it names and the mesh)."""
    scan, n_directions = task
    with scan.materialised() as (_, config_path, obj):
        mesh = load_object(obj, scan.spec.object_scale)
        return cell_coverage_limit(load_config(config_path), mesh, scan.spec.placement,
                                   n_directions).coverage_pct


def _limit_key(spec: ScanSpec, n_directions: int) -> str:
    return input_digest(spec.config, spec.object, placement=spec.placement, scale=spec.object_scale,
                        n_directions=n_directions, roll_step_deg=ROLL_STEP_DEG)


def _read_limits(path: Path) -> dict[str, float]:
    return json.loads(path.read_text()) if path.is_file() else {}


def coverage_limits(specs: Sequence[ScanSpec], out: Path, n_directions: int, executor: Executor,
                    stream: TextIO | None = None, shard: Shard = WHOLE) -> Limits:
    """The coverage limit [%] of each object and placement of ``specs`` on its cell, by (object,
    placement) as results.csv writes them; computed once per set of inputs (``shard``'s part of them),
    the new ones side by side on ``executor`` (each is minutes of inverse kinematics on one core), and
    each added to ``limits.json`` as it ends. ``stream`` (default stderr) gets a line saying how many
    are to compute before they start and one with each limit as it ends: the run is silent otherwise
    between its last scan and its report. A limit whose computation failed is left out (the report
    shows none), and why is written to ``stream``. Returns every limit of ``specs`` in
    ``limits.json``, whoever computed it."""
    cache_path = out / LIMITS_JSON
    keyed = {_limit_key(spec, n_directions): spec for spec in specs}
    with writers(out):
        done = _read_limits(cache_path)
    # the part dealt from all the limits, not from those left: the same on every shard whenever it starts
    pending = [key for key in shard.select(keyed) if key not in done]

    def say(text: str) -> None:
        print(f"eval: {text}", file=stream if stream is not None else sys.stderr, flush=True)

    finished = 0

    def on_done(index: int, value: float | TaskFailure) -> None:
        nonlocal finished
        spec = keyed[pending[index]]
        finished += 1
        if isinstance(value, TaskFailure):
            say(f"no coverage limit of {spec.object} at {spec.placement}: {value.reason}")
            return
        say(f"coverage limit of {spec.object_label} at {spec.placement_text}: {value:.1f} % "
            f"({finished}/{len(pending)})")
        with writers(out):
            cache = _read_limits(cache_path)
            cache[pending[index]] = value
            write_text_atomic(cache_path, json.dumps(cache, indent=1, sort_keys=True) + "\n")

    if pending:  # minutes each, after the scans: say what the run is doing until the report
        say(f"{len(pending)} coverage limit{'s' if len(pending) > 1 else ''} to compute, {n_directions} view "
            "directions per hemisphere (minutes of inverse kinematics each; --limit-directions 0 skips "
            "them)")
        executor.run(run_limit_task, [(ScanTask.of(keyed[key], scan_key(keyed[key])), n_directions)
                                      for key in pending], on_done)
    with writers(out):
        cache = _read_limits(cache_path)
    return {(spec.object_label, spec.placement_text): cache[key]
            for key, spec in keyed.items() if key in cache}


@dataclass(frozen=True)
class Evaluation:
    """What a run left: report.md's path, the rows of every finished scan of the grid (results.csv's),
    those of this run's part (its shard; the whole grid without one) and how many scans of the grid
    have no row yet (another shard's, still running)."""

    report: Path
    rows: list[Row]
    mine: list[Row]
    unfinished: int


def evaluate(specs: Sequence[ScanSpec], out: Path, executor: Executor, *, limit_directions: int | None,
             task: Callable[[ScanTask], TaskOutput] = run_scan_task, stream: TextIO | None = None,
             title_lines: Sequence[str] = (), shard: Shard = WHOLE, packing: bool = True) -> Evaluation:
    """Run the grid (``shard``'s part), then the coverage limits on the same executor
    (``limit_directions`` directions per hemisphere; None: none), and the report of every finished scan
    of the grid, after ``title_lines`` a line naming the executors that ran them (``ran_on``), with the
    packing section if ``packing`` (``cell.evaluation.report.write_report``); refuses
    (``CellError``) while another run that could run the same scans runs on ``out``
    (``cell.evaluation.grid.running``)."""
    out.mkdir(parents=True, exist_ok=True)
    with running(out, shard):
        run_grid(specs, out, executor, task, stream, shard)
        limits = coverage_limits(specs, out, limit_directions, executor, stream, shard) \
            if limit_directions else {}
        keyed = {scan_key(spec): spec for spec in specs}
        with writers(out):
            rows = write_results(specs, out)
            unfinished = len(keyed) - len(rows)
            partial = [f"**Partial**: {unfinished} of the grid's {len(keyed)} scans have not finished "
                       "(another shard's, still running, or not run yet); the report is rebuilt as they "
                       "finish.", ""]
            ran = ", ".join(f"{name} ({n})" for name, n in ran_on(rows, out).items())
            executors = [f"Executors that ran these scans (scans each): {ran}.", ""] if ran else []
            report = write_report(rows, out, limits,
                                  [*title_lines, *executors, *(partial if unfinished else [])],
                                  timelines(specs, out), packing=packing,
                                  packing_radii_m=[surface_coverage_radius_m(load_config(config))
                                                   for config in dict.fromkeys(s.config for s in specs)]
                                  if packing else ())
    mine = {identity(keyed[key]) for key in shard.select(keyed)}
    return Evaluation(report, rows, [r for r in rows if row_id(r) in mine], unfinished)
