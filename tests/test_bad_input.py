"""Bad input that used to run a whole job and report success, or leave a broken job folder: refused before
the folder exists with a one-line reason, or ended with its own outcome; and how `cell scan` reports on a
pipe and when it ends."""

from __future__ import annotations

import itertools
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from importlib.metadata import entry_points

import numpy as np
import pytest
import trimesh
import yaml
from typer.testing import CliRunner

import cell.jobs.runner as runner
from cell.cli.entry import EXIT_INTERRUPTED
from cell.cli.jobs import EXIT_NOT_COMPLETED
from cell.cli.main import app
from cell.cli.scan import _arm_fault_hint
from cell.cli.signals import TERMINATING
from cell.config import load_config
from cell.evaluation.presets import write_heldout_shapes
from cell.evaluation.spec import check_specs, cross
from cell.jobs.placement import where_views_look
from cell.jobs.replay import replay_config
from cell.jobs.runner import ScanRequest, prepare_scan, run_scan
from cell.jobs.session import JobSession
from cell.jobs.stop_file import request_stop
from drivers.depth.sim_tof import SimToF
from drivers.errors import DeviceFault, JobError
from drivers.sim.objects import ObjectMesh, load_object, write_mesh

from .conftest import FRANKA, REPO, UR5E


def _scan(*args: str):
    return CliRunner().invoke(app, ["scan", "--config", str(FRANKA), *args])


@pytest.fixture(scope="module")
def cube_mm(tmp_path_factory):
    """The shipped cube exported in millimetres (a CAD export): 100 units a side."""
    cube = load_object("cube")
    path = tmp_path_factory.mktemp("meshes") / "cube_mm.ply"
    write_mesh(ObjectMesh("cube_mm", cube.vertices * 1000.0, cube.triangles), path)
    return path


def test_a_mesh_in_millimetres_is_refused_saying_what_the_scale_would_make_of_it(cube_mm, tmp_path):
    res = _scan("--object", str(cube_mm), "--out", str(tmp_path / "j"))
    assert res.exit_code == 1 and res.output.count("\n") == 1
    assert "cube_mm is 100.000 x 100.000 x 100.000 m" in res.output
    assert "--object-scale 0.001 would make it 0.100 x 0.100 x 0.100 m" in res.output
    assert not (tmp_path / "j").exists()
    job = prepare_scan(ScanRequest(config=load_config(FRANKA), config_path=str(FRANKA), object=str(cube_mm),
                                   object_scale=0.001, out=tmp_path / "j"))
    assert job.mesh is not None and np.allclose(job.mesh.extents_m, 0.1)
    assert not (tmp_path / "j").exists()


def test_object_scale_is_for_mesh_files_only(cube_mm, tmp_path):
    """Shipped objects are in metres: a scale meant for a millimetre mesh made the cube 0.1 mm a side."""
    res = _scan("--object", "cube", "--object-scale", "0.001", "--out", str(tmp_path / "j"))
    assert res.exit_code == 1
    assert res.stderr == "error: --object-scale is for a mesh file: the shipped object cube is in metres\n"
    assert not (tmp_path / "j").exists()
    # a grid mixing a millimetre mesh with a shipped object scales the mesh only, and can run
    specs = cross(str(FRANKA), [("cube", (0.0, 0.0, 0.0)), (str(cube_mm), (0.0, 0.0, 0.0))], ["raster"], [0],
                  object_scale=0.001)
    assert [s.object_scale for s in specs] == [1.0, 0.001]
    check_specs(specs)


def test_a_grid_is_checked_preparing_one_scan_of_the_seeds_that_share_the_rest(monkeypatch):
    """prepare_scan's checks other than the seed's range do not depend on the seed: a grid of two objects
    x two planners x three seeds prepares four scans, and a bad seed among good ones is still refused."""
    prepared = []

    def counted(req):
        prepared.append((req.object, req.planner))
        return prepare_scan(req)

    monkeypatch.setattr("cell.evaluation.spec.prepare_scan", counted)
    cases, planners = [("cube", (0.0, 0.0, 0.0)), ("bunny", (0.0, 0.0, 0.0))], ["raster", "vs-local"]
    check_specs(cross(str(FRANKA), cases, planners, [0, 1, 2]))
    assert sorted(prepared) == sorted((obj, planner) for obj, _ in cases for planner in planners)
    with pytest.raises(JobError, match="seed must be between 0 and"):
        check_specs(cross(str(FRANKA), cases, ["raster"], [0, -1]))


