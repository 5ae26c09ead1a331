"""What ``cell eval`` says while it runs: how many scans there are before the first one ends, and what
the coverage limits after the scans are doing (minutes of silence before the report otherwise)."""

from __future__ import annotations

import io
from pathlib import Path

from cell.evaluation.evaluate import coverage_limits
from cell.evaluation.executors import LocalPool
from cell.evaluation.grid import GridProgress
from cell.evaluation.spec import cross

CONFIG = str(Path(__file__).resolve().parents[1] / "config" / "sim-ur5e-tof.yaml")


def test_a_grid_says_how_many_scans_it_runs_before_the_first_ends():
    stream = io.StringIO()
    GridProgress(3, 0, stream)
    assert stream.getvalue() == "eval: 3 scans to run\n"
    stream = io.StringIO()
    GridProgress(3, 1, stream)
    assert stream.getvalue() == "eval: 1 scans already done, 2 to run\n"


def test_the_coverage_limits_say_how_many_there_are_and_each_as_it_ends(tmp_path):
    """The cube at the station, two planners: one limit (it depends on the object and its placement, not
    on the planner), announced before it starts, then given with its figure; none said when none is
    left to compute."""
    specs = cross(CONFIG, [("cube", (0.0, 0.0, 0.0))], ["heu", "lr-nbv"], [0])
    stream = io.StringIO()
    limits = coverage_limits(specs, tmp_path, 2, LocalPool(1), stream)
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("eval: 1 coverage limit to compute, 2 view directions per hemisphere")
    assert "--limit-directions 0 skips them" in lines[0]
    assert lines[1] == f"eval: coverage limit of cube at 0,0,0: {limits[('cube', '0,0,0')]:.1f} % (1/1)"
    again = io.StringIO()
    assert coverage_limits(specs, tmp_path, 2, LocalPool(1), again) == limits
    assert again.getvalue() == ""
