"""Algorithm 1 of the LR-NBV paper, its NBV and HEU baselines, and their registration."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from cell.config.load import load_config
from cell.config.models import CellConfig
from cell.evaluation.presets import write_heldout_shapes
from cell.jobs.runner import ScanRequest, run_scan
from cell.perception.pipeline import PerceptionPipeline
from cell.planning.lrnbv.heu import HEUPlanner, heu_views
from cell.planning.lrnbv.planner import (
    CachedNodes,
    LRNBVPlanner,
    NBVPlanner,
    RRTViewPlanner,
    Tree,
    look_at_rotations,
)
from cell.planning.registry import get_planner
from drivers.depth.base import SensorModel
from drivers.transforms import look_at
from tests.conftest import FRANKA, UR5E


def _with(cfg: CellConfig, section: str, **values: object) -> CellConfig:
    updated = getattr(cfg.planners, section).model_copy(update=values)
    planners = cfg.planners.model_copy(update={section: updated})
    return cfg.model_copy(update={"planners": planners})


def test_registered_by_name_and_default_of_the_tof_cell() -> None:
    assert get_planner("lr-nbv") is LRNBVPlanner
    assert get_planner("nbv") is NBVPlanner
    assert get_planner("heu") is HEUPlanner
    assert load_config(UR5E).scan.planner == "lr-nbv"


def test_nbv_leaves_density_and_visited_out() -> None:
    cfg = load_config(UR5E)
    lr, nbv = LRNBVPlanner(cfg).weights, NBVPlanner(cfg).weights
    assert (lr.w_e, lr.w_d, lr.w_q, lr.w_v) == (500.0, 0.05, 0.08, 500.0)  # Table 1
    assert (nbv.w_e, nbv.w_d, nbv.w_q, nbv.w_v) == (500.0, 0.0, 0.08, 0.0)


def test_look_at_rotations_match_look_at() -> None:
    rng = np.random.default_rng(0)
    eyes = rng.uniform(-1.0, 1.0, (20, 3))
    targets = rng.uniform(-1.0, 1.0, (20, 3))
    targets[0] = eyes[0] - [0.0, 0.0, 0.5]  # straight down: the +x fallback
    for R, e, t in zip(look_at_rotations(eyes, targets), eyes, targets, strict=True):
        np.testing.assert_allclose(R, look_at(e, t)[:3, :3], atol=1e-12)


def test_best_branch_maximises_the_cumulative_utility() -> None:
    # root 0 -> 1 (5) -> 2 (-1) -> 3 (4): cumulative 8; root -> 4 (7): 7; 1 -> 5 (-inf, refused).
    utility = np.array([-np.inf, 5.0, -1.0, 4.0, 7.0, -np.inf])
    tree = Tree(positions=np.zeros((6, 3)), rotations=np.zeros((6, 3, 3)), utility=utility,
                parent=np.array([-1, 0, 1, 2, 0, 1]))
    assert tree.best_branch() == [1, 2, 3]
    root_only = Tree(np.zeros((1, 3)), np.zeros((1, 3, 3)), np.array([-np.inf]), np.array([-1]))
    assert root_only.best_branch() == []


def test_cached_nodes_keep_and_append() -> None:
    c = CachedNodes()
    c.append(np.ones((2, 3)), np.zeros((2, 3, 3)), np.array([1.0, 2.0]))
    c.append(np.zeros((1, 3)), np.zeros((1, 3, 3)), np.array([3.0]))
    c.keep(np.array([False, True, True]))
    assert len(c) == 2 and c.utility.tolist() == [2.0, 3.0]


def test_heu_views_on_the_ellipse_look_at_the_object() -> None:
    cfg = load_config(UR5E)
    views = heu_views(cfg)
    h = cfg.planners.heu
    assert len(views) == 13
    centre = np.array([*cfg.station.xy_m, cfg.station.table_z_m])
    target = centre + np.array([0.0, 0.0, h.target_height_m])
    angles = []
    for T in views:
        rel = T[:3, 3] - centre
        assert (rel[0] / h.semi_axes_m[0]) ** 2 + (rel[1] / h.semi_axes_m[1]) ** 2 == pytest.approx(1.0)
        assert rel[2] == pytest.approx(h.height_m)
        look = (target - T[:3, 3]) / np.linalg.norm(target - T[:3, 3])
        np.testing.assert_allclose(T[:3, 2], look, atol=1e-9)
        angles.append(math.atan2(rel[1] / h.semi_axes_m[1], rel[0] / h.semi_axes_m[0]))
    steps = np.diff(np.unwrap(angles))
    np.testing.assert_allclose(steps, 2 * math.pi / 13)


@pytest.mark.parametrize("capture", ["branch", "best_node"])
def test_short_lr_nbv_scan_reports_packing(tmp_path, capture: str) -> None:
    cfg = _with(load_config(UR5E), "lrnbv", max_iterations=3, samples_per_iteration=20, capture=capture)
    outcome = run_scan(ScanRequest(config=cfg, config_path=str(UR5E), object="horizontal_box",
                                   out=tmp_path / "lr", planner="lr-nbv"))
    r = outcome.result
    assert r["status"] == "completed", r["termination"]
    assert f"after {r['n_captures']} captures" in r["termination"]  # the initial view(s) counted too
    pk = r["packing"]
    assert pk["n_poses"] == r["n_captures"] >= 2
    assert pk["dims_m"] is not None and pk["iou"] > 0.3
    assert 0 <= pk["n_useless_poses"] <= pk["n_poses"]
    assert pk["container"]["reason"]
    if capture == "best_node":  # one capture per iteration after the initial view(s)
        assert r["n_captures"] <= 3 + 1 + len(cfg.planners.lrnbv.search_heights_m)


def test_a_narrow_upright_part_too_small_from_above_is_found_from_the_ellipse(tmp_path) -> None:
    """A 6 cm spire 15 cm tall leaves too few voxels for a cluster in the views from above; the search
    goes on round the station's ellipse and finds it from the side (it ended ``no_object`` before)."""
    spire = write_heldout_shapes(tmp_path / "shapes")["spire"]
    cfg = _with(load_config(UR5E), "lrnbv", max_iterations=2, samples_per_iteration=20)
    r = run_scan(ScanRequest(config=cfg, config_path=str(UR5E), object=str(spire), out=tmp_path / "lr",
                             planner="lr-nbv")).result
    assert r["status"] == "completed", r["termination"]
    assert r["packing"]["dims_m"][2] > 0.06