def test_a_mesh_too_small_to_be_a_part_is_refused_giving_its_size_in_millimetres(tmp_path):
    """Its size read "0.000 x 0.000 x 0.000 m"."""
    with pytest.raises(JobError, match=r"bunny is 0\.156 x 0\.121 x 0\.154 mm .* side at least 0\.01"):
        prepare_scan(ScanRequest(config=load_config(FRANKA), config_path=str(FRANKA), object="bunny",
                                 object_scale=0.001, out=tmp_path / "j"))


def _box_file(folder, name, extents):
    path = folder / f"{name}.stl"
    trimesh.creation.box(extents=extents).export(path)
    return path


def _prepare(tmp_path, **request):
    return prepare_scan(ScanRequest(config=load_config(FRANKA), config_path=str(FRANKA),
                                    out=tmp_path / "j", **{"object": "bunny", **request}))


def test_a_part_too_thin_for_segmentation_is_refused_saying_why(tmp_path):
    """A 3 mm plate lies wholly below the segmentation's 6 mm cut above the table, in the voxel layer."""
    plate = _box_file(tmp_path, "plate", [0.15, 0.10, 0.003])
    res = _scan("--object", str(plate), "--out", str(tmp_path / "j"))
    assert res.exit_code == 1 and not (tmp_path / "j").exists()
    assert "plate is 0.150 x 0.100 x 0.003 m" in res.output and "taller than 3.5 mm" in res.output
    assert "plane_distance_m" in res.output
    thicker = _box_file(tmp_path, "thicker", [0.15, 0.10, 0.005])
    assert _prepare(tmp_path, object=str(thicker)).mesh is not None  # prepare_scan makes no folder


@pytest.mark.parametrize("pose", [(-0.42, 0.0, 0.0), (-0.4, 0.05, 30.0)])
def test_a_placement_into_the_robot_base_is_refused(tmp_path, pose):
    """-0.42,0,0 was accepted, and the job stopped at 0.02 s: 'link0 touched the object'."""
    with pytest.raises(JobError, match=r"into the robot base \(link0\) at the arm's home joints"):
        _prepare(tmp_path, object_pose=pose)
    assert not (tmp_path / "j").exists()


def test_a_part_taller_than_the_start_views_leave_room_for_is_refused(tmp_path):
    """An 8 cm x 1.0 m post was accepted, and the camera hit it on its way to the start view."""
    post = _box_file(tmp_path, "post", [0.08, 0.08, 1.0])
    with pytest.raises(JobError, match=r"post is 0\.080 x 0\.080 x 1\.000 m .* at most 0\.260 m tall"):
        _prepare(tmp_path, object=str(post))
    assert _prepare(tmp_path, object="vertical_box").mesh is not None  # 0.25 m, the tallest shipped


@pytest.mark.parametrize("pose", [(0.3, 0.0, 0.0), (0.0, 0.42, 0.0)])
def test_a_placement_no_search_view_sees_is_refused_naming_where_they_look(tmp_path, pose):
    """Both ended 'no_object: segmentation found nothing above the table' after 14 frames."""
    with pytest.raises(JobError, match=r"where none of the 2 views vs-local looks for an object from sees "
                                       r"it: they look at the station \(0\.45, 0\) m, each view keeping"):
        _prepare(tmp_path, object_pose=pose, planner="vs-local")
    assert _prepare(tmp_path, object_pose=(0.1, 0.1, 0.0), planner="vs-local").mesh is not None


