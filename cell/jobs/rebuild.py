"""A job folder whose ``result.json`` is missing or unreadable: the process that ran the job was killed
before it could write it (a power cut, ``kill -9``), the file was deleted, or it was damaged (a disk
error; a release that wrote it in place and was killed mid-write). ``cell reprocess`` rebuilds it from
what the folder still holds, so that the folder is a job folder again: what the job was asked
(``job.json``, written when the folder was made) and the frames it recorded. An unreadable
``result.json`` is kept aside, renamed ``result.json.unreadable`` (nothing recorded is deleted), and
rebuilt as a missing one is; the replays (``cell sensor replay``, ``cell scan --replay``) read the same
rebuilt result without writing it (:func:`recorded_result`).

The rebuilt result says ``status`` ``interrupted`` (the job's own outcome is unknown) and carries the
identity of the job (planner, object, its scale and pose, seed, cell file), the number of frames, and no
metrics: ``cell reprocess`` then computes its own from the frames (``result_hires.json``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cell.jobs.live_cloud import LIVE_CLOUD_FILE
from cell.jobs.recorder import JOB_FILE, RESULT_FILE
from cell.perception.reprocess import recorded_frames
from drivers.atomic_file import keep_aside, writable_folder, write_text_atomic
from drivers.errors import JobError

IDENTITY = ("planner", "object", "object_scale", "object_pose", "config", "seed")
"""The fields of ``job.json`` that the rebuilt result keeps."""


@dataclass(frozen=True)
class RecordedResult:
    """A job folder's result: ``result`` is its ``result.json`` when that is readable, else the one
    rebuilt from ``job.json`` and the frames; ``problem`` None for a readable ``result.json``, else why it
    was rebuilt (``missing``, or ``unreadable (<reason>)``); ``budget_s`` the job's time budget [s] as
    ``job.json`` records it (None: the cell's at the time, or no readable ``job.json``)."""

    result: dict[str, Any]
    problem: str | None
    budget_s: float | None = None


def _asked(job_dir: Path) -> dict[str, Any]:
    """What ``job.json`` says was asked of the job; empty when it is unreadable or missing (a folder made
    before job.json existed)."""
    try:
        asked = json.loads((job_dir / JOB_FILE).read_text())
    except (OSError, ValueError):
        return {}
    return asked if isinstance(asked, dict) else {}


def _budget(asked: dict[str, Any]) -> float | None:
    """The time budget [s] of ``job.json``'s ``asked``: a positive finite number, else None."""
    value = asked.get("max_time_s")
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) and value > 0 else None


def check_job_dir(job_dir: Path) -> None:
    """Raise ``JobError`` unless ``job_dir`` is an existing folder."""
    if not job_dir.exists():
        raise JobError(f"{job_dir} does not exist")
    if not job_dir.is_dir():
        raise JobError(f"{job_dir} is not a job folder: it is a file")


def output_folder(job_dir: Path, out: Path | None, names: tuple[str, ...]) -> Path:
    """Where an offline command writes the files ``names`` it makes from the job folder ``job_dir``: ``out``
    (made when missing), else the job folder; raises ``JobError`` naming them before any work when that
    folder cannot be written to."""
    folder = job_dir if out is None else out
    try:
        return writable_folder(folder)
    except OSError as exc:
        them = "it" if len(names) == 1 else "them"
        hint = f"; give --out DIR to write {them} elsewhere" if out is None else ""
        raise JobError(f"cannot write {' and '.join(names)} to {folder}: "
                       f"{exc.strerror or exc}{hint}") from None


def _read_result(path: Path) -> dict[str, Any]:
    """``result.json`` as a dict; raises ``ValueError`` (a JSON error, or not an object) or ``OSError``."""
    result = json.loads(path.read_text())
    if not isinstance(result, dict):
        raise ValueError(f"not a job result (a JSON {type(result).__name__}, expected an object)")
    return result


