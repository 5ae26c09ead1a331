"""Occupancy map: OctoMap sensor model (log-odds, hit/miss, clamping, one update per scan), ray traversal
on synthetic geometry, ToF carving, eq. 8 entropy and eq. 12 H_ROI."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.integrate import quad
from scipy.stats import beta

from cell.perception import _kernels as _k
from cell.perception.occupancy import (
    OccupancyMap,
    OccupancyParams,
    binary_entropy,
    logit,
    observation_information,
    observation_weight,
)

RES = 0.01


def make_map(**kw) -> OccupancyMap:
    return OccupancyMap(OccupancyParams(resolution_m=RES, **kw))


def plane_scan(depth_m: float = 0.3, half_m: float = 0.05, step_m: float = 0.0025) -> np.ndarray:
    """Endpoints on the plane z = 1 - depth_m seen from a sensor at (0.003, 0.004, 1.0) looking down -z."""
    g = np.arange(-half_m, half_m + 1e-9, step_m)
    x, y = np.meshgrid(g, g, indexing="ij")
    return np.stack([x.ravel() + 0.003, y.ravel() + 0.004, np.full(x.size, 1.0 - depth_m)], axis=1)


ORIGIN = np.array([0.003, 0.004, 1.0])


def test_params_validation():
    with pytest.raises(ValidationError):
        OccupancyParams(resolution_m=0.01, p_hit=0.4)
    with pytest.raises(ValidationError):
        OccupancyParams(resolution_m=0.01, p_miss=0.6)
    with pytest.raises(ValidationError):
        OccupancyParams(resolution_m=0.01, clamp_min=0.9, clamp_max=0.8)
    with pytest.raises(ValidationError):
        OccupancyParams(resolution_m=0.0)
    with pytest.raises(ValidationError):
        OccupancyParams(resolution_m=0.01, unknown_field=1)
    p = OccupancyParams(resolution_m=0.005)
    assert (p.p_hit, p.p_miss, p.clamp_min, p.clamp_max, p.occupied_threshold) == (0.7, 0.4, 0.12, 0.97, 0.5)


def test_unknown_is_half_and_ln2():
    m = make_map()
    pts = np.array([[0.0, 0.0, 0.0], [1.0, -2.0, 3.0]])
    assert np.allclose(m.probability(pts), 0.5)
    assert np.allclose(m.entropy(pts), math.log(2.0))
    assert not m.is_known(pts).any()
    assert m.n_known == 0 and m.bounds() is None
    m.integrate(ORIGIN, plane_scan())
    far = np.array([[5.0, 5.0, 5.0], [-3.0, 0.0, 0.0]])  # outside the block index
    assert np.allclose(m.probability(far), 0.5) and not m.is_known(far).any()


def test_plane_free_before_occupied_at_unknown_behind():
    m = make_map()
    m.integrate(ORIGIN, plane_scan(depth_m=0.3))
    z_plane = 0.7
    xy = np.array([0.003, 0.004])
    before = np.array([[*xy, z] for z in np.arange(z_plane + 0.02, 0.99, 0.01)])
    at = np.array([[*xy, z_plane + 1e-4]])
    behind = np.array([[*xy, z] for z in np.arange(z_plane - 0.02, 0.5, -0.01)])
    assert np.allclose(m.probability(before), 0.4)
    assert np.allclose(m.probability(at), 0.7)
    assert not m.is_known(behind).any()
    occ = m.occupied_centers()
    assert occ.shape[0] > 0
    assert np.allclose(occ[:, 2], (math.floor(z_plane / RES) + 0.5) * RES)
    free = m.free_centers()
    assert np.all(free[:, 2] > z_plane)
    keys, _ = m.known_keys()
    assert keys.shape[0] == m.n_known == occ.shape[0] + free.shape[0]
    lo_min, hi = m.bounds()
    assert lo_min[2] == pytest.approx(math.floor(z_plane / RES) * RES)
    assert hi[2] == pytest.approx((math.floor(1.0 / RES) + 1) * RES)


def test_single_ray_voxels_match_brute_force_sampling():
    m = make_map()
    o = np.array([0.0012, 0.0031, 0.0047])
    e = np.array([[0.137, -0.0615, 0.0893]])
    m.integrate(o, e)
    t = np.linspace(0.0, 1.0, 200001)[:-1]
    sampled = {tuple(k) for k in np.floor((o + t[:, None] * (e[0] - o)) / RES).astype(int)}
    end = tuple(np.floor(e[0] / RES).astype(int))
    sampled.discard(end)
    free = {tuple(k) for k in np.floor(m.free_centers() / RES).astype(int)}
    assert free == sampled
    occ = {tuple(k) for k in np.floor(m.occupied_centers() / RES).astype(int)}
    assert occ == {end}


def test_tof_no_target_carves_to_range_and_nothing_occupied():
    m = make_map()
    o = np.array([0.0, 0.0, 0.5])
    dirs = np.array([[0.0, 0.0, -1.0], [0.3, 0.0, -1.0], [0.0, -0.2, -1.0]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    range_m = 0.4
    ends = o + dirs * range_m
    m.integrate(o, ends, free_only=np.ones(3, dtype=bool))
    assert m.occupied_centers().shape[0] == 0
    for d in dirs:
        along = o + d * np.linspace(0.0, range_m - 1e-6, 200)[:, None]
        assert m.is_known(along).all()
        assert np.allclose(m.probability(along), 0.4)
        assert not m.is_known((o + d * (range_m + 0.03))[None]).any()


def test_free_only_mask_mixes_hits_and_carving():
    m = make_map()
    o = np.array([0.0, 0.0, 0.5])
    ends = np.array([[0.0, 0.0, 0.2], [0.1, 0.0, 0.2]])
    m.integrate(o, ends, free_only=np.array([False, True]))
    assert m.probability(ends[:1])[0] == pytest.approx(0.7)
    assert m.probability(ends[1:])[0] == pytest.approx(0.4)


def test_max_range_truncates_without_occupied_end():
    m = make_map(max_range_m=0.2)
    o = np.array([0.0, 0.0, 0.5])
    ends = np.array([[0.0, 0.0, 0.0], [0.0, 0.1, 0.4]])  # 0.5 m (truncated) and 0.14 m (kept)
    m.integrate(o, ends)
    occ = m.occupied_centers()
    assert occ.shape[0] == 1 and np.allclose(occ[0], (np.floor(ends[1] / RES) + 0.5) * RES)
    assert m.probability(np.array([[0.0, 0.0, 0.35]]))[0] == pytest.approx(0.4)
    assert not m.is_known(np.array([[0.0, 0.0, 0.29]])).any()  # beyond the truncated end (z = 0.3)


def test_one_update_per_voxel_per_scan_and_occupied_wins():
    m = make_map()
    o = np.array([0.0, 0.0, 0.5])
    # many rays to the same end voxel, and a longer ray that passes through it
    ends = np.array([[0.0021, 0.0033, 0.2041]] * 50 + [[0.0022, 0.0034, 0.1]])
    m.integrate(o, ends)
    assert m.logodds(ends[:1])[0] == pytest.approx(logit(0.7), rel=1e-6)
    assert m.logodds(np.array([[0.002, 0.003, 0.4]]))[0] == pytest.approx(logit(0.4), rel=1e-6)
    m.integrate(o, ends)
    assert m.logodds(ends[:1])[0] == pytest.approx(2 * logit(0.7), rel=1e-6)


def test_clamping_after_many_hits_and_misses():
    m = make_map()
    o = np.array([0.0, 0.0, 0.5])
    end = np.array([[0.0, 0.0, 0.2]])
    for _ in range(40):
        m.integrate(o, end)
    assert m.probability(end)[0] == pytest.approx(0.97, rel=1e-5)
    for _ in range(40):
        m.integrate(o, end, free_only=np.array([True]))
    assert m.probability(end)[0] == pytest.approx(0.12, rel=1e-5)
    m.integrate(o, end)
    assert m.logodds(end)[0] == pytest.approx(logit(0.12) + logit(0.7), rel=1e-5)


def test_observation_counts_per_scan_past_the_clamp():
    m = make_map()
    o = np.array([0.0, 0.0, 0.5])
    end = np.array([[0.0, 0.0, 0.2]])
    between = np.array([[0.0, 0.0, 0.35]])
    for _ in range(40):
        m.integrate(o, np.repeat(end, 5, axis=0))  # five rays to one voxel: one update of it per scan
    for _ in range(3):
        m.integrate(o, end, free_only=np.array([True]))
    hits, misses = m.observation_counts(np.vstack([end, between, [[1.0, 1.0, 1.0]]]))
    # the log-odds stopped at the clamp after 5 hits, the counts did not
    assert hits.tolist() == [40, 0, 0]
    assert misses.tolist() == [3, 43, 0]
    m.set_logodds(np.array([[50, 50, 50]]), np.array([2.0]))
    assert [c.tolist() for c in m.observation_counts(np.array([[0.505, 0.505, 0.505]]))] == [[0], [0]]


def test_entropy_eq8_on_known_values():
    p = np.array([0.5, 0.7, 0.4, 0.97, 0.12, 0.0, 1.0])
    expected = [-(q * math.log(q) + (1 - q) * math.log(1 - q)) if 0 < q < 1 else 0.0 for q in p]
    assert np.allclose(binary_entropy(p), expected)
    m = make_map()
    o = np.array([0.0, 0.0, 0.5])
    m.integrate(o, np.array([[0.0, 0.0, 0.2]]))
    h = m.entropy(np.array([[0.0, 0.0, 0.2], [0.0, 0.0, 0.3], [0.0, 0.0, 0.1]]))
    assert np.allclose(h, binary_entropy(np.array([0.7, 0.4, 0.5])))


def test_voxels_in_box_and_mean_entropy_eq12():
    m = make_map()
    keys = np.array([[0, 0, 0], [1, 0, 0]])
    m.set_logodds(keys, np.array([logit(0.7), logit(0.12)]))
    c = m.voxels_in_box([0.0, 0.0, 0.0], [0.02, 0.02, 0.01])  # 2 x 2 x 1 voxels
    assert c.shape == (4, 3)
    assert np.allclose(np.sort(c[:, 0]), [0.005, 0.005, 0.015, 0.015])
    h = binary_entropy(np.array([0.7, 0.12, 0.5, 0.5]))
    assert m.mean_entropy_in_box([0.0, 0.0, 0.0], [0.02, 0.02, 0.01]) == pytest.approx(h.mean(), rel=1e-6)
    # a box inside one voxel is that voxel
    assert m.voxels_in_box([0.001, 0.001, 0.001], [0.002, 0.002, 0.002]).shape == (1, 3)


def test_observation_aware_h_roi_weights_each_voxel_by_its_observation_weight():
    m = make_map()
    o = np.array([0.005, 0.005, 0.5])
    end = np.array([[0.005, 0.005, 0.205]])  # voxel (0, 0, 20), the ray crossing (0, 0, 21..49)
    for k in range(30):  # a surface voxel the views disagree on: hit, then crossed, and so on
        m.integrate(o, end, free_only=np.array([k % 2 == 1]))
    m.set_logodds(np.array([[1, 0, 20]]), np.array([logit(0.7)]))  # no counts: weighs as unseen
    lo, hi = np.array([0.0, 0.0, 0.2]), np.array([0.03, 0.01, 0.22])  # 3 x 1 x 2 voxels
    centres = m.voxels_in_box(lo, hi)
    h = m.entropy(centres)
    w = observation_weight(*m.observation_counts(centres))
    assert sorted(w.tolist())[:2] == pytest.approx(observation_weight(np.array([0, 15]), np.array([30, 15])))
    assert m.mean_entropy_in_box(lo, hi) == pytest.approx(h.mean(), rel=1e-6)  # eq. 12 as written
    assert m.mean_entropy_in_box(lo, hi, observation_aware=True) == pytest.approx((h * w).mean(), rel=1e-6)
    assert np.count_nonzero(w == 1.0) == 4  # the unseen voxels and the one set without counts keep eq. 8's


def test_negative_coordinates_and_growth():
    m = make_map()
    m.integrate(np.array([-0.5, -0.5, 0.5]), np.array([[-0.52, -0.49, -0.3]]))
    m.integrate(np.array([2.0, 1.0, 0.5]), np.array([[2.1, 1.05, 0.1]]))
    assert m.probability(np.array([[-0.52, -0.49, -0.3]]))[0] == pytest.approx(0.7)
    assert m.probability(np.array([[2.1, 1.05, 0.1]]))[0] == pytest.approx(0.7)


def test_empty_and_invalid_input():
    m = make_map()
    m.integrate(np.zeros(3), np.zeros((0, 3)))
    assert m.n_known == 0
    with pytest.raises(ValueError):
        m.integrate(np.zeros(3), np.array([[np.nan, 0.0, 0.0]]))


def test_occupied_keys_follow_voxels_that_turn_free_again():
    """occupied_keys reads only blocks the kernel counts as holding an occupied voxel: the counts must
    follow voxels that turn occupied, then free again under carving, and set_logodds."""
    m = make_map()
    rng = np.random.default_rng(4)
    o = np.array([0.0, 0.0, 0.5])
    ends = np.column_stack([rng.uniform(-0.2, 0.2, 300), rng.uniform(-0.2, 0.2, 300), np.full(300, 0.05)])
    m.integrate(o, ends)
    for _ in range(3):  # rays through half of the end voxels, to beyond them: those turn free
        m.integrate(o, o + (ends[:150] - o) * 1.5, free_only=np.ones(150, dtype=bool))
    assert not m.is_occupied(ends[:150]).any() and m.is_occupied(ends[150:]).mean() > 0.75
    m.set_logodds(np.array([[100, 100, 100]]), np.array([2.0]))
    keys, lo = m.known_keys()
    np.testing.assert_array_equal(m.occupied_keys(), keys[m.classify_logodds(lo)])


def test_discretize_casts_one_ray_per_end_voxel_to_its_centre():
    """OctoMap's discretize: the same map as integrating the centres of the distinct end voxels."""
    rng = np.random.default_rng(3)
    origin = np.array([0.01, -0.02, 0.3])
    ends = np.column_stack([rng.uniform(-0.05, 0.05, 3000), rng.uniform(-0.05, 0.05, 3000),
                            rng.uniform(0.0, 0.01, 3000)])
    disc = OccupancyMap(OccupancyParams(resolution_m=0.005, discretize=True))
    disc.integrate(origin, ends)
    ref = OccupancyMap(OccupancyParams(resolution_m=0.005))
    ref.integrate(origin, ref.centers_of(np.unique(ref.keys_of(ends), axis=0)))
    keys, lo = disc.known_keys()
    ref_keys, ref_lo = ref.known_keys()
    np.testing.assert_array_equal(keys, ref_keys)
    np.testing.assert_array_equal(lo, ref_lo)
    assert np.unique(disc.keys_of(ends), axis=0).shape[0] < ends.shape[0] / 2
    np.testing.assert_array_equal(disc.occupied_keys(), np.unique(disc.keys_of(ends), axis=0))


