"""``planner_requests.csv``: what a job's planner asked of the cell, and what the cell answered.

One row per request, in order: ``t`` [s, job clock] when it was asked; ``kind``; the sensor pose asked for
(``x, y, z`` [m] and ``qx, qy, qz, qw``, base frame) of a ``move`` or a ``reach`` check (whether the arm
reaches a view, asked before moving), or the sensor twist (``vx, vy, vz`` [m/s], ``wx, wy, wz`` [rad/s],
sensor frame) of a ``twist``; nothing for a ``hold``; the ``answer`` (``move``: reached or refused;
``reach``: reachable or unreachable) and, for a move, ``t_done`` [s] when it ended.

A live job records its moves and reach checks: the answers that come from the arm, which a replay
(:mod:`cell.jobs.replay`) cannot get from a recording. A replay answers them from here for as long as its
planner asks what the live one did (each request's pose, written at 9 decimals, the same), so that a job
replayed with its own planner and cell file asks for the same views and rebuilds the same cloud. A
replayed job records every request (twists and holds too) with the answers it gave.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from drivers.errors import JobError
from drivers.transforms import quat_xyzw

Array = NDArray[np.float64]

REQUESTS_FILE = "planner_requests.csv"
COLUMNS = ["t", "kind", "x", "y", "z", "qx", "qy", "qz", "qw", "vx", "vy", "vz", "wx", "wy", "wz", "answer",
           "t_done"]
REACHED, REFUSED = "reached", "refused"
REACHABLE, UNREACHABLE = "reachable", "unreachable"


def pose_cells(T_base_sensor: Array) -> tuple[str, ...]:
    """The 7 cells of a pose (4, 4): position [m] and unit quaternion (x, y, z, w), 9 decimals each."""
    return tuple(f"{v:.9f}" for v in (*T_base_sensor[:3, 3], *quat_xyzw(T_base_sensor)))


def request_row(t: float, kind: str, T_base_sensor: Array | None = None, v_sensor: Array | None = None,
                answer: str = "", t_done: float | None = None) -> list[str]:
    """One row of the file (the module docstring's columns)."""
    pose = pose_cells(T_base_sensor) if T_base_sensor is not None else ("",) * 7
    twist = tuple(f"{v:.9f}" for v in v_sensor) if v_sensor is not None else ("",) * 6
    return [f"{t:.6f}", kind, *pose, *twist, answer, "" if t_done is None else f"{t_done:.6f}"]


@dataclass(frozen=True)
class RecordedAnswer:
    """A recorded request's pose (:func:`pose_cells`), the cell's answer and when a move ended [s]."""

    pose: tuple[str, ...]
    answer: str
    t_done: float | None


def recorded_answers(job_dir: Path) -> dict[str, list[RecordedAnswer]]:
    """The answered requests of the job in ``job_dir`` by kind (``move``, ``reach``), in order; empty when
    it has no ``planner_requests.csv`` or its file carries no answers (a job recorded before they were).
    ``JobError`` when the file cannot be read."""
    path = job_dir / REQUESTS_FILE
    if not path.is_file():
        return {}
    answers: dict[str, list[RecordedAnswer]] = {}
    try:
        with path.open(newline="") as f:
            for row in csv.DictReader(f):
                if row.get("answer"):
                    done = row.get("t_done") or None
                    answers.setdefault(row["kind"], []).append(RecordedAnswer(
                        tuple(row[c] for c in ("x", "y", "z", "qx", "qy", "qz", "qw")), row["answer"],
                        None if done is None else float(done)))
    except (OSError, ValueError, KeyError, csv.Error) as exc:
        raise JobError(f"cannot read {path}: {exc}") from None
    return answers