def recorded_result(job_dir: Path) -> RecordedResult:
    """A job folder's result, read or rebuilt in memory (nothing is written; see :class:`RecordedResult`).
    Raises ``JobError`` for a folder that does not exist, and for one without a readable ``result.json``
    that holds no recorded frame either (not a job folder)."""
    check_job_dir(job_dir)
    path = job_dir / RESULT_FILE
    if not path.exists():
        problem = "missing"
    else:
        try:
            return RecordedResult(_read_result(path), None, _budget(_asked(job_dir)))
        except (OSError, ValueError) as exc:
            problem = f"unreadable ({exc})"
    frames = recorded_frames(job_dir)
    if not frames:
        what = f"no {RESULT_FILE}" if problem == "missing" else f"{RESULT_FILE} {problem}"
        raise JobError(f"{job_dir} is not a job folder: {what} and no recorded frames")
    asked = _asked(job_dir)  # empty: the job's identity is lost
    known = {key: asked[key] for key in IDENTITY if key in asked}
    result: dict[str, Any] = {
        **known,
        "status": "interrupted",
        "termination": f"the job ended without writing a readable result; rebuilt by cell reprocess from "
                       f"{len(frames)} recorded frames" + ("" if known else f" (no readable {JOB_FILE})"),
        "n_captures": len(frames),
        "metrics": {"chamfer_mm": None, "hausdorff_mm": None, "coverage_pct": None},
    }
    return RecordedResult(result, problem, _budget(asked))


def rebuild_result(job_dir: Path, recorded: RecordedResult) -> Path | None:
    """Write ``recorded``, the result :func:`recorded_result` rebuilt for a job folder that has lost its
    ``result.json`` or whose ``result.json`` is unreadable (kept aside first, renamed
    ``result.json.unreadable``); returns where the unreadable file was kept (None when there was none).
    Raises ``JobError`` for a folder it cannot write to."""
    path = job_dir / RESULT_FILE
    kept: Path | None = None
    try:
        if path.exists():
            kept = keep_aside(path)
        write_text_atomic(path, json.dumps(recorded.result, indent=2) + "\n", durable=True)
    except OSError as exc:
        raise JobError(f"cannot rebuild {path} ({RESULT_FILE} {recorded.problem}): {exc}") from None
    if (job_dir / "log.txt").is_file():
        with (job_dir / "log.txt").open("a") as log:
            aside = f", the unreadable file kept as {kept.name}" if kept is not None else ""
            log.write(f"[reprocess] {RESULT_FILE} was {recorded.problem}: rebuilt, status "
                      f"interrupted{aside}\n")
    return kept


def job_cell_file(job_dir: Path, result: dict[str, Any], config: Path | None = None) -> Path:
    """The cell file to process a recorded job with: ``config`` when given, else the one its ``result``
    names, found relative to the job folder (the service names its copy so, ``../../cells/<digest>.yaml``)
    or else as written. ``JobError`` naming the file and the paths looked at when neither is there (a job
    folder copied away from the data dir leaves its cell's copy behind): the crop box, the filters and
    the planner's settings are the cell's, and another cell's would give another cloud without a word."""
    if config is not None:
        return config  # loading it says what is wrong with it
    named = Path(str(result.get("config") or ""))
    if not named.name:
        raise JobError(f"{job_dir / RESULT_FILE} names no cell file; give the job's with --config FILE")
    candidates = list(dict.fromkeys((job_dir / named, named)))
    found = next((c for c in candidates if c.is_file()), None)
    if found is None:
        looked = " nor ".join(str(c) for c in candidates)
        raise JobError(f"the job's cell file {named} is not found (neither {looked} is a file): give it "
                       "with --config FILE (the service keeps a copy of each cell file in its data dir's "
                       "cells/ folder)")
    return found


def remove_live_cloud(job_dir: Path) -> bool:
    """Remove the live cloud snapshot (``cloud_live.npy``) a job killed while watched left behind, once
    the job has a result again; returns whether there was one. The snapshot is only for watching a
    running job, and a job with a result is not running."""
    snapshot = job_dir / LIVE_CLOUD_FILE
    if not snapshot.is_file() or not (job_dir / RESULT_FILE).is_file():
        return False
    try:
        snapshot.unlink()
    except OSError:
        return False
    return True
