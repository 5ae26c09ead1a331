"""``sim-tof``: a simulated multizone time-of-flight sensor (VL53L8CX-like), rendered by ray casting.

Sensor frame: z along the optical axis, x right, y down; units metres.

Zones: ``resolution`` x ``resolution`` zones tile a square ``fov_deg`` x ``fov_deg`` field of view evenly
in angle. Zone (row i, column j) covers the angles theta_x in [-fov/2 + j w, -fov/2 + (j + 1) w] and
theta_y in [-fov/2 + i w, -fov/2 + (i + 1) w] (w = fov / resolution), a ray at angles (theta_x, theta_y)
having the direction normalise(tan theta_x, tan theta_y, 1). Zones are numbered row-major from the top-left
zone as seen in the sensor frame: index = i * resolution + j, the row index i growing along +y (down) and
the column index j along +x (right). The zone's central ray is at the centre of its angular cell; its
``subrays`` x ``subrays`` rays sit at the centres of an even ``subrays`` x ``subrays`` split of the cell.

Per zone (one ray-casting call for all subrays of all zones):

- a subray counts as a hit when its range (distance along the ray) is within [range_min_m, range_max_m];
- hit fraction below ``min_hit_fraction``: no target (nb_targets 0, status 255, distance and sigma NaN,
  reflectance NaN, no point);
- otherwise ``distance_m`` = the median range of the hit subrays (a radial distance, reported along the
  zone's central ray) plus Gaussian noise N(0, sigma(r)^2), sigma(r) = sigma0_m + k_per_m r^2 with r that
  median range; the zone's point is ``distance_m * direction`` (sensor frame);
- ``status`` 9 (range valid, large pulse / merged target) when the zone spans a depth edge, else 5 (range
  valid). Depth edge: the sorted hit ranges have a gap larger than ``edge_gap_m`` (config, default 0.025 m)
  between two neighbours. A gap rather than the total spread is used so that a smooth slanted surface
  (e.g. the table seen at 60 deg incidence, whose ranges spread by several cm over one zone) stays
  status 5, while two surfaces at different depths in one zone give status 9;
- ``sigma_m`` = sigma(r) + the standard deviation of the hit ranges (the within-zone spread);
- ``nb_targets`` 1 for a zone with a target (single-target mode; merged targets are not split);
- ``reflectance_pct`` is not modelled: the mean over the hit subrays of 50 % for the object and 30 % for
  the table.

Per-zone bias (``zone_bias``): each zone's distance carries a constant offset [m], drawn once at
construction from a generator of its own (``zone_bias.seed``), as a real sensor's zones each range a little
long or short; ``zone_offsets_m`` holds them (the truth ``cell calibrate tof`` must find), and every zone
the common ``depth_offset_m`` (a calibration error, ``drivers.sim.errors``). A
``zone_correction`` file is applied after it, as the ``vl53l8cx`` backend does.

Random numbers come only from the generator given at construction; every frame draws exactly one normal
variate per zone, so a seed fixes the frame sequence exactly.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from drivers.clock import Clock
from drivers.depth.base import DepthFrame, SensorModel, ToFZones
from drivers.depth.config import SimToFConfig, ZoneBiasConfig
from drivers.depth.sim_base import SimDepthSensor
from drivers.depth.zone_correction import load_zone_correction
from drivers.sim.scene import HIT_OBJECT, HIT_TABLE, SimScene

Array = NDArray[np.float64]

STATUS_VALID: int = 5
STATUS_MERGED: int = 9
STATUS_NO_TARGET: int = 255

"""Default gap [m] between neighbouring sorted subray ranges above which a zone is a depth edge (status 9)."""

REFLECTANCE_OBJECT_PCT: float = 50.0
REFLECTANCE_TABLE_PCT: float = 30.0


def zone_directions(resolution: int, fov_deg: float, subrays: int = 1) -> Array:
    """Unit rays in the sensor frame, shape (resolution**2, subrays**2, 3), zones row-major from the
    top-left (row along +y, column along +x), subrays row-major inside each zone. ``subrays = 1`` gives
    the zones' central rays."""
    w = np.deg2rad(fov_deg) / resolution
    half = np.deg2rad(fov_deg) / 2.0
    offs = (np.arange(subrays) + 0.5) / subrays  # sub-cell centres in [0, 1]
    ang = -half + (np.arange(resolution)[:, None] + offs[None, :]) * w  # (res, sub) angles [rad]
    # axes: zone row i, zone col j, sub row a, sub col b
    ty = np.tan(ang)[:, None, :, None]
    tx = np.tan(ang)[None, :, None, :]
    shape = (resolution, resolution, subrays, subrays)
    d = np.stack([np.broadcast_to(tx, shape), np.broadcast_to(ty, shape), np.ones(shape)], axis=-1)
    d = d.reshape(resolution * resolution, subrays * subrays, 3)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def zone_offsets(bias: ZoneBiasConfig | None, n_zones: int) -> Array:
    """Each zone's constant range offset (n_zones,) [m] of the bias model ``bias`` (None: none), the same
    draw at every call (the module docstring)."""
    if bias is None:
        return np.zeros(n_zones)
    return bias.offset_std_m * np.random.default_rng(bias.seed).standard_normal(n_zones)


