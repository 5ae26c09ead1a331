"""Rows of an evaluation grid's ``results.csv`` written by hand, for the tests of what reads them."""

from __future__ import annotations

from cell.evaluation.results import COLUMNS


def result_row(obj: str, planner: str, seed: int, **columns: str) -> dict[str, str]:
    """A ``results.csv`` row (``cell.evaluation.results.COLUMNS``) of a completed scan of ``obj`` at the
    station by ``planner`` with ``seed``; ``columns`` fill or replace its other columns, empty otherwise."""
    return {**dict.fromkeys(COLUMNS, ""), "object": obj, "placement": "0,0,0", "planner": planner,
            "seed": str(seed), "status": "completed", "termination": "done", **columns}
