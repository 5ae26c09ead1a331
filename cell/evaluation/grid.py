"""Run a grid of scans on an executor, resumably, and leave ``results.csv`` under ``--out``.

Layout of the output folder: ``scans/<object>-<planner>-s<seed>-<key>/`` holds each scan's job folder
(shipped back from its worker, unpacked here) and ``results.csv`` a row per scan. A scan whose job folder
exists is done: running the grid again skips it (the key changes with any input, see
``cell.evaluation.spec``). A job folder appears at once, complete: it is unpacked beside its final name
and renamed. A scan that left no folder (refused, or its worker died twice) leaves
``scans/<folder name>.failed`` holding why: a ``failed`` row, and it runs again next time. A job folder
holds ``EXECUTOR_TXT``, the name of the executor that ran its scan (the report says which ran the grid's).

``results.csv`` is rebuilt from the output folder each time it is written, for every scan of the grid
whose folder (or ``.failed``) is there, whoever ran it; a scan neither done nor failed yet (another
shard's, still running) has no row. It is written whole (a temporary file renamed over it), one writer at
a time (``report_lock``), so that the last one written holds every scan finished before it.

Several machines can share a grid (``Shard``: ``--shard I/N`` runs the I-th of N disjoint parts, dealt
from the grid's scans by key), each on the same output folder (a shared file system). Runs that could
run the same scans are refused on one folder (``running``): a second run of the whole grid, or of the
same shard, or of a shard of another count, while one runs.
"""

from __future__ import annotations

import fcntl
import os
import re
import shutil
import socket
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TextIO

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
from drivers.atomic_file import write_text_atomic
from drivers.errors import CellError

SCANS_DIR = "scans"
RESULTS_CSV = "results.csv"
EXECUTOR_TXT = "eval_executor.txt"
"""In a scan's job folder: the name of the executor that ran it (``Executor.name``)."""
UNRECORDED = "not recorded"
"""The executor of a job folder that holds no ``EXECUTOR_TXT`` (left by a release that kept none)."""


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
    after each scan, and a line before the first saying how many there are to run (a scan takes minutes:
    without it a run was silent until its first scan ended); scans found done count as finished, and the
    estimate of the time left extrapolates from the scans this run finished."""

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
        elif self.total:
            self._line(f"{self.total} scans to run")

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


@dataclass(frozen=True)
class Shard:
    """The ``index``-th (1 to ``count``) of ``count`` parts of a grid: its scans' keys sorted, every
    ``count``-th from the ``index``-th (the same part on every machine for the same grid, whatever the
    order of its options; the parts differ in size by one scan at most)."""

    index: int = 1
    count: int = 1

    @classmethod
    def parse(cls, text: str) -> Shard:
        """``I/N``, e.g. ``2/4``; raises ``CellError``."""
        try:
            index, count = (int(p) for p in text.split("/"))
        except ValueError:
            raise CellError(f"a shard is I/N (the I-th of N parts, 1 <= I <= N), got {text!r}") from None
        if not 1 <= index <= count:
            raise CellError(f"a shard is I/N with 1 <= I <= N, got {text!r}")
        return cls(index, count)

    def select(self, keys: Iterable[str]) -> list[str]:
        """This part's keys of ``keys``."""
        return [k for n, k in enumerate(sorted(set(keys))) if n % self.count == self.index - 1]

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


WHOLE = Shard()
"""The whole grid: shard 1/1."""
LOCKS_DIR = ".running"
"""Under the output folder: a lock file per shard running (``<I>of<N>``) and the writers' lock."""
WRITERS_LOCK = "writers"


