"""Point-to-point moves of a job session: a view that the straight joint move to the joints solved from the
current ones cannot reach safely is reached on the arm's other branch, or through home, or rolled about the
sensor's axis where the roll sees the same."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest

from cell.config import load_config
from cell.jobs.runner import ScanRequest, run_scan
from cell.planning.base import Planner, ScanSession
from drivers.transforms import T_from_xyz_rpy, look_at

from .conftest import FRANKA, UR5E, ended_without_a_frame, register_planner


class CrossPlanner(Planner):
    """Moves to the sensor positions ``offsets`` [m] relative to a point 5 cm over the station, each
    looking at that point, rolled about its axis by ``roll_deg``; keeps what each move returned, the view
    and the sensor pose reached, and, asked before the move, whether the session held the view within a
    move's reach and within a servo's (``sensor_view_reachable``, ``sensor_path_reachable``)."""

    name: ClassVar[str] = "test-cross"
    offsets: ClassVar[tuple[np.ndarray, ...]] = ()
    roll_deg: ClassVar[float] = 0.0
    moves: ClassVar[list[tuple[bool, np.ndarray, np.ndarray]]] = []
    reach: ClassVar[list[tuple[bool, bool]]] = []

    def run(self, session: ScanSession) -> str:
        station = session.config.station
        centre = np.array([*station.xy_m, station.table_z_m + 0.05])
        roll = T_from_xyz_rpy(np.zeros(3), (0.0, 0.0, math.radians(self.roll_deg)))
        for offset in self.offsets:
            view = look_at(centre + offset, centre) @ roll
            reach = (session.sensor_view_reachable(view), session.sensor_path_reachable(view[None]))
            CrossPlanner.reach.append(reach)
            CrossPlanner.moves.append((session.move_to_sensor_pose(view), view, session.sensor_pose()))
        return "crossed"


def _cross(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, *offsets: list[float], cell: Path = UR5E,
           roll_deg: float = 0.0) -> np.ndarray:
    """Run the crossing on ``cell`` over an empty table (the crossing captures nothing, so the guard never
    learns an object's ROI, and the sim arm would hit one: it faults on contact); check that every view
    was reached with no move refused, and return the sensor's path (K, 3) [m], starting at home."""
    register_planner(monkeypatch, CrossPlanner)
    monkeypatch.setattr(CrossPlanner, "offsets", tuple(np.array(o) for o in offsets))
    monkeypatch.setattr(CrossPlanner, "roll_deg", roll_deg)
    monkeypatch.setattr(CrossPlanner, "moves", [])
    monkeypatch.setattr(CrossPlanner, "reach", [])
    result = run_scan(ScanRequest(config=load_config(cell), config_path=str(cell), object="none",
                                  out=tmp_path / "scan", planner=CrossPlanner.name)).result
    assert ended_without_a_frame(result, "crossed"), result["termination"]
    assert [moved for moved, _, _ in CrossPlanner.moves] == [True] * len(offsets)
    for _, view, reached in CrossPlanner.moves:
        np.testing.assert_allclose(reached[:3, 3], view[:3, 3], atol=1e-3)
    assert result["refused_moves"] == {} and result["safety"]["refusals"] == []
    with (tmp_path / "scan" / "trajectory.csv").open() as f:
        return np.array([[float(r["x"]), float(r["y"]), float(r["z"])] for r in csv.DictReader(f)])


def _back_home_after_leaving(path: np.ndarray) -> bool:
    off_home = np.linalg.norm(path - path[0], axis=1)
    left = int(np.argmax(off_home > 0.05))
    return bool(left > 0 and off_home[left:].min() < 1e-3)


def test_a_view_the_straight_move_cannot_reach_safely_is_reached_on_the_arms_other_branch(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Low on the station's far side, then high over its left (the arm keeps the branch it came on), then
    high over its right: the joints solved from the current ones would sweep the forearm into the wrist on
    the way; those solved from home are reached straight, not by way of home."""
    path = _cross(monkeypatch, tmp_path, [0.282, 0.0, 0.103], [0.106, 0.184, 0.212], [-0.106, -0.184, 0.212])
    assert not _back_home_after_leaving(path)


def test_a_view_no_straight_move_reaches_safely_is_reached_through_home(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """From low on the station's far side to low on the arm's side, to its left: every straight joint
    move takes the sensor 3 mm into the floor plane's 5 mm margin; through home it stays clear."""
    path = _cross(monkeypatch, tmp_path, [0.282, 0.0, 0.103], [-0.244, 0.141, 0.103])
    assert _back_home_after_leaving(path)


@pytest.mark.parametrize("offset", [[-0.404, 0.283, 0.098], [-0.398, -0.166, 0.165]],
                         ids=["solved from home", "rolled"])
def test_a_view_a_move_reaches_on_another_branch_or_rolled_is_within_its_reach_not_a_servos(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, offset: list[float]) -> None:
    """From high on the station's right, to near the arm on its left or on its right: at the joints
    solved from the current ones the upper arm would touch the table (left) or the shoulder the sensor's
    board (right). On the left the joints solved from home are clear, and no roll from the current ones
    is; on the right a quarter turn about the sensor's axis is, and the home seed gives the same joints.
    The move gets there. The move's reach check (LR-NBV's cached nodes) says so beforehand; the servo's,
    which stays on the present branch and the present roll, does not."""
    _cross(monkeypatch, tmp_path, [0.0, -0.35, 0.25], offset)
    assert CrossPlanner.reach == [(True, True), (True, False)]


@pytest.mark.parametrize(("cell", "offset", "roll_deg", "turn_deg"), [
    (UR5E, [-0.196, 0.113, 0.106], 45.0, 90.0),
    (FRANKA, [0.139, -0.08, 0.192], 270.0, 180.0),
])
def test_a_view_no_route_reaches_safely_is_reached_rolled_about_the_sensor_axis(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, cell: Path, offset: list[float], roll_deg: float,
        turn_deg: float) -> None:
    """Low on the arm's left, the UR5e's every route folds the base into the forearm; over the station,
    the Panda's wrist would enter its joint limit margin (and within the guard's bounds IK finds no
    joints at all). The ToF's square grid seen a quarter turn about
    its axis, and the camera's image seen upside down, are the same view: that one is reached, along the
    same axis from the same point, its image axes turned by that much."""
    _cross(monkeypatch, tmp_path, offset, cell=cell, roll_deg=roll_deg)
    [(_, view, reached)] = CrossPlanner.moves
    np.testing.assert_allclose(reached[:3, 2], view[:3, 2], atol=1e-3)
    turned = math.degrees(math.acos(np.clip(reached[:3, 0] @ view[:3, 0], -1.0, 1.0)))
    assert turned == pytest.approx(turn_deg, abs=0.5)


def test_a_view_whose_joints_solved_within_the_limits_lie_in_the_guards_margin_is_reached_inside_it(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The Panda's view from 16 cm behind the station and 19 cm over it: IK solved within the joint limits
    puts the elbow in the guard's margin (from the current joints and from home alike), and the guard
    would refuse the move; solved within the guard's bounds it reaches the view."""
    _cross(monkeypatch, tmp_path, [-0.161, 0.0, 0.192], cell=FRANKA)
    assert CrossPlanner.reach == [(True, True)]
