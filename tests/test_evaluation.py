"""cell.evaluation: a small grid through the local pool and Ray with identical results.csv, resume, a
killed worker retried and reported, a re-processed scan's 1 mm figures and timeline, the report against
results.csv, and the coverage limit (computed on the grid's executor, once per input)."""

from __future__ import annotations

import io
import json
import os
import shutil
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from cell.config import load_config
from cell.evaluation import presets
from cell.evaluation import spec as spec_module
from cell.evaluation.evaluate import LIMITS_JSON, coverage_limits
from cell.evaluation.executors import LocalPool, RayExecutor
from cell.evaluation.grid import RESULTS_CSV, SCANS_DIR, run_grid, scan_folder, timelines
from cell.evaluation.limit import cell_coverage_limit, reachable_views
from cell.evaluation.report import REPORT_MD, write_report
from cell.evaluation.results import read_csv, row_from_folder, row_from_result
from cell.evaluation.spec import ScanSpec, code_digest, cross, scan_key
from cell.evaluation.task import ScanTask, TaskOutput, run_scan_task, unpack_folder
from drivers.sim.objects import face_normals, load_object
from drivers.transforms import look_at
from tests.result_rows import result_row

REPO = Path(__file__).resolve().parents[1]
CONFIG = str(REPO / "config" / "sim-ur5e-tof.yaml")
# two objects x two planners x one seed, 6 s of sim time each (a few captures, well under a second of work)
SPECS = cross(CONFIG, [("cube", (0.0, 0.0, 0.0)), ("horizontal_box", (0.0, 0.0, 0.0))], ["heu", "lr-nbv"],
              [0], max_time_s=6.0)
CRASH_MARKER_ENV = "CELL_TEST_CRASH_MARKERS"


@dataclass
class CountingPool(LocalPool):
    """A local pool that keeps how many items each of its runs was given."""

    given: list[int] = field(default_factory=list)

    def run(self, fn, items, on_done):
        self.given.append(len(items))
        super().run(fn, items, on_done)


def crash_first_attempt(task: ScanTask) -> TaskOutput:
    """Kill the worker on the first attempt of every lr-nbv scan (a marker file per scan says it was
    tried), then scan as usual."""
    marker = Path(os.environ[CRASH_MARKER_ENV]) / task.key
    if task.spec.planner == "lr-nbv" and not marker.exists():
        marker.touch()
        os._exit(3)
    return run_scan_task(task)


def crash_always(task: ScanTask) -> TaskOutput:
    """Kill the worker of every cube scan, every time."""
    if task.spec.object == "cube":
        os._exit(4)
    return run_scan_task(task)


