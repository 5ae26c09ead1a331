"""How soon ``cell serve`` answers after it starts: the wall time [s] from starting the process (as a
user does, ``python -m cell.cli.entry serve`` on ``config/sim-ur5e-tof.yaml``, a fresh data dir each run)
to the first ``/healthz`` that answers 200, polled every 50 ms; the process is then stopped (SIGTERM).

With ``--reference DIR`` (another checkout of the cell, e.g. ``git worktree add /tmp/ref REV`` with its
compiled kernels copied in) the same is measured there, interleaved run by run, the one that runs
first alternating from repeat to repeat (this, reference; reference, this; ...:
``benchmarks/interleaved.py``), and the median of the repeats' own ratios (this / reference) is printed
with their range: both share the machine's load alike. Before the first repeat each tree's service is
started once, untimed, so that a fresh checkout's first run does not pay for compiling its bytecode where
the other tree's does not. The service starts its spare job worker while it starts
(``service.warm_worker``), which competes for the cores, as on a cell's PC.

Prints one line per run, then the median and range of each tree and the ratio, then as its last line
JSON {"runs": {tree: [s, ...]}, "median_s": {...}, "range_s": {tree: [min, max]}, "ratio": the
median of the repeats' this / reference or null, "ratio_range": [min, max] over the repeats or null}.

    .venv/bin/python benchmarks/serve_startup.py [--repeats 6] [--reference /tmp/ref]
"""

from __future__ import annotations

import contextlib
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
from interleaved import compared, in_turn
from options import BenchmarkParser, checkout, count, first_paragraph

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.service_process import free_port

REPO = Path(__file__).resolve().parent.parent
CELL_FILE = Path("config") / "sim-ur5e-tof.yaml"
POLL_S = 0.05
TIMEOUT_S = 120.0


def time_to_healthz(tree: Path) -> float:
    """Seconds from starting ``cell serve`` in ``tree`` to its first healthy ``/healthz``."""
    port = free_port()
    with tempfile.TemporaryDirectory() as data_dir:
        cmd = [sys.executable, "-m", "cell.cli.entry", "serve", "--config", str(tree / CELL_FILE),
               "--data-dir", data_dir, "--port", str(port)]
        start = time.monotonic()
        proc = subprocess.Popen(cmd, cwd=tree, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            while time.monotonic() - start < TIMEOUT_S:
                if proc.poll() is not None:
                    raise RuntimeError(f"cell serve in {tree} exited with {proc.returncode}")
                with contextlib.suppress(httpx.HTTPError):
                    if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1.0).status_code == 200:
                        return time.monotonic() - start
                time.sleep(POLL_S)
            raise RuntimeError(f"cell serve in {tree} did not answer within {TIMEOUT_S:g} s")
        finally:
            proc.terminate()
            proc.wait(timeout=60)


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--repeats", type=count, default=6, help="runs of each tree, interleaved")
    parser.add_argument("--reference", type=checkout, default=None,
                        help="another checkout, measured interleaved")
    args = parser.parse_args()
    trees = {"this": REPO, **({"reference": args.reference} if args.reference else {})}
    for tree in trees.values():  # warm-up, untimed: the bytecode compiled, the libraries in the page cache
        time_to_healthz(tree)
    runs: dict[str, list[float]] = {name: [] for name in trees}
    for repeat in range(args.repeats):
        for name in in_turn(repeat, list(trees)):
            runs[name].append(time_to_healthz(trees[name]))
            print(f"run {repeat} {name}: {runs[name][-1]:.2f} s", flush=True)
    medians = {name: statistics.median(values) for name, values in runs.items()}
    for name, values in runs.items():
        print(f"{name}: median {medians[name]:.2f} s (range {min(values):.2f}-{max(values):.2f} s)")
    c = compared(runs["this"], runs["reference"]) if "reference" in runs else None
    if c is not None:
        print(f"this / reference: {c.text()}")
    print(json.dumps({"runs": {k: [round(v, 3) for v in vs] for k, vs in runs.items()},
                      "median_s": {k: round(v, 3) for k, v in medians.items()},
                      "range_s": {k: [round(min(vs), 3), round(max(vs), 3)] for k, vs in runs.items()},
                      **(c.ratios() if c is not None else {"ratio": None, "ratio_range": None})}))


if __name__ == "__main__":
    main()
