"""``cell calibrate compare A B``: how far two mount calibrations (their JSON results) are apart, and
whether the difference is within what their uncertainties allow."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from calibration.mount import pose_difference
from cell.config.models import PoseConfig
from drivers.errors import CalibrationError

CONSISTENT_SIGMAS = 3.0
"""Two calibrations agree when each axis differs by at most this many combined standard deviations."""


def read_result(path: Path) -> dict[str, Any]:
    """A calibration result written by ``cell calibrate mount``; ``CalibrationError`` (one line) when
    ``path`` cannot be read, is no JSON, holds no ``mount`` section (a job's result.json) or a mount that is
    not a pose."""
    try:
        data = json.loads(path.read_bytes())
    except FileNotFoundError:
        raise CalibrationError(f"cannot read {path}: no such file") from None
    except OSError as exc:
        raise CalibrationError(f"cannot read {path}: {exc.strerror or exc}") from None
    except ValueError as exc:  # not JSON, or not text
        raise CalibrationError(f"{path} is not a mount calibration result: not JSON ({exc})") from None
    if not isinstance(data, dict) or "mount" not in data:
        raise CalibrationError(f"{path} has no 'mount' section: it is not a mount calibration result (a "
                               "job's result.json?); cell calibrate mount --out writes one")
    try:
        PoseConfig.model_validate(data["mount"])
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, ('mount', *e['loc'])))}: {e['msg']}" for e in exc.errors())
        raise CalibrationError(f"{path} is not a mount calibration result: {problems}") from None
    return data


def compare_results(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """B's mount less A's: per axis (translation [mm] in the flange frame, roll-pitch-yaw [deg]), the
    distance [mm] and the rotation angle [deg] between them, and, when both carry their standard
    deviations, whether every axis differs by at most ``CONSISTENT_SIGMAS`` combined ones."""
    Ta, Tb = PoseConfig(**a["mount"]).matrix(), PoseConfig(**b["mount"]).matrix()
    d_mm = (Tb[:3, 3] - Ta[:3, 3]) * 1e3
    d_deg = np.asarray(b["mount"]["rpy_deg"], dtype=float) - np.asarray(a["mount"]["rpy_deg"], dtype=float)
    d_deg = (d_deg + 180.0) % 360.0 - 180.0
    distance_m, angle_deg = pose_difference(Ta, Tb)
    out: dict[str, Any] = {
        "delta_xyz_mm": np.round(d_mm, 4).tolist(), "delta_rpy_deg": np.round(d_deg, 5).tolist(),
        "distance_mm": round(distance_m * 1e3, 4), "angle_deg": round(angle_deg, 5), "consistent": None,
    }
    if all(k in r for r in (a, b) for k in ("std_mm", "std_deg")):
        s_mm = np.hypot(np.asarray(a["std_mm"], dtype=float), np.asarray(b["std_mm"], dtype=float))
        s_deg = np.hypot(np.asarray(a["std_deg"], dtype=float), np.asarray(b["std_deg"], dtype=float))
        out["consistent"] = bool(np.all(np.abs(d_mm) <= CONSISTENT_SIGMAS * s_mm) and
                                 np.all(np.abs(d_deg) <= CONSISTENT_SIGMAS * s_deg))
    return out