@pytest.fixture(scope="module")
def local_run(tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("local")
    progress = io.StringIO()
    run_grid(SPECS, out, LocalPool(2), stream=progress)
    return out, progress.getvalue()


def test_grid_writes_every_scan_and_progress(local_run):
    out, progress = local_run
    rows = read_csv(out / RESULTS_CSV)
    assert [(r["object"], r["planner"]) for r in rows] == [
        ("cube", "heu"), ("cube", "lr-nbv"), ("horizontal_box", "heu"), ("horizontal_box", "lr-nbv")]
    assert all(r["status"] == "completed" for r in rows)
    assert all(float(r["coverage_pct"]) > 0.0 and r["iou"] for r in rows)
    assert len(list((out / SCANS_DIR).glob("*/result.json"))) == 4
    assert "eval: 4/4 scans (0 failed)" in progress and "left" in progress


def test_one_worker_gives_the_same_bytes(local_run, tmp_path):
    out, _ = local_run
    run_grid(SPECS, tmp_path, LocalPool(1), stream=io.StringIO())
    assert (tmp_path / RESULTS_CSV).read_bytes() == (out / RESULTS_CSV).read_bytes()


def test_rerun_skips_done_scans(local_run, tmp_path):
    out = tmp_path / "again"
    shutil.copytree(local_run[0], out)
    extra = cross(CONFIG, [("cube", (0.0, 0.0, 0.0))], ["heu"], [1], max_time_s=6.0)
    pool = CountingPool(2)
    progress = io.StringIO()
    run_grid([*SPECS, *extra], out, pool, stream=progress)
    assert pool.given == [1]
    assert "4 scans already done, 1 to run" in progress.getvalue()
    rows = read_csv(out / RESULTS_CSV)
    jobs = sorted(scan_folder(out, spec).name for spec in [*SPECS, *extra])
    assert sorted(row["job"] for row in rows) == jobs


def test_a_scan_is_keyed_by_the_code_it_runs(tmp_path, monkeypatch):
    """An edited module or kernel source gives the scans other keys, so a grid run again after a change of
    the code scans again rather than reporting what the old code left; other files do not count."""
    package = tmp_path / "package"
    package.mkdir()
    (package / "a.py").write_text("x = 1\n")
    first = code_digest([package])
    (package / "notes.txt").write_text("not code")
    assert code_digest([package]) == first
    (package / "a.py").write_text("x = 2\n")
    edited = code_digest([package])
    assert edited != first
    (package / "kernels").mkdir()
    (package / "kernels" / "k.so").write_bytes(b"\x7fELF")  # a build of the kernel: not a source
    assert code_digest([package]) == edited
    (package / "kernels" / "k.pyx").write_text("def f(): pass\n")
    assert code_digest([package]) != edited
    key = scan_key(SPECS[0])
    monkeypatch.setattr(spec_module, "software_digest", lambda: first)
    assert scan_key(SPECS[0]) != key


def test_a_killed_worker_is_retried_then_reported(local_run, tmp_path, monkeypatch):
    out, _ = local_run
    monkeypatch.setenv(CRASH_MARKER_ENV, str(tmp_path))
    retried = tmp_path / "retried"
    run_grid(SPECS, retried, LocalPool(2), task=crash_first_attempt, stream=io.StringIO())
    assert len(list(tmp_path.glob("*"))) == 3  # two markers and the output folder: each lr-nbv scan died once
    assert (retried / RESULTS_CSV).read_bytes() == (out / RESULTS_CSV).read_bytes()

    dead = tmp_path / "dead"
    progress = io.StringIO()
    rows = run_grid(SPECS, dead, LocalPool(2), task=crash_always, stream=progress)
    failed = [r for r in rows if r["status"] == "failed"]
    assert [(r["object"], r["planner"]) for r in failed] == [("cube", "heu"), ("cube", "lr-nbv")]
    assert all("worker died twice" in r["termination"] and r["coverage_pct"] == "" for r in failed)
    assert "4/4 scans (2 failed)" in progress.getvalue()


def test_ray_gives_the_same_results_and_retries_a_killed_worker(local_run, tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")
    out, _ = local_run
    monkeypatch.setenv(CRASH_MARKER_ENV, str(tmp_path))
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {CRASH_MARKER_ENV: str(tmp_path)}})
    try:
        ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
        run_grid(SPECS, tmp_path / "ray", RayExecutor(), task=crash_first_attempt, stream=io.StringIO())
    finally:
        ray.shutdown()
    assert len(list(tmp_path.iterdir())) == 3  # two markers and the output folder: each lr-nbv scan died once
    assert (tmp_path / "ray" / RESULTS_CSV).read_bytes() == (out / RESULTS_CSV).read_bytes()


def test_a_reprocessed_scan_reports_the_1mm_figures_and_its_timeline(tmp_path):
    spec = ScanSpec(str(REPO / "config" / "sim-franka-rgbd.yaml"), "cube", (0.0, 0.0, 0.0), "vs-local", 0,
                    max_time_s=3.0, reprocess=True)
    output = run_scan_task(ScanTask.of(spec, scan_key(spec)))
    assert output.error is None and output.archive is not None
    folder = scan_folder(tmp_path, spec)
    unpack_folder(output.archive, folder)
    hires = json.loads((folder / "result_hires.json").read_text())
    online = json.loads((folder / "result.json").read_text())["metrics"]
    assert hires["metrics"] != online
    row = row_from_folder(spec, folder)
    assert [row[k] for k in ("coverage_pct", "chamfer_mm", "hausdorff_mm")] == [
        f"{hires['metrics'][k]:.4f}" for k in ("coverage_pct", "chamfer_mm", "hausdorff_mm")]
    online_spec = replace(spec, reprocess=False)
    assert scan_key(online_spec) != scan_key(spec)
    assert timelines([spec, online_spec], tmp_path) == {("cube", "0,0,0", "vs-local", "0"): hires["timeline"]}


