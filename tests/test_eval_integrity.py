"""What a grid's rows and report say: a failed re-process is a failed row (never the online figures
under the re-processed title), an online grid keeps the online figures whatever the folder holds since,
and scans that did not complete stay out of the means and ``n`` and are listed."""

from __future__ import annotations

import io
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import yaml

from cell.config import load_config
from cell.evaluation.evaluate import LIMITS_JSON, coverage_limits, evaluate
from cell.evaluation.executors import LocalPool, RayExecutor
from cell.evaluation.grid import EXECUTOR_TXT, RESULTS_CSV, SCANS_DIR, WHOLE, Shard, running
from cell.evaluation.report import REPORT_MD, write_report
from cell.evaluation.results import read_csv, row_from_folder
from cell.evaluation.spec import ScanSpec, cross, scan_key
from cell.evaluation.task import ScanTask, TaskOutput, pack_folder, run_scan_task, unpack_folder
from cell.perception.hires_files import RESULT_HIRES_FILE
from drivers.depth.zone_correction import ZoneCorrection, write_zone_correction
from drivers.errors import CellError
from tests.test_evaluation import CountingPool

REPO = Path(__file__).resolve().parents[1]
TOF = str(REPO / "config" / "sim-ur5e-tof.yaml")


def _job(folder: Path, status: str = "completed", coverage: float = 50.0, hires: float | None = None) -> Path:
    folder.mkdir(parents=True)
    (folder / "result.json").write_text(json.dumps({
        "status": status, "termination": "budget", "scan_time_s": 1.0, "n_captures": 3,
        "metrics": {"coverage_pct": coverage, "chamfer_mm": 2.0}}))
    if hires is not None:
        hires_result = {"metrics": {"coverage_pct": hires, "chamfer_mm": 1.0}}
        (folder / RESULT_HIRES_FILE).write_text(json.dumps(hires_result))
    return folder


def test_a_failed_reprocess_is_a_failed_row_with_no_online_figures(tmp_path):
    # 1 s of budget: no frame, nothing to re-process
    spec = ScanSpec(TOF, "cube", (0.0, 0.0, 0.0), "heu", 0, max_time_s=1.0, reprocess=True)
    output = run_scan_task(ScanTask.of(spec, scan_key(spec)))
    assert output.archive is not None and output.error is not None
    unpack_folder(output.archive, tmp_path / "job")
    row = row_from_folder(spec, tmp_path / "job")
    assert row["status"] == "failed" and "re-process failed" in row["termination"], row
    assert row["coverage_pct"] == row["chamfer_mm"] == "" and row["job"] == "job"


def test_an_online_row_keeps_the_online_figures_after_a_reprocess(tmp_path):
    spec = ScanSpec(TOF, "cube", (0.0, 0.0, 0.0), "heu", 0)
    folder = _job(tmp_path / "job", coverage=50.0, hires=90.0)
    assert row_from_folder(spec, folder)["coverage_pct"] == "50.0000"
    assert row_from_folder(replace(spec, reprocess=True), folder)["coverage_pct"] == "90.0000"


def test_scans_that_did_not_complete_are_out_of_the_means_and_listed(tmp_path):
    spec = ScanSpec(TOF, "cube", (0.0, 0.0, 0.0), "heu", 0)
    rows = [row_from_folder(replace(spec, seed=seed), _job(tmp_path / f"s{seed}", status, coverage))
            for seed, status, coverage in ((0, "completed", 60.0), (1, "completed", 80.0),
                                           (2, "stopped", 5.0), (3, "failed", 1.0))]
    write_report(rows, tmp_path, {})
    md = (tmp_path / REPORT_MD).read_text()
    assert "| cube | heu | 2 | 70.0 ± 10.0 |" in md, md
    listed = md.split("## Scans that did not complete")[1]
    assert "cube 0,0,0 heu seed 2: stopped: budget" in listed and "seed 3: failed" in listed


def _box_stl(path: Path, size: float) -> str:
    mesh = o3d.geometry.TriangleMesh.create_box(size, size, size)
    mesh.compute_triangle_normals()
    path.parent.mkdir(parents=True, exist_ok=True)
    o3d.io.write_triangle_mesh(str(path), mesh)
    return str(path)


