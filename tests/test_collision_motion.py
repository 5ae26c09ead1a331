"""The collision world's continuous checks against the configurations along the path: a joint path
(``CollisionWorld.check_path``) and the arm's way ahead, looked at again every control period
(``check_motion``), keep each pair's distance from where they last measured it and must still find every
contact, after the arm moved on and after a new ROI; the pair bound they rest on, with the joints that
turn a body about a capsule on their axis, holds."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cell.config import load_config
from cell.safety.collision import PATH_CONTACT_M, CollisionWorld
from drivers.robots import get_robot_model

from .safety_rig import CELLS

# FCL's distance between a box (the tool) and a capsule comes out to about 1e-5 m (its GJK's tolerance):
# two bodies moved as one rigid piece show that much change.
FCL_TOL_M = 5e-5


def _world(model_name: str) -> tuple[CollisionWorld, np.ndarray]:
    cfg = load_config(CELLS[model_name])
    model = get_robot_model(model_name)
    world = CollisionWorld(model, cfg.safety.collision, cfg.station.table_z_m)
    return world, np.asarray(cfg.arm.home_joints_rad)


def _walk_towards(q0: np.ndarray, q_goal: np.ndarray, ticks: int, lookahead: float
                  ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The ticks of an arm going straight from ``q0`` to ``q_goal`` in ``ticks`` steps, each with the
    configuration ``lookahead`` steps ahead (the guard's predicted path), as (q, q_pred)."""
    step = (q_goal - q0) / ticks
    return [(q0 + k * step, q0 + (k + lookahead) * step) for k in range(ticks)]


@pytest.mark.parametrize("model_name", ["ur5e", "panda"])
def test_the_way_ahead_finds_every_contact_the_configurations_along_it_show(model_name):
    """An arm driven down at the object's box, each tick's way ahead checked, and checked again at 41
    configurations along it: kept distances may only save work, never hide a contact (each answer is the
    same)."""
    world, q_home = _world(model_name)
    model = get_robot_model(model_name)
    flange = model.fk(q_home)[:3, 3]
    world.set_roi(flange - np.array([0.04, 0.04, 0.30]), flange - np.array([-0.04, -0.04, 0.18]))
    T = model.fk(q_home)
    T[2, 3] -= 0.25
    q_goal = model.ik_pose(T, q_home)
    answers = []
    for q, q_pred in _walk_towards(q_home, q_goal, ticks=120, lookahead=15):
        sampled = [world.check(q + s * (q_pred - q)) for s in np.linspace(0.0, 1.0, 41)]
        ahead = world.check_motion(q, q_pred)
        assert (ahead is None) == all(hit is None for hit in sampled), (q, ahead)
        answers.append(ahead is not None)
    first = answers.index(True)
    assert 10 < first < 110 and all(answers[first:first + 5])


@pytest.mark.parametrize("model_name", ["ur5e", "panda"])
def test_a_path_is_refused_where_the_configurations_along_it_touch(model_name):
    """Random joint paths of a few samples around the object's box, checked once, and again at 30
    configurations per segment: the path check reports a contact exactly when one of them touches, at
    the segment where the first does."""
    world, q_home = _world(model_name)
    model = get_robot_model(model_name)
    flange = model.fk(q_home)[:3, 3]
    world.set_roi(flange - np.array([0.05, 0.05, 0.35]), flange - np.array([-0.05, -0.05, 0.2]))
    rng = np.random.default_rng(5)
    refused = 0
    for _ in range(25):
        path = q_home + np.cumsum(rng.uniform(-0.25, 0.25, (4, model.n_joints)), axis=0)
        path = np.vstack([q_home, np.clip(path, model.q_min, model.q_max)])
        along = np.linspace(0.0, 1.0, 30)
        touching = [k for k in range(1, len(path))
                    if any(world.check(path[k - 1] + s * (path[k] - path[k - 1])) is not None for s in along)]
        hit = world.check_path(path, 0.02)
        assert (hit is None) == (not touching)
        if hit is not None:
            assert hit[0] == touching[0]
            refused += 1
    assert 3 <= refused <= 22  # paths both ways


@pytest.mark.parametrize("model_name", ["ur5e", "panda"])
def test_a_new_roi_is_seen_by_the_next_tick(model_name):
    """The arm's way ahead cleared many times with no ROI, then a box appears on it: the next check sees it
    (the kept distances were about the bodies as they were)."""
    world, q_home = _world(model_name)
    model = get_robot_model(model_name)
    q_pred = q_home + 0.01
    for _ in range(5):
        assert world.check_motion(q_home, q_pred) is None
    flange = model.fk(q_pred)[:3, 3]
    world.set_roi(flange - 0.02, flange + 0.02)
    hit = world.check_motion(q_home, q_pred)
    assert hit is not None and hit[1].body_b == "object ROI"


