"""A multizone ToF sensor's per-zone range correction: the file ``cell calibrate tof`` writes and the
``vl53l8cx`` and ``sim-tof`` backends apply (``sensor.zone_correction: FILE``).

Each zone's reported distance [m, along its central ray] is corrected by subtracting the zone's measured
bias: ``d_corrected = d_reported - offset_m[zone]``, zones row-major from the top-left zone as seen in the
sensor frame (the order of ``ToFZones``). ``noise_m`` is each zone's measured range noise (one standard
deviation [m]), kept for the record; it changes nothing.

File (JSON): ``{"resolution": 8, "offset_m": [64 floats], "noise_m": [64 floats], ...}``; any further keys
(date, method, distances) are kept by the writer and ignored by the reader.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.errors import ConfigError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ZoneCorrection:
    """Per-zone range bias ``offset_m`` and noise ``noise_m`` (resolution**2,) [m], row-major."""

    resolution: int
    offset_m: Array
    noise_m: Array

    def apply(self, distance_m: Array) -> Array:
        """``distance_m`` (n_zones,) [m] less each zone's offset (NaN stays NaN)."""
        if distance_m.shape != self.offset_m.shape:
            raise ValueError(f"a zone correction for {self.resolution}x{self.resolution} zones cannot "
                             f"correct {distance_m.shape[0]} zones")
        return distance_m - self.offset_m

    def as_dict(self, **extra: Any) -> dict[str, Any]:
        return {"resolution": self.resolution, "offset_m": np.round(self.offset_m, 6).tolist(),
                "noise_m": np.round(self.noise_m, 6).tolist(), **extra}


def write_zone_correction(correction: ZoneCorrection, path: Path, **extra: Any) -> None:
    """Write ``correction`` (and ``extra`` keys for the record) as JSON to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(correction.as_dict(**extra), indent=2) + "\n")


def load_zone_correction(path: str | Path, resolution: int) -> ZoneCorrection:
    """Read a correction file for a sensor running ``resolution`` x ``resolution`` zones; raises
    ``ConfigError`` naming the file for an unreadable file, a resolution that differs or a bad table."""
    where = Path(path)
    try:
        data = json.loads(where.read_text())
    except (OSError, ValueError) as exc:
        raise ConfigError(f"cannot read the zone correction: {exc}", file=str(where),
                          field="sensor.zone_correction") from None
    n = resolution * resolution
    try:
        res = int(data["resolution"])
        offset = np.asarray(data["offset_m"], dtype=np.float64)
        noise = np.asarray(data["noise_m"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"not a zone correction (needs resolution, offset_m, noise_m): {exc}",
                          file=str(where), field="sensor.zone_correction") from None
    if res != resolution:
        raise ConfigError(f"the correction is for {res}x{res} zones, the sensor runs "
                          f"{resolution}x{resolution}", file=str(where), field="sensor.zone_correction")
    if offset.shape != (n,) or noise.shape != (n,) or not np.all(np.isfinite(offset)):
        raise ConfigError(f"offset_m and noise_m must hold {n} finite values", file=str(where),
                          field="sensor.zone_correction")
    offset.setflags(write=False)
    noise.setflags(write=False)
    return ZoneCorrection(resolution=res, offset_m=offset, noise_m=noise)