def _table(md: str, first_header: str) -> list[list[str]]:
    lines = md.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_header}"))
    body = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        body.append([c.strip() for c in line.strip("|").split("|")])
    return body


def test_report_tables_match_results_csv(local_run, tmp_path):
    out, _ = local_run
    rows = read_csv(out / RESULTS_CSV)
    # a second seed per scan, so that the table shows means and standard errors
    twin = [{**r, "seed": "1", "coverage_pct": f"{float(r['coverage_pct']) + 1.0:.4f}"} for r in rows]
    write_report(rows + twin, tmp_path, {("cube", "0,0,0"): 100.0})
    md = (tmp_path / REPORT_MD).read_text()
    table = _table(md, "object | planner | n | coverage %")
    assert len(table) == len(rows)
    for r, line in zip(rows, table, strict=True):
        a, b = float(r["coverage_pct"]), float(r["coverage_pct"]) + 1.0
        se = np.std([a, b], ddof=1) / np.sqrt(2)
        assert line[:5] == [r["object"], r["planner"], "2", f"{(a + b) / 2:.1f} ± {se:.1f}",
                            "100.0" if r["object"] == "cube" else "-"]
        assert line[5] == f"{float(r['chamfer_mm']):.1f} ± 0.0"
    packing = _table(md, "object | planner | n | L m")
    for r, line in zip(rows, packing, strict=True):
        assert line[3:7] == [f"{float(d):.4f} ± 0.0000" for d in r["dims_m"].split()] + \
            [f"{float(r['iou']):.3f} ± 0.000"]
    assert (tmp_path / "fig5.png").stat().st_size > 0 and (tmp_path / "fig3.png").stat().st_size > 0
    # Mann-Whitney U between planners: a p with two seeds a side; none with one (p = 1 whatever the values)
    tests = _table(md, "object | figure | planner A | planner B | U (A) | p")
    assert tests and any(line[5] != "-" for line in tests)
    (tmp_path / "one-seed").mkdir()
    write_report(rows, tmp_path / "one-seed", {})
    single = _table((tmp_path / "one-seed" / REPORT_MD).read_text(), "object | figure | planner A")
    assert single and all(line[4:6] == ["-", "-"] for line in single)


def test_the_report_says_what_its_figures_mean(tmp_path):
    boxes = [result_row("horizontal_box", planner, seed, coverage_pct=f"{50 + seed + k:.4f}",
                        iou=f"0.{7 + k}000", dims_m=f"0.2{seed}00 0.1000 0.0500",
                        dims_true_m="0.2000 0.1000 0.0500", dims_upper_m=f"0.2{4 + seed}00 0.1400 0.0700",
                        container="medium", n_poses="4")
             for k, planner in enumerate(("lr-nbv", "heu")) for seed in (0, 1)]
    write_report(boxes, tmp_path, {})
    md = (tmp_path / REPORT_MD).read_text()
    # no object or planner of the paper's tables: no brackets, and no word of them
    assert "in brackets" not in md and "(" not in _table(md, "object | planner | n | coverage %")[0][3]
    assert "Higher is better: `coverage %`, `unregistered coverage %`; lower is better: `Chamfer mm`, " \
        "`Hausdorff mm`, `scan time s`, `path m`." in md
    assert "Higher is better: `IoU`, `surface reconstructed %`; lower is better: `poses`, `useless poses`." \
        in md
    header = next(line for line in md.splitlines() if line.startswith("| object | planner | n | L m"))
    assert header.endswith("| truth L x W x H m | upper bound L x W x H m (mean) | containers |")
    packing = _table(md, "object | planner | n | L m")
    assert packing[0][-3:] == ["0.2000 x 0.1000 x 0.0500", "0.2450 x 0.1400 x 0.0700", "medium (2)"]
    # two scans a side: Mann-Whitney U cannot give a p below 1/3, and the report says so
    tests = _table(md, "object | figure | planner A | planner B | U (A) | p | smallest exact p")
    assert tests and all(line[6] == "0.3333" for line in tests)
    assert "the exact test cannot reach p < 0.05 whatever the values" in md and "2 against 2 (0.333)" in md
    # an object and a strategy of Table I: brackets, and the text says what they hold
    write_report([result_row("cube", "vs-local", 0, coverage_pct="80.0000")], tmp_path, {})
    md = (tmp_path / REPORT_MD).read_text()
    assert "in brackets the paper's figures: Table I's in an object's row where it has the object and " \
        "strategy and the paper's mean over its eight objects (section III-C) in a row " \
        "`mean over N objects`" in md


