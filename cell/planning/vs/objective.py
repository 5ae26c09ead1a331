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
S_j = prod_{i<j} (1 - p_i), the probability that the ray reaches sample j: one pass along the ray with a
running product, in the compiled kernel ``_objective.Scorer``. A plain transcription of eq. 7-9
lives in the tests and agrees with this to 1e-9 relative.

Because only voxels inside the ROI are ever read, ``EntropyObjective`` takes a snapshot of them when built
(after each map update, O(ROI voxels)): a dense array of (1 - p, H(p)) per voxel in key order, so that a
sample costs one read instead of a block-index lookup, an exp and a log; between map updates f is a pure
function of the pose. A sample's voxel is floor(x / res), as the map keys it, up to rounding: the kernel
steps the grid coordinate x / res along the ray, so a sample within ~1e-12 voxel of a face may be read from
the voxel on its other side.

Observation-aware entropy (``observation_aware``, a departure from eq. 8; ``planners.vs.objective.entropy``).
Eq. 8 counts a voxel's uncertainty as H(p), the entropy of the map's estimate p. For a voxel that a surface
crosses at a slant, or that the views disagree on (a calibration error moves the surface by a voxel from
one view to the next), the outcome of an observation is itself random: some views hit it, some pass
through, and p stays at 0.2-0.8 however often it is seen. H(p) then never falls, and a view of such voxels
scores as high as a view of unseen space, which a threshold on f cannot tell apart. The map's per-voxel
counts (``OccupancyMap.observation_counts``) do: the observation-aware objective weights each voxel's H of
eq. 8 (``voxel_entropy``) by w(h, m) = I(h, m) / I(0, 0) (``cell.perception.occupancy.observation_weight``:
the Beta-Bernoulli information one more observation gives about the voxel's hit rate), 1 for an unseen
voxel (so f of unseen space is eq. 9's) and falling like 1 / (h + m) whatever the hit rate, so a voxel the
views keep disagreeing on fades from f as it is seen. Eq. 7's stopping probabilities (1 - p) stay as they
are. A voxel without counts (a map read from a .bt file) weighs as unseen: the paper's form.

The observation-aware objective also reads the side each voxel was hit from (``OccupancyMap.hit_sides``,
the sum u of the unit directions of the rays that hit it): a sample whose ray d points against it,
d . u < 0, reads the voxel's H as that of a voxel never hit and seen free as often as the map's misses
count, H(0.5) w(0, m) (its own 1 - p still stops the ray): its hits only say what its other side looks
like, and from this side it is unseen unless rays from here have crossed it since. A surface voxel of a
solid is reached from its other side only through the solid, by rays that eq. 7 has already stopped, so
this changes nothing there; but the two faces of a wall thinner than a voxel share voxels, and once one
face is seen the map holds the other as known. In a VS-Local cup scan (4 mm walls, 5 mm voxels, seed 0)
45 % of the surface left unseen lay in voxels hit from the other face, f at the views of that side was
0.006-0.02 nats, below what the coarse differences of ``cell.planning.vs.local`` need to go there, and
the scan converged on one side (63.7 %; with the rule 88.6 %). Without the misses' weight a camera that
crossed such voxels from their unseen side (a face that fills only part of its voxel) read them as unseen
however often it did, and held in place until the time budget. A voxel hit from both sides (a hit
against the sum turns it NaN in the map) is read as it is; so is a voxel never hit (u = 0).

A batch of poses is shared between OpenMP threads (``batch_threads``, OMP_NUM_THREADS) once it holds
``PARALLEL_MIN_POSES`` poses (the 5000 candidates of eq. 10); smaller ones (the five poses of a servo
iteration, eq. 5-6) run on the calling thread. Each pose is one sequential sum whichever thread runs it,
so results do not depend on the thread count.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, overload

import numpy as np
from numpy.typing import NDArray

from cell.perception.filters import CropBox, crop_interval
from cell.perception.occupancy import OccupancyMap, binary_entropy, observation_weight
from cell.planning.vs import _objective as _k
from drivers.errors import PlanningError

Array = NDArray[np.float64]
Pose = np.ndarray[tuple[int, int], np.dtype[np.float64]]
"""One camera pose T_base_cam (4, 4); an ``Array`` of unknown shape passed to an objective reads as one."""
PoseBatch = np.ndarray[tuple[int, int, int], np.dtype[np.float64]]
"""A batch of camera poses (B, 4, 4), typed so that an objective's result types as an array (B,)."""

# Batches from this many poses on are split between threads; below, thread start-up outweighs the gain.
PARALLEL_MIN_POSES = 64


def batch_threads() -> int:
    """The OpenMP threads a batch of ``PARALLEL_MIN_POSES`` poses or more runs on (OMP_NUM_THREADS, else
    the number of cores)."""
    return _k.max_threads()


class NBVObjective(Protocol):
    """An NBV objective f(r) (paper eq. 1, 4, 10): the score of camera poses ``T_base_cam`` (4, 4) or a
    batch (B, 4, 4) in the base frame; a float for one pose, an array (B,) for a batch. The servo law
    only ever calls this, so it is agnostic to the objective (paper section II-C)."""

    @overload
    def __call__(self, T_base_cam: Pose) -> float: ...
    @overload
    def __call__(self, T_base_cam: PoseBatch) -> Array: ...


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


class EntropyObjective:
    """Eq. 7-9 on a snapshot of the occupancy map inside the ROI box (see the module docstring).

    ``roi_min`` / ``roi_max`` [m]: the object's ROI box in the base frame; ``crop``: the perception crop
    box in the camera frame [m]; ``directions_cam`` (K, 3): unit rays in the camera frame (``ray_grid``);
    ``voxel_entropy``: H(p) of eq. 8 [nats] per voxel probability (the binary entropy unless a planner
    chooses another measure of a voxel's uncertainty); with ``observation_aware`` each voxel's H is
    weighted by ``observation_weight`` of its counts (module docstring). Samples are spaced at the map's
    resolution.
    """

    def __init__(self, occupancy: OccupancyMap, roi_min: Array, roi_max: Array, crop: CropBox,
                 directions_cam: Array, voxel_entropy: Callable[[Array], Array] = binary_entropy,
                 observation_aware: bool = False) -> None:
        self.resolution_m = occupancy.resolution_m
        self.roi_min = np.asarray(roi_min, dtype=np.float64).reshape(3)
        self.roi_max = np.asarray(roi_max, dtype=np.float64).reshape(3)
        self.directions_cam = np.ascontiguousarray(directions_cam, dtype=np.float64).reshape(-1, 3)
        res = self.resolution_m
        # Every sample inside the ROI box falls in a voxel with key in [floor(min / res), floor(max / res)]
        # (keys as the map's); one more voxel on each side absorbs rounding at the faces, so no sample
        # needs clipping.
        k_lo = np.floor(self.roi_min / res).astype(np.int64) - 1
        k_hi = np.floor(self.roi_max / res).astype(np.int64) + 1
        shape = k_hi - k_lo + 1
        axes = [np.arange(k_lo[i], k_hi[i] + 1) for i in range(3)]
        keys = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)
        centers = occupancy.centers_of(keys)
        p = occupancy.probability(centers)
        entropy = voxel_entropy(p)
        sides = np.zeros((centers.shape[0], 3))
        other_side = entropy
        if observation_aware:
            hits, misses = occupancy.observation_counts(centers)
            entropy = entropy * observation_weight(hits, misses)
            sides = np.nan_to_num(occupancy.hit_sides(centers), nan=0.0)  # hit from both sides: none
            other_side = voxel_entropy(np.full(1, 0.5)) * observation_weight(np.zeros_like(misses), misses)
        # Per voxel in key order (x, then y, then z): 1 - p of eq. 7, H(p) of eq. 8 [nats], the H a ray
        # against the side it was hit from reads, and that side.
        voxels = np.ascontiguousarray(np.column_stack([1.0 - p, entropy, other_side, sides]))
        # The crop box is fixed in the camera frame: its interval per ray is the same for every pose.
        crop_in, crop_out = crop_interval(self.directions_cam, crop)
        self._scorer = _k.Scorer(self.directions_cam, crop_in, crop_out, self.roi_min, self.roi_max, res,
                                 k_lo, shape, voxels)

    @property
    def n_rays(self) -> int:
        """K of eq. 9."""
        return int(self.directions_cam.shape[0])

    @overload
    def __call__(self, T_base_cam: Pose) -> float: ...
    @overload
    def __call__(self, T_base_cam: PoseBatch) -> Array: ...

    def __call__(self, T_base_cam: Array) -> float | Array:
        """f(r) of eq. 9 [nats] for one pose (4, 4) (a float) or a batch (B, 4, 4) (an array (B,))."""
        T = np.asarray(T_base_cam, dtype=np.float64)
        if T.shape[-2:] != (4, 4):
            raise ValueError(f"T_base_cam must be (4, 4) or (B, 4, 4), got {T.shape}")
        batch = np.ascontiguousarray(T.reshape(-1, 4, 4))
        out = np.empty(batch.shape[0])
        self._scorer.score(batch, out, batch_threads() if batch.shape[0] >= PARALLEL_MIN_POSES else 1)
        if np.isnan(out).any():
            i = int(np.flatnonzero(np.isnan(out))[0])
            if not np.all(np.isfinite(batch[i, :3, :])):
                raise ValueError(f"T_base_cam must be finite, pose {i} is not")
            # The snapshot covers the ROI box with a voxel to spare: a sample outside it is a bug here.
            raise PlanningError(f"entropy objective: a ray sample of pose {i} left the map snapshot around "
                                f"the ROI box {self.roi_min.tolist()} .. {self.roi_max.tolist()} m")
        return float(out[0]) if T.ndim == 2 else out.reshape(T.shape[:-2])
