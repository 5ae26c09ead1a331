"""The benchmarks refuse a bad option before they run: one line naming it, exit code 1 (as ``cell``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.mark.parametrize(("script", "option", "expected"), [
    ("sim_render.py", ["--frames", "0"], "argument --frames: expected at least 1, got 0"),
    ("vl53l8cx_link.py", ["--seconds", "0"], "argument --seconds: expected a number above 0, got 0"),
    ("guard_tick.py", ["--ticks", "0"], "argument --ticks: expected at least 1, got 0"),
    ("serve_startup.py", ["--reference", "/nonexistent"], "/nonexistent is not a checkout of the cell"),
    ("calibration_accuracy.py", ["--seeds", "abc"], "expected comma-separated seeds"),
    ("soak.py", ["--no-such-option"], "unrecognized arguments: --no-such-option"),
])
def test_a_bad_option_is_refused_in_one_line_with_exit_code_1(script: str, option: list[str],
                                                              expected: str) -> None:
    done = subprocess.run([sys.executable, str(BENCHMARKS / script), *option], capture_output=True, text=True,
                          timeout=120, check=False)
    assert done.returncode == 1
    assert done.stderr.startswith(f"{script}: error: ")
    assert expected in done.stderr
    assert done.stderr.count("\n") == 1
    assert done.stdout == ""


@pytest.mark.parametrize(("script", "ends"), [
    ("calibration_accuracy.py", "what a calibrated mount does to a scan's Chamfer distance."),
    ("eval_executors.py", "Also the mean wall time of one scan of the grid."),
])
def test_help_describes_the_benchmark_in_whole_sentences(script: str, ends: str) -> None:
    """--help shows the docstring's first paragraph, not its first line, which ends mid-sentence."""
    done = subprocess.run([sys.executable, str(BENCHMARKS / script), "--help"], capture_output=True,
                          text=True, timeout=120, check=True)
    assert ends in " ".join(done.stdout.split())