def test_an_object_is_known_by_its_mesh_not_its_file_name(tmp_path):
    a = _box_stl(tmp_path / "a" / "part.stl", 0.05)
    b = _box_stl(tmp_path / "b" / "part.stl", 0.06)
    same = _box_stl(tmp_path / "c" / "part.stl", 0.05)
    labels = [ScanSpec(TOF, obj, (0.0, 0.0, 0.0), "heu", 0).object_label for obj in (a, b, same)]
    assert labels[0] != labels[1] and labels[0] == labels[2] and labels[0].startswith("part@")
    assert ScanSpec(TOF, "cube", (0.0, 0.0, 0.0), "heu", 0).object_label == "cube"
    assert ScanSpec(TOF, "cube", (0.0, 0.0, 0.0), "heu", 0, object_scale=0.5).object_label.startswith("cube@")
    # a user's bunny.stl gets no figure of the paper's bunny in brackets
    fake = ScanSpec(TOF, _box_stl(tmp_path / "fake" / "bunny.stl", 0.05), (0.0, 0.0, 0.0), "vs-local", 0)
    write_report([row_from_folder(fake, _job(tmp_path / "job"))], tmp_path, {})
    line = next(x for x in (tmp_path / REPORT_MD).read_text().splitlines() if "vs-local" in x)
    assert line.startswith(f"| {fake.object_label} | vs-local | 1 | 50.0 |"), line


def _cell_with_obstacle(tmp_path: Path, mesh: str) -> str:
    data = yaml.safe_load(Path(TOF).read_text())
    data["safety"]["collision"]["obstacles"] = [
        {"shape": "mesh", "name": "post", "path": mesh, "pose": {"xyz_m": [0.9, 0.45, 0.025]}}]
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_the_key_covers_the_files_the_cell_file_names_and_a_task_carries_them(tmp_path):
    mesh = _box_stl(tmp_path / "post.stl", 0.05)
    spec = ScanSpec(_cell_with_obstacle(tmp_path, mesh), "cube", (0.0, 0.0, 0.0), "heu", 0)
    key = scan_key(spec)
    task = ScanTask.of(spec, key)
    _box_stl(tmp_path / "post.stl", 0.04)
    assert scan_key(spec) != key
    # the worker's copy of the cell file names its own copy of the mesh, the bytes the driver read
    worker = tmp_path / "worker"
    worker.mkdir()
    copy = load_config(task.write_config(worker))
    (obstacle,) = copy.safety.collision.obstacles
    assert Path(obstacle.path).parent == worker / "files"
    assert Path(obstacle.path).read_bytes() == task.config_files[0] != Path(mesh).read_bytes()


def test_a_comment_or_layout_edit_of_the_cell_file_keeps_the_key_and_a_setting_changes_it(tmp_path):
    """The key hashes the cell file's settings, not its text: a grid run again after a note in the cell
    file keeps its scans, and one after a changed setting runs them again."""
    text = Path(TOF).read_text()
    cell = tmp_path / "cell.yaml"
    cell.write_text(text)
    spec = ScanSpec(str(cell), "cube", (0.0, 0.0, 0.0), "heu", 0)
    key = scan_key(spec)
    data = yaml.safe_load(text)
    cell.write_text("# a note on this cell\n" + yaml.safe_dump(data, sort_keys=True, indent=4))
    assert scan_key(spec) == key
    data["scan"]["standoff_m"] = 0.35
    cell.write_text(yaml.safe_dump(data))
    assert scan_key(spec) != key


def test_a_cell_folder_with_a_zone_correction_keeps_its_key_wherever_it_lies(tmp_path):
    """cell.config makes a relative ``sensor.zone_correction`` absolute; the key takes it as the cell file
    names it (and the file's content), so a grid's cell folder copied or mounted elsewhere (a shard's
    ``--out``) keeps its scans."""
    data = yaml.safe_load(Path(TOF).read_text())
    data["sensor"]["zone_correction"] = "zones.json"
    keys = []
    for folder in (tmp_path / "here", tmp_path / "there"):
        folder.mkdir()
        write_zone_correction(ZoneCorrection(resolution=8, offset_m=np.full(64, 0.001), noise_m=np.zeros(64)),
                              folder / "zones.json")
        (folder / "cell.yaml").write_text(yaml.safe_dump(data))
        keys.append(scan_key(ScanSpec(str(folder / "cell.yaml"), "cube", (0.0, 0.0, 0.0), "heu", 0)))
    assert keys[0] == keys[1]


