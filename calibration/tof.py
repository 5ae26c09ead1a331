"""``cell calibrate tof``: each zone's range bias and noise, measured on the flat table.

The arm holds the sensor looking straight down at the table beside the station at several heights
(``heights_m`` above the table, one flange orientation for all), ``frames_per_height`` frames each. Only
the flange's vertical steps are taken from the arm; the mount and the table height are not needed, so
the zone biases do not absorb a wrong mount. Model of zone z's distance in a frame at height step k:

    d = (h0 + dh_k) / (r_z . u) + b_z

with r_z the zone's central ray, u the unit direction from the sensor to the table along the table's
normal (sensor frame; two angles), h0 the sensor's height at the first step, dh_k the flange's reported
rise since then, and b_z the zone's bias. The heights make b_z separable from the geometry (a bias is
the same at every height, the geometry's term grows with it), all but one pattern: h0 / (r_z . u) and
b_z trade against each other, so the biases are taken with zero mean. A range offset common to all zones
is the mount's business: the known-shape calibration of the mount takes it in as a shift along the
optical axis. Least squares over the even frames; the
odd frames are held back to measure the mean absolute range error over the zones (each zone's mean
distance at each height against the model's range) before and after subtracting the biases. A zone's
noise is the standard deviation of its residuals. Zones of status 5 only (see ``calibration.views``).

A sensor that already applies a correction file is calibrated on top of it: the file written holds the
sum, so it replaces the old one.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from calibration.shape_fit import Array
from calibration.views import ZONE_STATUS_VALID, capture_views
from cell.config.models import CellConfig
from drivers.depth.config import SimToFConfig, VL53L8CXConfig
from drivers.depth.zone_correction import ZoneCorrection, load_zone_correction
from drivers.errors import CalibrationError
from drivers.sim.objects import EMPTY_TABLE
from drivers.transforms import look_at

DEFAULT_HEIGHTS_M = (0.15, 0.25, 0.35, 0.45)
DEFAULT_FRAMES_PER_HEIGHT = 10
ASIDE_M = 0.15
"""The spot looked at is this far from the station along -y of the base frame [m], off a part left there."""


@dataclass(frozen=True)
class ZoneFrames:
    """The ToF frames of a zone calibration: per frame the flange's reported height [m] (base z) and the
    zone distances [m] (NaN where not status 5), shape (F, Z); the zones' central rays (Z, 3)."""

    flange_z_m: Array
    distance_m: Array
    directions: Array


@dataclass(frozen=True)
class ZoneFit:
    """The correction, the sensor's height above the table at the first step [m] and the direction to
    the table (sensor frame), the held-back mean absolute range errors before and after [m], and the
    number of frames."""

    correction: ZoneCorrection
    height0_m: float
    toward_table: Array
    error_before_m: float
    error_after_m: float
    n_frames: int


def tof_views(config: CellConfig, heights_m: tuple[float, ...]) -> list[Array]:
    """Sensor poses straight down at ``heights_m`` [m] above the table beside the station."""
    x, y = config.station.xy_m[0], config.station.xy_m[1] - ASIDE_M
    z = config.station.table_z_m
    return [look_at(np.array([x, y, z + h]), np.array([x, y, z]), up_hint=np.array([1.0, 0.0, 0.0]))
            for h in heights_m]


def load_zone_frames(folder: Path) -> ZoneFrames:
    """The zone distances and flange heights of a job folder's frames."""
    heights, distances, directions = [], [], None
    for path in sorted((folder / "frames").glob("*.npz")):
        with np.load(path) as f:
            if "zone_status" not in f:
                raise CalibrationError(f"{path} holds no ToF zones: zone calibration needs a ToF sensor")
            d = np.where(f["zone_status"] == ZONE_STATUS_VALID, f["zone_distance_m"], np.nan)
            heights.append(float(f["T_base_flange"][2, 3]))
            distances.append(d.astype(np.float64))
            directions = np.array(f["zone_directions"], dtype=np.float64)
    if directions is None:
        raise CalibrationError(f"no frames in {folder}")
    return ZoneFrames(np.array(heights), np.stack(distances), directions)


def _toward(angles: Array) -> Array:
    u = np.array([np.tan(angles[0]), np.tan(angles[1]), 1.0])
    return u / np.linalg.norm(u)


def _model_range(frames: ZoneFrames, h0: float, angles: Array) -> Array:
    """The range (F, Z) [m] along each zone's ray to the table of the geometry (h0, angles)."""
    h = h0 + (frames.flange_z_m - frames.flange_z_m[0])
    return h[:, None] / (frames.directions @ _toward(angles))[None, :]


