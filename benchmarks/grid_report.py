"""The closing output of the grid benchmarks (``packing_grid.py``, ``vs_table.py``): the summary line, then
the whole result as one line of JSON (the last line, for scripts), optionally also written to a file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def print_result(result: dict[str, Any], json_path: Path | None) -> None:
    """Print ``result["summary"]`` and then ``result`` as JSON; write the JSON to ``json_path`` too."""
    print(f"summary: {result['summary']}")
    text = json.dumps(result)
    if json_path is not None:
        json_path.write_text(text + "\n")
    print(text)
