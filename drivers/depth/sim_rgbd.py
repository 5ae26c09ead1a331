"""``sim-rgbd``: a simulated pinhole depth camera, rendered by ray casting a :class:`SimScene`.

Sensor frame: z along the optical axis, x right, y down; units metres.

Pixel convention: pixel (u, v) is column u, row v, and its centre is at the integer coordinates (u, v);
the ray of pixel (u, v) goes through ((u - cx) / fx, (v - cy) / fy, 1) in the sensor frame. So with
``cx = (width - 1) / 2`` the principal point is the image centre. Back-projection of a depth z [m]:
x = (u - cx) z / fx, y = (v - cy) z / fy.

Per frame (one ray-casting call for all pixels):

1. the true depth z = t * d_z (z coordinate of the hit, not the range along the ray);
2. grazing dropouts: with the incidence angle a between the ray and the surface normal, a return with
   a > ``grazing_deg`` is always dropped and one with ``grazing_deg - 15`` < a <= ``grazing_deg`` is
   dropped with probability (a - (grazing_deg - 15)) / 15 (linear from 0 to 1);
3. the depth bias ``depth_offset_m`` (a calibration error, ``drivers.sim.errors``) and axial Gaussian noise
   N(0, sigma(z)^2) with sigma(z) = sigma0_m + k_per_m z^2, z the true depth;
4. range gating on the measured (noisy) depth: outside [range_min_m, range_max_m] is no return (depth 0).

The grey ``intensity`` image is rendered from the same rays (from ``SUPERSAMPLE`` x ``SUPERSAMPLE`` rays
per pixel, averaged, when a texture is printed on the table), noise-free and without dropouts (a camera's
image sees what its depth misses): the table's grey or what is printed on it (a calibration board,
``SimScene.texture``), the object's grey, black where a ray hits nothing.

Random numbers come only from the generator given at construction; every frame draws the same number of
variates (one uniform and one normal per pixel) whatever the scene, so a seed fixes the frame sequence
exactly.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from drivers.clock import Clock
from drivers.depth.base import DepthFrame, SensorModel
from drivers.depth.config import SimRGBDConfig
from drivers.depth.projection import back_project, pinhole_fov_deg
from drivers.depth.sim_base import SimDepthSensor
from drivers.sim.scene import HIT_NONE, RayHits, SimScene

Array = NDArray[np.float64]

SUPERSAMPLE = 2
"""Rays per pixel side of the grey image when a texture is printed on the table (a calibration board):
a pixel sees the mean over its area, as a real camera does, so corners are found to a fraction of a
pixel."""
GRAZING_RAMP_DEG: float = 15.0
"""Width [deg] of the band below ``grazing_deg`` in which the dropout probability rises from 0 to 1."""


class SimRGBD(SimDepthSensor):
    """Simulated RGB-D depth camera (depth only), see the module docstring for the image model.

    ``pose_source()`` returns the true T_base_sensor (4x4) at capture time; ``clock`` stamps frames;
    ``rng`` is the only source of noise. ``capture()`` returns a ``DepthFrame`` with ``depth`` (H, W)
    float32 [m] (0 = no return) and ``points`` (N, 3) float64 [m, sensor frame] for the valid pixels in
    row-major pixel order.
    """

    name = "sim-rgbd"

    def __init__(self, config: SimRGBDConfig, scene: SimScene, pose_source: Callable[[], Array],
                 clock: Clock, rng: np.random.Generator, depth_offset_m: float = 0.0) -> None:
        super().__init__(scene, pose_source, clock, rng, depth_offset_m)
        self.config = config
        self.intrinsics = np.array([[config.fx, 0.0, config.cx],
                                    [0.0, config.fy, config.cy],
                                    [0.0, 0.0, 1.0]])
        rays = self._pixel_rays(0.0, 0.0)
        norm = np.linalg.norm(rays, axis=1)
        self._dirs_sensor: Array = rays / norm[:, None]  # (H*W, 3) unit rays, sensor frame
        self._z_per_t: Array = 1.0 / norm  # depth z per unit range along each ray
        # the grey image of a printed texture: each pixel the mean of SUPERSAMPLE^2 rays over its area
        offsets = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
        self._grey_dirs: list[Array] = []
        if scene.texture is not None:
            for du in offsets:
                for dv in offsets:
                    r = self._pixel_rays(float(du), float(dv))
                    self._grey_dirs.append(r / np.linalg.norm(r, axis=1, keepdims=True))
        g = config.grazing_deg
        self._cos_hard = np.cos(np.deg2rad(g))  # cos(a) below this: always dropped
        self._cos_soft = np.cos(np.deg2rad(g - GRAZING_RAMP_DEG))  # cos(a) below this: may be dropped

    def _pixel_rays(self, du: float, dv: float) -> Array:
        """Rays (H*W, 3), sensor frame, not normalized, through each pixel's centre shifted by (du, dv)
        [px]."""
        c = self.config
        w, h = c.width, c.height
        xn = np.broadcast_to((np.arange(w) + du - c.cx) / c.fx, (h, w))
        yn = np.broadcast_to(((np.arange(h) + dv - c.cy) / c.fy)[:, None], (h, w))
        return np.stack([xn, yn, np.ones((h, w))], axis=-1).reshape(-1, 3)

    def _grey(self, T: Array, hits: RayHits, dirs_base: Array) -> NDArray[np.uint8]:
        """The grey image (H*W,): from the depth rays' hits, or, with a printed texture in the scene,
        the mean over each pixel's supersampled rays."""
        if not self._grey_dirs:
            return self._scene.intensity(hits, T[:3, 3], dirs_base)
        total = np.zeros(dirs_base.shape[0])
        for d in self._grey_dirs:
            d_base = d @ T[:3, :3].T
            total += self._scene.intensity(self._scene.cast(T[:3, 3], d_base), T[:3, 3], d_base)
        return np.round(total / len(self._grey_dirs)).astype(np.uint8)

    @property
    def model(self) -> SensorModel:
        c = self.config
        fov_x, fov_y = pinhole_fov_deg(self.intrinsics, c.width, c.height)
        return SensorModel(kind="rgbd", width=c.width, height=c.height, fov_x_deg=fov_x, fov_y_deg=fov_y,
                           range_min_m=c.range_min_m, range_max_m=c.range_max_m)

    @property
    def rays_sensor(self) -> Array:
        """Unit ray of every pixel (H*W, 3), row-major, sensor frame (read-only view)."""
        view = self._dirs_sensor.view()
        view.setflags(write=False)
        return view

    # -- capture ---------------------------------------------------------------------------------------
    def capture(self) -> DepthFrame:
        c = self.config
        T = self._begin_capture()
        R = T[:3, :3]
        dirs_base = self._dirs_sensor @ R.T
        hits = self._scene.cast(T[:3, 3], dirs_base)

        n_pix = c.width * c.height
        u_drop = self._rng.random(n_pix, dtype=np.float32)
        noise = self._rng.standard_normal(n_pix, dtype=np.float32)

        cos_inc = hits.cos_incidence
        keep = (hits.what != HIT_NONE) & (cos_inc > self._cos_hard)
        band = keep & (cos_inc < self._cos_soft)  # incidence in the ramp below grazing_deg
        angle = np.degrees(np.arccos(np.clip(cos_inc[band], -1.0, 1.0)))
        p_drop = (angle - (c.grazing_deg - GRAZING_RAMP_DEG)) / GRAZING_RAMP_DEG
        keep[band] = u_drop[band] >= p_drop

        idx = np.flatnonzero(keep)
        z_true = hits.t[idx] * self._z_per_t[idx]
        z = z_true + self.depth_offset_m + (c.noise.sigma0_m + c.noise.k_per_m * z_true ** 2) * noise[idx]
        in_range = (z >= c.range_min_m) & (z <= c.range_max_m)
        idx = idx[in_range]
        zf = z[in_range].astype(np.float32)
        depth: NDArray[np.float32] = np.zeros(n_pix, dtype=np.float32)
        depth[idx] = zf
        depth = depth.reshape(c.height, c.width)
        # The same back-projection as replay and reprocessing, so that a recorded depth image gives back
        # exactly the points this frame had.
        points = back_project(depth, self.intrinsics)
        intensity = self._grey(T, hits, dirs_base).reshape(c.height, c.width)

        frame = DepthFrame(seq=self._next_seq(), timestamp=self._clock.now(), points=points,
                           depth=depth, intrinsics=self.intrinsics, intensity=intensity)
        return frame
