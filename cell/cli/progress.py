"""How a long command shows its progress: a bar on a terminal, and on a pipe or under a service manager
(standard error not a terminal) a line to standard error every few seconds, so that a log shows the job
alive long before it ends.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn

from cell.jobs.progress import JobProgress
from cell.perception.reprocess import StageReport

LINE_INTERVAL_S = 5.0
"""The least time [s] between two progress lines: job time for a scan (simulated in sim), wall time for
offline work."""

class ProgressLines:
    """Lines ``<label>: <text>`` to standard error, at most one per ``interval_s`` of the clock the
    caller gives, the first at once; ``force`` writes one whatever the time."""

    def __init__(self, label: str, interval_s: float = LINE_INTERVAL_S) -> None:
        self._label = label
        self._interval_s = interval_s
        self._last: float | None = None

    def offer(self, t: float, text: str, force: bool = False) -> None:
        if not force and self._last is not None and t - self._last < self._interval_s:
            return
        self._last = t
        print(f"{self._label}: {text}", file=sys.stderr, flush=True)


BAR_CONSOLE = Console(stderr=True)
"""Standard error as the bars write it: a line printed through it while a bar shows goes above the bar
(through another console, the bar's next refresh would write over it)."""


def _bar(*columns: TextColumn | BarColumn | MofNCompleteColumn) -> Progress:
    return Progress(*columns, console=BAR_CONSOLE, transient=True)


def scan_line(p: JobProgress, budget_s: float) -> str:
    """One progress line of a scan: job time of the budget [s], captures, cloud size, cloud coverage
    (eq. 13 of the cloud as it stands, before the ground truth is registered to it: the final line's
    registered figure differs, README)."""
    coverage = "-" if p.coverage_pct is None else f"{p.coverage_pct:.1f} %"
    return (f"{p.t_s:.1f} of {budget_s:g} s, {p.n_captures} captures, {p.n_cloud_points} points, "
            f"cloud coverage {coverage}")


@contextmanager
def scan_progress(budget_s: float) -> Iterator[Callable[[JobProgress], None]]:
    """The ``on_progress`` of ``cell scan``: a bar over the time budget [s] on a terminal, else a line
    every ``LINE_INTERVAL_S`` of job time."""
    if not sys.stderr.isatty():
        lines = ProgressLines("scan")
        yield lambda p: lines.offer(p.t_s, scan_line(p, budget_s))
        return
    with _bar(TextColumn("[bold]scan"), BarColumn(),
              TextColumn("{task.fields[sim]:6.1f} s  {task.fields[captures]:3d} captures  "
                         "cloud coverage {task.fields[coverage]:5.1f} %")) as bar:
        task = bar.add_task("scan", total=budget_s, sim=0.0, captures=0, coverage=0.0)

        def show(p: JobProgress) -> None:
            bar.update(task, completed=p.t_s, sim=p.t_s, captures=p.n_captures,
                       coverage=p.coverage_pct or 0.0)

        yield show


class _StageLines:
    """A :data:`StageReport` as lines: one every ``LINE_INTERVAL_S`` of wall time, and one at the start and
    the end of each stage."""

    def __init__(self, label: str) -> None:
        self._lines = ProgressLines(label)
        self._stage: str | None = None

    def __call__(self, stage: str, done: int, total: int) -> None:
        new, self._stage = stage != self._stage, stage
        self._lines.offer(time.monotonic(), f"{stage} {done}/{total}", force=new or done == total)


@contextmanager
def stage_progress(label: str) -> Iterator[StageReport]:
    """A :data:`StageReport` for offline work: a bar per stage on a terminal, else lines
    (:class:`_StageLines`)."""
    if not sys.stderr.isatty():
        yield _StageLines(label)
        return
    with _bar(TextColumn(f"[bold]{label}" + " {task.description}"), BarColumn(), MofNCompleteColumn()) as bar:
        tasks: dict[str, TaskID] = {}

        def show(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done, total=total)

        yield show