def _try_lock(f: IO[str], mode: int) -> bool:
    try:
        fcntl.flock(f, mode | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError as exc:
        raise CellError(f"cannot lock {f.name}: {exc} (the output folder must be on a file system with "
                        "locks)") from None
    return True


@contextmanager
def running(out: Path, shard: Shard) -> Iterator[None]:
    """Hold ``shard``'s lock on ``out`` while inside; refuse (``CellError``) when a run that could run
    the same scans holds one: the same shard, or a shard of another count (the whole grid is 1/1)."""
    folder = out / LOCKS_DIR
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{shard.index}of{shard.count}"
    with path.open("a+") as own:
        if not _try_lock(own, fcntl.LOCK_EX):
            raise CellError(f"another cell eval is running on {out} ({_holder(path, shard)}): wait for it to "
                            "end, or give another --out")
        for other in folder.iterdir():
            named = re.fullmatch(r"(\d+)of(\d+)", other.name)
            if named is None or int(named[2]) == shard.count:  # the writers' lock, or a disjoint part
                continue
            with other.open("a+") as f:
                if not _try_lock(f, fcntl.LOCK_SH):
                    theirs = Shard(int(named[1]), int(named[2]))
                    raise CellError(f"another cell eval is running on {out} ({_holder(other, theirs)}), "
                                    f"whose scans overlap these (shard {shard}): wait for it to end, or run "
                                    f"the same --shard count")
        own.seek(0)
        own.truncate()
        own.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        own.flush()
        yield


def _holder(path: Path, shard: Shard) -> str:
    what = "the whole grid" if shard.count == 1 else f"shard {shard}"
    try:
        who = path.read_text().strip()
    except OSError:
        who = ""
    return f"{what}, {who}" if who else what


@contextmanager
def writers(out: Path) -> Iterator[None]:
    """While inside, the only writer of ``out``'s shared files (results.csv, report.md and its figures,
    limits.json) among the runs on it (waits for the one writing)."""
    folder = out / LOCKS_DIR
    folder.mkdir(parents=True, exist_ok=True)
    with (folder / WRITERS_LOCK).open("a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        yield


def failed_marker(folder: Path) -> Path:
    """The file saying why the scan of job folder ``folder`` left none."""
    return folder.with_name(folder.name + ".failed")


def grid_rows(specs: Sequence[ScanSpec], out: Path) -> list[Row]:
    """The rows (sorted) of every scan of ``specs`` finished under ``out``: done (its folder) or failed
    (its ``.failed``); none for the others."""
    rows = []
    for spec in {scan_key(spec): spec for spec in specs}.values():
        folder = scan_folder(out, spec)
        if (folder / "result.json").is_file():
            rows.append(row_from_folder(spec, folder))
        elif (marker := failed_marker(folder)).is_file():
            rows.append(failed_row(spec, marker.read_text()))
    return sorted_rows(rows)


def ran_on(rows: Sequence[Row], out: Path) -> dict[str, int]:
    """How many of the scans of ``rows`` that left a job folder under ``out`` each executor ran, by name
    (``UNRECORDED`` for a folder that does not say), in the order first met."""
    names = []
    for row in rows:
        if row["job"]:
            recorded = out / SCANS_DIR / row["job"] / EXECUTOR_TXT
            names.append(recorded.read_text().strip() if recorded.is_file() else UNRECORDED)
    return {name: names.count(name) for name in dict.fromkeys(names)}


def write_results(specs: Sequence[ScanSpec], out: Path) -> list[Row]:
    """Rebuild results.csv from ``out`` (:func:`grid_rows`; hold :func:`writers`); returns its rows."""
    rows = grid_rows(specs, out)
    write_text_atomic(out / RESULTS_CSV, csv_text(rows))
    return rows


def run_grid(specs: Sequence[ScanSpec], out: Path, executor: Executor,
             task: Callable[[ScanTask], TaskOutput] = run_scan_task,
             stream: TextIO | None = None, shard: Shard = WHOLE) -> list[Row]:
    """Run the scans of ``specs`` (of ``shard``'s part) not done yet under ``out`` on ``executor`` and
    write ``results.csv`` (of every scan of the grid finished, :func:`write_results`); returns its rows.
    ``task`` runs one scan in a worker (the real scan by default)."""
    (out / SCANS_DIR).mkdir(parents=True, exist_ok=True)
    keyed = {scan_key(spec): spec for spec in specs}  # a scan listed twice runs once
    mine = shard.select(keyed)
    folders = {key: scan_folder(out, keyed[key], key) for key in mine}
    todo = [key for key, folder in folders.items() if not (folder / "result.json").is_file()]
    progress = GridProgress(len(mine), len(mine) - len(todo), stream if stream is not None else sys.stderr)

    def on_done(index: int, output: TaskOutput | TaskFailure) -> None:
        key = todo[index]
        spec, folder = keyed[key], folders[key]
        marker = failed_marker(folder)
        if isinstance(output, TaskFailure) or output.archive is None:
            reason = output.reason if isinstance(output, TaskFailure) else output.error
            write_text_atomic(marker, " ".join((reason or "the scan left no job folder").split()))
            progress.done(failed=True)
            return
        partial = folder.with_name(f"{folder.name}.partial-{socket.gethostname()}-{os.getpid()}")
        shutil.rmtree(partial, ignore_errors=True)
        unpack_folder(output.archive, partial)
        (partial / EXECUTOR_TXT).write_text(f"{executor.name}\n")
        try:
            partial.rename(folder)
        except OSError:  # another run on this folder finished the same scan first: the same inputs
            shutil.rmtree(partial)
        marker.unlink(missing_ok=True)
        progress.done(row_from_folder(spec, folder)["status"] == "failed")

    executor.run(task, [ScanTask.of(keyed[key], key) for key in todo], on_done)
    with writers(out):
        return write_results(specs, out)
