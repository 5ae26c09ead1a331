"""Soak: many short sim jobs back to back, in one process and through the service; does anything grow?

Two runs of ``--jobs`` (200) sim scans, one after the other (``--only`` runs one of them):

- ``in_process``: ``cell.jobs.runner.run_scan`` called in this process, job after job, as an embedding
  program (or ``cell.evaluation``'s executors) calls it. Measured: this process.
- ``service``: one ``cell serve`` subprocess (tests/service_process.ServedCell, its own data dir and
  keys), each job ``POST /api/v1/jobs`` and polled to its end before the next is posted, as a client
  that submits one job at a time does. Measured: the service process (each job runs in its own worker
  process, which exits with the job), and the number of its child processes (a worker left behind shows
  as growth there).

The job: ``--config`` (config/sim-ur5e-tof.yaml, the cheaper of the two sim cells), its default planner
unless ``--planner``, the ``horizontal_box`` at the station, seed = the job's index, a ``--max-time`` of
10 s of sim time (about five captures: every part of a scan runs, perception, the planner, the artefacts)
so that a job takes well under a second in process. Each job's folder is deleted after the job (in
process), so that the disk does not fill; the service keeps its own.

Sampled after every ``--sample-every`` (10) jobs and after the last: RSS [MiB] (VmRSS), open file
descriptors, threads (the kernel's tasks, native pools included). Reported: the samples, RSS at the
start (after the first job: imports and first-use caches are not a leak), after ``--warmup`` jobs (20)
and at the end, and the growth from after the warmup to the end [%] against the goal of issue 25
(<= 5 %); fds and threads at the same three points; every job that did not end ``completed``. Each
sample is printed as it is taken (standard error), the figures at the end as one line of JSON.

``run_scan`` gives the C heap's free memory back to the system after each job (``cell.jobs.memory``):
before that, the in-process RSS crept up by what glibc kept of the jobs' freed allocations (5.9 % from
job 20 to 200, in +-30 MiB steps), while the Python heap grew by 63 KiB over 40 jobs (tracemalloc) and
RSS with ``malloc_trim`` before each sample by 0.6 %: retention, not a leak. Since: 0.6 %.

    nice .venv/bin/python benchmarks/soak.py [--jobs 200] [--warmup 20] [--max-time 10] [--only service]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from options import BenchmarkParser, count, first_paragraph, positive

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.config import load_config
from cell.jobs.runner import ScanRequest, run_scan
from tests.service_process import REPO, ServedCell

OBJECT = "horizontal_box"
GOAL_RSS_GROWTH_PCT = 5.0
JOB_TIMEOUT_S = 300.0
UNDER_WAY = ("queued", "running")
POLL_S = 0.05


def process_figures(pid: int) -> dict[str, float]:
    """RSS [MiB], open file descriptors and threads of process ``pid``, from /proc."""
    status = Path(f"/proc/{pid}/status").read_text().splitlines()
    fields = dict(line.split(":", 1) for line in status if ":" in line)
    return {"rss_mib": round(int(fields["VmRSS"].split()[0]) / 1024, 2),
            "fds": len(os.listdir(f"/proc/{pid}/fd")), "threads": int(fields["Threads"])}


def children(pid: int) -> int:
    """How many processes have ``pid`` as their parent."""
    count = 0
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue  # ended meanwhile
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                count += 1
    return count


def soak(run_job: Callable[[int], tuple[str, str]], sample: Callable[[], dict[str, float]],
         args: argparse.Namespace) -> dict[str, Any]:
    """Run ``args.jobs`` jobs through ``run_job`` (index -> status, termination), sampling as it goes."""
    samples: list[dict[str, Any]] = []
    not_completed: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for i in range(args.jobs):
        status, termination = run_job(i)
        if status != "completed":
            not_completed.append({"job": i, "status": status, "termination": termination})
        done = i + 1
        if done in (1, args.warmup, args.jobs) or done % args.sample_every == 0:
            gc.collect()  # this process's garbage is not a leak; the service's own collector runs by itself
            samples.append({"jobs": done, "t_s": round(time.perf_counter() - t0, 1), **sample()})
            print(json.dumps(samples[-1]), file=sys.stderr, flush=True)
    at = {s["jobs"]: s for s in samples}
    first, warm, last = at[1], at[args.warmup], at[args.jobs]
    growth = 100.0 * (last["rss_mib"] - warm["rss_mib"]) / warm["rss_mib"]
    return {
        "jobs": args.jobs, "wall_s": round(time.perf_counter() - t0, 1),
        "rss_mib": {"after_first_job": first["rss_mib"], f"after_{args.warmup}": warm["rss_mib"],
                    "end": last["rss_mib"]},
        "rss_growth_after_warmup_pct": round(growth, 2),
        "goal": {"limit_pct": GOAL_RSS_GROWTH_PCT, "met": growth <= GOAL_RSS_GROWTH_PCT},
        "fds": {"after_first_job": first["fds"], f"after_{args.warmup}": warm["fds"], "end": last["fds"]},
        "threads": {"after_first_job": first["threads"], f"after_{args.warmup}": warm["threads"],
                    "end": last["threads"]},
        "not_completed": not_completed, "samples": samples,
    }


def in_process(args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    cfg = load_config(args.config)

    def run_job(i: int) -> tuple[str, str]:
        folder = tmp / f"job{i}"
        out = run_scan(ScanRequest(config=cfg, config_path=str(args.config), object=OBJECT,
                                   planner=args.planner, seed=i, out=folder, max_time_s=args.max_time))
        shutil.rmtree(folder)
        return out.result["status"], out.result["termination"]

    return soak(run_job, lambda: process_figures(os.getpid()), args)


def service(args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    (tmp / "data").mkdir()
    with ServedCell(args.config.resolve(), tmp / "data") as served, served.client() as client:
        assert served.proc is not None
        pid = served.proc.pid
        body: dict[str, Any] = {"object": OBJECT, "max_time_s": args.max_time}
        if args.planner:
            body["planner"] = args.planner

        def run_job(i: int) -> tuple[str, str]:
            response = client.post("/api/v1/jobs", json={**body, "seed": i})
            response.raise_for_status()
            job_id = response.json()["id"]
            deadline = time.monotonic() + JOB_TIMEOUT_S
            while True:
                job = client.get(f"/api/v1/jobs/{job_id}").json()
                if job["status"] not in UNDER_WAY:
                    return job["status"], job["termination"]
                if time.monotonic() > deadline:
                    raise RuntimeError(f"job {job_id} still {job['status']} after {JOB_TIMEOUT_S:g} s")
                time.sleep(POLL_S)

        def sample() -> dict[str, float]:
            return {**process_figures(pid), "children": children(pid)}

        return soak(run_job, sample, args)


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--jobs", type=count, default=200)
    parser.add_argument("--warmup", type=count, default=20, help="jobs before the RSS baseline")
    parser.add_argument("--sample-every", type=count, default=10)
    parser.add_argument("--config", type=Path, default=REPO / "config" / "sim-ur5e-tof.yaml")
    parser.add_argument("--planner", default=None, help="the cell file's default planner unless given")
    parser.add_argument("--max-time", type=positive, default=10.0, help="each job's budget [s of sim time]")
    parser.add_argument("--only", choices=("in_process", "service"), default=None)
    args = parser.parse_args()
    if args.warmup > args.jobs:  # --warmup is a count: at least 1
        parser.error("--warmup must lie between 1 and --jobs")
    runs = {"in_process": in_process, "service": service}
    figures: dict[str, Any] = {"config": str(args.config), "planner": args.planner, "object": OBJECT,
                               "max_time_s": args.max_time, "warmup": args.warmup,
                               "cpus": os.cpu_count(), "load_avg_1min": round(os.getloadavg()[0], 2)}
    for name, run in runs.items():
        if args.only in (None, name):
            with tempfile.TemporaryDirectory(prefix=f"soak-{name}-") as tmp:
                figures[name] = run(args, Path(tmp))
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
