"""What the benchmarks that run scan jobs (``packing_grid.py``, ``vs_table.py``, ``vs_heldout.py``) share:
their common command-line options, the refusal of job folders that already hold a job, and their closing
output: the summary line, then the whole result as one line of JSON (the last line, for scripts),
optionally also written to a file."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cell.jobs.recorder import holds_job


def jobs_parser(description: str, config: Path, out: Path) -> argparse.ArgumentParser:
    """A parser with the options of every benchmark that runs scan jobs: ``--config`` (cell file),
    ``--out`` (root of the job folders) and ``--json``, with these defaults; a script adds its own."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--config", type=Path, default=config)
    parser.add_argument("--out", type=Path, default=out, help="root of the job folders")
    parser.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    return parser


def grid_parser(description: str, config: Path, objects: Sequence[str], planners: Sequence[str],
                out: Path) -> argparse.ArgumentParser:
    """:func:`jobs_parser` with the options of an objects x planners grid: ``--objects``, ``--planners``
    and ``--object-pose``, with these defaults."""
    parser = jobs_parser(description, config, out)
    parser.add_argument("--objects", nargs="+", default=list(objects))
    parser.add_argument("--planners", nargs="+", default=list(planners))
    parser.add_argument("--object-pose", nargs=3, type=float, default=(0.0, 0.0, 0.0),
                        metavar=("X_M", "Y_M", "YAW_DEG"), help="object pose relative to the station")
    return parser


def refuse_taken(parser: argparse.ArgumentParser, folders: Sequence[Path]) -> None:
    """Exit with a usage error when one of the run's job folders already holds a job: a job refuses such
    a folder, and this says so before the run starts, not after its scans."""
    taken = [f for f in folders if holds_job(f)]
    if taken:
        parser.error(f"{len(taken)} of the job folders already hold a job (e.g. {taken[0]}); "
                     "choose another --out")


def print_result(result: dict[str, Any], json_path: Path | None) -> None:
    """Print ``result["summary"]`` and then ``result`` as JSON; write the JSON to ``json_path`` too."""
    print(f"summary: {result['summary']}")
    text = json.dumps(result)
    if json_path is not None:
        json_path.write_text(text + "\n")
    print(text)
