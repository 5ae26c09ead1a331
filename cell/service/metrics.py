"""The service's Prometheus metrics (names in base units, labels for what varies, never a job id).

- ``cell_jobs{status}``: the cell's jobs in the store by status (read at each scrape; no samples when the
  store does not answer or answers damaged, so that the rest still scrapes, ``cell_store_damaged`` with it);
- ``cell_queue_length``: jobs waiting behind the running one;
- ``cell_queue_held``: 1 while queued jobs do not start until someone acts, 0 otherwise;
- ``cell_store_damaged``: 1 once the service found its job store's data damaged (``Store.damaged``, cleared
  by a restart after a restore), 0 otherwise;
- ``cell_scan_duration_seconds{planner}``: job time of each finished scan (histogram);
- ``cell_control_tick_period_seconds``: the control loop's tick periods in job time, over every job the
  service has run since it started and the running one (histogram, ``cell.jobs.progress.TICK_BUCKETS_S``);
- ``cell_control_tick_overruns_total``: ticks more than half a period late (``OVERRUN_FACTOR``);
- ``cell_perception_cycle_seconds``: wall time perception took per frame (histogram, from progress);
- ``cell_stop_requests_total``: stop requests the service passed on to a running job;
- ``cell_event_stream_clients``: clients following a job's events now.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily
from prometheus_client.registry import Collector

from cell.jobs.progress import TICK_BUCKETS_S
from drivers.errors import StoreError

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
SCAN_BUCKETS_S = (5.0, 10.0, 20.0, 30.0, 45.0, 60.0, 90.0, 120.0, 180.0, 300.0, 600.0)
PERCEPTION_BUCKETS_S = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


class TickTotals:
    """The tick histograms of finished jobs added up, plus the running job's latest."""

    def __init__(self) -> None:
        self.finished = self._empty()
        self.running: dict[str, Any] | None = None

    @staticmethod
    def _empty() -> dict[str, Any]:
        return {"buckets": [0] * len(TICK_BUCKETS_S), "count": 0, "sum_s": 0.0, "overruns": 0}

    def job_ended(self, ticks: dict[str, Any] | None) -> None:
        """Add a job's final histogram (None: the job never ticked, or its worker died)."""
        final = ticks or self.running
        self.running = None
        if final is None:
            return
        self.finished = self._added(self.finished, final)

    @staticmethod
    def _added(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
        return {"buckets": [x + y for x, y in zip(a["buckets"], b["buckets"], strict=True)],
                "count": a["count"] + b["count"], "sum_s": a["sum_s"] + b["sum_s"],
                "overruns": a["overruns"] + b["overruns"]}

    def total(self) -> dict[str, Any]:
        return self.finished if self.running is None else self._added(self.finished, self.running)


class _LiveCollector(Collector):
    """What is read at scrape time: the store's counts, the queue and whether it is held, whether the
    store was found damaged, the tick totals."""

    def __init__(self, counts: Callable[[], dict[str, int]], queue_length: Callable[[], int],
                 held: Callable[[], bool], damaged: Callable[[], bool], ticks: TickTotals) -> None:
        self._counts = counts
        self._queue_length = queue_length
        self._held = held
        self._damaged = damaged
        self._ticks = ticks

    def collect(self) -> Iterator[Any]:
        jobs = GaugeMetricFamily("cell_jobs", "The cell's jobs in the store, by status.", labels=["status"])
        try:
            counts = self._counts()
        except StoreError:  # /readyz and cell_store_damaged say what is wrong with it; the rest still counts
            counts = {}
        for status, n in sorted(counts.items()):
            jobs.add_metric([status], n)
        yield jobs
        yield GaugeMetricFamily("cell_queue_length", "Jobs waiting behind the running one.",
                                value=self._queue_length())
        # 0/1: the reason is free text (it names jobs and stops), unbounded as a label; /api/v1/cell says it
        yield GaugeMetricFamily("cell_queue_held", "1 while no queued job starts until someone acts (an "
                                "operator's resume, an arm recovery, a restart): GET /api/v1/cell says why.",
                                value=int(self._held()))
        yield GaugeMetricFamily("cell_store_damaged", "1 once the job store's data was found damaged: no job "
                                "starts until it is restored from a backup and the service restarted.",
                                value=int(self._damaged()))
        t = self._ticks.total()
        yield HistogramMetricFamily(
            "cell_control_tick_period_seconds", "Control-loop tick periods in job time, all jobs.",
            buckets=[*((repr(b), n) for b, n in zip(TICK_BUCKETS_S, t["buckets"], strict=True)),
                     ("+Inf", t["count"])], sum_value=t["sum_s"])
        overruns = CounterMetricFamily("cell_control_tick_overruns", "Ticks more than half a period late.")
        overruns.add_metric([], t["overruns"])
        yield overruns


class ServiceMetrics:
    """The registry the service reports through ``GET /metrics``."""

    def __init__(self, counts: Callable[[], dict[str, int]], queue_length: Callable[[], int],
                 held: Callable[[], bool], damaged: Callable[[], bool]) -> None:
        self.registry = CollectorRegistry()
        self.ticks = TickTotals()
        self.registry.register(_LiveCollector(counts, queue_length, held, damaged, self.ticks))
        self.scan_duration = Histogram("cell_scan_duration_seconds", "Job time of finished scans.",
                                       ["planner"], buckets=SCAN_BUCKETS_S, registry=self.registry)
        self.perception_cycle = Histogram("cell_perception_cycle_seconds", "Perception wall time per frame.",
                                          buckets=PERCEPTION_BUCKETS_S, registry=self.registry)
        self.stop_requests = Counter("cell_stop_requests", "Stop requests passed on to a running job.",
                                     registry=self.registry)
        self.sse_clients = Gauge("cell_event_stream_clients", "Clients following a job's events.",
                                 registry=self.registry)

    def render(self) -> bytes:
        """The Prometheus text format."""
        return generate_latest(self.registry)