@pytest.mark.parametrize("keep_surface", [False, True])
def test_keep_surface_spares_occupied_neighbours_of_hits_from_grazing_rays(keep_surface):
    """Two voxels seen occupied from above; then rays along the surface: one ends in the voxel next to
    the first (a grazing ray to the surface beyond it), one ends four voxels past the second. OctoMap
    carves both; with ``keep_surface`` the first, next to a hit of the scan, keeps its log-odds."""
    m = make_map(keep_surface=keep_surface)
    near, far = np.array([0.005, 0.005, 0.005]), np.array([0.005, 0.055, 0.005])
    for _ in range(2):
        m.integrate(np.array([0.005, 0.03, 0.5]), np.vstack([near, far]))
    before = m.logodds(np.vstack([near, far]))
    assert np.all(before > 0.0)
    grazing = np.array([[0.015, 0.005, 0.005], [0.045, 0.055, 0.005]])
    m.integrate(np.array([-0.3, 0.03, 0.005]), grazing)
    after = m.logodds(np.vstack([near, far]))
    assert after[1] == pytest.approx(before[1] + logit(0.4))  # away from every hit: carved
    if keep_surface:
        assert after[0] == before[0]
    else:
        assert after[0] == pytest.approx(before[0] + logit(0.4))


def test_observation_information_is_the_beta_bernoulli_mutual_information():
    # I = H(E theta) - E H(theta) for theta ~ Beta(1 + h, 1 + m), by quadrature over theta.
    for h, m in [(0, 0), (1, 0), (0, 3), (4, 4), (2, 9)]:
        posterior = beta(1 + h, 1 + m)
        expected_entropy = quad(lambda t, d=posterior: float(binary_entropy(np.array([t]))[0]) * d.pdf(t),
                                0.0, 1.0)[0]
        mu = (1 + h) / (2 + h + m)
        expected = float(binary_entropy(np.array([mu]))[0]) - expected_entropy
        assert observation_information(np.array([h]), np.array([m]))[0] == pytest.approx(expected, abs=1e-9)
    assert observation_weight(np.array([0]), np.array([0]))[0] == pytest.approx(1.0, rel=1e-12)


