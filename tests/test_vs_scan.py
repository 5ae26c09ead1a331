"""Short simulated scans with the visual-servoing planners on both cells, through ``cell scan``."""

from __future__ import annotations

import json
from collections import Counter
from typing import ClassVar

import numpy as np
import pytest
from typer.testing import CliRunner

from cell.cli.main import app
from cell.config import load_config
from cell.jobs.runner import ScanRequest, run_scan
from cell.jobs.session import JobSession
from cell.planning.base import Planner, ScanSession
from cell.planning.vs.servo_scan import ServoScanPlanner
from drivers.transforms import look_at

from .conftest import FRANKA, PANDA_AT_REACH, UR5E, ended_without_a_frame, register_planner


class ReachProbe(Planner):
    """Asks the session whether the arm reaches a few sensor poses, and moves nowhere."""

    name = "test-reach-probe"
    answers: ClassVar[dict[str, bool]] = {}

    def run(self, session: ScanSession) -> str:
        here = session.sensor_pose()
        station = np.array([0.45, 0.0, 0.05])
        above = look_at(station + np.array([0.0, 0.0, 0.25]), station, up_hint=np.array([1.0, 0.0, 0.0]))
        in_table = look_at(np.array([0.45, -0.25, -0.03]), station)
        edge = look_at(np.array([0.665, 0.0, 0.35]), station)
        inside = look_at(np.array([0.62, 0.0, 0.35]), station)
        ReachProbe.answers = {
            "current pose": session.sensor_path_reachable(here[None]),
            "above the station": session.sensor_path_reachable(above[None]),
            "1.5 m out": session.sensor_path_reachable(look_at(np.array([1.5, 0.0, 0.3]), station)[None]),
            "into the table (IK within the margins)": session.sensor_path_reachable(in_table[None]),
            "a move above the station": session.sensor_view_reachable(above),
            "a move 1.5 m out": session.sensor_view_reachable(look_at(np.array([1.5, 0.0, 0.3]), station)),
            "a move into the table, at any roll": session.sensor_view_reachable(in_table),
            # looking back at the station from beyond it: the arm near the edge of its reach (smallest
            # singular value 0.055 at x = 0.665 m) and well inside it (0.126 at x = 0.62 m)
            "at the edge of the reach": session.sensor_path_reachable(edge[None]),
            "at the edge of the reach, clear of it": session.sensor_path_reachable(edge[None], 0.06),
            "inside the reach, clear of its edge": session.sensor_path_reachable(inside[None], 0.06),
        }
        moved = float(np.linalg.norm(session.sensor_pose()[:3, 3] - here[:3, 3]))
        return f"probed; moved {moved:.6f} m"


def test_reachability_is_inverse_kinematics_within_the_joint_margins_free_of_collision(tmp_path,
                                                                                       monkeypatch):
    register_planner(monkeypatch, ReachProbe)
    r = run_scan(ScanRequest(config=load_config(FRANKA), config_path=str(FRANKA), object="cube",
                             planner=ReachProbe.name, out=tmp_path / "job", max_time_s=5.0)).result
    assert ended_without_a_frame(r, "probed; moved 0.000000 m")  # a query moves nothing
    assert ReachProbe.answers == {"current pose": True, "above the station": True, "1.5 m out": False,
                                  "into the table (IK within the margins)": False,
                                  "a move above the station": True, "a move 1.5 m out": False,
                                  "a move into the table, at any roll": False,
                                  "at the edge of the reach": True,
                                  "at the edge of the reach, clear of it": False,
                                  "inside the reach, clear of its edge": True}


class SingularityProbe(Planner):
    """Reads the rows of ``singularity_twists`` and the rate at which a sensor twist moving the flange
    out along +x (base frame) would lower the arm's smallest singular value; moves nowhere."""

    name = "test-singularity-probe"
    found: ClassVar[dict[str, object]] = {}

    def run(self, session: ScanSession) -> str:
        rows = session.singularity_twists(0.06)
        outward = np.concatenate([session.sensor_pose()[:3, :3].T @ np.array([0.02, 0.0, 0.0]), np.zeros(3)])
        SingularityProbe.found = {"rows": rows.shape[0], "outward": [float(a @ outward) for a in rows],
                                  "inward": [float(a @ -outward) for a in rows]}
        return "probed"