def _before_table(md: str, first_header: str) -> str:
    """The paragraph just above the table whose header starts with ``first_header``."""
    lines = md.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_header}"))
    return lines[start - 2]


def test_the_sentence_before_each_table_says_what_its_coverage_is_and_within_what_radius(tmp_path):
    """A flange scanned by LR-NBV on the ToF cell: eq. 13's coverage (2.5 mm to a cloud point) 7.6 %
    against 73.2 % of the surface within 10 mm of an object voxel; each table's sentence says which is
    which, and why they differ so on a sparse cloud."""
    flange = [result_row("flange", "lr-nbv", seed, coverage_pct="7.6000", packing_coverage_pct="73.2000",
                         iou="0.7000", dims_m="0.2000 0.2000 0.0500") for seed in (0, 1)]
    write_report(flange, tmp_path, {("flange", "0,0,0"): 99.7}, packing_radii_m=[0.01])
    md = (tmp_path / REPORT_MD).read_text()
    reconstruction = _before_table(md, "object | planner | n | coverage %")
    assert "`coverage %`: the visual-servoing paper's eq. 13, the share of the object's surface" \
        in reconstruction
    assert "within 2.5 mm of a point of the measured cloud" in reconstruction
    assert "`limit %`: the coverage limit" in reconstruction
    packing = _before_table(md, "object | planner | n | L m")
    assert "`surface reconstructed %`: the packing paper's surface coverage, the share of the same surface " \
        "sample within 10 mm (`packing.coverage_radius_m`" in packing
    assert "an 8 x 8 time-of-flight sensor" in packing and "few surface points lie within 2.5 mm" in packing


def test_the_papers_means_over_its_objects_are_in_a_mean_row_not_in_an_objects_row(tmp_path):
    rows = [result_row(obj, "vs-local", seed, coverage_pct="80.0000", scan_time_s=f"{time + seed:.4f}",
                       path_m="0.9000") for obj, time in (("bunny", 46.0), ("cube", 40.0)) for seed in (0, 1)]
    write_report(rows, tmp_path, {})
    table = _table((tmp_path / REPORT_MD).read_text(), "object | planner | n | coverage %")
    bunny, cube, mean = table
    assert bunny[:4] == ["bunny", "vs-local", "2", "80.0 ± 0.0 (90.1)"] and bunny[7] == "46.5 ± 0.5"
    assert cube[7] == "40.5 ± 0.5"
    assert mean == ["mean over 2 objects", "vs-local", "4", "", "", "", "", "43.5 ± 3.0 (42.0)",
                    "0.90 ± 0.00 (0.80)", ""]
    # one object at two placements is one object, each placement's mean counted
    twice = [result_row("bunny", "vs-local", 0, scan_time_s=f"{time:.4f}", path_m="0.9000", placement=where)
             for where, time in (("0,0,0", 46.0), ("0.02,0,0", 40.0))]
    write_report(twice, tmp_path, {})
    table = _table((tmp_path / REPORT_MD).read_text(), "object | planner | n | coverage %")
    assert table[-1][:3] == ["mean over 1 object at 2 placements", "vs-local", "2"]


