"""The information-oriented NBV objective of the visual-servoing paper (section II-C, eq. 7-9).

From a candidate camera pose r (``T_base_cam``, 4x4, camera frame z along the optical axis, x right, y
down), K rays leave the camera origin on a centred square grid (``ray_grid``). Each ray is clipped to the
object's ROI box (base frame) and to the perception crop box (camera frame, section II-A), and sampled
every map resolution along the clipped segment: t_i = t_in + (i + 1/2) res [m], i = 0 .. N-1, while
t_i < t_out. Each sample reads the occupancy probability p_i of its voxel (unknown: 0.5).

Eq. 7 gives the probability that the ray passes samples 1 .. i-1 and stops at i,
P_i = prod_{j<i} (1 - p_j) p_i, and the pass-through event P_{N+1} = 1 - sum_i P_i. A realization that
stops at i has seen the entropy C_i = sum_{j<=i} H(p_j) (eq. 8, nats); the pass-through realization sees
C_N (there is no sample N+1 inside the clipped segment, so it adds nothing). Eq. 9 averages the
expectation over the K rays: f(r) = 1/K sum_k sum_{i=1}^{N+1} P_i^k C_i^k. Rays that miss the ROI
contribute 0 and still count in K.

Exchanging the sums gives the form computed here: sum_i P_i C_i + P_{N+1} C_N = sum_j H(p_j) S_j with
S_j = prod_{i<j} (1 - p_i), the probability that the ray reaches sample j. S_j is exp of an exclusive
cumulative sum of log(1 - p), which vectorises over poses, rays and samples. The occupancy map clamps
p to [clamp_min, clamp_max] (OctoMap), so log(1 - p) is finite. A plain transcription of eq. 7-9 lives in
the tests and agrees with this to 1e-9 relative.

Because only voxels inside the ROI are ever read, ``EntropyObjective`` takes a snapshot of them as dense
arrays when built (after each map update); between map updates it is a pure function of the pose.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from cell.perception.filters import CropBox
from cell.perception.occupancy import OccupancyMap, binary_entropy

Array = NDArray[np.float64]

# Samples handled per vectorised block (poses x rays x samples): bounds the temporaries to a few MB.
_BLOCK_SAMPLES = 1 << 18


class NBVObjective(Protocol):
    """An NBV objective f(r) (paper eq. 1, 4, 10): the score of camera poses ``T_base_cam`` (4, 4) or a
    batch (B, 4, 4) in the base frame; a float for one pose, an array (B,) for a batch. The servo law
    only ever calls this, so it is agnostic to the objective (paper section II-C)."""

    def __call__(self, T_base_cam: Array) -> float | Array: ...


def ray_grid(rays_per_side: int, fov_deg: float) -> Array:
    """Unit ray directions (n^2, 3) in the camera frame: a centred n x n grid spread evenly in angle over
    a square ``fov_deg`` field of view, at the centres of the n x n angular cells (the zone centres of a
    multizone ToF sensor with n zones per side), row-major from the top-left (rows along +y)."""
    n = int(rays_per_side)
    half = np.deg2rad(fov_deg) / 2.0
    ang = -half + (np.arange(n) + 0.5) * (2.0 * half / n)
    tx, ty = np.meshgrid(np.tan(ang), np.tan(ang), indexing="xy")
    d = np.stack([tx.ravel(), ty.ravel(), np.ones(n * n)], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def slab_interval(origin: Array, direction: Array, lo: Array, hi: Array) -> tuple[Array, Array]:
    """Ray parameters [t_in, t_out] where rays origin + t direction (broadcast, last axis 3) lie inside
    the axis-aligned box [lo, hi]; t_in > t_out when a ray misses it. Ray parameters [m] for unit
    directions."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo - origin) / direction
        tb = (hi - origin) / direction
    # fmin / fmax ignore the NaN of a ray lying exactly in a face plane and parallel to it.
    t_in = np.max(np.fmin(ta, tb), axis=-1)
    t_out = np.min(np.fmax(ta, tb), axis=-1)
    return t_in, t_out


