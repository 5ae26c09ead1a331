"""Does a busy web side slow the control loop? A dry-run scan (config/dryrun-ur5e-peer.yaml: the UR5e
driver against the RTDE controller peer of tests/rtde_peer, a simulated ToF sensor, the wall clock) run
through a real ``cell serve`` subprocess (tests/service_process.ServedCell), as a user runs it: once alone
and once while ``--subscribers`` (50) clients follow the job's ``GET /api/v1/jobs/{id}/events`` stream to
its ``result`` event and ``--pollers`` (20) clients poll ``GET /api/v1/cell`` at ``--poll-hz`` (10) each,
in interleaved repeats (alone, loaded, alone, loaded, ...; ``--repeats``, default 3). Medians over the
repeats.

Each run: ``POST /api/v1/jobs`` (planner ``raster``, object ``horizontal_box``, the cell file's time
budget), wait for the job's ``result`` event, then read ``GET /api/v1/jobs/{id}`` → ``result``: its
``control`` section (tick periods in job time, which is the wall clock here, and overruns),
``safety.stops`` (a watchdog trip is a stop whose reason names the watchdog), ``wall_time_s`` and status.

- Start pose. The raster planner ends at its last view and does not go back home (the peer's joints after
  a run are not ``arm.home_joints_rad``), and the peer has no operation that sets its joints. So every run
  gets a fresh peer started at the home joints and, since a fresh peer listens on a fresh 127.0.0.N, a
  fresh copy of the cell file and a fresh ``cell serve`` (own data dir and keys): every run, alone or
  loaded, starts from the same state, and a cold service in both conditions. Nothing in the cell file but
  ``arm.host`` is changed.
- Waiting. One SSE stream (the benchmark's own, in both conditions: the smallest web activity that tells
  when the job ends) is followed to the ``result`` event; the job's result is read once after it.
- Load. asyncio and httpx.AsyncClient in this process, one client per simulated user, all on 127.0.0.1.
  It starts as soon as the job is submitted (subscribers may connect while it is queued) and stops when
  the job ends (pollers) or when their stream ends (subscribers, bounded by ``JOB_TIMEOUT_S``). Each
  poller keeps a schedule of absolute deadlines (t0 + k / hz, phases spread evenly over one period across
  the pollers); a request that ends after its next deadline makes it skip the slots it missed (counted
  as ``missed_slots``) rather than burst. Latency is from sending the request to reading the whole
  answer. The load generator shares the machine (and its cores) with the service, the job's worker and
  the peer: its own CPU use is part of what the control loop competes with. Each loaded run also reports
  the CPU time [s] the service process (the web side, not its job's worker) and this process (the
  clients) used from the POST to the result, how late this process's event loop woke at worst (when it
  is starved, every latency measured meanwhile grows by as much), and every run the machine's load
  average at its start.

A dry run's ~400 ticks put p99 at about the 5th longest period; the loop has a few long ticks of its own
in every run (at captures and move starts, ~7 overruns), so p99 mostly measures those, and a ratio near 1
says the web side added none longer. ``ticks_over_watchdog_deadline`` counts the ticks a watchdog trip is
made of (it trips after ``safety.watchdog.max_missed_deadlines`` in a row).

    .venv/bin/python benchmarks/service_load.py [--repeats 3] [--subscribers 50] [--pollers 20] [--poll-hz 10]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import yaml
from options import BenchmarkParser, at_least, count, first_paragraph, positive

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.jobs.progress import TICK_BUCKETS_S
from tests.rtde_peer import ControllerPeer
from tests.service_process import ServedCell

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config" / "dryrun-ur5e-peer.yaml"
OBJECT, PLANNER = "horizontal_box", "raster"
JOB_TIMEOUT_S = 180.0  # a bound on waiting for one job (submitted to result), not a timed check
SSE_READ_TIMEOUT_S = 30.0  # above the service's 15 s keep-alive
WATCHDOG = "watchdog"
GOAL_TICK_P99_RATIO = 1.2
GOAL_CELL_P99_MS = 50.0


@dataclass
class Load:
    """What the simulated users saw in one run."""

    poll_latencies_s: list[float] = field(default_factory=list)
    poll_errors: int = 0
    missed_slots: int = 0
    sse_events: int = 0
    sse_results: int = 0
    sse_errors: int = 0
    elapsed_s: float = 0.0  # from the POST to the job's result event
    service_cpu_s: float = 0.0  # the service process's own CPU time over it (not its job's worker)
    loadgen_cpu_s: float = 0.0  # this process's CPU time over it (the clients)
    loop_lag_max_s: float = 0.0  # the longest this event loop was late waking up (the clients starved)


LAG_PROBE_S = 0.01


async def lag_probe(done: asyncio.Event, load: Load) -> None:
    """How late this process's event loop wakes from a 10 ms sleep: when the clients themselves are
    starved of CPU, every latency they measure in that moment grows by as much."""
    while not done.is_set():
        t0 = time.perf_counter()
        await asyncio.sleep(LAG_PROBE_S)
        load.loop_lag_max_s = max(load.loop_lag_max_s, time.perf_counter() - t0 - LAG_PROBE_S)


def cpu_s(pid: int) -> float:
    """User + system CPU time [s] of process ``pid`` (not of its children)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def follow_events(client: httpx.AsyncClient, job_id: str) -> tuple[int, bool]:
    """Read the job's event stream to its end: (events received, whether the ``result`` came)."""
    n, result = 0, False
    async with client.stream("GET", f"/api/v1/jobs/{job_id}/events") as response:
        response.raise_for_status()
        async for line in response.aiter_lines():
            if line.startswith("event:"):
                n += 1
                result = result or line.split(":", 1)[1].strip() == "result"
    return n, result


