"""The entropy NBV objective (visual-servoing paper eq. 7-9) against a plain transcription of the paper."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cell.config.models import CropBoxConfig
from cell.perception.occupancy import OccupancyMap, OccupancyParams, observation_weight
from cell.planning.vs.objective import (
    PARALLEL_MIN_POSES,
    EntropyObjective,
    ray_grid,
)
from drivers.depth.sim_tof import zone_directions
from drivers.transforms import look_at

CROP = CropBoxConfig(x_m=(-0.15, 0.15), y_m=(-0.15, 0.15), z_m=(0.05, 0.40))
ROI_MIN = np.array([0.38, -0.07, 0.0])
ROI_MAX = np.array([0.52, 0.06, 0.15])


def reference_f(occupancy: OccupancyMap, T_base_cam, directions_cam, roi_min, roi_max, crop) -> float:
    """Eq. 7-9 written out ray by ray, realization by realization, as the paper states them."""
    res = occupancy.resolution_m
    R, o = T_base_cam[:3, :3], T_base_cam[:3, 3]
    crop_lo = np.array([crop.x_m[0], crop.y_m[0], crop.z_m[0]])
    crop_hi = np.array([crop.x_m[1], crop.y_m[1], crop.z_m[1]])
    total = 0.0
    for d_cam in directions_cam:
        d = R @ d_cam
        # The ray's stretch inside the ROI (base frame) and inside the crop box (camera frame).
        t_in, t_out = 0.0, math.inf
        for axis in range(3):
            for origin, direction, lo, hi in ((o[axis], d[axis], roi_min[axis], roi_max[axis]),
                                              (0.0, d_cam[axis], crop_lo[axis], crop_hi[axis])):
                if direction == 0.0:
                    if not lo < origin < hi:
                        t_in = math.inf
                    continue
                a, b = (lo - origin) / direction, (hi - origin) / direction
                t_in, t_out = max(t_in, min(a, b)), min(t_out, max(a, b))
        samples = []
        t = t_in + 0.5 * res
        while t < t_out:
            samples.append(o + t * d)
            t += res
        if not samples:
            continue
        p = occupancy.probability(np.array(samples))
        n = len(p)
        entropy = [-(q * math.log(q) + (1 - q) * math.log(1 - q)) for q in p]  # eq. 8
        stop = [math.prod(1.0 - p[j] for j in range(i)) * p[i] for i in range(n)]  # eq. 7
        stop.append(1.0 - sum(stop))  # the pass-through realization
        seen = [sum(entropy[:min(i + 1, n)]) for i in range(n + 1)]
        total += sum(stop[i] * seen[i] for i in range(n + 1))  # eq. 9, inner sums
    return total / len(directions_cam)


def random_map(rng: np.random.Generator, resolution: float = 0.005) -> OccupancyMap:
    """Known voxels with random log-odds over most of the ROI, unknown voxels between them."""
    occupancy = OccupancyMap(OccupancyParams(resolution_m=resolution))
    keys = occupancy.voxel_keys_in_box(ROI_MIN - 0.02, ROI_MAX + 0.02)
    keys = keys[rng.random(keys.shape[0]) < 0.7]
    occupancy.set_logodds(keys, rng.uniform(-2.5, 3.5, keys.shape[0]))
    return occupancy


def poses_around(rng: np.random.Generator, n: int, radius: float = 0.25) -> np.ndarray:
    """Camera poses at ``radius`` from the ROI centre, each looking near it."""
    centre = (ROI_MIN + ROI_MAX) / 2
    out = []
    for _ in range(n):
        v = rng.normal(size=3)
        v[2] = abs(v[2])
        eye = centre + radius * v / np.linalg.norm(v)
        out.append(look_at(eye, centre + rng.normal(scale=0.02, size=3)))
    return np.array(out)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fast_objective_agrees_with_the_paper_transcription(seed):
    rng = np.random.default_rng(seed)
    occupancy = random_map(rng)
    dirs = ray_grid(23, 30.0)
    f = EntropyObjective(occupancy, ROI_MIN, ROI_MAX, CROP, dirs)
    poses = poses_around(rng, 4)
    batch = f(poses)
    for T, value in zip(poses, batch, strict=True):
        expected = reference_f(occupancy, T, dirs, ROI_MIN, ROI_MAX, CROP)
        assert expected > 0.1
        assert value == pytest.approx(expected, rel=1e-9)
        assert f(T) == pytest.approx(value, rel=1e-12)


def test_tof_grid_and_coarse_map_agree_with_the_transcription():
    rng = np.random.default_rng(7)
    occupancy = random_map(rng, resolution=0.01)
    dirs = ray_grid(8, 45.0)
    crop = CropBoxConfig(x_m=(-0.5, 0.5), y_m=(-0.5, 0.5), z_m=(0.02, 1.0))
    f = EntropyObjective(occupancy, ROI_MIN, ROI_MAX, crop, dirs)
    for T in poses_around(rng, 3, radius=0.4):
        assert f(T) == pytest.approx(reference_f(occupancy, T, dirs, ROI_MIN, ROI_MAX, crop), rel=1e-9)


def test_a_threaded_batch_equals_the_poses_one_by_one():
    # Batches from PARALLEL_MIN_POSES poses on are split over OpenMP threads; single poses are not. Each
    # pose is one sequential sum, so the values are bit-identical (job outputs must be byte-identical).
    rng = np.random.default_rng(11)
    f = EntropyObjective(random_map(rng), ROI_MIN, ROI_MAX, CROP, ray_grid(23, 30.0))
    poses = poses_around(rng, PARALLEL_MIN_POSES + 37)
    batch = f(poses)
    assert batch.tolist() == [f(T) for T in poses]
    assert f(poses).tolist() == batch.tolist()


def test_ray_grid_is_the_tof_zone_centres_and_spans_the_fov():
    np.testing.assert_allclose(ray_grid(8, 45.0), zone_directions(8, 45.0)[:, 0, :], atol=1e-12)
    d = ray_grid(23, 30.0)
    assert d.shape == (529, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    np.testing.assert_allclose(d[264], [0.0, 0.0, 1.0], atol=1e-15)  # the centre ray is the optical axis
    half = np.rad2deg(np.arctan2(d[:, 0], d[:, 2]))
    assert half.max() == pytest.approx(15.0 - 15.0 / 23)  # cell centres of a 30 deg fan of 23
    assert d[0, 0] < 0 and d[0, 1] < 0  # row-major from the top-left


def test_unknown_space_gives_the_closed_form():
    # All voxels unknown (p = 1/2, H = ln 2): a ray of N samples gives ln 2 sum_{j<N} 2^-j.
    occupancy = OccupancyMap(OccupancyParams(resolution_m=0.005))
    lo, hi = np.array([-0.05, -0.05, 0.2]), np.array([0.05, 0.05, 0.3])
    f = EntropyObjective(occupancy, lo, hi, CROP, np.array([[0.0, 0.0, 1.0]]))
    T = np.eye(4)
    T[:3, 3] = [0.0001, 0.0002, 0.0]  # off the voxel faces
    n = 20  # 10 cm of ROI along the axis at 5 mm
    assert f(T) == pytest.approx(math.log(2) * (2 - 2.0 ** (1 - n)), rel=1e-12)


def test_rays_that_miss_the_roi_or_the_crop_box_score_zero():
    occupancy = random_map(np.random.default_rng(3))
    f = EntropyObjective(occupancy, ROI_MIN, ROI_MAX, CROP, ray_grid(23, 30.0))
    centre = (ROI_MIN + ROI_MAX) / 2
    up = np.array([0.0, 0.0, 1.0])
    away = look_at(centre + 0.3 * up, centre + up)  # looking up, away from the ROI
    far = look_at(centre + np.array([-0.7, 0.0, 0.1]), centre)  # the ROI lies beyond the 40 cm crop depth
    assert f(away) == 0.0 and f(far) == 0.0
    assert f(np.array([away, far])).tolist() == [0.0, 0.0]


def test_a_known_surface_hides_the_unknown_space_behind_it():
    # Seen from above, a confidently occupied top layer stops the rays before the unknown interior.
    occupancy = OccupancyMap(OccupancyParams(resolution_m=0.005))
    centre = (ROI_MIN + ROI_MAX) / 2
    T = look_at(centre + np.array([0.0, 0.0, 0.25]), centre, up_hint=np.array([1.0, 0.0, 0.0]))
    f_unknown = EntropyObjective(occupancy, ROI_MIN, ROI_MAX, CROP, ray_grid(23, 30.0))(T)
    keys = occupancy.voxel_keys_in_box(ROI_MIN, ROI_MAX)
    top = keys[keys[:, 2] == keys[:, 2].max()]
    occupancy.set_logodds(top, np.full(top.shape[0], 4.0))  # clamped to p = 0.97
    f_wall = EntropyObjective(occupancy, ROI_MIN, ROI_MAX, CROP, ray_grid(23, 30.0))(T)
    assert 0.0 < f_wall < 0.25 * f_unknown


def test_rejects_a_malformed_pose():
    f = EntropyObjective(random_map(np.random.default_rng(5)), ROI_MIN, ROI_MAX, CROP, ray_grid(3, 30.0))
    with pytest.raises(ValueError, match="4, 4"):
        f(np.eye(3))
    T = np.eye(4)
    T[0, 3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        f(T)


def ambiguous_voxel_map(n_scans: int) -> tuple[OccupancyMap, np.ndarray, np.ndarray]:
    """A map where one voxel was hit and crossed in alternate scans (a surface that partly fills it),
    ``n_scans`` (even) in all, with p_miss = 1 - p_hit so that it ends at p = 1/2; the camera pose looking
    straight down at it and a ROI box whose top is that voxel's top face (the voxels the scans crossed
    above it lie outside)."""
    occupancy = OccupancyMap(OccupancyParams(resolution_m=0.005, p_hit=0.7, p_miss=0.3))
    voxel = np.array([[0.4525, 0.0025, 0.0525]])  # the centre of voxel (90, 0, 10)
    origin = voxel[0] + [0.0, 0.0, 0.25]
    for k in range(n_scans):
        occupancy.integrate(origin, voxel, free_only=np.array([k % 2 == 1]))
    roi = np.stack([voxel[0] - [0.05, 0.05, 0.05], voxel[0] + [0.05, 0.05, 0.0025]])
    return occupancy, look_at(origin, voxel[0], up_hint=np.array([1.0, 0.0, 0.0])), roi


def test_an_often_seen_ambiguous_voxel_weighs_less_than_an_unseen_one():
    axis = np.array([[0.0, 0.0, 1.0]])
    paper, aware = {}, {}
    for n_scans in (0, 2, 40):
        occupancy, T, roi = ambiguous_voxel_map(n_scans)
        assert occupancy.probability(T[:3, 3] - [0.0, 0.0, 0.25])[0] == pytest.approx(0.5)
        paper[n_scans] = EntropyObjective(occupancy, *roi, CROP, axis)(T)
        aware[n_scans] = EntropyObjective(occupancy, *roi, CROP, axis, observation_aware=True)(T)
    # eq. 8 cannot tell the voxel seen 40 times from unseen space: same p, same entropy
    assert paper[40] == pytest.approx(paper[0], rel=1e-12) and paper[2] == pytest.approx(paper[0], rel=1e-12)
    # weighted by what one more observation can tell, it fades the more it was seen; unseen space does not
    assert aware[0] == pytest.approx(paper[0], rel=1e-12)
    assert aware[40] < aware[2] < aware[0]
    ln2 = math.log(2.0)
    # the voxel is the ray's first sample; the unseen ones behind it are reached with probability 1/2
    w40 = observation_weight(np.array([20]), np.array([20]))[0]
    assert paper[0] - aware[40] == pytest.approx(ln2 * (1.0 - w40), rel=1e-9)


def test_a_voxel_hit_only_from_the_other_side_reads_as_unseen_from_this_one():
    # A one-voxel wall seen from above, as the inside of a cup's 4 mm wall shares a 5 mm voxel with its
    # outside: from below, what the voxel's far face looks like has never been seen.
    occupancy = OccupancyMap(OccupancyParams(resolution_m=0.005))
    voxel = np.array([[0.4525, 0.0025, 0.0525]])
    above, below = voxel[0] + [0.0, 0.0, 0.25], voxel[0] - [0.0, 0.0, 0.25]
    for _ in range(5):
        occupancy.integrate(above, voxel)
    roi = (voxel[0] - 0.0025, voxel[0] + 0.0025)  # the voxel alone: one sample per ray
    axis = np.array([[0.0, 0.0, 1.0]])
    up = np.array([1.0, 0.0, 0.0])

    def f(eye, aware=True):
        return EntropyObjective(occupancy, *roi, CROP, axis, observation_aware=aware)(
            look_at(eye, voxel[0], up_hint=up))

    seen = f(above)
    assert seen < 0.1 * math.log(2.0)
    assert f(below, aware=False) == pytest.approx(seen / observation_weight(np.array([5]), np.array([0]))[0])
    assert f(below) == pytest.approx(math.log(2.0), rel=1e-9)
    beyond = voxel + np.array([0.0, 0.0, 0.05])
    occupancy.integrate(below, beyond, free_only=np.array([True]))  # crossed from below
    assert f(below) == pytest.approx(math.log(2.0) * observation_weight(np.array([0]), np.array([1]))[0])
    occupancy.integrate(below, voxel)  # and now hit from below: as the map holds it, either side
    assert f(below) == pytest.approx(f(above), rel=1e-12)