def test_observation_weight_falls_like_one_over_the_observations():
    n = np.array([10, 100, 1000, 65535])
    for share in (0.0, 0.5, 0.9):
        hits = np.round(share * n).astype(np.int64)
        w = observation_weight(hits, n - hits)
        assert np.all(np.diff(w) < 0)
        if share == 0.0:
            continue  # a hit rate at 0: I falls faster still
        # I ~ 1 / (2 (n + 3)) once the posterior is narrow, whatever the (inner) hit rate
        assert w[-1] * (np.log(2.0) - 0.5) * 2.0 * (n[-1] + 3) == pytest.approx(1.0, rel=0.02)
    # symmetric in hits and misses, and a settled voxel gives little more than an ambiguous one
    assert observation_weight(np.array([3]), np.array([7]))[0] == pytest.approx(
        observation_weight(np.array([7]), np.array([3]))[0])
    settled, ambiguous = observation_weight(np.array([10, 5]), np.array([0, 5]))
    assert settled < ambiguous


@pytest.mark.parametrize("keep_surface", [False, True])
def test_dense_marking_and_lanes_give_the_map_of_the_walk_in_the_pool(monkeypatch, keep_surface):
    """The kernel marks a scan's misses in a dense box and sweeps it when the box is small, walking the
    rays several at once in SIMD lanes where the processor has them, and walks the pool otherwise: all
    must give the same map, bit for bit, over scans that mix hits, ToF carving, truncation at max range,
    rays exactly along grid planes and edges (the tie rules), and voxels updated by earlier scans."""
    rng = np.random.default_rng(7)

    def scans() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        out = []
        for origin in ([0.003, 0.004, 0.5], [0.02, -0.01, 0.45], [0.0, 0.0, 0.4]):  # the last on a corner
            o = np.array(origin)
            ends = np.column_stack([rng.uniform(-0.15, 0.15, 400), rng.uniform(-0.15, 0.15, 400),
                                    rng.uniform(0.0, 0.1, 400)])
            grid = np.array([[0.1, 0.0, 0.0], [0.1, 0.1, 0.0], [0.0, 0.1, 0.3], [-0.05, 0.05, 0.35]])
            free = rng.random(ends.shape[0] + grid.shape[0]) < 0.2
            out.append((o, np.vstack([ends, grid]), free))
        return out

    def build(max_dense: int, lanes: bool) -> tuple[np.ndarray, ...]:
        monkeypatch.setattr("cell.perception.occupancy._MAX_DENSE_VOXELS", max_dense)
        monkeypatch.setattr("cell.perception.occupancy._RAY_LANES", lanes)
        m = make_map(max_range_m=0.42, keep_surface=keep_surface)
        for o, ends, free in recorded:
            m.integrate(o, ends)
            m.integrate(o, ends[::2], free_only=free[::2])
        keys, lo = m.known_keys()
        assert keys.shape[0] > 10_000 and m.occupied_keys().shape[0] > 100
        return keys, lo, *m.observation_counts(m.centers_of(keys))

    recorded = scans()
    walked = build(0, lanes=False)
    variants = [(1 << 25, False)] + ([(1 << 25, True)] if _k.ray_lanes() else [])
    for max_dense, lanes in variants:
        for a, b in zip(build(max_dense, lanes), walked, strict=True):
            np.testing.assert_array_equal(a, b)


def test_hit_sides_sum_the_directions_of_the_hits_until_one_comes_from_the_other_side():
    m = make_map()
    end = np.array([[0.0025, 0.0025, 0.2025]])
    above, below = end[0] + [0.0, 0.0, 0.3], end[0] - [0.0, 0.4, 0.3]
    for _ in range(3):
        m.integrate(above, np.repeat(end, 4, axis=0))  # four rays to one voxel: one direction per scan
    m.integrate(above, end - np.array([0.0, 0.0, 0.1]))  # crossed, not hit: no direction
    np.testing.assert_allclose(m.hit_sides(end), [[0.0, 0.0, -3.0]], atol=1e-6)
    np.testing.assert_array_equal(m.hit_sides(np.array([[1.0, 1.0, 1.0], [0.0025, 0.0025, 0.3025]])), 0.0)
    m.integrate(below, end)  # (0, 0.8, 0.6): against the sum
    assert np.isnan(m.hit_sides(end)).all()
    m.integrate(above, end)
    assert np.isnan(m.hit_sides(end)).all()  # hit from both sides, for good
