"""``planner_requests.csv``: what a job's planner asked of the cell, and what the cell answered.

One row per request, in order: ``t`` [s, job clock] when it was asked; ``kind``; the sensor pose asked for
(``x, y, z`` [m] and ``qx, qy, qz, qw``, base frame) of a ``move`` or a ``reach`` check (whether the arm
reaches a view, asked before moving), or the sensor twist (``vx, vy, vz`` [m/s], ``wx, wy, wz`` [rad/s],
sensor frame) of a ``twist``; nothing for a ``hold`` or a ``retrace`` (going back along the arm's joint
path after a refused twist, ``JobSession.retrace``); the ``answer`` (``move`` and ``retrace``: reached or
refused; ``reach``: reachable or unreachable; ``twist``: refused, or nothing), for a move and a retrace
``t_done`` [s] when it ended, and for a refusal the guard's ``refusal`` (what it counts it as:
``collision``, ``speed``, ...) and ``reason`` (its words: ``link6 would touch table within 0.15 s``).

A refused twist is the streamed twist the guard stopped the arm for, at ``t`` the control tick it did
so, with the twist last commanded; a retrace that the guard refused at every distance back carries the
last refusal (the job's ``refused_moves`` counts each).

A live job records its moves, reach checks, refused twists and retraces: the answers that come from the
arm, which a replay (:mod:`cell.jobs.replay`) cannot get from a recording. A replay answers them from here
for as long as its planner asks what the live one did (each request's pose, written at 9 decimals, the
same; a refused twist at its tick), so that a job replayed with its own planner and cell file asks for the
same views and rebuilds the same cloud. A replayed job records every request (twists and holds too) with
the answers it gave. A file without the ``refusal`` and ``reason`` columns was recorded before refusals of
twists and retraces were (:attr:`RecordedRequests.refusals`).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cell.safety.events import Refusal
from drivers.errors import JobError
from drivers.transforms import quat_xyzw

Array = NDArray[np.float64]

REQUESTS_FILE = "planner_requests.csv"
POSE_COLUMNS = ["x", "y", "z", "qx", "qy", "qz", "qw"]
COLUMNS = ["t", "kind", *POSE_COLUMNS, "vx", "vy", "vz", "wx", "wy", "wz", "answer", "t_done", "refusal",
           "reason"]
REACHED, REFUSED = "reached", "refused"
REACHABLE, UNREACHABLE = "reachable", "unreachable"


def pose_cells(T_base_sensor: Array | None) -> tuple[str, ...]:
    """The 7 cells of a pose (4, 4): position [m] and unit quaternion (x, y, z, w), 9 decimals each; empty
    for None (a request without a pose)."""
    if T_base_sensor is None:
        return ("",) * len(POSE_COLUMNS)
    return tuple(f"{v:.9f}" for v in (*T_base_sensor[:3, 3], *quat_xyzw(T_base_sensor)))


def request_row(t: float, kind: str, T_base_sensor: Array | None = None, v_sensor: Array | None = None,
                answer: str = "", t_done: float | None = None, refusal: Refusal | None = None) -> list[str]:
    """One row of the file (the module docstring's columns)."""
    twist = tuple(f"{v:.9f}" for v in v_sensor) if v_sensor is not None else ("",) * 6
    why = (refusal.kind, refusal.message) if refusal is not None else ("", "")
    return [f"{t:.6f}", kind, *pose_cells(T_base_sensor), *twist, answer,
            "" if t_done is None else f"{t_done:.6f}", *why]


@dataclass(frozen=True)
class RecordedAnswer:
    """A recorded request: when it was asked [s], its pose (:func:`pose_cells`), the cell's answer, when a
    move or retrace ended [s] and the guard's refusal, if any."""

    t: float
    pose: tuple[str, ...]
    answer: str
    t_done: float | None
    refusal: Refusal | None


@dataclass(frozen=True)
class RecordedRequests:
    """The answered requests of a job by kind (``move``, ``reach``, ``twist``: the refused ones,
    ``retrace``), in order, and whether its file records refusals (False for a job recorded before
    refused twists and retraces were: a replay of it cannot refuse what its arm refused)."""

    answers: dict[str, list[RecordedAnswer]] = field(default_factory=dict)
    refusals: bool = False


def recorded_answers(job_dir: Path) -> RecordedRequests:
    """The answered requests of the job in ``job_dir``; none when it has no ``planner_requests.csv`` or its
    file carries no answers (a job recorded before they were). ``JobError`` when the file cannot be
    read."""
    path = job_dir / REQUESTS_FILE
    if not path.is_file():
        return RecordedRequests()
    answers: dict[str, list[RecordedAnswer]] = {}
    try:
        with path.open(newline="") as f:
            rows = csv.DictReader(f)
            for row in rows:
                if row.get("answer"):
                    done = row.get("t_done") or None
                    refusal = Refusal(row["refusal"], row["reason"]) if row.get("refusal") else None
                    answers.setdefault(row["kind"], []).append(RecordedAnswer(
                        float(row["t"]), tuple(row[c] for c in POSE_COLUMNS), row["answer"],
                        None if done is None else float(done), refusal))
            refusals = "reason" in (rows.fieldnames or ())
    except (OSError, ValueError, KeyError, csv.Error) as exc:
        raise JobError(f"cannot read {path}: {exc}") from None
    return RecordedRequests(answers, refusals)