def _mean_abs_error(frames: ZoneFrames, rows: Array, expected: Array, offset: Array) -> float:
    """Mean over zones and heights of |the zone's mean corrected distance - the expected range|."""
    errors = []
    heights = np.round(frames.flange_z_m[rows], 4)
    for z_m in np.unique(heights):
        at = rows[heights == z_m]
        measured = np.nanmean(frames.distance_m[at], axis=0) - offset
        errors.append(np.abs(measured - expected[at[0]]))
    return float(np.nanmean(np.concatenate(errors)))


def fit_zone_bias(frames: ZoneFrames, resolution: int) -> ZoneFit:
    """Fit the model of the module docstring; ``CalibrationError`` with fewer than two heights or no
    valid zones."""
    n_zones = resolution * resolution
    if frames.distance_m.shape[1] != n_zones:
        raise CalibrationError(f"frames of {frames.distance_m.shape[1]} zones for a {resolution}x"
                               f"{resolution} sensor")
    if np.unique(np.round(frames.flange_z_m, 4)).size < 2:
        raise CalibrationError("the zone calibration needs frames at two heights at least")
    rows = np.arange(frames.distance_m.shape[0])
    fit_rows, held_rows = rows[rows % 2 == 0], rows[rows % 2 == 1]
    d = frames.distance_m[fit_rows]
    ok = np.isfinite(d)
    if not np.any(ok):
        raise CalibrationError("no zone saw the table (status 5) in any frame")
    sub = ZoneFrames(frames.flange_z_m[fit_rows], d, frames.directions)
    h_start = float(np.nanmedian(d))

    def biases(x: Array) -> Array:
        return np.concatenate([x[3:], [-np.sum(x[3:])]])  # zero mean

    def residuals(x: Array) -> Array:
        predicted = _model_range(sub, float(x[0]), x[1:3]) + biases(x)[None, :]
        return (d - predicted)[ok]

    x0 = np.concatenate([[h_start, 0.0, 0.0], np.zeros(n_zones - 1)])
    sol = least_squares(residuals, x0, x_scale="jac")
    h0, angles, offset = float(sol.x[0]), sol.x[1:3], biases(sol.x)
    seen = ok.any(axis=0)
    offset = np.where(seen, offset, 0.0)
    r = np.where(ok, d - _model_range(sub, h0, angles) - offset[None, :], np.nan)
    noise = np.where(seen, np.nanstd(r, axis=0), 0.0)
    expected = _model_range(frames, h0, angles)
    return ZoneFit(correction=ZoneCorrection(resolution=resolution, offset_m=offset, noise_m=noise),
                   height0_m=h0, toward_table=_toward(angles),
                   error_before_m=_mean_abs_error(frames, held_rows, expected, np.zeros(n_zones)),
                   error_after_m=_mean_abs_error(frames, held_rows, expected, offset),
                   n_frames=int(rows.size))


def calibrate_zones(config: CellConfig, config_path: str, *, folder: Path,
                    heights_m: tuple[float, ...] = DEFAULT_HEIGHTS_M,
                    frames_per_height: int = DEFAULT_FRAMES_PER_HEIGHT, seed: int = 0) -> ZoneFit:
    """Run the zone calibration's views as a job into ``folder`` (the table must be flat and clear
    there) and fit the per-zone biases; when the sensor already applies a correction, the result holds
    the sum (it replaces that file)."""
    sensor = config.sensor
    if not isinstance(sensor, SimToFConfig | VL53L8CXConfig):
        raise CalibrationError(f"zone calibration is for a multizone ToF sensor, not {sensor.type}")
    capture_views(config, config_path, tof_views(config, heights_m), target_object=EMPTY_TABLE,
                  folder=folder, seed=seed, frames_per_view=frames_per_height)
    fit = fit_zone_bias(load_zone_frames(folder), sensor.resolution)
    if sensor.zone_correction is None:
        return fit
    applied = load_zone_correction(sensor.zone_correction, sensor.resolution)
    return dataclasses.replace(fit, correction=dataclasses.replace(
        fit.correction, offset_m=fit.correction.offset_m + applied.offset_m))


def zone_record(fit: ZoneFit, config_path: str, folder: Path) -> dict[str, Any]:
    """What the correction file keeps beside the table, for the record."""
    return {"method": "flat table at several heights", "config": config_path, "views_dir": str(folder),
            "n_frames": fit.n_frames, "error_before_mm": round(fit.error_before_m * 1e3, 4),
            "error_after_mm": round(fit.error_after_m * 1e3, 4)}
