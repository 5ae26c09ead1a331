"""The benchmarks refuse a bad option before they run: one line naming it, exit code 1 (as ``cell``)."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
from pathlib import Path
from types import ModuleType, SimpleNamespace

import numpy as np
import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _run(script: str, *args: str, check: bool = False,
         timeout_s: float = 120.0) -> subprocess.CompletedProcess[str]:
    """The benchmark ``script`` run with ``args`` as a user runs it, its output captured."""
    return subprocess.run([sys.executable, str(BENCHMARKS / script), *args], capture_output=True, text=True,
                          timeout=timeout_s, check=check)


def _benchmark(monkeypatch: pytest.MonkeyPatch, name: str) -> ModuleType:
    """The benchmark module ``name``, imported as the benchmarks import their helpers (from their folder)."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    return importlib.import_module(name)


def _main(monkeypatch: pytest.MonkeyPatch, benchmark: ModuleType, *args: str) -> None:
    """``benchmark.main()`` as its command line with ``args`` runs it."""
    monkeypatch.setattr(sys, "argv", [f"{benchmark.__name__}.py", *args])
    benchmark.main()


@pytest.mark.parametrize(("script", "option", "expected"), [
    ("sim_render.py", ["--frames", "0"], "argument --frames: expected at least 1, got 0"),
    ("vl53l8cx_link.py", ["--seconds", "0"], "argument --seconds: expected a number above 0, got 0"),
    ("guard_tick.py", ["--ticks", "0"], "argument --ticks: expected at least 1, got 0"),
    ("seen_update.py", ["--repeats", "0"], "argument --repeats: expected at least 1, got 0"),
    ("serve_startup.py", ["--reference", "/nonexistent"], "/nonexistent is not a checkout of the cell"),
    ("calibration_accuracy.py", ["--seeds", "abc"], "expected comma-separated seeds"),
    ("calibration_accuracy.py", ["--poses-board", "4"], "argument --poses-board: expected at least 5, got 4"),
    ("soak.py", ["--no-such-option"], "unrecognized arguments: --no-such-option"),
    ("line_cycle.py", ["--parts", "1"], "argument --parts: expected at least 2, got 1"),
    ("calibration_accuracy.py", ["--max-mm", "-1"], "--max-mm: expected a number of at least 0, got -1"),
    ("safety_mutants.py", ["--soak", "-1"], "argument --soak: expected at least 0, got -1"),
])
def test_a_bad_option_is_refused_in_one_line_with_exit_code_1(script: str, option: list[str],
                                                              expected: str) -> None:
    done = _run(script, *option)
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
    done = _run(script, "--help", check=True)
    assert ends in " ".join(done.stdout.split())


def test_map_vs_octomap_refuses_a_frames_folder_with_no_depth_frames(tmp_path: Path) -> None:
    """An empty or missing folder, or a ToF scan's frames (points, no depth image), is refused before
    anything runs, where OctoMap crashed on the empty tree (exit 139) or a KeyError ended the run."""
    missing = tmp_path / "missing"
    for folder, problem in ((missing, f"{missing} is not a folder"),
                            (tmp_path, f"{tmp_path} holds no recorded frames (*.npz, a job's frames/)")):
        done = _run("map_vs_octomap.py", "--frames-dir", str(folder))
        assert done.returncode == 1
        assert done.stderr.splitlines() == [f"map_vs_octomap.py: error: --frames-dir: {problem}"]
    np.savez_compressed(tmp_path / "000000.npz", points=np.zeros((3, 3)), T_base_sensor=np.eye(4))
    done = _run("map_vs_octomap.py", "--frames-dir", str(tmp_path))
    assert done.returncode == 1
    assert done.stderr.splitlines() == [f"map_vs_octomap.py: error: --frames-dir: {tmp_path} holds no RGB-D "
                                        "depth frames (000000.npz has no depth image: a ToF scan's?)"]


def test_eval_executors_names_the_scans_that_did_not_complete(tmp_path: Path, monkeypatch) -> None:
    """A grid whose scans failed (too short a budget) is refused, where its wall time was taken as the
    executor's and a grid with none completed ended in a ZeroDivisionError."""
    not_completed = _benchmark(monkeypatch, "eval_executors").not_completed

    from cell.evaluation.grid import RESULTS_CSV
    from cell.evaluation.results import csv_text
    from tests.result_rows import result_row

    refused = result_row("cube", "heu", 0, status="failed", termination="refused")
    completed = result_row("cube", "heu", 1, termination="time budget")
    (tmp_path / RESULTS_CSV).write_text(csv_text([refused, completed]))
    assert not_completed(tmp_path) == ("1 of 2 scans did not complete, so their wall time measures no "
                                       "executor (the first: cube heu seed 0, failed: refused)")
    (tmp_path / RESULTS_CSV).write_text(csv_text([completed]))
    assert not_completed(tmp_path) is None