@pytest.mark.parametrize("model_name", ["ur5e", "panda"])
def test_no_pair_comes_closer_than_its_bound_says(model_name):
    """The pairs' bounds (the moving bodies' levers, nothing for a joint that moves both bodies or turns one
    about a capsule on its axis) against FCL's distances, along random moves and along turns of each joint
    alone, from random configurations: a pair's distance never changes by more than its bound."""
    world, _ = _world(model_name)
    model = get_robot_model(model_name)
    statics = world._statics()
    pairs, levers = world._path_pairs(statics)
    objs = world._objs + [st.obj for st in statics]
    rng = np.random.default_rng(11)
    n = model.n_joints
    moves = [rng.uniform(-0.4, 0.4, n) for _ in range(12)] + [0.4 * np.eye(n)[j] for j in range(n)]
    axial_pairs = 0
    for dq in moves:
        q0 = rng.uniform(model.q_min, model.q_max)
        world._place(q0)
        before = np.array([world._distance(objs[a], objs[b]) for a, b in pairs])
        world._place(q0 + dq)
        after = np.array([world._distance(objs[a], objs[b]) for a, b in pairs])
        bound = levers @ np.abs(dq)
        apart = (before > 0.0) & (after > 0.0)  # FCL's distance is a depth, not a distance, once they touch
        excess = np.where(apart, np.abs(after - before) - bound, 0.0)
        assert np.max(excess) <= FCL_TOL_M
        axial_pairs += int(np.sum((bound == 0.0) & (np.abs(dq) @ world._lever[pairs[:, 0]].T > 0.0)))
    assert axial_pairs > 0  # some bounds were zero only because a joint turned a body about a capsule


def _link_pairs(world: CollisionWorld, model_name: str) -> tuple[set[tuple[str, str]], set[tuple[str, str]]]:
    """The non-adjacent pairs of the model's link capsules, and those of them the world checks."""
    model = get_robot_model(model_name)
    names = [c.name for c in model.capsule_specs]
    pairs = {(a, b) for i, a in enumerate(names) for b in names[i + 1:] if not model.are_adjacent(a, b)}
    checked = {(world.moving_names[a], world.moving_names[b]) for a, b in world._self_pairs}
    return pairs, checked & pairs


@pytest.mark.parametrize("model_name", ["ur5e", "panda"])
def test_a_pair_of_links_left_unchecked_never_touches(model_name):
    """The link pairs the world does not check, against FCL's distance between their capsules: at random
    configurations across the joint limits, and along every joint's whole range from random configuration
    (the one that changes such a pair's distance among them, 5 mrad apart), they never come within the
    contact distance. The UR5e's upper arm and base, 3 mm apart at every shoulder angle, are one of them;
    its shoulder and forearm, which the elbow folds onto each other, are checked."""
    world, _ = _world(model_name)
    model = get_robot_model(model_name)
    pairs, checked = _link_pairs(world, model_name)
    unchecked = sorted(pairs - checked)
    assert unchecked
    if model_name == "ur5e":
        assert ("base", "upper_arm") in unchecked and ("shoulder", "forearm") in checked
    index = {name: k for k, name in enumerate(world.moving_names)}
    rng = np.random.default_rng(12)
    configurations = list(rng.uniform(model.q_min, model.q_max, (1000, model.n_joints)))
    for j in range(model.n_joints):
        n_angles = int((model.q_max[j] - model.q_min[j]) / 5e-3)
        sweep = np.tile(rng.uniform(model.q_min, model.q_max), (n_angles, 1))
        sweep[:, j] = np.linspace(model.q_min[j], model.q_max[j], sweep.shape[0])
        configurations += list(sweep)
    closest = np.inf
    for q in configurations:
        world._place(q)
        d = min(world._distance(world._objs[index[a]], world._objs[index[b]]) for a, b in unchecked)
        closest = min(closest, d)
    assert closest > PATH_CONTACT_M


def test_links_that_can_touch_stay_checked():
    """A UR5e whose base capsule is 5 mm wider reaches its upper arm at some shoulder angles: that pair is
    then checked, and a configuration where FCL finds them overlapping is a collision."""
    nominal = get_robot_model("ur5e")
    wide = tuple(dataclasses.replace(c, radius=c.radius + 0.005) if c.name == "base" else c
                 for c in nominal.capsule_specs)
    model = dataclasses.replace(nominal, capsule_specs=wide)
    cfg = load_config(CELLS["ur5e"])
    world = CollisionWorld(model, cfg.safety.collision, cfg.station.table_z_m)
    pairs = {(world.moving_names[a], world.moving_names[b]) for a, b in world._self_pairs}
    assert ("base", "upper_arm") in pairs
    base, upper = world.moving_names.index("base"), world.moving_names.index("upper_arm")
    q = np.array(cfg.arm.home_joints_rad, dtype=float)
    overlapping = []
    for angle in np.linspace(model.q_min[1], model.q_max[1], 721):
        q[1] = angle
        world._place(q)
        if world._distance(world._objs[base], world._objs[upper]) <= 0.0:
            overlapping.append(q.copy())
    assert overlapping and all(world.check(qo) is not None for qo in overlapping)


@pytest.mark.parametrize("model_name", ["ur5e", "panda"])
def test_the_arm_keeps_the_table_s_clearance_from_it(model_name):
    """The flange lowered from home in 1 mm steps: the last configuration that touches nothing with the
    table at its own height lies within millimetres of it, and with the configured clearance (5 mm: the
    tool where the calibration puts it may be off by that much) it already touches the table."""
    cfg = load_config(CELLS[model_name])
    model = get_robot_model(model_name)
    collision = cfg.safety.collision
    at_top = collision.model_copy(update={"table": collision.table.model_copy(update={"clearance_m": 0.0})})
    bare = CollisionWorld(model, at_top, cfg.station.table_z_m)
    world = CollisionWorld(model, collision, cfg.station.table_z_m)
    assert collision.table.clearance_m == pytest.approx(0.005)
    q = np.asarray(cfg.arm.home_joints_rad)
    T = model.fk(q)
    last_free = None
    for _ in range(1000):
        T[2, 3] -= 0.001
        q = model.ik_pose(T, q)
        hit = bare.check(q)
        if hit is not None:
            break
        last_free = q
    assert hit is not None and "table" in str(hit) and last_free is not None
    touching = world.check(last_free)
    assert touching is not None and "table" in str(touching)