async def subscriber(client: httpx.AsyncClient, job_id: str, load: Load) -> None:
    try:
        n, result = await follow_events(client, job_id)
    except httpx.HTTPError:
        load.sse_errors += 1
        return
    load.sse_events += n
    load.sse_results += result


async def poller(client: httpx.AsyncClient, hz: float, phase_s: float, done: asyncio.Event,
                 load: Load) -> None:
    period = 1.0 / hz
    t0 = time.perf_counter() + phase_s
    k = 0
    while not done.is_set():
        delay = t0 + k * period - time.perf_counter()
        if delay > 0:
            try:
                await asyncio.wait_for(done.wait(), delay)
                return
            except TimeoutError:
                pass
        start = time.perf_counter()
        try:
            response = await client.get("/api/v1/cell")
            ok = response.status_code == 200
        except httpx.HTTPError:
            ok = False
        end = time.perf_counter()
        if ok:
            load.poll_latencies_s.append(end - start)
        else:
            load.poll_errors += 1
        k_next = int((end - t0) / period) + 1  # the first deadline still ahead
        load.missed_slots += max(0, k_next - (k + 1))
        k = max(k + 1, k_next)


async def drive(served: ServedCell, loaded: bool, args: argparse.Namespace) -> tuple[dict[str, Any], Load]:
    """Submit the job, load the service if ``loaded``, wait for the job's end; its result and the load.
    Every client is made before the job is submitted: making an httpx client takes ~15 ms of CPU (its
    TLS context), which would otherwise stall this event loop, and the pollers' timings, at the start."""
    load = Load()
    sse_timeout = httpx.Timeout(10.0, read=SSE_READ_TIMEOUT_S)
    async with contextlib.AsyncExitStack() as stack:
        async def client(role: str, timeout: httpx.Timeout) -> httpx.AsyncClient:
            headers = {"Authorization": f"Bearer {served.keys[role]}"}
            return await stack.enter_async_context(httpx.AsyncClient(base_url=served.url, headers=headers,
                                                                     timeout=timeout))

        op = await client("operator", httpx.Timeout(30.0))
        watch = await client("viewer", sse_timeout)
        subscribers = [await client("viewer", sse_timeout) for _ in range(args.subscribers if loaded else 0)]
        pollers = [await client("viewer", httpx.Timeout(10.0)) for _ in range(args.pollers if loaded else 0)]
        assert served.proc is not None
        t0, cpu0, service0 = time.perf_counter(), time.process_time(), cpu_s(served.proc.pid)
        response = await op.post("/api/v1/jobs", json={"planner": PLANNER, "object": OBJECT})
        response.raise_for_status()
        job_id = response.json()["id"]
        done = asyncio.Event()
        tasks = [asyncio.create_task(subscriber(c, job_id, load)) for c in subscribers]
        tasks += [asyncio.create_task(poller(c, args.poll_hz, i / (len(pollers) * args.poll_hz), done, load))
                  for i, c in enumerate(pollers)]
        if loaded:
            tasks.append(asyncio.create_task(lag_probe(done, load)))
        try:
            _, seen = await asyncio.wait_for(follow_events(watch, job_id), JOB_TIMEOUT_S)
            if not seen:
                raise RuntimeError(f"job {job_id}: its event stream ended without a result")
            load.elapsed_s = time.perf_counter() - t0
            load.loadgen_cpu_s = time.process_time() - cpu0
            load.service_cpu_s = cpu_s(served.proc.pid) - service0
        finally:
            done.set()
            if tasks:
                _, pending = await asyncio.wait(tasks, timeout=SSE_READ_TIMEOUT_S)
                for task in pending:
                    task.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)
        job: dict[str, Any] = (await op.get(f"/api/v1/jobs/{job_id}")).json()
    return job, load