def test_interleaved_repeats_alternate_which_side_runs_first_and_give_the_spread(monkeypatch) -> None:
    interleaved = _benchmark(monkeypatch, "interleaved")

    assert [interleaved.in_turn(r, ("this", "reference")) for r in range(3)] == [
        ["this", "reference"], ["reference", "this"], ["this", "reference"]]
    c = interleaved.compared([2.0, 3.0, 9.0], [4.0, 3.0, 6.0])
    # the repeats' own ratios are 0.5, 1.0 and 1.5: their median, where the medians' ratio is 3 / 4
    assert (c.this, c.reference, c.ratio, c.ratio_min, c.ratio_max) == (3.0, 4.0, 1.0, 0.5, 1.5)
    assert c.ratios() == {"ratio": 1.0, "ratio_range": [0.5, 1.5]}
    assert c.text() == "ratio 1.000 (repeats 0.500-1.500)"


def test_guard_tick_judges_the_goal_per_kind_of_tick_on_its_cpu_p99(monkeypatch) -> None:
    """1 ms per tick is a deadline: 97 `bound` ticks of 0.4 ms and 3 of 2 ms miss it on the p99 (the median
    passed them); the `fcl` ticks keep it in CPU time, however long their wall time."""
    guard_tick = _benchmark(monkeypatch, "guard_tick")
    Tick = guard_tick.Tick

    fast, slow = Tick(0.0004, 0.0005, checked=True, measured=False), Tick(0.002, 0.002, True, False)
    ticks = [*[fast] * 97, *[slow] * 3, Tick(0.0009, 0.003, True, True), Tick(0.0008, 0.0012, True, True)]
    judged = guard_tick.figures(ticks)
    assert {kind: f["goal_met"] for kind, f in judged.items()} == {"bound": False, "fcl": True}


def test_soak_prints_its_figures_as_one_line_of_json_last() -> None:
    """As the other benchmarks do (their docstrings promise it), where it printed them indented over many
    lines."""
    done = _run("soak.py", "--jobs", "1", "--warmup", "1", "--only", "in_process", "--max-time", "2",
                check=True, timeout_s=300.0)
    assert json.loads(done.stdout.splitlines()[-1])["in_process"]["jobs"] == 1


def test_safety_soak_too_short_for_a_move_reports_none() -> None:
    """20 commands of seed 0 on the UR5e send no move: 0 moves, where the summary line's KeyError ended it."""
    done = _run("safety_soak.py", "--commands", "20", "--robot", "ur5e", check=True, timeout_s=300.0)
    assert json.loads(done.stdout.splitlines()[-1])["robots"][0]["moves"] == 0


def _object_uploads_served_by_nothing(monkeypatch: pytest.MonkeyPatch) -> tuple[ModuleType, list[Path]]:
    """The object_uploads benchmark with no service behind it (its ``Served`` and ``create_key``
    replaced): an upload does nothing and a listing takes 0.4 ms. Returns the module, and the list of the
    checkouts a service is started from, in order."""
    object_uploads = _benchmark(monkeypatch, "object_uploads")
    started: list[Path] = []

    class Served:
        def __init__(self, tree: Path, *args: object) -> None:
            started.append(tree)
            self.proc = SimpleNamespace(pid=0)

        def upload(self, path: Path) -> None:
            pass

        def list_s(self) -> float:
            return 0.0004

        def close(self) -> None:
            pass

    monkeypatch.setattr(object_uploads, "Served", Served)
    monkeypatch.setattr(object_uploads, "create_key", lambda *args, **kwargs: "key")
    return object_uploads, started


def test_object_uploads_keeps_its_figures_unrounded_for_the_comparison(monkeypatch, tmp_path: Path) -> None:
    """A listing of 0.4 ms is 0.0004 s to the ratio, where rounding to 3 decimals made it 0.0 (a ratio
    dividing by zero) and moved millisecond figures by up to half."""
    object_uploads, _ = _object_uploads_served_by_nothing(monkeypatch)
    monkeypatch.setattr(object_uploads, "rss_mib", lambda pid: 100.0004)
    monkeypatch.setattr(object_uploads.time, "sleep", lambda s: None)
    figures = object_uploads.measure("this", tmp_path, [tmp_path / "a.stl"], [tmp_path / "b.stl"])
    assert figures["first_list_s"] == 0.0004
    assert figures["rss_at_end_mib"] == 100.0004


def test_calibration_accuracy_takes_a_largest_error_of_zero() -> None:
    """--max-mm 0 and --max-deg 0 (a mount believed exactly) are values of their own, where they were
    refused as not above 0 (the options are read in order, so --help after them exits 0 only if taken)."""
    done = _run("calibration_accuracy.py", "--max-mm", "0", "--max-deg", "0", "--help")
    assert done.returncode == 0, done.stderr