@pytest.mark.parametrize(("home", "n_rows"), [(None, 0), (list(PANDA_AT_REACH), 1)])
def test_singularity_rows_say_which_sensor_motion_drives_the_arm_into_its_reach(tmp_path, monkeypatch,
                                                                               home, n_rows):
    """At home no row; stretched to its reach (the flange at x = 0.65 m, smallest singular value 4e-4),
    one, by which moving the sensor further out lowers the singular value and moving it back raises it."""
    register_planner(monkeypatch, SingularityProbe)
    SingularityProbe.found = {}
    cfg = load_config(FRANKA)
    if home is not None:
        cfg = cfg.model_copy(update={"arm": cfg.arm.model_copy(update={"home_joints_rad": home})})
    run_scan(ScanRequest(config=cfg, config_path=str(FRANKA), object="cube", planner=SingularityProbe.name,
                         out=tmp_path / "job", max_time_s=5.0))
    found = SingularityProbe.found
    assert found["rows"] == n_rows
    assert all(rate > 0.0 for rate in found["outward"]) and all(rate < 0.0 for rate in found["inward"])


@pytest.mark.parametrize(("cell_file", "planner", "budget"), [(FRANKA, "vs-local", "12"),
                                                              (UR5E, "vs-local", "10"),
                                                              (FRANKA, "vs-global", "10")])
def test_servo_scan_runs_on_the_cell(tmp_path, cell_file, planner, budget):
    out = tmp_path / "job"
    args = ["scan", "--config", str(cell_file), "--object", "bunny", "--planner", planner, "--seed", "0",
            "--out", str(out), "--max-time", budget]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "completed" and result["planner"] == planner
    assert result["safety"]["stops"] == [] and result["safety"]["refusals"] == []
    assert result["n_captures"] >= 5
    assert result["perception"]["roi"] is not None
    # The primary task brought the object to the optical axis at Z* (within the 5 mm convergence),
    # then the secondary task moved the camera: more path than the move to the start view.
    log = (out / "log.txt").read_text()
    assert "capture" in log
    if planner == "vs-global":  # the goal the arm reaches, on record
        assert "goal 1: sensor at" in log
    if cell_file == FRANKA:  # (the 8x8 ToF finds the object only from the second start view, after 5 s)
        # The servo telemetry (paper Fig. 4 and Fig. 3, left), with the coverage over time in sim.
        lines = (out / "servo.csv").read_text().splitlines()
        assert lines[0].endswith(",mode,coverage_pct") and len(lines) > 100
        assert lines[-1].split(",")[-2] in ("local", "global")
        for name in ("servo.png", "path.png"):
            assert (out / name).read_bytes()[:4] == b"\x89PNG"
    traj = np.loadtxt(out / "trajectory.csv", delimiter=",", skiprows=1)
    moving = traj[traj[:, 0] > float(budget) - 3.0, 1:4]
    assert np.linalg.norm(moving[-1] - moving[0]) > 0.01


def test_the_limit_rows_are_built_once_per_servo_iteration(tmp_path, monkeypatch):
    """The joint-limit and singularity rows at the planner's activations are built once per iteration of
    the secondary task and shared by what uses them: VS-Local's ``follows`` (twice near a refusal) and
    the projection of g (``_within_limits``), which built them again each."""
    cfg = load_config(FRANKA)
    activation_rad = cfg.planners.vs.joint_activation_rad
    calls: Counter[str] = Counter()

    def counted(name, method, *only):
        """``method``, counting under ``name`` its calls (those whose arguments after the first are
        ``only``, when given)."""
        def spy(first, *args):
            calls[name] += not only or args == only
            return method(first, *args)
        return spy

    # _limits_ahead's look ahead, at a multiple of the activation, is another question than the rows'
    monkeypatch.setattr(JobSession, "joint_limit_twists",
                        counted("joint rows", JobSession.joint_limit_twists, activation_rad))
    monkeypatch.setattr(JobSession, "singularity_twists",
                        counted("singularity rows", JobSession.singularity_twists))
    monkeypatch.setattr(ServoScanPlanner, "_within_limits",
                        counted("iterations", ServoScanPlanner._within_limits))
    run_scan(ScanRequest(config=cfg, config_path=str(FRANKA), object="bunny", planner="vs-local",
                         out=tmp_path / "job", max_time_s=8.0))
    assert calls["iterations"] > 100
    assert calls["joint rows"] == calls["singularity rows"] == calls["iterations"]
