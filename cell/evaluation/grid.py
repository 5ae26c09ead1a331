"""Run a grid of scans on an executor, resumably, and leave ``results.csv`` under ``--out``.

Layout of the output folder: ``scans/<object>-<planner>-s<seed>-<key>/`` holds each scan's job folder
(shipped back from its worker, unpacked here) and ``results.csv`` a row per scan. A scan whose job folder
exists is done: running the grid again skips it (the key changes with any input, see
``cell.evaluation.spec``). A job folder appears at once, complete: it is unpacked beside its final name
and renamed. A scan that left no folder (refused, or its worker died twice) is a ``failed`` row and runs
again next time.
"""

from __future__ import annotations

import shutil
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from cell.evaluation.executors import Executor, TaskFailure
from cell.evaluation.results import (
    Row,
    RowId,
    Timeline,
    csv_text,
    failed_row,
    identity,
    row_from_folder,
    sorted_rows,
    timeline_from_folder,
)
from cell.evaluation.spec import ScanSpec, folder_name, scan_key
from cell.evaluation.task import ScanTask, TaskOutput, run_scan_task, unpack_folder

SCANS_DIR = "scans"
RESULTS_CSV = "results.csv"


def scan_folder(out: Path, spec: ScanSpec, key: str | None = None) -> Path:
    """The job folder of the scan ``spec`` (of key ``key``, computed when None) under ``out``."""
    return out / SCANS_DIR / folder_name(spec, key or scan_key(spec))


def timelines(specs: Sequence[ScanSpec], out: Path) -> dict[RowId, Timeline]:
    """The timelines of the re-processed scans of ``specs`` under ``out``, by row."""
    found = ((identity(spec), timeline_from_folder(scan_folder(out, spec))) for spec in specs)
    return {row: timeline for row, timeline in found if timeline is not None}


def _duration(seconds: float) -> str:
    minutes, s = divmod(round(seconds), 60)
    hours, m = divmod(minutes, 60)
    return f"{hours}h{m:02d}m{s:02d}s" if hours else f"{m}m{s:02d}s"


@dataclass
class GridProgress:
    """``eval: <finished>/<total> scans (<failed> failed), <elapsed>, about <left> left`` on ``stream``
    after each scan; scans found done count as finished, and the estimate of the time left extrapolates
    from the scans this run finished."""

    total: int
    already_done: int
    stream: TextIO = field(default_factory=lambda: sys.stderr)
    finished: int = 0
    failed: int = 0
    _start: float = field(default_factory=time.monotonic)

    def __post_init__(self) -> None:
        self.finished = self.already_done
        if self.already_done:
            self._line(f"{self.already_done} scans already done, {self.total - self.already_done} to run")

    def _line(self, text: str) -> None:
        print(f"eval: {text}", file=self.stream, flush=True)

    def done(self, failed: bool) -> None:
        self.finished += 1
        self.failed += failed
        elapsed = time.monotonic() - self._start
        ran = self.finished - self.already_done
        left = elapsed / ran * (self.total - self.finished)
        self._line(f"{self.finished}/{self.total} scans ({self.failed} failed), {_duration(elapsed)}, "
                   f"about {_duration(left)} left")


def run_grid(specs: Sequence[ScanSpec], out: Path, executor: Executor,
             task: Callable[[ScanTask], TaskOutput] = run_scan_task,
             stream: TextIO | None = None) -> list[Row]:
    """Run the scans of ``specs`` not done yet under ``out`` on ``executor`` and write ``results.csv``;
    returns its rows (sorted). ``task`` runs one scan in a worker (the real scan by default)."""
    (out / SCANS_DIR).mkdir(parents=True, exist_ok=True)
    keyed = {scan_key(spec): spec for spec in specs}  # a scan listed twice runs once
    folders = {key: scan_folder(out, spec, key) for key, spec in keyed.items()}
    todo = [key for key, folder in folders.items() if not (folder / "result.json").is_file()]
    rows = {key: row_from_folder(keyed[key], folder) for key, folder in folders.items() if key not in todo}
    progress = GridProgress(len(keyed), len(rows), stream if stream is not None else sys.stderr)

    def on_done(index: int, output: TaskOutput | TaskFailure) -> None:
        key = todo[index]
        spec, folder = keyed[key], folders[key]
        if isinstance(output, TaskFailure):
            rows[key] = failed_row(spec, output.reason)
        elif output.archive is None:
            rows[key] = failed_row(spec, output.error or "the scan left no job folder")
        else:
            partial = folder.with_name(folder.name + ".partial")
            shutil.rmtree(partial, ignore_errors=True)
            unpack_folder(output.archive, partial)
            partial.rename(folder)
            rows[key] = row_from_folder(spec, folder)
        progress.done(rows[key]["status"] == "failed")

    executor.run(task, [ScanTask.of(keyed[key], key) for key in todo], on_done)
    ordered = sorted_rows(rows.values())
    (out / RESULTS_CSV).write_text(csv_text(ordered))
    return ordered