class SimToF(SimDepthSensor):
    """Simulated multizone ToF sensor, see the module docstring for the zone model.

    ``pose_source()`` returns the true T_base_sensor (4x4) at capture time; ``clock`` stamps frames;
    ``rng`` is the only source of noise. ``capture()`` returns a ``DepthFrame`` with ``zones`` (all
    zones, row-major) and ``points`` (N, 3) [m, sensor frame], one per zone with a target (status 5 or 9),
    in zone order; ``config.edge_gap_m`` [m] is the depth-edge threshold for status 9.
    """

    name = "sim-tof"

    def __init__(self, config: SimToFConfig, scene: SimScene, pose_source: Callable[[], Array],
                 clock: Clock, rng: np.random.Generator, depth_offset_m: float = 0.0) -> None:
        super().__init__(scene, pose_source, clock, rng, depth_offset_m)
        self.config = config
        self.edge_gap_m = config.edge_gap_m
        self._sub = zone_directions(config.resolution, config.fov_deg, config.subrays)  # (Z, S, 3)
        self._central = zone_directions(config.resolution, config.fov_deg, 1)[:, 0, :]  # (Z, 3)
        self._central.setflags(write=False)
        self.zone_offsets_m = zone_offsets(config.zone_bias, config.resolution ** 2)
        self._correction = (None if config.zone_correction is None
                            else load_zone_correction(config.zone_correction, config.resolution))

    @property
    def model(self) -> SensorModel:
        c = self.config
        return SensorModel(kind="tof", width=c.resolution, height=c.resolution, fov_x_deg=c.fov_deg,
                           fov_y_deg=c.fov_deg, range_min_m=c.range_min_m, range_max_m=c.range_max_m)

    @property
    def directions(self) -> Array:
        """Central unit ray of each zone (n_zones, 3), sensor frame, row-major (read-only)."""
        return self._central

    # -- capture ---------------------------------------------------------------------------------------
    def capture(self) -> DepthFrame:
        c = self.config
        T = self._begin_capture()
        n_zones, n_sub, _ = self._sub.shape
        dirs_base = self._sub.reshape(-1, 3) @ T[:3, :3].T
        hits = self._scene.cast(T[:3, 3], dirs_base)
        noise = self._rng.standard_normal(n_zones)

        t = hits.t.reshape(n_zones, n_sub)
        what = hits.what.reshape(n_zones, n_sub)
        valid = (t >= c.range_min_m) & (t <= c.range_max_m)
        k = valid.sum(axis=1)
        has_target = (k > 0) & (k / n_sub >= c.min_hit_fraction)

        ts = np.sort(np.where(valid, t, np.inf), axis=1)  # valid ranges first, ascending
        kk = np.maximum(k, 1)
        lo = np.take_along_axis(ts, ((kk - 1) // 2)[:, None], axis=1)[:, 0]
        hi = np.take_along_axis(ts, (kk // 2)[:, None], axis=1)[:, 0]
        median = 0.5 * (lo + hi)
        gaps = np.diff(np.where(np.isfinite(ts), ts, 0.0), axis=1)
        gap_ok = np.arange(n_sub - 1)[None, :] < (k - 1)[:, None]  # both neighbours valid
        max_gap = np.where(gap_ok, gaps, 0.0).max(axis=1, initial=0.0)
        tv = np.where(valid, t, 0.0)
        mean = tv.sum(axis=1) / kk
        std = np.sqrt(np.where(valid, (tv - mean[:, None]) ** 2, 0.0).sum(axis=1) / kk)
        refl = np.where(what == HIT_OBJECT, REFLECTANCE_OBJECT_PCT,
                        np.where(what == HIT_TABLE, REFLECTANCE_TABLE_PCT, 0.0))
        refl = np.where(valid, refl, 0.0).sum(axis=1) / kk

        sigma_noise = c.noise.sigma0_m + c.noise.k_per_m * np.where(has_target, median, 0.0) ** 2
        bias = self.zone_offsets_m + self.depth_offset_m
        distance = np.where(has_target, median + bias + sigma_noise * noise, np.nan)
        if self._correction is not None:
            distance = self._correction.apply(distance)
        sigma = np.where(has_target, sigma_noise + std, np.nan)
        status = np.full(n_zones, STATUS_NO_TARGET, dtype=np.uint8)
        status[has_target] = STATUS_VALID
        status[has_target & (max_gap > self.edge_gap_m)] = STATUS_MERGED
        nb_targets = has_target.astype(np.uint8)
        reflectance = np.where(has_target, refl, np.nan)

        zones = ToFZones(distance_m=distance, sigma_m=sigma, status=status, nb_targets=nb_targets,
                         reflectance_pct=reflectance, directions=self._central.copy())
        points = distance[has_target, None] * self._central[has_target]
        frame = DepthFrame(seq=self._next_seq(), timestamp=self._clock.now(), points=points, zones=zones)
        return frame