def run_once(data: dict[str, Any], home: list[float], loaded: bool, args: argparse.Namespace,
             folder: Path) -> tuple[dict[str, Any], Load]:
    """One run on a fresh peer (at home) and a fresh ``cell serve`` (see the module docstring)."""
    folder.mkdir(parents=True)
    load_avg = os.getloadavg()[0]  # the machine at the run's start (this script's previous run included)
    peer = ControllerPeer(q=home)
    served: ServedCell | None = None
    try:
        cell = {**data, "arm": {**data["arm"], "host": peer.host}}
        config = folder / "cell.yaml"
        config.write_text(yaml.safe_dump(cell, sort_keys=False))
        (folder / "data").mkdir()
        served = ServedCell(config, folder / "data")
        job, load = asyncio.run(drive(served, loaded, args))
    finally:
        if served is not None:  # the job's worker, the client, is gone before the peer stops
            served.close()
        peer.stop()
    result = job.get("result") or {}
    control = result.get("control") or {}
    stops = (result.get("safety") or {}).get("stops") or []
    row = {
        "condition": "loaded" if loaded else "alone",
        "status": job["status"], "termination": job["termination"],
        "wall_time_s": result.get("wall_time_s"),
        "n_ticks": control.get("n_ticks"),
        "tick_p50_ms": ms(control.get("period_p50_s")), "tick_p99_ms": ms(control.get("period_p99_s")),
        "tick_max_ms": ms(control.get("period_max_s")), "overruns": control.get("overruns"),
        "ticks_over_watchdog_deadline": over_deadline(control, data),
        "safety_stops": len(stops), "watchdog_trips": sum(WATCHDOG in s["reason"] for s in stops),
    }
    row |= {"load_avg_1min_before": round(load_avg, 2), "post_to_result_s": round(load.elapsed_s, 3),
            "service_cpu_s": round(load.service_cpu_s, 3), "loadgen_cpu_s": round(load.loadgen_cpu_s, 3)}
    if loaded:
        lat = np.asarray(load.poll_latencies_s) * 1e3
        row |= {"n_polls": int(lat.size), "poll_errors": load.poll_errors, "missed_slots": load.missed_slots,
                "api_cell_latency_p50_ms": round(float(np.percentile(lat, 50)), 3) if lat.size else None,
                "api_cell_latency_p99_ms": round(float(np.percentile(lat, 99)), 3) if lat.size else None,
                "n_sse_events": load.sse_events, "sse_results": load.sse_results,
                "sse_errors": load.sse_errors, "loadgen_loop_lag_max_ms": round(load.loop_lag_max_s * 1e3, 1)}
    return row, load


def over_deadline(control: dict[str, Any], data: dict[str, Any]) -> int | None:
    """Tick periods above the watchdog's deadline (``deadline_factor`` control periods), from the
    result's tick histogram when one of its bounds is that deadline (5 x 20 ms = 100 ms here); a trip
    needs ``max_missed_deadlines`` of them in a row."""
    deadline = data["safety"]["watchdog"]["deadline_factor"] / data["scan"]["control_rate_hz"]
    hist = control.get("histogram")
    bound = next((i for i, b in enumerate(TICK_BUCKETS_S) if abs(b - deadline) < 1e-9), None)
    return None if hist is None or bound is None else int(hist["count"] - hist["buckets"][bound])


def describe(i: int, row: dict[str, Any]) -> str:
    """One run in words."""
    text = (f"run {i + 1} {row['condition']:6s}: {row['status']}, tick p50 {row['tick_p50_ms']} ms, p99 "
            f"{row['tick_p99_ms']} ms, max {row['tick_max_ms']} ms, {row['overruns']} overruns of "
            f"{row['n_ticks']} ticks, {row['ticks_over_watchdog_deadline']} over the watchdog's deadline, "
            f"{row['watchdog_trips']} watchdog trips, job {row['wall_time_s']} s")
    if row["condition"] == "loaded":
        text += (f"; GET /cell p50 {row['api_cell_latency_p50_ms']} ms, p99 {row['api_cell_latency_p99_ms']} "
                 f"ms over {row['n_polls']} polls ({row['missed_slots']} slots missed, {row['poll_errors']} "
                 f"errors; the clients' loop up to {row['loadgen_loop_lag_max_ms']} ms late), "
                 f"{row['n_sse_events']} SSE events, {row['sse_results']} of the subscribers saw "
                 f"the result")
    return text + (f"; CPU over {row['post_to_result_s']} s: service {row['service_cpu_s']} s, clients "
                   f"{row['loadgen_cpu_s']} s")


