"""Kinematic models: FK against known poses, Jacobian, differential and pose IK, capsules, perturbation."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.errors import KinematicsError
from drivers.robots import ROBOT_MODEL_NAMES, RobotModel, get_robot_model
from drivers.transforms import pose_error

from .conftest import PANDA_AT_REACH

PI = np.pi
MODELS = {name: get_robot_model(name) for name in ROBOT_MODEL_NAMES}


def random_q(m: RobotModel, rng: np.random.Generator, margin: float = 0.05) -> np.ndarray:
    lo = np.maximum(m.q_min + margin, -PI)
    hi = np.minimum(m.q_max - margin, PI)
    return rng.uniform(lo, hi)


def test_factory_names_and_unknown() -> None:
    assert set(ROBOT_MODEL_NAMES) == {"panda", "ur5e"}
    assert get_robot_model("panda").n_joints == 7
    assert get_robot_model("ur5e").n_joints == 6
    with pytest.raises(ValueError, match="panda, ur5e"):
        get_robot_model("kuka")


# ---------------------------------------------------------------- forward kinematics


def test_ur5e_fk_at_zero() -> None:
    m = MODELS["ur5e"]
    T = m.fk(np.zeros(6))
    a2, a3 = -0.425, -0.3922
    d1, d4, d5, d6 = 0.1625, 0.1333, 0.0997, 0.0996
    np.testing.assert_allclose(T[:3, 3], [a2 + a3, -(d4 + d6), d1 - d5], atol=1e-12)
    # flange x along base x, y along base z, z along base -y
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)


def test_ur5e_fk_home_and_shoulder_rotation() -> None:
    m = MODELS["ur5e"]
    T = m.fk(m.q_home)
    # upper arm up (d1 + |a2|), forearm horizontal along -x (|a3|), wrist 2 out by d5, flange down by d6
    np.testing.assert_allclose(T[:3, 3], [-(0.3922 + 0.0997), -0.1333, 0.1625 + 0.425 - 0.0996], atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-12)  # tool points down
    # pan by pi/2 rotates the whole q=0 pose about base z
    q = np.zeros(6)
    q[0] = PI / 2
    p0 = m.fk(np.zeros(6))[:3, 3]
    np.testing.assert_allclose(m.fk(q)[:3, 3], [-p0[1], p0[0], p0[2]], atol=1e-12)


def test_panda_fk_at_zero_and_home() -> None:
    m = MODELS["panda"]
    T = m.fk(np.zeros(7))
    np.testing.assert_allclose(T[:3, 3], [0.088, 0.0, 0.333 + 0.316 + 0.384 - 0.107], atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(T[:3, 0], [1, 0, 0], atol=1e-12)
    # ready pose: tool down, flange in front of the robot at about 0.31 m, 0.59 m high (libfranka example)
    Th = m.fk(m.q_home)
    np.testing.assert_allclose(Th[:3, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(Th[:3, 3], [0.30689, 0.0, 0.59027], atol=1e-4)


def test_panda_fk_elbow_bent() -> None:
    # q4 = -pi/2 with the rest zero: the forearm points horizontally along +x from the elbow.
    m = MODELS["panda"]
    q = np.zeros(7)
    q[3] = -PI / 2
    F = m.fk_all(q)
    elbow = F[4][:3, 3]
    np.testing.assert_allclose(elbow, [0.0825, 0.0, 0.333 + 0.316], atol=1e-12)
    wrist = F[5][:3, 3]
    np.testing.assert_allclose(wrist, [0.0825 + 0.384, 0.0, 0.333 + 0.316 + 0.0825], atol=1e-12)


def test_fk_all_shape_and_convention() -> None:
    for m in MODELS.values():
        F = m.fk_all(m.q_home)
        assert F.shape == (m.n_joints + 2, 4, 4)
        np.testing.assert_array_equal(F[0], np.eye(4))
        np.testing.assert_allclose(F[-1], m.fk(m.q_home))
        for T in F:
            np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    ur = MODELS["ur5e"]
    F = ur.fk_all(ur.q_home)
    np.testing.assert_array_equal(F[-1], F[-2])  # UR5e: the last link frame is the flange


@pytest.mark.parametrize("bad", [np.zeros(5), np.zeros(8), [0, 0, 0, 0, 0, np.nan], "abc"])
def test_bad_q_raises(bad: object) -> None:
    with pytest.raises(KinematicsError):
        MODELS["ur5e"].fk(bad)


# ---------------------------------------------------------------- Jacobian


@pytest.mark.parametrize("name", ROBOT_MODEL_NAMES)
def test_jacobian_matches_finite_differences(name: str) -> None:
    m = MODELS[name]
    rng = np.random.default_rng(1)
    h = 1e-6
    for _ in range(10):
        q = random_q(m, rng)
        J = m.jacobian(q)
        assert J.shape == (6, m.n_joints)
        T0 = m.fk(q)
        Jn = np.empty_like(J)
        for i in range(m.n_joints):
            dq = np.zeros(m.n_joints)
            dq[i] = h
            Jn[:, i] = pose_error(T0, m.fk(q + dq)) / h
        np.testing.assert_allclose(J, Jn, atol=1e-5)


# ---------------------------------------------------------------- differential IK


@pytest.mark.parametrize("name", ROBOT_MODEL_NAMES)
def test_ik_velocity_tracks_small_twist(name: str) -> None:
    m = MODELS[name]
    v = np.array([0.05, -0.02, 0.03, 0.05, 0.0, -0.1])
    qd = m.ik_velocity(m.q_home, v, 0.01)
    np.testing.assert_allclose(m.jacobian(m.q_home) @ qd, v, atol=2e-3)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    name=st.sampled_from(ROBOT_MODEL_NAMES),
    seed=st.integers(0, 2**31 - 1),
    scale=st.floats(0.01, 20.0),
    dt=st.floats(1e-3, 0.2),
    at_limit=st.booleans(),
)
def test_ik_velocity_respects_limits(name: str, seed: int, scale: float, dt: float, at_limit: bool) -> None:
    m = MODELS[name]
    rng = np.random.default_rng(seed)
    q = random_q(m, rng, margin=0.0)
    if at_limit:  # push a few joints onto or just inside their limits
        idx = rng.choice(m.n_joints, size=3, replace=False)
        q[idx] = np.where(rng.random(3) < 0.5, m.q_min[idx], m.q_max[idx] - 1e-4)
    v = rng.normal(size=6)
    v *= scale / np.linalg.norm(v)
    qd = m.ik_velocity(q, v, dt)
    assert np.all(np.isfinite(qd))
    assert np.all(np.abs(qd) <= m.qd_max * (1 + 1e-9))
    q_next = q + qd * dt
    assert np.all(q_next >= m.q_min - 1e-9)
    assert np.all(q_next <= m.q_max + 1e-9)


def test_ik_velocity_keeps_direction_when_saturated() -> None:
    m = MODELS["panda"]
    v = np.array([5.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    qd_fast = m.ik_velocity(m.q_home, v, 0.001)
    qd_slow = m.ik_velocity(m.q_home, v * 1e-3, 0.001)
    assert np.max(np.abs(qd_fast) / m.qd_max) == pytest.approx(1.0)
    cos = qd_fast @ qd_slow / np.linalg.norm(qd_fast) / np.linalg.norm(qd_slow)
    assert cos == pytest.approx(1.0, abs=1e-9)


def test_ik_velocity_bad_twist() -> None:
    m = MODELS["panda"]
    with pytest.raises(KinematicsError):
        m.ik_velocity(m.q_home, np.zeros(5), 0.01)
    with pytest.raises(KinematicsError):
        m.ik_velocity(m.q_home, np.full(6, np.inf), 0.01)
    with pytest.raises(KinematicsError):
        m.ik_velocity(m.q_home, np.zeros(6), 0.0)


def limit_cost(m: RobotModel, q: np.ndarray) -> float:
    """H(q) of the null-space joint-limit avoidance (drivers.robots.model, "Redundancy")."""
    x = (2.0 * q - m.q_max - m.q_min) / (m.q_max - m.q_min)
    return float(0.5 * x @ x)


# A sideways Panda configuration with the base and third joints twisted against each other, near their
# limits (what the plain DLS pose IK returned for the visual-servoing start view).
PANDA_TWISTED = np.array([2.013, -0.396, -2.697, -2.2, 0.609, 1.763, -1.03])


@pytest.mark.parametrize("q", [PANDA_TWISTED, MODELS["panda"].q_home])
def test_panda_null_space_motion_leaves_the_flange_twist_and_lowers_the_limit_cost(q: np.ndarray) -> None:
    m = MODELS["panda"]
    ik = m.velocity_map(q)
    J = m.jacobian(q)
    np.testing.assert_allclose(J @ ik.null, 0.0, atol=1e-12)
    dq = 1e-6 * ik.null
    assert limit_cost(m, q + dq) < limit_cost(m, q)
    v = np.array([0.05, -0.02, 0.03, 0.05, 0.0, -0.1])
    np.testing.assert_allclose(J @ ik(v), J @ ik.task @ v, atol=1e-12)  # the twist is realised as without it
    np.testing.assert_allclose(ik(2.5 * v), 2.5 * ik(v), rtol=1e-12)  # positively homogeneous
    np.testing.assert_array_equal(ik(np.zeros(6)), np.zeros(7))  # a zero twist is rest


def test_velocity_map_task_part_is_damped_least_squares() -> None:
    for m in MODELS.values():
        J = m.jacobian(m.q_home)
        dls = J.T @ np.linalg.inv(J @ J.T + 0.02**2 * np.eye(6))
        np.testing.assert_allclose(m.velocity_map(m.q_home).task, dls, atol=1e-10)
    np.testing.assert_array_equal(MODELS["ur5e"].velocity_map(MODELS["ur5e"].q_home).null, 0.0)


def test_ik_velocity_is_the_velocity_map_away_from_the_limits() -> None:
    m = MODELS["panda"]
    v = np.array([0.02, 0.01, -0.01, 0.0, 0.05, 0.0])
    np.testing.assert_allclose(m.ik_velocity(PANDA_TWISTED, v, 0.01), m.velocity_map(PANDA_TWISTED)(v),
                               rtol=1e-12)


def test_min_singular_value_falls_at_the_reach_and_its_gradient_leads_away() -> None:
    m = MODELS["panda"]
    stretched = np.array(PANDA_AT_REACH)
    assert m.min_singular_value(m.q_home) == pytest.approx(
        np.linalg.svd(m.jacobian(m.q_home), compute_uv=False).min(), rel=1e-12)
    assert m.min_singular_value(m.q_home) > 0.1 and m.min_singular_value(stretched) < 0.01
    d = np.random.default_rng(3).normal(size=7)
    d /= np.linalg.norm(d)
    for q in (m.q_home, PANDA_TWISTED, stretched):
        grad = m.min_singular_value_gradient(q)
        step = 1e-4 * grad / np.linalg.norm(grad)
        assert m.min_singular_value(q - step) < m.min_singular_value(q) < m.min_singular_value(q + step)
        slope = (m.min_singular_value(q + 1e-6 * d) - m.min_singular_value(q - 1e-6 * d)) / 2e-6
        assert grad @ d == pytest.approx(slope, rel=1e-3, abs=1e-7)


def test_streaming_a_twist_unwinds_a_twisted_panda() -> None:
    m = MODELS["panda"]
    plain = dataclasses.replace(m, limit_avoidance_gain=0.0)
    v = np.array([0.0, 0.03, 0.0, 0.0, 0.0, 0.0])
    ends = []
    for model in (m, plain):
        q = PANDA_TWISTED.copy()
        for _ in range(300):  # 3 s at 100 Hz: 9 cm of flange travel
            q = q + model.ik_velocity(q, v, 0.01) * 0.01
        ends.append(q)
    np.testing.assert_allclose(m.fk(ends[0])[:3, 3], plain.fk(ends[1])[:3, 3], atol=2e-3)
    assert limit_cost(m, ends[0]) < limit_cost(m, ends[1]) - 0.1


def test_panda_pose_ik_prefers_a_solution_away_from_the_limits() -> None:
    m = MODELS["panda"]
    q = m.ik_pose(m.fk(PANDA_TWISTED), m.q_home)
    np.testing.assert_allclose(m.fk(q)[:3, 3], m.fk(PANDA_TWISTED)[:3, 3], atol=1e-4)
    assert limit_cost(m, q) < 0.5 * limit_cost(m, PANDA_TWISTED)


# ---------------------------------------------------------------- pose IK


@pytest.mark.parametrize("name", ROBOT_MODEL_NAMES)
def test_ik_pose_round_trip(name: str) -> None:
    m = MODELS[name]
    rng = np.random.default_rng(7)
    for _ in range(15):
        q_true = random_q(m, rng, margin=0.2)
        T_goal = m.fk(q_true)
        q_seed = np.clip(q_true + rng.normal(0.0, 0.25, m.n_joints), m.q_min, m.q_max)
        q = m.ik_pose(T_goal, q_seed)
        e = pose_error(m.fk(q), T_goal)
        assert np.linalg.norm(e[:3]) <= 1e-4
        assert np.linalg.norm(e[3:]) <= 1e-3
        assert m.within_limits(q)


def test_ik_pose_keeps_within_bounds_inside_the_limits() -> None:
    """A safety layer's bounds (the limits less 0.05 rad): where the limits alone give a solution in that
    margin, the bounded one lies inside the bounds and reaches the pose."""
    m = MODELS["panda"]
    T_goal = m.fk(np.array([-2.712, 0.726, -0.726, -2.791, 0.927, 3.485, -1.691]))
    lo, hi = m.q_min + 0.05, m.q_max - 0.05
    unbounded = m.ik_pose(T_goal, m.q_home)
    assert np.any((unbounded < lo) | (unbounded > hi))
    q = m.ik_pose(T_goal, m.q_home, q_bounds=(lo, hi))
    assert np.all((q >= lo) & (q <= hi))
    e = pose_error(m.fk(q), T_goal)
    assert np.linalg.norm(e[:3]) <= 1e-4 and np.linalg.norm(e[3:]) <= 1e-3


def test_ik_pose_unreachable_names_residual() -> None:
    m = MODELS["ur5e"]
    T = m.fk(m.q_home)
    T[:3, 3] = [3.0, 0.0, 0.5]  # 3 m away: out of reach
    with pytest.raises(KinematicsError, match=r"residual .* mm"):
        m.ik_pose(T, m.q_home, max_iter=50)


# ---------------------------------------------------------------- capsules


def _segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> float:
    t = np.linspace(0.0, 1.0, 101)
    A = p1 + np.outer(t, q1 - p1)
    B = p2 + np.outer(t, q2 - p2)
    return float(np.min(np.linalg.norm(A[:, None] - B[None], axis=2)))


@pytest.mark.parametrize("name", ROBOT_MODEL_NAMES)
def test_capsules_shapes_and_links(name: str) -> None:
    m = MODELS[name]
    caps = m.capsules(m.q_home)
    assert len(caps) >= m.n_joints
    for c in caps:
        assert c.a.shape == (3,) and c.b.shape == (3,)
        assert 0.02 <= c.radius <= 0.1
        assert np.linalg.norm(c.b - c.a) < 0.5
    # every link frame origin (the joint axes) lies inside some capsule
    rng = np.random.default_rng(3)
    for q in [m.q_home, random_q(m, rng), random_q(m, rng)]:
        caps = m.capsules(q)
        F = m.fk_all(q)
        for T in F[1:]:
            p = T[:3, 3]
            d = min(_segment_distance(c.a, c.b, p, p) - c.radius for c in caps)
            assert d <= 0.0
    # capsules follow the links: the last capsule moves with the flange
    q2 = m.q_home.copy()
    q2[0] += 0.3
    last0, last1 = m.capsules(m.q_home)[-1], m.capsules(q2)[-1]
    R = m.fk(q2)[:3, :3] @ m.fk(m.q_home)[:3, :3].T
    np.testing.assert_allclose(last1.a, R @ last0.a, atol=1e-12)  # pure rotation about base z


@pytest.mark.parametrize("name", ROBOT_MODEL_NAMES)
def test_no_self_collision_at_home(name: str) -> None:
    m = MODELS[name]
    caps = m.capsules(m.q_home)
    assert frozenset((caps[0].name, caps[1].name)) in m.adjacent_capsule_pairs
    for c1, c2 in itertools.combinations(caps, 2):
        if m.are_adjacent(c1.name, c2.name):
            continue
        assert _segment_distance(c1.a, c1.b, c2.a, c2.b) > c1.radius + c2.radius, (c1.name, c2.name)


def test_panda_folded_elbow_collides() -> None:
    # the fully folded elbow brings the forearm onto the upper arm: a non-adjacent pair must touch
    m = MODELS["panda"]
    q = np.zeros(7)
    q[3] = m.q_min[3]
    caps = {c.name: c for c in m.capsules(q)}
    hits = [
        (n1, n2) for n1, n2 in itertools.combinations(caps, 2)
        if not m.are_adjacent(n1, n2)
        and _segment_distance(caps[n1].a, caps[n1].b, caps[n2].a, caps[n2].b)
        <= caps[n1].radius + caps[n2].radius
    ]
    assert hits


# ---------------------------------------------------------------- perturbation


@pytest.mark.parametrize("name", ROBOT_MODEL_NAMES)
def test_perturbed(name: str) -> None:
    m = MODELS[name]
    same = m.perturbed(np.random.default_rng(0), 0.0, 0.0)
    rng = np.random.default_rng(5)
    for _ in range(5):
        q = random_q(m, rng)
        np.testing.assert_array_equal(same.fk_all(q), m.fk_all(q))
    p1 = m.perturbed(np.random.default_rng(42), 0.002, 0.001)
    p2 = m.perturbed(np.random.default_rng(42), 0.002, 0.001)
    errs = []
    for _ in range(10):
        q = random_q(m, rng)
        np.testing.assert_array_equal(p1.fk(q), p2.fk(q))  # deterministic for a seed
        errs.append(np.linalg.norm(p1.fk(q)[:3, 3] - m.fk(q)[:3, 3]))
    assert 5e-4 < np.mean(errs) < 2e-2  # millimetre level
    assert p1.name == m.name and np.array_equal(p1.q_max, m.q_max)
    with pytest.raises(ValueError):
        m.perturbed(np.random.default_rng(0), -1.0, 0.0)