def fake_scan(task: ScanTask) -> TaskOutput:
    """A scan in no time: seed 1 leaves no folder (refused), the others a completed job."""
    if task.spec.seed == 1:
        return TaskOutput(task.key, None, "JobError: refused")
    with tempfile.TemporaryDirectory() as tmp:
        folder = _job(Path(tmp) / "job", coverage=10.0 * task.spec.seed)
        return TaskOutput(task.key, pack_folder(folder), None)


FAKE_GRID = cross(TOF, [("cube", (0.0, 0.0, 0.0)), ("horizontal_box", (0.0, 0.0, 0.0))], ["heu", "nbv"],
                  [0, 1, 2])


def test_shards_part_the_grid_and_each_rebuilds_results_and_report_from_every_finished_scan(tmp_path):
    keys = [scan_key(s) for s in FAKE_GRID]
    parts = [Shard(i, 3).select(reversed(keys)) for i in (1, 2, 3)]
    assert sorted(k for p in parts for k in p) == sorted(keys) and [len(p) for p in parts] == [4, 4, 4]
    assert parts[0] == Shard(1, 3).select(keys)  # whatever the grid's order
    first = evaluate(FAKE_GRID, tmp_path, LocalPool(1), limit_directions=None, task=fake_scan,
                     stream=io.StringIO(), shard=Shard(1, 2))
    assert len(first.rows) == len(first.mine) == 6 and first.unfinished == 6
    assert "**Partial**: 6 of the grid's 12 scans" in first.report.read_text()
    second = evaluate(FAKE_GRID, tmp_path, LocalPool(1), limit_directions=None, task=fake_scan,
                      stream=io.StringIO(), shard=Shard(2, 2))
    assert second.unfinished == 0 and len(read_csv(tmp_path / RESULTS_CSV)) == 12
    report = second.report.read_text()
    assert "Partial" not in report and "| cube | heu | 2 | 10.0 ± 10.0 |" in report
    # a scan that left no folder is a failed row of every rebuild, and runs again next time
    failed = [r for r in second.rows if r["status"] == "failed"]
    assert len(failed) == 4 and all("refused" in r["termination"] for r in failed)
    assert len(list((tmp_path / SCANS_DIR).glob("*.failed"))) == 4
    pool = CountingPool(1)
    evaluate(FAKE_GRID, tmp_path, pool, limit_directions=None, task=fake_scan, stream=io.StringIO())
    assert pool.given == [4]


def test_a_run_with_nothing_left_starts_no_executor_and_the_report_names_those_that_ran(tmp_path,
                                                                                       monkeypatch):
    """A finished grid run again with --executor ray: no scan to run, so Ray is not started (importing it
    fails here, as starting it would take seconds), and the report still names the pool that ran them."""
    specs = cross(TOF, [("cube", (0.0, 0.0, 0.0))], ["heu"], [0, 2])
    evaluate(specs, tmp_path, LocalPool(1), limit_directions=None, task=fake_scan, stream=io.StringIO())
    monkeypatch.setitem(sys.modules, "ray", None)
    done = evaluate(specs, tmp_path, RayExecutor(), limit_directions=None, task=fake_scan,
                    stream=io.StringIO())
    said = [line for line in done.report.read_text().splitlines() if line.startswith("Executors")]
    assert said == ["Executors that ran these scans (scans each): local (2)."]
    # a job folder of a release that recorded no executor
    (tmp_path / SCANS_DIR / done.rows[0]["job"] / EXECUTOR_TXT).unlink()
    again = evaluate(specs, tmp_path, RayExecutor(), limit_directions=None, task=fake_scan,
                     stream=io.StringIO())
    assert "Executors that ran these scans (scans each): not recorded (1), local (1)." in \
        again.report.read_text()


