"""``cell calibrate table``: the table plane (height and tilt) and the station, from a short scan.

Views: one straight down over the station and ``ring`` more around it at ``RING_ELEVATION_DEG``, all at
the cell's ``scan.standoff_m``, run as a job (``calibration.views``). Every frame's points go to the base
frame with the arm's reported flange pose and the cell file's mount. The plane z = a x + b y + c is
fitted by least squares first to the points of the table's height band, then again without the points
more than ``TRIM_SIGMAS`` robust standard deviations off the plane (a part on the table, the table's
edge), until nothing changes. The table is the lowest extended plane under the views: everything else
the views see stands on it, so its band is the lowest ``SEED_BAND_M`` of height that holds at least
``SEED_SHARE`` of the points (fewer are stray points below it). Neither a first fit to every point nor
one to the points about their median height does: the views of the simulated Franka cell's 10 cm cube, a
tenth of the points, pulled the first up and tilted it, and the trimming then converged onto the cube's
top; the 0.30 x 0.20 m box fills most of the views, and the median lay on its top (the table found 0.1 m
high, no part on it). Reported against the cell file: the table's height at the
station (``station.table_z_m``), its tilt from the base frame's x-y plane [deg] and its direction, and,
when points stand more than ``ABOVE_M`` and ``ABOVE_SIGMAS`` residual standard deviations above the
plane (a part placed on the station's mark), the centre of those points (of what the views saw of the
part, so a coarse sensor's figure leans towards the sides it saw) against ``station.xy_m``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration.shape_fit import Array, robust_std
from calibration.views import capture_views, load_views
from cell.config.models import CellConfig
from drivers.errors import CalibrationError
from drivers.transforms import look_at, transform_points

RING_ELEVATION_DEG = 60.0
TRIM_SIGMAS = 3.0
ABOVE_M = 0.01
ABOVE_SIGMAS = 4.0
MAX_ROUNDS = 10
MIN_POINTS = 10
"""The fewest points of the table a fit is made from."""
SEED_BAND_M = 0.02
"""The height band [m] the table's first fit starts from: it holds the table's points under a ToF's
range noise (about 5 mm, one standard deviation) and a table's tilt of a few tenths of a degree over the
views' footprint, and a part the cell scans (some centimetres tall or more) stands above it."""
SEED_SHARE = 0.01
"""The least share of the points the table's band holds: stray points below the table (range noise
tails, multipath at a part's foot) are fewer; the table seen around a part holds more (5 % of the RGB-D
Franka cell's points around the 0.30 x 0.20 m box, the least of the shipped targets; 16 % on the ToF
cell)."""


@dataclass(frozen=True)
class TableFit:
    """The plane z = a x + b y + c (``coefficients`` (a, b, c)) [m, base frame], its RMS residual [m]
    and points, and the centre (x, y) [m] of what stands on it (None: nothing)."""

    coefficients: Array
    residual_m: float
    n_points: int
    part_xy_m: Array | None


def table_views(config: CellConfig, ring: int) -> list[Array]:
    """Straight down over the station, then ``ring`` views around it, at ``scan.standoff_m``."""
    st = config.station
    target = np.array([st.xy_m[0], st.xy_m[1], st.table_z_m])
    d = config.scan.standoff_m
    views = [look_at(target + np.array([0.0, 0.0, d]), target, up_hint=np.array([1.0, 0.0, 0.0]))]
    el = np.deg2rad(RING_ELEVATION_DEG)
    for az in np.pi + 2.0 * np.pi * np.arange(ring) / max(ring, 1):
        views.append(look_at(target + d * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                                    np.sin(el)]), target))
    return views


def _lowest_band(z: Array) -> NDArray[np.bool_]:
    """Which heights ``z`` [m] lie in the lowest ``SEED_BAND_M`` band holding ``SEED_SHARE`` of them (at
    least the 10 points a fit takes)."""
    order = np.sort(z)
    in_band = np.searchsorted(order, order + SEED_BAND_M, side="right") - np.arange(order.size)
    bottom = order[int(np.argmax(in_band >= max(SEED_SHARE * order.size, MIN_POINTS)))]
    return (z >= bottom) & (z <= bottom + SEED_BAND_M)


def fit_table(points_base: Array) -> TableFit:
    """The trimmed least-squares plane of the module docstring; ``CalibrationError`` with too few
    points."""
    if points_base.shape[0] < MIN_POINTS:
        raise CalibrationError(f"only {points_base.shape[0]} points of the table were measured")
    A = np.column_stack([points_base[:, 0], points_base[:, 1], np.ones(points_base.shape[0])])
    z = points_base[:, 2]
    keep = _lowest_band(z)
    coef = np.zeros(3)
    for _ in range(MAX_ROUNDS):
        coef = np.linalg.lstsq(A[keep], points_base[keep, 2], rcond=None)[0]
        r = points_base[:, 2] - A @ coef
        sigma = robust_std(r[keep])
        new = np.abs(r) <= max(TRIM_SIGMAS * sigma, 1e-4)
        if np.array_equal(new, keep):
            break
        keep = new
    r = points_base[:, 2] - A @ coef
    residual = float(np.sqrt(np.mean(r[keep] ** 2)))
    above = r > max(ABOVE_M, ABOVE_SIGMAS * residual)
    part = points_base[above, :2].mean(axis=0) if np.count_nonzero(above) >= 3 else None
    return TableFit(coefficients=coef, residual_m=residual,
                    n_points=int(np.count_nonzero(keep)), part_xy_m=part)


def calibrate_table(config: CellConfig, config_path: str, *, folder: Path, ring: int = 4,
                    target_object: str = "none", seed: int = 0) -> TableFit:
    """Run the table views as a job into ``folder`` and fit the plane (``target_object``: what stands on
    the station in sim, see ``capture_views``)."""
    capture_views(config, config_path, table_views(config, ring), target_object=target_object,
                  folder=folder, seed=seed)
    T_mount = config.mount.matrix()
    points = [transform_points(v.T_base_flange @ T_mount, v.points_sensor) for v in load_views(folder)]
    if not points:
        raise CalibrationError("no view of the table was captured")
    return fit_table(np.concatenate(points))


def table_report(fit: TableFit, config: CellConfig) -> dict[str, Any]:
    """The fit against the cell file: height at the station, tilt and its direction, the part's centre."""
    a, b, c = fit.coefficients
    x, y = config.station.xy_m
    height = a * x + b * y + c
    report: dict[str, Any] = {
        "table_z_at_station_m": round(float(height), 6), "cell_file_table_z_m": config.station.table_z_m,
        "table_z_difference_mm": round(float(height - config.station.table_z_m) * 1e3, 3),
        "tilt_deg": round(float(np.degrees(np.arctan(np.hypot(a, b)))), 4),
        "tilt_direction_deg": round(float(np.degrees(np.arctan2(b, a))), 2),
        "residual_mm": round(fit.residual_m * 1e3, 4), "n_points": fit.n_points,
        "cell_file_station_xy_m": list(config.station.xy_m), "part_xy_m": None, "station_difference_mm": None,
    }
    if fit.part_xy_m is not None:
        report["part_xy_m"] = np.round(fit.part_xy_m, 5).tolist()
        report["station_difference_mm"] = np.round((fit.part_xy_m - np.array([x, y])) * 1e3, 2).tolist()
    return report
