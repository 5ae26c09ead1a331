"""The same sim scan through the service and through ``cell scan``: does the service take at most 10 % longer?

The default sim scan (config/sim-franka-rgbd.yaml, VS-Local, the bunny, seed 0, a ``--max-time`` of 30 s
of sim time to keep it short) run ``--repeats`` times (3) each way, interleaved, the order alternating
from one repeat to the next (CLI then service, service then CLI, ...: ``benchmarks/interleaved.py``) so
that neither way always runs first on a cold cache; a ratio is the median of the repeats' own ratios
(service / CLI of one repeat), with their range, and the goal is judged on it:

- ``cell scan``: ``.venv/bin/cell scan --out DIR ...`` as a subprocess, timed from its launch to its exit
  (what a user at a shell waits);
- the service: ``POST /api/v1/jobs`` to one ``cell serve`` (tests/service_process.ServedCell) started
  before the first repeat and kept running, timed from the POST to the job's ``completed`` state seen on
  its ``GET /api/v1/jobs/{id}/events`` stream (what a client of the service waits; the stream is opened
  right after the POST and replays the job's events from the first).

The CLI's time includes a process start (Python, imports, the cell file); the service's mostly does not:
with ``service.warm_worker`` (true by default, and not set otherwise by the cell file) the job runs on
the spare worker process the service started ahead (at its start for the first job, beside the previous
job for the others: a sim cell warms its spare while a job runs), its libraries imported by the POST;
the next job's spare starts while this job runs and competes with it for the cores. Both times include
writing the job folder. The service's time also includes queueing, the worker's report lines and the SSE
stream.

Also each job's own ``wall_time_s`` from its result.json (from the job's start to its end, without the process
start) and the ratio of those. Every ratio (``ratio_service_over_cli``, ``job_wall_time_ratio``,
``cpu_ratio``) is the median of the repeats' own ratios, its ``*_range`` their least and greatest. The sim is
deterministic: the two ways' result.json must agree on ``n_captures``, ``sim_time_s`` and ``metrics``, and are
checked to. And the CPU time [s] of each job's process (the CLI's; the service's worker, counted in the
service's children once it was waited for) and of the service itself meanwhile: a job this size uses more than
one core, so its wall time moves with whatever else runs on the machine; its CPU time much less. Each run
records the 1-minute load average at its start.

    nice .venv/bin/python benchmarks/service_vs_scan.py [--repeats 4] [--max-time 30]
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from interleaved import compared, in_turn
from options import BenchmarkParser, count, first_paragraph, positive

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.cli.client import parse_events
from tests.service_process import ServedCell

REPO = Path(__file__).resolve().parents[1]
CELL = REPO / ".venv" / "bin" / "cell"
CONFIG = REPO / "config" / "sim-franka-rgbd.yaml"
OBJECT, PLANNER, SEED = "bunny", "vs-local", 0
GOAL_RATIO = 1.10  # the service takes at most 10 % longer than the CLI
JOB_TIMEOUT_S = 600.0  # a bound on waiting for one job, not a timed check
REAP_TIMEOUT_S = 10.0  # a bound on waiting for the service to reap an ended job's worker
SAME = ("n_captures", "sim_time_s", "metrics")


def children_cpu_s() -> float:
    """User + system CPU time [s] of this process's ended (waited-for) children."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def cpu_s(pid: int) -> tuple[float, float]:
    """User + system CPU time [s] of process ``pid`` and of its ended (waited-for) children."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    tick = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / tick, (int(fields[13]) + int(fields[14])) / tick


def run_cli(out: Path, max_time_s: float) -> tuple[float, dict[str, Any], dict[str, float]]:
    """``cell scan`` into ``out``: (seconds from launch to exit, its result.json, its CPU time [s])."""
    cmd = [str(CELL), "scan", "--config", str(CONFIG), "--object", OBJECT, "--planner", PLANNER,
           "--seed", str(SEED), "--max-time", f"{max_time_s:g}", "--out", str(out)]
    cpu0 = children_cpu_s()
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=JOB_TIMEOUT_S)
    elapsed = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"cell scan exited with {proc.returncode}:\n{proc.stdout}\n{proc.stderr}")
    return elapsed, json.loads((out / "result.json").read_text()), {"job_cpu_s": children_cpu_s() - cpu0}


def run_service(served: ServedCell, max_time_s: float) -> tuple[float, str, dict[str, Any], dict[str, float]]:
    """One job through the service: (seconds from the POST to its end on the event stream, its status,
    its result.json, the CPU time [s] of its worker and of the service meanwhile). The service publishes
    the job's end on its worker's last message, while the worker is still exiting; its CPU time joins
    the service's children's once the service has waited for it, which this waits for (at most
    ``REAP_TIMEOUT_S``)."""
    assert served.proc is not None
    with served.client("operator", timeout_s=JOB_TIMEOUT_S) as client:
        own0, children0 = cpu_s(served.proc.pid)
        t0 = time.perf_counter()
        response = client.post("/api/v1/jobs", json={"planner": PLANNER, "object": OBJECT, "seed": SEED,
                                                      "max_time_s": max_time_s})
        response.raise_for_status()
        job_id = response.json()["id"]
        status = None
        with client.stream("GET", f"/api/v1/jobs/{job_id}/events") as stream:
            stream.raise_for_status()
            for event in parse_events(stream.iter_lines()):
                if event.event in ("state", "result") and event.data["status"] not in ("queued", "running"):
                    status = event.data["status"]
                    break
        elapsed = time.perf_counter() - t0
        own1, children1 = cpu_s(served.proc.pid)
        reaped_by = time.monotonic() + REAP_TIMEOUT_S
        while children1 == children0 and time.monotonic() < reaped_by:
            time.sleep(0.05)
            own1, children1 = cpu_s(served.proc.pid)
        if status is None:
            raise RuntimeError(f"job {job_id}: its event stream ended before the job did")
        result = client.get(f"/api/v1/jobs/{job_id}/files/result.json")
        result.raise_for_status()
    return elapsed, status, result.json(), {"job_cpu_s": children1 - children0, "service_cpu_s": own1 - own0}


def median(values: list[float]) -> float:
    return round(float(statistics.median(values)), 4)


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--repeats", type=count, default=4,
                        help="runs each way (even: each way runs first as often)")
    parser.add_argument("--max-time", type=positive, default=30.0,
                        help="the scan's time budget [s of sim time]")
    args = parser.parse_args()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="service-vs-scan-") as tmp:
        (Path(tmp) / "data").mkdir()
        served = ServedCell(CONFIG, Path(tmp) / "data")
        try:
            for i in range(args.repeats):
                for way in in_turn(i, ("cli", "service")):
                    load_avg = os.getloadavg()[0]
                    if way == "cli":
                        elapsed, result, cpu = run_cli(Path(tmp) / f"cli-{i}", args.max_time)
                        status = result["status"]
                    else:
                        elapsed, status, result, cpu = run_service(served, args.max_time)
                    row = {"way": way, "repeat": i, "elapsed_s": round(elapsed, 4), "status": status,
                           "wall_time_s": result["wall_time_s"], **{k: round(v, 3) for k, v in cpu.items()},
                           "load_avg_1min_before": round(load_avg, 2), **{k: result[k] for k in SAME}}
                    rows.append(row)
                    web = f" + service {cpu['service_cpu_s']:.2f} s" if "service_cpu_s" in cpu else ""
                    print(f"repeat {i + 1} {way:7s}: {elapsed:.3f} s to the end ({status}), job wall "
                          f"{result['wall_time_s']:.3f} s, CPU {cpu['job_cpu_s']:.2f} s{web}, "
                          f"{result['n_captures']} captures, {result['sim_time_s']} s sim, "
                          f"{result['metrics']}", flush=True)
        finally:
            served.close()
    cli = [r for r in rows if r["way"] == "cli"]
    svc = [r for r in rows if r["way"] == "service"]
    ratio, job_ratio, cpu_ratio = (compared([r[key] for r in svc], [r[key] for r in cli])
                                   for key in ("elapsed_s", "wall_time_s", "job_cpu_s"))
    # each comparison carries the two medians as well
    (svc_s, cli_s), (svc_job, cli_job), (svc_cpu, cli_cpu) = ((round(c.this, 4), round(c.reference, 4))
                                                              for c in (ratio, job_ratio, cpu_ratio))
    identical = all({k: r[k] for k in SAME} == {k: rows[0][k] for k in SAME} for r in rows)
    figures = {
        "cli_s": cli_s, "service_s": svc_s, "ratio_service_over_cli": round(ratio.ratio, 4),
        "ratio_range": ratio.ratios()["ratio_range"],
        "goal": {"limit": GOAL_RATIO, "met": ratio.ratio <= GOAL_RATIO},
        "cli_job_wall_time_s": cli_job, "service_job_wall_time_s": svc_job,
        "job_wall_time_ratio": round(job_ratio.ratio, 4),
        "job_wall_time_ratio_range": job_ratio.ratios()["ratio_range"],
        "cli_cpu_s": cli_cpu, "service_worker_cpu_s": svc_cpu, "cpu_ratio": round(cpu_ratio.ratio, 4),
        "cpu_ratio_range": cpu_ratio.ratios()["ratio_range"],
        "service_web_cpu_s": median([r["service_cpu_s"] for r in svc]),
        "results_identical": identical, "all_completed": all(r["status"] == "completed" for r in rows),
        **{k: rows[0][k] for k in SAME},
        "repeats": args.repeats, "max_time_s": args.max_time, "config": str(CONFIG.relative_to(REPO)),
        "object": OBJECT, "planner": PLANNER, "seed": SEED,
        "cpus": os.cpu_count(), "load_avg_1min": round(os.getloadavg()[0], 2),
        "runs": rows,
    }
    print(f"cell scan: median {cli_s:.3f} s launch to exit (job {cli_job:.3f} s); service: median "
          f"{svc_s:.3f} s POST to completed (job {svc_job:.3f} s)")
    verdict = "met" if figures["goal"]["met"] else "NOT met"
    print(f"service / CLI: {ratio.text()}, goal <= {GOAL_RATIO:g}: {verdict}; job wall time "
          f"{job_ratio.text()}")
    print(f"CPU time: cell scan {cli_cpu:.2f} s, the service's worker {svc_cpu:.2f} s (+ the service itself "
          f"{figures['service_web_cpu_s']:.2f} s) (medians)")
    print(f"n_captures, sim_time_s and metrics identical across all runs: {identical}")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