@pytest.mark.parametrize("cell", [UR5E, FRANKA])
def test_heu_scan_reaches_every_pose_of_the_ellipse(tmp_path, cell) -> None:
    r = run_scan(ScanRequest(config=load_config(cell), config_path=str(cell), object="vertical_box",
                             out=tmp_path / "heu", planner="heu")).result
    assert r["status"] == "completed"
    assert r["termination"] == "heu complete: 13 of 13 poses captured, 0 refused"
    assert r["packing"]["n_poses"] == r["n_captures"] == 13


class _BranchSession:
    """A session that reaches every pose but ``refuse`` and whose captures add nothing to the map; it
    counts its reach checks."""

    def __init__(self, cfg: CellConfig, refuse: tuple[float, float, float] | None = None) -> None:
        self.perception = PerceptionPipeline(cfg.perception, table_z_m=cfg.station.table_z_m,
                                             range_max_m=4.0, rng=np.random.default_rng(0))
        self.pose = np.eye(4)
        self.refuse = refuse
        self.captured: list[np.ndarray] = []
        self.reach_checks = 0

    def sensor_pose(self) -> np.ndarray:
        return self.pose

    def sensor_view_reachable(self, T: np.ndarray) -> bool:
        self.reach_checks += 1
        return self.refuse is None or not np.allclose(T[:3, 3], self.refuse)

    def move_to_sensor_pose(self, T: np.ndarray) -> bool:
        if self.refuse is not None and np.allclose(T[:3, 3], self.refuse):
            return False
        self.pose = T
        return True

    def wait(self, dt: float) -> None:
        del dt

    def capture(self) -> int:
        self.captured.append(self.pose[:3, 3].copy())
        return 0


def _branch_tree() -> tuple[Tree, np.ndarray]:
    """Root, then a branch of three nodes looking at an object at the station: nodes 1 and 2 share a
    0.18 m visited cell, node 3 lies in another."""
    obj = np.array([[0.45, 0.0, 0.05], [0.47, 0.02, 0.08]])
    positions = np.array([[0.0, 0.0, 0.5], [0.19, 0.01, 0.37], [0.21, 0.05, 0.4], [0.45, -0.3, 0.4]])
    rotations = look_at_rotations(positions, np.repeat(obj.mean(axis=0)[None], 4, axis=0))
    tree = Tree(positions=positions, rotations=rotations, utility=np.array([-np.inf, 1.0, 1.0, 1.0]),
                parent=np.array([-1, 0, 1, 2]))
    return tree, obj


def _prepared(planner: RRTViewPlanner, cfg: CellConfig) -> RRTViewPlanner:
    """``planner`` ready to plan as a run would make it, for the cell's 8 x 8 ToF sensor."""
    s = cfg.sensor
    assert s.type == "sim-tof"
    planner.prepare(SensorModel(kind="tof", width=s.resolution, height=s.resolution, fov_x_deg=s.fov_deg,
                                fov_y_deg=s.fov_deg, range_min_m=s.range_min_m, range_max_m=s.range_max_m),
                    np.random.default_rng(0))
    return planner


def test_lr_nbv_captures_along_the_branch_but_not_twice_in_a_visited_cell() -> None:
    cfg = load_config(UR5E)
    tree, obj = _branch_tree()
    session = _BranchSession(cfg)
    _, captured, refused = _prepared(LRNBVPlanner(cfg), cfg).capture_branch(session, obj, tree, [1, 2, 3])
    assert (captured, refused) == (2, 0)
    np.testing.assert_allclose(session.captured, tree.positions[[1, 3]])