def _checkout(folder: Path) -> Path:
    """A folder that passes for another checkout of the cell (--reference)."""
    for sub in ("cell", "config"):
        (folder / sub).mkdir(parents=True)
    return folder


def test_eval_executors_alternates_the_attached_ray_too(monkeypatch, tmp_path: Path, capsys) -> None:
    """With --attached the three take turns in an order reversed every repeat, where the attached Ray always
    ran last; Ray's throughput is the median of the repeats' pool / Ray, with its range."""
    eval_executors = _benchmark(monkeypatch, "eval_executors")

    from cell.evaluation.grid import RESULTS_CSV

    order: list[str] = []
    seconds = iter([10.0, 20.0, 30.0, 40.0, 30.0, 20.0])

    def ran(kind: str, out: Path) -> float:
        order.append(kind)
        (out / "scans" / "a").mkdir(parents=True)
        (out / "scans" / "a" / "result.json").write_text('{"wall_time_s": 1.0}')
        (out / RESULTS_CSV).write_text("same")
        return next(seconds)

    monkeypatch.setattr(eval_executors, "timed", lambda executor, specs, out: ran(
        "pool" if isinstance(executor, eval_executors.LocalPool) else "ray", out))
    monkeypatch.setattr(eval_executors, "timed_attached",
                        lambda jobs, specs, out: (1.0, ran("attached", out)))
    monkeypatch.setattr(eval_executors, "not_completed", lambda out: None)
    _main(monkeypatch, eval_executors, "--repeats", "2", "--attached")
    assert order == ["pool", "ray", "attached", "attached", "ray", "pool"]
    report = json.loads(capsys.readouterr().out.splitlines()[-1])
    # pool 10 and 20 s, Ray 20 and 30 s: pool / Ray 0.5 and 0.667
    assert report["ray_throughput_vs_pool"] == 0.583
    assert report["ray_throughput_vs_pool_range"] == [0.5, 0.667]


def test_serve_startup_warms_each_tree_then_alternates_which_starts_first(monkeypatch, tmp_path: Path,
                                                                           capsys) -> None:
    serve_startup = _benchmark(monkeypatch, "serve_startup")

    reference = _checkout(tmp_path / "ref")
    started: list[Path] = []
    monkeypatch.setattr(serve_startup, "time_to_healthz", lambda tree: started.append(tree) or 1.0)
    _main(monkeypatch, serve_startup, "--repeats", "2", "--reference", str(reference))
    this = serve_startup.REPO
    assert started == [this, reference, this, reference, reference, this]  # the first two untimed
    assert json.loads(capsys.readouterr().out.splitlines()[-1])["runs"] == {"this": [1.0, 1.0],
                                                                           "reference": [1.0, 1.0]}


def test_object_uploads_warms_each_tree_then_alternates_which_runs_first(monkeypatch, tmp_path: Path) -> None:
    object_uploads, warmed = _object_uploads_served_by_nothing(monkeypatch)
    reference = _checkout(tmp_path / "ref")
    measured: list[Path] = []

    def measure(name: str, tree: Path, meshes: list[Path], more: list[Path]) -> dict[str, float]:
        measured.append(tree)
        return {"first_list_s": 1.0}

    monkeypatch.setattr(object_uploads, "measure", measure)
    monkeypatch.setattr(object_uploads, "write_meshes",
                        lambda folder, n: [folder / f"{i}.stl" for i in range(n)])
    _main(monkeypatch, object_uploads, "--reference", str(reference))
    this = object_uploads.REPO
    assert warmed == [this, reference]
    assert measured == [this, reference, reference, this]  # the default --repeats, 2


def test_ik_solve_alternates_which_implementation_runs_first(monkeypatch) -> None:
    ik_solve = _benchmark(monkeypatch, "ik_solve")

    solved: list[str] = []
    timed: list[str] = []

    def solve_all(name: str, goals: list[object], error: object) -> float:
        solved.append("closed" if error is ik_solve.pose_error else "scipy")
        return 1.0

    monkeypatch.setattr(ik_solve, "solve_all", solve_all)
    monkeypatch.setattr(ik_solve, "per_call_us", lambda fn: timed.append(fn) or 1.0)
    _main(monkeypatch, ik_solve, "--goals", "1", "--repeats", "2")
    # an untimed warm-up of each model, then repeat 0 (UR5e, Panda), then repeat 1 in the other order
    assert solved == ["closed", "scipy"] * 4 + ["scipy", "closed"] * 2
    # the first primitive: closed form then SciPy in repeat 0, SciPy then closed form in repeat 1
    assert timed[6:8] == [timed[1], timed[0]]
