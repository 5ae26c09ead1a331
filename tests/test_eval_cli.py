"""``cell eval grid`` as a user runs it (the installed ``cell`` console script): a one-scan grid leaves
results.csv and report.md and a second run skips the scan; bad input is refused with one line on
standard error and a failing exit code before any scan runs (the real app in this process: no scan
would start anyway, and a fresh interpreter per case costs seconds)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import open3d as o3d
import pytest
from typer.testing import CliRunner

from cell.cli.main import app
from cell.evaluation.grid import RESULTS_CSV, SCANS_DIR
from cell.evaluation.report import REPORT_MD
from cell.evaluation.results import read_csv

REPO = Path(__file__).resolve().parents[1]
CELL = Path(sys.executable).with_name("cell")
GRID_DEFAULTS = {"--config": str(REPO / "config" / "sim-ur5e-tof.yaml"), "--limit-directions": "0",
                 "--jobs": "1", "--max-time": "6"}


def grid(*args: str) -> list[str]:
    """``cell eval grid ARGS`` with each of ``GRID_DEFAULTS`` that ``args`` does not give itself (an option
    of one value given twice is refused)."""
    defaults = [word for option, value in GRID_DEFAULTS.items() if option not in args
                for word in (option, value)]
    return [str(CELL), "eval", "grid", *defaults, *args]


def cell_eval(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(grid(*args), capture_output=True, text=True, timeout=120, check=False)


def test_a_grid_writes_its_report_and_a_rerun_skips_the_done_scan(tmp_path):
    out = tmp_path / "run"
    first = cell_eval("--objects", "cube", "--planners", "heu", "--out", str(out))
    assert first.returncode == 0, first.stderr
    assert "eval: 1/1 scans (0 failed)" in first.stderr
    assert first.stdout.strip() == f"report: {out / REPORT_MD}"
    rows = read_csv(out / RESULTS_CSV)
    assert [(r["object"], r["planner"], r["status"]) for r in rows] == [("cube", "heu", "completed")]
    assert "| cube | heu | 1 |" in (out / REPORT_MD).read_text()
    first_csv = (out / RESULTS_CSV).read_text()

    again = cell_eval("--objects", "cube", "--planners", "heu", "--out", str(out))
    assert again.returncode == 0, again.stderr
    assert "eval: 1 scans already done, 0 to run" in again.stderr
    assert (out / RESULTS_CSV).read_text() == first_csv


@pytest.mark.parametrize(("args", "reason"), [
    (["--objects", "cube", "--planners", "no-such-planner"], "unknown planner 'no-such-planner'"),
    (["--objects", "no_such_object", "--planners", "heu"], "unknown object 'no_such_object'"),
    (["--objects", "cube", "--planners", "heu", "--placements", "{placements}"], "a placement is"),
    (["--objects", "cube", "--planners", "heu", "--placements", "{text_nan}"],
     "expected x,y,yaw_deg (three finite numbers), got '0,0,nan'"),
    (["--objects", "cube"], "the grid is empty"),
    # what cell scan refuses before it starts, refused before the grid starts
    (["--objects", "cube", "--planners", "heu", "--max-time", "-1"], "time budget must be a positive"),
    (["--objects", "cube", "--planners", "heu", "--seeds", "-3"], "seed must be between 0"),
    (["--objects", "cube", "--planners", "heu", "--placements", "{off_table}"], "off the table"),
    (["--objects", "{mm_mesh}", "--planners", "heu"], "not a size this cell scans"),
    # the scale the size error suggests exists, and takes the mesh (the time budget is what is wrong)
    (["--objects", "{mm_mesh}", "--object-scale", "0.001", "--planners", "heu", "--max-time", "0"],
     "time budget must be a positive"),
    (["--objects", "none", "--planners", "heu"], "'none' (an empty table) has nothing to measure"),
    (["--objects", "cube", "--planners", "heu", "--shard", "3/2"], "a shard is I/N with 1 <= I <= N"),
    (["--objects", "cube", "--planners", "heu", "--limit-directions", "-5"],
     "--limit-directions must be at least 1, or 0 for no coverage limit, got -5"),
])
def test_bad_input_fails_in_one_line_before_any_scan(tmp_path, args, reason):
    placements = tmp_path / "placements.yaml"
    placements.write_text("- [0.0, 0.0]\n")
    off_table = tmp_path / "off_table.yaml"
    off_table.write_text("- [0.9, 0.0, 90.0]\n")
    text_nan = tmp_path / "text_nan.yaml"
    text_nan.write_text("- '0,0,nan'\n")
    box = o3d.geometry.TriangleMesh.create_box(60.0, 40.0, 30.0)  # a part of 6 x 4 x 3 cm in millimetres
    o3d.io.write_triangle_mesh(str(tmp_path / "part_mm.obj"), box)
    out = tmp_path / "run"
    given = [a.format(placements=placements, off_table=off_table, text_nan=text_nan,
                      mm_mesh=tmp_path / "part_mm.obj") for a in args]
    done = CliRunner().invoke(app, [*grid(*given, "--out", str(out))[1:]])
    assert done.exit_code not in (0, None)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and reason in lines[0], done.stderr
    assert not (out / SCANS_DIR).exists()


@pytest.mark.parametrize(("script", "command"), [("vs_table.py", "vs-table"), ("packing_grid.py", "packing")])
def test_a_benchmark_of_a_preset_lists_the_options_it_passes_to_cell_eval(script, command):
    """README passes ``--planners``, ``--placements``, ``--seeds`` and ``--config`` to these benchmarks,
    which hand them to ``cell eval``: their --help lists every option of that command but ``--out``."""
    done = subprocess.run([sys.executable, str(REPO / "benchmarks" / script), "--help"], capture_output=True,
                          text=True, timeout=120, check=True)
    passed = done.stdout.split(f"other options go to `cell eval {command}`", 1)[1]
    for option in ("--config", "--planners", "--objects", "--placements", "--seeds", "--jobs", "--executor",
                   "--max-time", "--reprocess, --online"):
        assert f"\n  {option}: " in passed
    assert "--out:" not in passed


def test_a_grid_with_a_scan_that_did_not_complete_exits_1_and_names_it(tmp_path):
    """1 s of budget: the scan takes no frame, so its re-process fails: a failed row, listed."""
    out = tmp_path / "run"
    done = cell_eval("--objects", "cube", "--planners", "heu", "--reprocess", "--max-time", "1",
                     "--out", str(out))
    assert done.returncode == 1, done.stderr
    assert "error: 1 of 1 scans did not complete:" in done.stderr
    assert "cube 0,0,0 heu seed 0: failed: re-process failed" in done.stderr
    (row,) = read_csv(out / RESULTS_CSV)
    assert row["status"] == "failed" and row["coverage_pct"] == ""
    report = (out / REPORT_MD).read_text()
    assert "re-processed" in report and "## Scans that did not complete" in report


def test_the_limit_refuses_what_a_scan_refuses():
    done = CliRunner().invoke(app, ["eval", "limit", "--object", "cube", "--placement", "0.9,0,0"])
    assert done.exit_code == 1 and "off the table" in done.stderr, done.stderr


def test_the_limit_refuses_a_scale_for_a_shipped_object():
    """As cell scan does (and as its help says): it took the scale and ignored it, the shipped object being
    in metres."""
    done = CliRunner().invoke(app, ["eval", "limit", "--object", "cube", "--object-scale", "0.001"])
    assert done.exit_code == 1 and done.stdout == "", done.stdout
    assert done.stderr.strip().splitlines() == [
        "error: --object-scale is for a mesh file: the shipped object cube is in metres"]


@pytest.mark.parametrize("placement", ["0,0,nan", "0,0"])
def test_the_limit_names_a_malformed_placement(placement):
    """As cell scan and cell jobs submit name their --object-pose (a yaw of nan was "its yaw must lie
    within +-360 deg")."""
    done = CliRunner().invoke(app, ["eval", "limit", "--object", "cube", "--placement", placement])
    assert done.exit_code == 1 and done.stdout == "", done.stdout
    assert done.stderr.strip().splitlines() == [
        f"error: --placement: expected x,y,yaw_deg (three finite numbers), got '{placement}'"]


@pytest.mark.parametrize("directions", ["0", "-5"])
def test_the_limit_refuses_fewer_than_one_direction(directions):
    """No view direction: no view, a limit of 0 % that says nothing (0 skips the limit of a grid only)."""
    done = CliRunner().invoke(app, ["eval", "limit", "--object", "cube", "--directions", directions])
    assert done.exit_code == 1 and done.stdout == "", done.stdout
    assert done.stderr.strip().splitlines() == [
        f"error: --directions must be at least 1 (view directions per hemisphere), got {directions}"]


def _children(pid: int) -> set[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


def _wait_for(predicate, timeout: float) -> None:
    end = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.2)


def _alive(pids: set[int]) -> set[int]:
    return {p for p in pids if Path(f"/proc/{p}").exists()
            and Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"}


@pytest.mark.parametrize(("stage", "sig"), [("scan", signal.SIGTERM), ("limit", signal.SIGINT)])
def test_a_signal_stops_the_workers_and_says_so_in_one_line(tmp_path, stage, sig):
    """SIGTERM (a scheduler's stop) to the driver alone while it scans, Ctrl-C (SIGINT to the terminal's
    whole process group) while it computes the coverage limit: the workers end with it, one line says
    what was kept, no traceback; the exit code is the shell's for the signal."""
    err = tmp_path / "stderr"
    # a scan of about a minute; a scan in no time, then a limit of minutes
    args = ["--config", str(REPO / "config" / "sim-franka-rgbd.yaml"), "--planners", "vs-global",
            "--max-time", "600", "--limit-directions", "0"] if stage == "scan" else \
        ["--planners", "heu", "--max-time", "1", "--limit-directions", "300"]
    with err.open("w") as stderr:
        proc = subprocess.Popen(grid("--objects", "cube", *args, "--out", str(tmp_path / "run")),
                                stderr=stderr, stdout=subprocess.DEVNULL,
                                start_new_session=True)
    try:
        _wait_for(lambda: _children(proc.pid), 60)
        if stage == "limit":
            _wait_for(lambda: "eval: 1/1 scans" in err.read_text(), 60)
        time.sleep(3.0)  # the worker busy with its task
        workers = _children(proc.pid)
        if sig == signal.SIGINT:
            os.killpg(proc.pid, sig)
        else:
            proc.send_signal(sig)
        assert proc.wait(timeout=30) == 128 + sig
        time.sleep(0.5)
        assert not _alive(workers)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    text = err.read_text()
    assert "Traceback" not in text, text
    name = "SIGTERM" if sig == signal.SIGTERM else "Ctrl-C"
    assert [line for line in text.splitlines() if line.startswith("error:")] == [
        f"error: interrupted ({name}): the scans and coverage limits finished so far are kept in "
        f"{tmp_path / 'run'}; the same command resumes"], text