def ms(seconds: float | None) -> float | None:
    return None if seconds is None else round(seconds * 1e3, 3)


def median(values: list[Any]) -> float | None:
    known = [v for v in values if v is not None]
    return round(float(statistics.median(known)), 4) if known else None


def condition(rows: list[dict[str, Any]]) -> dict[str, Any]:
    return {"tick_p50_ms": median([r["tick_p50_ms"] for r in rows]),
            "tick_p99_ms": median([r["tick_p99_ms"] for r in rows]),
            "tick_max_ms": median([r["tick_max_ms"] for r in rows]),
            "overruns": median([r["overruns"] for r in rows]),
            "watchdog_trips": median([r["watchdog_trips"] for r in rows]),
            "watchdog_trips_total": sum(r["watchdog_trips"] for r in rows),
            "ticks_over_watchdog_deadline_total": sum(r["ticks_over_watchdog_deadline"] or 0 for r in rows),
            "wall_time_s": median([r["wall_time_s"] for r in rows]),
            "completed": sum(r["status"] == "completed" for r in rows), "runs": len(rows)}


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--repeats", type=count, default=3, help="pairs of runs (alone, loaded)")
    parser.add_argument("--subscribers", type=at_least(0), default=50, help="SSE clients following the job")
    parser.add_argument("--pollers", type=at_least(0), default=20, help="clients polling GET /api/v1/cell")
    parser.add_argument("--poll-hz", type=positive, default=10.0, help="each poller's rate [Hz]")
    args = parser.parse_args()
    data = yaml.safe_load(CONFIG.read_text())
    home = data["arm"]["home_joints_rad"]
    rows: list[dict[str, Any]] = []
    latencies: list[float] = []
    with tempfile.TemporaryDirectory(prefix="service-load-") as tmp:
        for i in range(args.repeats):
            for loaded in (False, True):
                row, load = run_once(data, home, loaded, args, Path(tmp) / f"run{i}-{int(loaded)}")
                rows.append(row)
                latencies += load.poll_latencies_s
                print(describe(i, row), flush=True)
    alone = [r for r in rows if r["condition"] == "alone"]
    busy = [r for r in rows if r["condition"] == "loaded"]
    ratios = [b["tick_p99_ms"] / a["tick_p99_ms"] for a, b in zip(alone, busy, strict=True)
              if a["tick_p99_ms"] and b["tick_p99_ms"] is not None]
    ratio = median(ratios)
    lat = np.asarray(latencies) * 1e3
    p50 = round(float(np.percentile(lat, 50)), 3) if lat.size else None
    p99 = round(float(np.percentile(lat, 99)), 3) if lat.size else None
    trips = sum(r["watchdog_trips"] for r in rows)
    goals = {
        "tick_p99_ratio": {"value": ratio, "limit": GOAL_TICK_P99_RATIO,
                           "met": ratio is not None and ratio <= GOAL_TICK_P99_RATIO},
        "watchdog_trips": {"value": trips, "limit": 0, "met": trips == 0},
        "api_cell_latency_p99_ms": {"value": p99, "limit": GOAL_CELL_P99_MS,
                                    "met": p99 is not None and p99 <= GOAL_CELL_P99_MS},
    }
    figures = {
        "alone": condition(alone), "loaded": condition(busy),
        "tick_p99_ratio": ratio, "tick_p99_ratios": [round(r, 4) for r in ratios],
        "api_cell_latency_p50_ms": p50, "api_cell_latency_p99_ms": p99,
        "n_polls": int(lat.size), "n_sse_events": sum(r["n_sse_events"] for r in busy),
        "goals": goals,
        "repeats": args.repeats, "subscribers": args.subscribers, "pollers": args.pollers,
        "poll_hz": args.poll_hz, "cpus": os.cpu_count(), "load_avg_1min": round(os.getloadavg()[0], 2),
        "runs": rows,
    }
    a, b = figures["alone"], figures["loaded"]
    print(f"alone : tick p50 {a['tick_p50_ms']} ms, p99 {a['tick_p99_ms']} ms, {a['overruns']} overruns "
          f"(medians of {a['runs']})")
    print(f"loaded: tick p50 {b['tick_p50_ms']} ms, p99 {b['tick_p99_ms']} ms, {b['overruns']} overruns "
          f"(medians of {b['runs']})")
    for name, goal in goals.items():
        print(f"goal {name}: {goal['value']} (limit {goal['limit']}): {'met' if goal['met'] else 'NOT met'}")
    print(f"GET /api/v1/cell: p50 {p50} ms, p99 {p99} ms over {lat.size} polls; "
          f"{figures['n_sse_events']} SSE events received")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