class EntropyObjective:
    """Eq. 7-9 on a snapshot of the occupancy map inside the ROI box (see the module docstring).

    ``roi_min`` / ``roi_max`` [m]: the object's ROI box in the base frame; ``crop``: the perception crop
    box in the camera frame [m]; ``directions_cam`` (K, 3): unit rays in the camera frame (``ray_grid``);
    ``voxel_entropy``: H(p) of eq. 8 [nats] per voxel probability (the binary entropy unless a planner
    chooses another measure of a voxel's uncertainty). Samples are spaced at the map's resolution.
    """

    def __init__(self, occupancy: OccupancyMap, roi_min: Array, roi_max: Array, crop: CropBox,
                 directions_cam: Array, voxel_entropy: Callable[[Array], Array] = binary_entropy) -> None:
        self.resolution_m = occupancy.resolution_m
        self.roi_min = np.asarray(roi_min, dtype=np.float64).reshape(3)
        self.roi_max = np.asarray(roi_max, dtype=np.float64).reshape(3)
        self.directions_cam = np.asarray(directions_cam, dtype=np.float64).reshape(-1, 3)
        res = self.resolution_m
        # Every sample inside the ROI box falls in a voxel with key in [floor(min / res), floor(max / res)]
        # (keys as the map's); one more voxel on each side absorbs rounding at the faces, so no sample
        # needs clipping.
        self._k_lo = np.floor(self.roi_min / res).astype(np.int64) - 1
        k_hi = np.floor(self.roi_max / res).astype(np.int64) + 1
        self._shape = k_hi - self._k_lo + 1
        axes = [np.arange(self._k_lo[i], k_hi[i] + 1) for i in range(3)]
        keys = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)
        p = occupancy.probability(occupancy.centers_of(keys))
        # Flat in key order (x, then y, then z), plus a last entry of zeros that samples past the end of
        # their ray read: log(1 - p_j) and H(p_j) of eq. 8 [nats].
        self._sentinel = keys.shape[0]
        self._log_free = np.append(np.log1p(-p), 0.0)
        self._entropy = np.append(voxel_entropy(p), 0.0)
        # The crop box is fixed in the camera frame: its interval per ray is the same for every pose.
        lo = np.array([crop.x_m[0], crop.y_m[0], crop.z_m[0]])
        hi = np.array([crop.x_m[1], crop.y_m[1], crop.z_m[1]])
        self._crop_in, self._crop_out = slab_interval(np.zeros(3), self.directions_cam, lo, hi)

    @property
    def n_rays(self) -> int:
        """K of eq. 9."""
        return int(self.directions_cam.shape[0])

    def __call__(self, T_base_cam: Array) -> float | Array:
        """f(r) of eq. 9 [nats] for one pose (4, 4) (a float) or a batch (B, 4, 4) (an array (B,))."""
        T = np.asarray(T_base_cam, dtype=np.float64)
        if T.shape[-2:] != (4, 4):
            raise ValueError(f"T_base_cam must be (4, 4) or (B, 4, 4), got {T.shape}")
        batch = T.reshape(-1, 4, 4)
        R = batch[:, :3, :3]
        o = batch[:, :3, 3]
        d = np.einsum("bij,kj->bki", R, self.directions_cam)  # ray directions, base frame (B, K, 3)
        t_in, t_out = slab_interval(o[:, None, :], d, self.roi_min, self.roi_max)
        t_in = np.maximum(np.maximum(t_in, self._crop_in), 0.0)
        t_out = np.minimum(t_out, self._crop_out)
        # Samples t_in + (i + 1/2) res < t_out, i = 0 .. n-1.
        n = np.maximum(np.ceil((t_out - t_in) / self.resolution_m - 0.5), 0.0).astype(np.int64)
        out = np.zeros(batch.shape[0])
        n_max = n.max(axis=1) if n.size else np.zeros(0, dtype=np.int64)
        start = 0
        while start < batch.shape[0]:
            # As many poses as keep poses x rays x (their longest ray's samples) within _BLOCK_SAMPLES.
            stop = start + 1
            longest = max(int(n_max[start]), 1)
            while stop < batch.shape[0]:
                longest_next = max(longest, int(n_max[stop]))
                if (stop + 1 - start) * self.n_rays * longest_next > _BLOCK_SAMPLES:
                    break
                longest, stop = longest_next, stop + 1
            sl = slice(start, stop)
            out[sl] = self._expected_entropy(o[sl], d[sl], t_in[sl], n[sl])
            start = stop
        return float(out[0]) if T.ndim == 2 else out.reshape(T.shape[:-2])

    def _expected_entropy(self, o: Array, d: Array, t_in: Array, n: NDArray[np.int64]) -> Array:
        """Eq. 9 for a block of poses: origins (b, 3), directions (b, K, 3), entries (b, K), sample
        counts (b, K)."""
        n_samples = int(n.max()) if n.size else 0
        if n_samples == 0:
            return np.zeros(o.shape[0])
        res = self.resolution_m
        i = np.arange(n_samples)
        t = t_in[..., None] + (i + 0.5) * res  # (b, K, N)
        # Flat voxel index ((kx * sy) + ky) * sz + kz, one axis at a time (no (b, K, N, 3) temporaries);
        # k = floor(x / res) exactly as the map computes keys.
        flat = np.zeros(t.shape, dtype=np.int64)
        for axis in range(3):
            x = o[:, axis, None, None] + t * d[:, :, axis, None]
            k = np.floor(x / res).astype(np.int64) - self._k_lo[axis]
            flat = flat * self._shape[axis] + k if axis else k
        flat[i >= n[..., None]] = self._sentinel
        log_free = self._log_free[flat]
        # S_j = prod_{i<j} (1 - p_i): exclusive cumulative sum of log(1 - p).
        reach = np.exp(np.cumsum(log_free, axis=-1) - log_free)
        reach *= self._entropy[flat]
        return reach.sum(axis=(1, 2)) / self.n_rays