def test_a_report_without_the_packing_section_and_the_claims_only_for_the_papers_grid(tmp_path):
    """Table I's report leaves out the packing section of its scans (and its tests), saying where those
    figures are; a packing section of objects or planners not the packing paper's quotes no claim of it."""
    assert not presets.VS_TABLE.packing_report and presets.PACKING.packing_report
    bunny = [result_row("bunny", planner, seed, coverage_pct=f"{80 + seed:.4f}", iou=f"0.{5 + seed}000",
                        dims_m="0.1000 0.1000 0.1000", n_poses=f"{3 + seed}")
             for planner in ("vs-local", "lr-nbv") for seed in (0, 1)]
    write_report(bunny, tmp_path, {}, packing=False)
    md = (tmp_path / REPORT_MD).read_text()
    assert "## Packing" not in md and "claims" not in md and not (tmp_path / "fig3.png").exists()
    assert "The packing figures of these scans (the LR-NBV paper's Fig. 3: box, IoU, surface " \
        "reconstructed, poses) are not this report's; `results.csv` holds them." in md
    assert {line[1] for line in _table(md, "object | figure | planner A")} == {"coverage_pct"}
    write_report(bunny, tmp_path, {})
    md = (tmp_path / REPORT_MD).read_text()
    assert "## Packing (LR-NBV paper, Fig. 3)" in md and "claims" not in md
    assert {"iou", "n_poses", "L m"} <= {line[1] for line in _table(md, "object | figure | planner A")}
    flange = [{**r, "object": "flange"} for r in bunny]
    write_report(flange, tmp_path, {})
    assert "The paper gives Fig. 3 as plots only; its text claims:" in (tmp_path / REPORT_MD).read_text()


def test_results_rows_hold_the_true_box_the_upper_bound_and_the_container():
    spec = ScanSpec(CONFIG, "cube", (0.0, 0.0, 0.0), "lr-nbv", 0)
    result = {"status": "completed", "termination": "done", "object_pose": np.eye(4).tolist(),
              "packing": {"dims_m": [0.11, 0.1, 0.1], "dims_upper_m": [0.14, 0.13, 0.12],
                          "container": {"name": "small"}}}
    row = row_from_result(spec, result)
    assert (row["dims_true_m"], row["dims_upper_m"], row["container"]) == (
        "0.1000 0.1000 0.1000", "0.1400 0.1300 0.1200", "small")
    # no ground truth on a real cell; no container fits: none
    no_fit = {**result["packing"], "container": {}}
    row = row_from_result(spec, {**result, "object_pose": None, "packing": no_fit})
    assert (row["dims_true_m"], row["container"]) == ("", "none")


def _box(lo, hi, inward=False):
    mesh = o3d.geometry.TriangleMesh.create_box(*(np.subtract(hi, lo)))
    mesh.translate(lo)
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    return v, (t[:, ::-1] if inward else t)


def _kept_area(v, t) -> float:
    """Area [m^2] of the faces eq. 13's sample keeps (not within 45 degrees of straight down)."""
    normals, areas = face_normals(v, t.astype(np.int32))
    return float(areas[normals[:, 2] > -np.cos(np.pi / 4)].sum())


def test_a_view_counts_as_reachable_at_any_roll_about_its_optical_axis():
    # The Panda's last joint ends before an upright camera on the arm's left (+y) can be turned that far:
    # the view is taken rolled, from the same place along the same axis.
    config = load_config(REPO / "config" / "sim-franka-rgbd.yaml")
    centre = np.array([0.45, 0.0, 0.05])
    direction = np.array([0.0, np.cos(np.pi / 4), np.sin(np.pi / 4)])
    view = look_at(centre + 0.25 * direction, centre)
    posed, reachable = reachable_views(config, view[None], centre - [0.05, 0.05, 0.05], centre + 0.05)
    assert reachable.tolist() == [True]
    np.testing.assert_allclose(posed[0][:3, 2:], view[:3, 2:], atol=1e-12)
    roll_deg = np.degrees(np.arccos(np.clip(posed[0][:3, 0] @ view[:3, 0], -1.0, 1.0)))
    assert roll_deg > 1.0  # upright, the first roll tried, was out of reach


