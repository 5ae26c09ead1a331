"""What a running job reports: a progress snapshot at each perception update, and its control-loop ticks.

:class:`JobProgress` is built on the control thread after each perception update (cheap: a few numbers,
never the cloud) and handed to ``run_scan``'s ``on_progress``; the service streams it to its clients.
:class:`ControlTicks` counts the control loop's tick periods in job time (the wall clock on a hardware
arm, the simulated clock in sim), as the watchdog judges them.
"""

from __future__ import annotations

import bisect
import itertools
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from cell.control.decimation import DecimatedSeries
from cell.perception.entropy_form import EntropyForm
from drivers.transforms import quat_xyzw

TICK_BUCKETS_S = (0.001, 0.002, 0.004, 0.006, 0.008, 0.01, 0.015, 0.02, 0.03, 0.05, 0.1, 0.25, 0.5, 1.0)
"""Upper bounds [s] of the tick-period histogram (Prometheus ``le`` buckets; +Inf is implied): control
periods of 2 ms (500 Hz RTDE) to 20 ms (50 Hz), and the late ticks a watchdog counts."""

TICK_EDGE_TOLERANCE_S = 1e-9
"""A period up to this much [s] over a bucket's bound counts in that bucket: a period is the difference
of two job times that are sums of control periods, and their float arithmetic puts many ticks of a perfect
10 ms loop just above 0.01 s (0.010000000000000009 s). That error is at most an ulp of the job
time [s] (1.5e-11 s a day into a job), far below 1 ns, and 1 ns is a millionth of the narrowest bucket
(1 ms): no tick the loop really made late moves bucket."""

OVERRUN_FACTOR = 1.5
"""A tick is an overrun when its period exceeds the control period by more than half a period: it then
lands nearer the next slot than its own, so one command period was lost."""


@dataclass
class ControlTicks:
    """Tick periods [s] of one job's control loop, in job time. ``period_s`` is the configured one. The
    histogram, the count, the sum and the longest period are kept exactly as the ticks come, so that
    reading them on the control thread costs the same at any point of a long job; the periods themselves,
    for the percentiles, in a :class:`DecimatedSeries` (bounded memory: a job longer than its capacity has
    p50 and p99 from evenly spaced ticks)."""

    period_s: float
    periods: DecimatedSeries[float] = field(default_factory=DecimatedSeries)
    overruns: int = 0
    _last: float | None = None
    _per_bucket: list[int] = field(default_factory=lambda: [0] * len(TICK_BUCKETS_S))
    _sum_s: float = 0.0
    _max_s: float = 0.0

    def record(self, t: float) -> None:
        """A control tick at job time ``t`` [s]."""
        if self._last is not None:
            dt = t - self._last
            self.periods.append(dt)
            self._sum_s += dt
            self._max_s = max(self._max_s, dt)
            bucket = bisect.bisect_left(TICK_BUCKETS_S, dt - TICK_EDGE_TOLERANCE_S)
            if bucket < len(TICK_BUCKETS_S):
                self._per_bucket[bucket] += 1
            if dt > OVERRUN_FACTOR * self.period_s:
                self.overruns += 1
        self._last = t

    def histogram(self) -> dict[str, Any]:
        """Cumulative counts per ``TICK_BUCKETS_S`` bound, the count, sum [s] and overruns."""
        return {"buckets": list(itertools.accumulate(self._per_bucket)), "count": self.periods.count,
                "sum_s": self._sum_s, "overruns": self.overruns}

    def summary(self) -> dict[str, Any]:
        """The ``control`` section of result.json: tick count, period p50 / p99 / max [s], overruns and
        the histogram."""
        stats: dict[str, float | None] = dict.fromkeys(("period_p50_s", "period_p99_s", "period_max_s"))
        if self.periods:
            p50, p99 = np.percentile(self.periods.records(), [50, 99])
            stats = {"period_p50_s": round(float(p50), 6), "period_p99_s": round(float(p99), 6),
                     "period_max_s": round(self._max_s, 6)}
        return {"period_s": self.period_s, "n_ticks": self.periods.count + (self._last is not None), **stats,
                "overruns": self.overruns, "histogram": self.histogram()}


def xyz_m(v: np.ndarray) -> tuple[float, float, float]:
    """A point (3,) [m] as JSON-ready floats, rounded to 1 um."""
    return round(float(v[0]), 6), round(float(v[1]), 6), round(float(v[2]), 6)


def quat_of(T: np.ndarray) -> tuple[float, float, float, float]:
    """The rotation of a 4x4 pose as a quaternion (x, y, z, w), rounded to 1e-6."""
    q = [round(float(v), 6) for v in quat_xyzw(T)]
    return q[0], q[1], q[2], q[3]


@dataclass(frozen=True)
class JobProgress:
    """A running job after a perception update. Base frame, SI units: job time ``t_s`` [s], the sensor
    pose (``sensor_xyz_m``, quaternion ``sensor_quat_xyzw``), the sensor's path so far [m], H_ROI [nats]
    (eq. 12 in the form the servo planners' termination judges, ``planners.vs.objective.entropy``; None
    before an object is found) and that form ``h_roi_entropy``, coverage [%] against the ground truth
    (sim and dry runs; None otherwise: eq. 13's coverage of the cloud so far before registering the ground
    truth to it, ``cell.perception.metrics.CloudCoverage``, not the result's registered figure), the box
    (min, max) of every ROI so far [m], the accumulated cloud's size, the wall time perception took for
    the frame [s], the planner's own figures, and the tick histogram so far."""

    t_s: float
    n_captures: int
    sensor_xyz_m: tuple[float, float, float]
    sensor_quat_xyzw: tuple[float, float, float, float]
    path_length_m: float
    h_roi: float | None
    h_roi_entropy: EntropyForm
    coverage_pct: float | None
    roi_box_m: tuple[tuple[float, float, float], tuple[float, float, float]] | None
    n_cloud_points: int
    perception_cycle_s: float | None
    planner: dict[str, float | int | str | None]
    ticks: dict[str, Any]

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return asdict(self)
