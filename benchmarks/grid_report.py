"""What the grid benchmarks (``packing_grid.py``, ``vs_table.py``) share: their common command-line options,
and their closing output: the summary line, then the whole result as one line of JSON (the last line, for
scripts), optionally also written to a file."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any


def grid_parser(description: str, config: Path, objects: Sequence[str], planners: Sequence[str],
                out: Path) -> argparse.ArgumentParser:
    """A parser with the options of every grid: ``--config`` (cell file), ``--objects``, ``--planners``,
    ``--object-pose``, ``--out`` (root of the job folders) and ``--json``, with these defaults; a script
    adds its own."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--config", type=Path, default=config)
    parser.add_argument("--objects", nargs="+", default=list(objects))
    parser.add_argument("--planners", nargs="+", default=list(planners))
    parser.add_argument("--object-pose", nargs=3, type=float, default=(0.0, 0.0, 0.0),
                        metavar=("X_M", "Y_M", "YAW_DEG"), help="object pose relative to the station")
    parser.add_argument("--out", type=Path, default=out, help="root of the job folders")
    parser.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    return parser


def print_result(result: dict[str, Any], json_path: Path | None) -> None:
    """Print ``result["summary"]`` and then ``result`` as JSON; write the JSON to ``json_path`` too."""
    print(f"summary: {result['summary']}")
    text = json.dumps(result)
    if json_path is not None:
        json_path.write_text(text + "\n")
    print(text)