def test_coverage_limit_of_a_cube_and_of_a_hidden_cavity(tmp_path):
    config = load_config(CONFIG)
    cube = load_object("cube")
    assert cell_coverage_limit(config, cube, (0.0, 0.0, 0.0), 60, reachable=False).coverage_pct == 100.0
    # a 10 cm box holding a closed 6 cm cavity: its walls and floor face into the box, seen from nowhere
    outer = _box((-0.05, -0.05, 0.0), (0.05, 0.05, 0.1))
    inner = _box((-0.03, -0.03, 0.02), (0.03, 0.03, 0.08), inward=True)
    v = np.vstack([outer[0], inner[0]])
    t = np.vstack([outer[1], inner[1] + len(outer[0])])
    path = tmp_path / "cavity.ply"
    o3d.io.write_triangle_mesh(path, o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v),
                                                                o3d.utility.Vector3iVector(t)))
    hidden_pct = 100.0 * _kept_area(*inner) / (_kept_area(*outer) + _kept_area(*inner))
    limit = cell_coverage_limit(config, load_object(str(path)), (0.0, 0.0, 0.0), 60, reachable=False)
    assert limit.coverage_pct == pytest.approx(100.0 - hidden_pct, abs=1.5)
    # the arm reaches only some of the views, and they still see the whole cube (12 directions: each
    # view's reach is an IK solve, and 36 views show it as well as 180)
    reachable = cell_coverage_limit(config, cube, (0.0, 0.0, 0.0), 12)
    assert 0 < reachable.n_reachable < reachable.n_views
    assert reachable.coverage_pct == 100.0


def test_coverage_limits_run_side_by_side_on_the_executor_once_per_input(tmp_path):
    """Two planners and two placements of the cube, and a mesh file that is no mesh: the executor gets one
    limit to compute per object and placement, each as the driver would compute it; the broken one is
    reported and left out. Asked again, nothing is computed: limits.json holds them."""
    broken = tmp_path / "broken.ply"
    broken.write_text("not a mesh\n")
    placements = [("cube", (0.0, 0.0, 0.0)), ("cube", (0.04, -0.02, 30.0)), (str(broken), (0.0, 0.0, 0.0))]
    specs = cross(CONFIG, placements, ["heu", "lr-nbv"], [0])
    pool = CountingPool(2)
    progress = io.StringIO()
    limits = coverage_limits(specs, tmp_path, 8, pool, progress)
    config = load_config(CONFIG)
    assert pool.given == [3]
    assert limits == {("cube", "0,0,0"): cell_coverage_limit(config, load_object("cube"), (0.0, 0.0, 0.0),
                                                              8).coverage_pct,
                      ("cube", "0.04,-0.02,30"): cell_coverage_limit(config, load_object("cube"),
                                                                     (0.04, -0.02, 30.0), 8).coverage_pct}
    assert f"no coverage limit of {broken} at (0.0, 0.0, 0.0)" in progress.getvalue()
    assert len(json.loads((tmp_path / LIMITS_JSON).read_text())) == 2
    assert coverage_limits(specs, tmp_path, 8, pool, progress) == limits
    assert pool.given == [3, 1]  # the broken mesh only


def test_a_presets_own_objects_given_by_name_keep_their_placements(tmp_path):
    """``cell eval heldout --objects cylinder``: the held-out cylinder (a shape file) where the suite puts
    it, one scan a seed; an object the preset lacks runs at each of its placements, as before."""
    preset = presets.heldout(tmp_path / "shapes")
    placements = list(dict.fromkeys(p for _, p in presets.HELDOUT_CASES))
    (cylinder,) = preset.specs(objects=["cylinder"])
    assert cylinder.object == str(tmp_path / "shapes" / "cylinder.ply")
    assert cylinder.placement == (0.0, 0.0, 0.0)
    (bunny,) = preset.specs(objects=["bunny"])
    assert bunny.object == "bunny" and bunny.placement == (0.05, -0.04, 60.0)
    banana = preset.specs(objects=["banana"])
    assert [s.placement for s in banana] == placements
    given = preset.specs(objects=["cylinder"], placements=[(0.01, 0.0, 10.0)])
    assert [(s.object, s.placement) for s in given] == [(cylinder.object, (0.01, 0.0, 10.0))]