def fake_packing_scan(task: ScanTask) -> TaskOutput:
    """A scan in no time whose job has the packing figures."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = _job(Path(tmp) / "job")
        result = json.loads((folder / "result.json").read_text())
        result["packing"] = {"dims_m": [0.1, 0.1, 0.1], "iou": 0.5, "coverage_pct": 70.0, "n_poses": 3}
        (folder / "result.json").write_text(json.dumps(result))
        return TaskOutput(task.key, pack_folder(folder), None)


def test_the_report_gives_the_cell_files_surface_coverage_radius_and_the_packing_section_on_request(tmp_path):
    specs = cross(TOF, [("flange", (0.0, 0.0, 0.0))], ["lr-nbv"], [0])
    done = evaluate(specs, tmp_path, LocalPool(1), limit_directions=None, task=fake_packing_scan,
                    stream=io.StringIO())
    assert "within 10 mm (`packing.coverage_radius_m`, the occupancy map's resolution when unset)" in \
        done.report.read_text()
    table_i = evaluate(specs, tmp_path, LocalPool(1), limit_directions=None, task=fake_packing_scan,
                       stream=io.StringIO(), packing=False)
    assert "## Packing" not in table_i.report.read_text()


def test_a_second_run_that_could_run_the_same_scans_is_refused(tmp_path):
    with running(tmp_path, WHOLE), pytest.raises(CellError, match=r"running on .* \(the whole grid, pid"):
        evaluate(FAKE_GRID, tmp_path, LocalPool(1), limit_directions=None, task=fake_scan)
    with running(tmp_path, Shard(1, 2)):
        overlap = r"\(shard 1/2, pid .* overlap these \(shard 1/3\)"
        # disjoint parts run side by side; parts of another count do not
        with running(tmp_path, Shard(2, 2)), pytest.raises(CellError, match=overlap), \
                running(tmp_path, Shard(1, 3)):
            pass
        with pytest.raises(CellError, match="another cell eval is running"), running(tmp_path, Shard(1, 2)):
            pass
    with running(tmp_path, WHOLE):  # all ended: free again
        pass


class InterruptedAfterOne:
    """An executor interrupted (Ctrl-C) after its first result."""

    def run(self, fn, items, on_done):
        on_done(0, 42.0)
        raise KeyboardInterrupt


def test_an_interrupted_limit_stage_keeps_the_limits_it_finished(tmp_path):
    specs = cross(TOF, [("cube", (0.0, 0.0, 0.0)), ("pyramid", (0.0, 0.0, 0.0))], ["heu"], [0])
    with pytest.raises(KeyboardInterrupt):
        coverage_limits(specs, tmp_path, 8, InterruptedAfterOne())
    assert list(json.loads((tmp_path / LIMITS_JSON).read_text()).values()) == [42.0]


def test_a_job_folder_names_the_user_mesh_as_the_driver_has_it(tmp_path):
    mesh = _box_stl(tmp_path / "part.stl", 0.05)
    spec = ScanSpec(TOF, mesh, (0.0, 0.0, 0.0), "heu", 0, max_time_s=1.0)
    output = run_scan_task(ScanTask.of(spec, scan_key(spec)))
    unpack_folder(output.archive, tmp_path / "job")
    for name in ("result.json", "job.json"):
        assert json.loads((tmp_path / "job" / name).read_text())["object"] == str(Path(mesh).resolve())


class Constant:
    """An executor that gives every item the same limit, at once; keeps the items it was given."""

    def __init__(self):
        self.given = []

    def run(self, fn, items, on_done):
        self.given += [task.spec.object for task, _ in items]
        for index in range(len(items)):
            on_done(index, 50.0)


def test_shards_compute_disjoint_parts_of_the_limits_whenever_each_starts(tmp_path):
    specs = cross(TOF, [(o, (0.0, 0.0, 0.0)) for o in ("cube", "pyramid", "teapot", "bunny")], ["heu"], [0])
    first, second = Constant(), Constant()
    coverage_limits(specs, tmp_path, 8, first, shard=Shard(1, 2))
    limits = coverage_limits(specs, tmp_path, 8, second, shard=Shard(2, 2))  # after the first's are in
    assert sorted(first.given + second.given) == sorted(["cube", "pyramid", "teapot", "bunny"])
    assert len(limits) == 4 and len(json.loads((tmp_path / LIMITS_JSON).read_text())) == 4