def test_nbv_captures_the_whole_branch() -> None:
    cfg = load_config(UR5E)
    tree, obj = _branch_tree()
    session = _BranchSession(cfg)
    assert _prepared(NBVPlanner(cfg), cfg).capture_branch(session, obj, tree, [1, 2, 3])[1:] == (3, 0)


def test_a_refused_move_ends_the_branch_and_keeps_nodes_away_from_it() -> None:
    cfg = load_config(UR5E)
    tree, obj = _branch_tree()
    refusing = _BranchSession(cfg, refuse=tuple(tree.positions[2]))
    planner = _prepared(NBVPlanner(cfg), cfg)
    assert planner.capture_branch(refusing, obj, tree, [1, 2, 3])[1:] == (1, 1)
    np.testing.assert_allclose(refusing.captured, tree.positions[[1]])
    np.testing.assert_allclose(planner.refused_positions, tree.positions[[2]])
    r = cfg.planners.nbv.refused_radius_m
    probes = tree.positions[2] + np.array([[0.0, 0.0, 0.9 * r], [0.0, 0.0, 1.1 * r]])
    assert planner.near_refused(probes).tolist() == [True, False]


def test_the_cache_keeps_the_best_nodes_the_arm_reaches_and_checks_each_once() -> None:
    cfg = load_config(UR5E)
    tree, obj = _branch_tree()
    planner = _prepared(LRNBVPlanner(cfg), cfg)
    f = planner.field(_BranchSession(cfg), obj)
    _, utility = planner.score(f, planner.look_targets(obj), tree.positions[1:])
    rank = np.argsort(-utility, kind="stable")
    session = _BranchSession(cfg, refuse=tuple(tree.positions[1 + rank[0]]))  # the best node: out of reach
    cache = CachedNodes()
    cache.append(tree.positions[1:], tree.rotations[1:], np.zeros(3))
    planner._rescore(session, f, obj, cache, 2)
    np.testing.assert_allclose(cache.positions, tree.positions[1 + rank[1:]])
    np.testing.assert_allclose(cache.utility, utility[rank[1:]])
    assert session.reach_checks == 3
    planner._rescore(session, f, obj, cache, 2)  # the same map: the same look targets, no new check
    assert session.reach_checks == 3 and len(cache) == 2


class _ScriptedPlanner(LRNBVPlanner):
    """Algorithm 1's loop over a one-node tree of the utility ``tree_utility[i]`` at iteration i, each
    branch captured; re-scoring ``i`` leaves one cached node of utility ``rescored[i]``, or none (None)."""

    def __init__(self, cfg: CellConfig, tree_utility: list[float], rescored: list[float | None]) -> None:
        super().__init__(cfg)
        self.tree_utility, self.rescored = iter(tree_utility), iter(rescored)

    def prepare(self, sensor: SensorModel, rng: np.random.Generator) -> None:
        del sensor, rng

    def _initial_object(self, session: object) -> tuple[np.ndarray, int]:
        return np.zeros((1, 3)), 1

    def field(self, session: object, obj: np.ndarray) -> None:
        return None

    def expand(self, session: object, f: object, obj: np.ndarray, around: np.ndarray | None) -> Tree:
        return Tree(positions=np.zeros((2, 3)), rotations=np.repeat(np.eye(3)[None], 2, axis=0),
                    utility=np.array([-np.inf, next(self.tree_utility)]), parent=np.array([-1, 0]))

    def capture_branch(self, session: object, obj: np.ndarray, tree: Tree,
                       branch: list[int]) -> tuple[np.ndarray, int, int]:
        return obj, 1, 0

    def _rescore(self, session: object, f: object, obj: np.ndarray, cache: CachedNodes, m: int) -> None:
        utility = next(self.rescored)
        cache.keep(np.zeros(len(cache), dtype=bool))
        if utility is not None:
            cache.append(np.zeros((1, 3)), np.eye(3)[None], np.array([utility]))


def test_a_re_scoring_that_keeps_no_cached_node_leaves_no_threshold() -> None:
    """Lines 20-21 over an empty cache (every cached node out of reach): no best or worst cached node, so
    a view worse than the nodes the cache has dropped is still captured, as before the first re-scoring."""
    cfg = _with(load_config(UR5E), "lrnbv", max_iterations=4)
    session = SimpleNamespace(sensor_model=lambda: None, rng=None)
    emptied = _ScriptedPlanner(cfg, [3.0, 3.0, 0.5, 0.5], [1.0, None, None, None])
    assert emptied.run(session) == "iteration limit (4) reached after 5 captures"
    kept = _ScriptedPlanner(cfg, [3.0, 3.0, 0.5, 0.5], [1.0, 1.0, 1.0, 1.0])
    assert kept.run(session).startswith("converged: best view U = 0.5 not above the worst cached node's 1 "
                                        "after 3 captures")