def test_no_scale_is_suggested_that_makes_a_size_the_cell_refuses(tmp_path):
    """A 1.5 m box was told "a mesh in centimetres? --object-scale 0.01 would make it 0.015 x 0.004 x
    0.003 m", a size no scan finds."""
    big = _box_file(tmp_path, "big", [1.5, 0.4, 0.3])
    res = _scan("--object", str(big), "--out", str(tmp_path / "j"))
    assert res.exit_code == 1 and "big is 1.500 x 0.400 x 0.300 m" in res.output
    assert "centimetres" not in res.output  # 3 mm tall: table to segmentation
    assert "a mesh in inches? --object-scale 0.0254 would make it 0.038 x 0.010 x 0.008 m" in res.output
    assert _prepare(tmp_path, object=str(big), object_scale=0.0254).mesh is not None
    huge = _box_file(tmp_path, "huge", [100.0, 0.4, 0.3])  # no unit makes it a part
    res = _scan("--object", str(huge), "--out", str(tmp_path / "j"))
    assert res.exit_code == 1 and "would make it" not in res.output


def test_a_pose_off_the_table_is_refused_naming_the_table(tmp_path):
    res = _scan("--object-pose", "2,2,0", "--out", str(tmp_path / "j"))
    assert res.exit_code == 1 and res.output.count("\n") == 1
    assert "off the table" in res.output
    assert "the table spans x -0.100..1.100 m, y -0.500..0.500 m" in res.output
    assert not (tmp_path / "j").exists()


@pytest.mark.parametrize("args, message", [
    (["--seed", "-1"], "seed must be between 0 and 9223372036854775807, got -1"),
    (["--max-time", "nan"], "time budget must be a positive number of seconds, got nan"),
    (["--object-pose", "inf,0,0"],
     "--object-pose: expected x,y,yaw_deg (three finite numbers), got 'inf,0,0'"),
    # a malformed pose was Typer's usage box, which named no option ("Invalid value: expected ...")
    (["--object-pose", "1,2"], "--object-pose: expected x,y,yaw_deg (three finite numbers), got '1,2'"),
    (["--object-scale", "0"], "scale must be a positive number, got 0.0"),
])
def test_every_input_is_checked_before_the_job_folder_exists(tmp_path, args, message):
    res = _scan(*args, "--out", str(tmp_path / "j"))
    assert res.exit_code == 1 and res.output.startswith("error: ") and message in res.output
    assert res.output.count("\n") == 1
    assert not (tmp_path / "j").exists()


