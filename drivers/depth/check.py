"""Commissioning figures of a depth sensor from the frames it delivers (``cell sensor check``).

- frame rate [Hz]: frames delivered per second between the first and the last, on the host's monotonic
  clock; for the VL53L8CX also on the device's clock (its microsecond stamps, which do not include the
  link's latency jitter);
- share of valid zones (ToF: a target and a status among the valid ones) or of pixels with depth (RGB-D),
  over all frames;
- per-zone noise [m]: the standard deviation (ddof 1) of each zone's distance over the frames in which
  that zone was valid, NaN for a zone valid fewer than twice. Taken with the sensor and the scene still,
  it is the sensor's range noise (ST specifies a few mm at short range);
- the link counters of a serial sensor (CRC errors, sequence gaps and lost frames, ...), when it has them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from drivers.depth.base import DepthFrame
from drivers.depth.vl53l8cx.protocol import U32

Array = NDArray[np.float64]


@dataclass(frozen=True)
class CheckReport:
    """See the module docstring. ``zone_noise_m`` is (resolution, resolution) for a ToF sensor, else
    None; ``device_rate_hz`` None when the sensor has no device clock."""

    frames: int
    duration_s: float
    rate_hz: float
    device_rate_hz: float | None
    valid_share: float
    zone_noise_m: Array | None


@dataclass
class SensorCheck:
    """Accumulates frames for a :class:`CheckReport`; ``valid_statuses`` are the ToF statuses that count
    as valid."""

    valid_statuses: tuple[int, ...]
    _host_t: list[float] = field(default_factory=list)
    _device_us: list[int] = field(default_factory=list)
    _valid: int = 0
    _total: int = 0
    _distances: list[Array] = field(default_factory=list)

    @property
    def count(self) -> int:
        """Frames added so far."""
        return len(self._host_t)

    def add(self, frame: DepthFrame, host_t: float, device_timestamp_us: int | None = None) -> None:
        """One frame, received at ``host_t`` [s, monotonic]; ``device_timestamp_us`` its device stamp."""
        self._host_t.append(host_t)
        if device_timestamp_us is not None:
            self._device_us.append(device_timestamp_us)
        if frame.zones is not None:
            z = frame.zones
            ok = (z.nb_targets > 0) & np.isin(z.status, np.asarray(self.valid_statuses)) & (z.distance_m > 0)
            self._valid += int(ok.sum())
            self._total += ok.size
            self._distances.append(np.where(ok, z.distance_m, np.nan))
        elif frame.depth is not None:
            self._valid += int(np.count_nonzero(frame.depth > 0))
            self._total += frame.depth.size

    def report(self) -> CheckReport:
        n = len(self._host_t)
        span = self._host_t[-1] - self._host_t[0] if n > 1 else 0.0
        rate = (n - 1) / span if span > 0 else float("nan")
        device_rate = None
        if len(self._device_us) > 1:
            # device stamps wrap at 2**32 us; consecutive differences modulo 2**32 unwrap them
            stamps = np.asarray(self._device_us, dtype=np.int64)
            steps = np.diff(stamps) % U32
            total_s = float(steps.sum()) * 1e-6
            device_rate = (len(self._device_us) - 1) / total_s if total_s > 0 else float("nan")
        noise = None
        if self._distances:
            d = np.stack(self._distances)
            counts = np.sum(np.isfinite(d), axis=0)
            mean = np.nansum(d, axis=0) / np.maximum(counts, 1)
            var = np.nansum((d - mean) ** 2, axis=0) / np.maximum(counts - 1, 1)
            res = math.isqrt(d.shape[1])
            noise = np.where(counts >= 2, np.sqrt(var), np.nan).reshape(res, res)
        share = self._valid / self._total if self._total else 0.0
        return CheckReport(frames=n, duration_s=span, rate_hz=rate, device_rate_hz=device_rate,
                           valid_share=share, zone_noise_m=noise)