def test_out_must_be_a_new_or_empty_folder(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("my own file\n")
    res = _scan("--out", str(mine))
    assert res.exit_code == 1 and "is not empty and holds no job" in res.output
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    empty = tmp_path / "empty"
    empty.mkdir()
    request = ScanRequest(config=load_config(FRANKA), config_path=str(FRANKA), object="cube", out=empty)
    assert prepare_scan(request).folder == empty


def test_an_empty_table_ends_no_object_and_the_cli_says_so(tmp_path):
    out = tmp_path / "empty"
    # a budget that lets the raster visit all its views (19.5 s): it ends its path, having seen nothing
    res = _scan("--object", "none", "--planner", "raster", "--max-time", "25", "--out", str(out))
    assert res.exit_code == 2, res.output
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "no_object" and result["n_captures"] >= 3
    assert result["termination"].startswith("no object found: segmentation found nothing above the table "
                                            "near the station (0.45, 0) m, each view keeping its crop box")
    assert result["termination"].endswith("(raster complete: 12 of 14 views captured, 2 unreachable)")
    assert result["metrics"]["coverage_pct"] is None and result["packing"]["dims_m"] is None
    assert f"job folder: {out}" in res.output
    # decided from what the job saw, not from ground truth: a replay of the recording has none, and the
    # same frames give the same outcome
    replay = run_scan(ScanRequest(config=replay_config(load_config(FRANKA), out),
                                  config_path=str(FRANKA), object="none", planner="raster",
                                  out=tmp_path / "replay"))
    assert replay.result["object_pose"] is None and replay.result["status"] == "no_object"


@pytest.mark.parametrize("planner, max_time, frames",
                         [("lr-nbv", "1", "1 frame"), ("raster", "5", "2 frames")])
def test_a_budget_that_ends_the_search_before_an_object_is_found_is_not_no_object(tmp_path, planner, max_time,
                                                                                  frames):
    """A cube on the ToF cell: one frame of 8 x 8 zones does not show it to segmentation, and a budget that
    ended the planner's run after it used to end no_object (exit 2, "no part" to a packing line)."""
    out = tmp_path / "short"
    res = CliRunner().invoke(app, ["scan", "--config", str(UR5E), "--object", "cube", "--planner", planner,
                                   "--seed", "1" if planner == "raster" else "0", "--max-time", max_time,
                                   "--out", str(out)])
    assert res.exit_code == 0, res.output
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "completed" and result["packing"]["dims_m"] is None
    assert result["termination"] == (
        f"time budget of {max_time} s used up before an object was found or the planner's search for one had "
        f"ended (segmentation found nothing above the table near {where_views_look(load_config(UR5E))} in "
        f"{frames}): too soon to tell an empty table, "
        "so not no_object")


def test_a_part_only_the_map_shows_ends_completed_with_its_box(tmp_path):
    """The 12 mm washer of the held-out shapes on the ToF cell, LR-NBV, seed 1: as high as the table cut,
    its 8 x 8 zones mixed with the table and its 4 cm hole, no single frame's segmentation finds it, but
    the map built from the 8 frames does; LR-NBV scans it and the packing box is measured. The job reports
    it found the part (it said ``no_object`` beside a box)."""
    washer = write_heldout_shapes(tmp_path / "shapes")["washer"]
    outcome = run_scan(ScanRequest(config=load_config(UR5E), config_path=str(UR5E), object=str(washer),
                                   planner="lr-nbv", seed=1, out=tmp_path / "j"))
    log = (tmp_path / "j" / "log.txt").read_text().splitlines()
    captures = [line for line in log if "] capture " in line]
    assert captures and all(line.endswith("H_ROI -") for line in captures), \
        "a frame's segmentation found the washer: this scan no longer shows what the test is about"
    assert outcome.result["status"] == "completed", outcome.result["termination"]
    assert outcome.result["packing"]["dims_m"] is not None


def test_a_scan_with_its_object_completes(tmp_path):
    outcome = run_scan(ScanRequest(config=load_config(FRANKA), config_path=str(FRANKA), object="cube",
                                   planner="raster", max_time_s=4.0, out=tmp_path / "j"))
    assert outcome.result["status"] == "completed" and outcome.result["n_captures"] >= 1


def test_a_failure_while_setting_up_still_leaves_a_result(tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("the guard could not be built")

    monkeypatch.setattr(runner.MotionGuard, "from_config", broken)
    res = _scan("--object", "cube", "--out", str(tmp_path / "j"))
    assert res.exit_code == 1
    assert res.output == (f"job folder: {tmp_path / 'j'}\n"
                          "error: internal error: RuntimeError: the guard could not be built\n"
                          f"job folder: {tmp_path / 'j'}\n")
    result = json.loads((tmp_path / "j" / "result.json").read_text())
    assert result["status"] == "failed"
    assert result["termination"] == "internal error: RuntimeError: the guard could not be built"
    assert result["object"] == "cube" and result["safety"] is None
    log = (tmp_path / "j" / "log.txt").read_text()
    assert "Traceback (most recent call last)" in log and "in broken" in log


def test_a_fault_the_sensor_latches_mid_move_ends_a_stop_and_go_job_within_a_tick(tmp_path, monkeypatch):
    """A VL53L8CX whose port vanished is noticed by its reader thread at once; a raster move, which needs
    no frame, would otherwise run to its end before the next capture found it."""
    vanished_at = 4.0

    def latched(self):
        if self._clock.now() < vanished_at:
            return None
        return DeviceFault("faulted: port vanished; reconnect to clear", device=self.device)

    monkeypatch.setattr(SimToF, "latched_fault", latched)
    config = load_config(UR5E)
    with pytest.raises(DeviceFault, match="port vanished"):
        run_scan(ScanRequest(config=config, config_path=str(UR5E), object="cube", planner="raster",
                             max_time_s=30.0, out=tmp_path / "j"))
    result = json.loads((tmp_path / "j" / "result.json").read_text())
    assert result["status"] == "failed" and "port vanished" in result["termination"]
    (stop,) = result["safety"]["stops"]
    assert vanished_at <= stop["t"] <= vanished_at + 1.0 / config.scan.control_rate_hz + 1e-9
    assert "port vanished" in stop["reason"]


def test_a_failure_while_writing_the_outputs_still_leaves_a_result(tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise ValueError("no packing today")

    monkeypatch.setattr(runner, "packing_section", broken)
    with pytest.raises(ValueError, match="no packing today"):
        run_scan(ScanRequest(config=load_config(FRANKA), config_path=str(FRANKA), object="cube",
                             planner="raster", max_time_s=2.0, out=tmp_path / "j"))
    result = json.loads((tmp_path / "j" / "result.json").read_text())
    assert result["status"] == "failed" and result["seed"] == 0
    assert result["termination"] == ("internal error while writing the job's outputs: ValueError: no packing "
                                     "today")


def test_ctrl_c_in_a_scan_stops_it_and_exits_130_with_the_folder(tmp_path, monkeypatch):
    def interrupted(self, session):
        session.wait(0.5)
        raise KeyboardInterrupt

    monkeypatch.setattr(runner.get_planner("raster"), "run", interrupted)
    res = _scan("--object", "cube", "--planner", "raster", "--out", str(tmp_path / "j"))
    assert res.exit_code == 130
    assert "interrupted (Ctrl-C)" in res.output and f"job folder: {tmp_path / 'j'}" in res.output
    assert json.loads((tmp_path / "j" / "result.json").read_text())["status"] == "stopped"


def test_a_sim_scan_stopped_by_an_arm_fault_says_the_next_job_starts_fresh(tmp_path):
    """``cell arm recover`` is for hardware arms (it refuses a sim arm's file): a rehearsed fault in sim
    does not send the operator there."""
    data = yaml.safe_load(FRANKA.read_text())
    data["sim"]["faults"] = [{"at_s": 3.5, "kind": "protective stop"}]
    faulty = tmp_path / "faulty.yaml"
    faulty.write_text(yaml.safe_dump(data))
    res = CliRunner().invoke(app, ["scan", "--config", str(faulty), "--object", "cube", "--out",
                                   str(tmp_path / "j")])
    assert res.exit_code == 1
    assert "stopped: arm fault: protective stop" in res.output
    assert "the simulated arm starts fresh with the next job" in res.output
    assert "cell arm recover" not in res.output


def test_a_hardware_arm_stopped_by_its_fault_is_to_be_recovered_with_its_cell_file(tmp_path):
    cell_file = REPO / "config" / "dryrun-ur5e-peer.yaml"
    request = ScanRequest(config=load_config(cell_file), config_path=str(cell_file), object="none")
    assert _arm_fault_hint(request) == ("the arm stays faulted until recovered: clear the cause, then cell "
                                        f"arm recover --config {cell_file}")


def test_scan_help_gives_every_exit_code_the_scan_has():
    """``cell scan --help`` names the code of each ending: the codes of the command line's constants, and
    128 + each signal that stops a scan as Ctrl-C does."""
    text = " ".join(CliRunner().invoke(app, ["scan", "--help"], env={"COLUMNS": "300"}).stdout.split())
    codes = text.split("Exit code ", 1)[1].split(";", 1)[0]
    assert {int(n) for n in re.findall(r"\b\d+\b", codes)} == {
        0, 1, EXIT_NOT_COMPLETED, EXIT_INTERRUPTED, *(128 + sig for sig in TERMINATING)}
    for sig in TERMINATING:
        assert f"{128 + sig} after {signal.Signals(sig).name}" in codes


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_or_sighup_in_a_scan_stops_the_arm_and_finishes_the_folder(tmp_path, monkeypatch, sig):
    def terminated(self, session):
        session.wait(0.5)
        os.kill(os.getpid(), sig)  # as systemd, docker stop or a closed terminal would
        session.wait(5.0)

    monkeypatch.setattr(runner.get_planner("raster"), "run", terminated)
    before = signal.getsignal(sig)
    res = _scan("--object", "cube", "--planner", "raster", "--out", str(tmp_path / "j"))
    assert res.exit_code == 128 + sig
    name = signal.Signals(sig).name
    assert f"stopped: operator stop: received {name}" in res.output
    result = json.loads((tmp_path / "j" / "result.json").read_text())
    assert result["status"] == "stopped"
    assert result["termination"] == f"operator stop: received {name}"
    assert any(name in stop["reason"] for stop in result["safety"]["stops"])  # the guard stopped the arm
    assert signal.getsignal(sig) == before


def test_signals_after_the_first_do_not_interrupt_the_stop_they_asked_for(tmp_path, monkeypatch):
    """systemd sends SIGTERM to every process of the unit, a shell's user may press on: the stop the first
    asked for, and the folder, are finished all the same."""
    def terminated(self, session):
        session.wait(0.5)
        os.kill(os.getpid(), signal.SIGTERM)

    settle, write_outputs = JobSession.settle, runner._write_outputs

    def settle_under_a_signal(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)  # while the arm is being stopped
        return settle(self, *args, **kwargs)

    def write_under_a_signal(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGHUP)  # while the folder is being written
        return write_outputs(*args, **kwargs)

    monkeypatch.setattr(runner.get_planner("raster"), "run", terminated)
    monkeypatch.setattr(JobSession, "settle", settle_under_a_signal)
    monkeypatch.setattr(runner, "_write_outputs", write_under_a_signal)
    res = _scan("--object", "cube", "--planner", "raster", "--out", str(tmp_path / "j"))
    assert res.exit_code == 128 + signal.SIGTERM
    result = json.loads((tmp_path / "j" / "result.json").read_text())
    assert result["termination"] == "operator stop: received SIGTERM"


def test_progress_lines_on_a_pipe_every_few_seconds_of_job_time(tmp_path):
    res = _scan("--object", "cube", "--planner", "raster", "--max-time", "14", "--out", str(tmp_path / "j"))
    assert res.exit_code == 0, res.output
    lines = [line for line in res.stderr.splitlines() if line.startswith("scan: ")]
    times = [float(line.split()[1]) for line in lines]
    assert len(lines) >= 2 and all(b - a >= 5.0 for a, b in itertools.pairwise(times))
    assert lines[0].endswith(" %") and " of 14 s, " in lines[0] and " captures, " in lines[0]
    # the folder comes first, for a `cell stop` while it runs, and again with the result on standard output
    assert res.stderr.splitlines()[0] == f"job folder: {tmp_path / 'j'}"
    assert res.stderr.count("job folder:") == 1 and res.stdout.endswith(f"job folder: {tmp_path / 'j'}\n")


def test_a_scan_names_its_folder_as_soon_as_it_exists_for_a_stop_from_another_terminal(tmp_path):
    """``cell stop JOB_DIR`` while a scan runs needs its folder, which only the scan's end named: standard
    error and output in one pipe, in the order written, the folder comes before the progress lines."""
    out = tmp_path / "j"
    proc = subprocess.run([sys.executable, "-m", "cell.cli.entry", "scan", "--config", str(UR5E), "--object",
                           "cube", "--planner", "raster", "--max-time", "6", "--out", str(out)], cwd=REPO,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout
    lines = proc.stdout.splitlines()
    assert lines[0] == f"job folder: {out}" and lines[1].startswith("scan: ")
    assert lines[-1] == f"job folder: {out}" and lines.count(lines[0]) == 2


# Ctrl-C (SIGINT) at the moment `cell` imports a module of its command line, as a person typing it during
# the second or two that the imports take would
_CTRL_C_DURING_IMPORTS = """
import builtins, os, signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal, whatever this test runs under
real_import, target = builtins.__import__, sys.argv[1]
def import_(name, *args, **kwargs):
    if name == target:
        os.kill(os.getpid(), signal.SIGINT)
    return real_import(name, *args, **kwargs)
builtins.__import__ = import_
sys.argv = ["cell", "scan", "--help"]  # a command that loads Open3D and SciPy
from cell.cli.entry import main
main()
"""


@pytest.mark.parametrize("module", ["cell.cli.commands", "open3d", "scipy.spatial"])
def test_ctrl_c_while_importing_exits_quietly_with_130(module):
    (script,) = entry_points(group="console_scripts", name="cell")
    assert script.value == "cell.cli.entry:main"
    proc = subprocess.run([sys.executable, "-c", _CTRL_C_DURING_IMPORTS, module], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 130
    assert proc.stdout == "" and proc.stderr == ""


def test_a_scan_stopped_by_the_operator_says_stopped_not_error(tmp_path):
    out = tmp_path / "job"

    def stop_once_running() -> None:
        while not (out / "log.txt").exists():
            time.sleep(0.01)
        request_stop(out, "lunch")

    stopper = threading.Thread(target=stop_once_running, daemon=True)
    stopper.start()
    res = _scan("--planner", "raster", "--out", str(out))
    stopper.join(timeout=60)
    assert res.exit_code == 1
    assert res.stderr.splitlines() == [f"job folder: {out}", "stopped: operator stop: lunch (cell stop)",
                                       f"job folder: {out}"]
    assert json.loads((out / "result.json").read_text())["status"] == "stopped"


def test_a_scan_that_reached_no_view_failed_and_says_what_to_check(tmp_path):
    """Every raster view out of the arm's reach (views 1.5 m from the station; a mount, station or TCP that
    is wrong does the same): the scan ended ``completed`` with 0 of 13 views captured, exit code 0."""
    text = UR5E.read_text()
    assert "\n  standoff_m: 0.4\n" in text
    far = tmp_path / "far.yaml"
    far.write_text(text.replace("\n  standoff_m: 0.4\n", "\n  standoff_m: 1.5\n"))
    out = tmp_path / "job"
    res = CliRunner().invoke(app, ["scan", "--config", str(far), "--planner", "raster", "--out", str(out)])
    assert res.exit_code == 1, res.output
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "failed" and result["n_captures"] == 0 and result["n_unreachable_views"] == 13
    assert result["termination"] == (
        "nothing captured: no view was reachable (13 unreachable): check the cell file's mount, station, "
        "scan.standoff_m and the arm's TCP (tcp_offset) (raster complete: 0 of 13 views captured, "
        "13 unreachable)")
    assert f"failed: {result['termination']}" in res.output and f"job folder: {out}" in res.output


def test_the_services_arm_checks_build_the_cells_collision_world_once(tmp_path, built_worlds):
    """Every Start of the line and every job submitted checks a shipped object's placement against the arm
    (``ArmClearance``), and every upload its mesh's, in the same ``ArmClearance`` (the object library's);
    the cell's collision world is built at the first check and kept, where each check, and each upload,
    built one (10-100 ms)."""
    from cell.service.arm_clearance import ArmClearance
    from cell.service.objects import ObjectLibrary

    config = load_config(UR5E)
    arm, bunny = ArmClearance(config), load_object("bunny")
    library = ObjectLibrary(tmp_path / "objects", config, arm)
    for name in ("crate", "tray"):
        source = tmp_path / f"{name}.stl"
        trimesh.creation.box(extents=(0.06, 0.05, 0.04)).export(source)
        library.add(source.name, source.read_bytes())
    arm.check(bunny, (0.0, 0.0, 0.0))
    arm.check(bunny, (0.02, -0.01, 25.0))
    with pytest.raises(JobError, match="robot base"):
        arm.check(bunny, (-0.42, 0.0, 0.0))
    assert len(built_worlds) == 1
