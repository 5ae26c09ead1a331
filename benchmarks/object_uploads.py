"""What uploaded meshes cost the service: its RSS [MiB] and the time of ``GET /api/v1/objects`` [s] with
``--objects`` large uploads (binary STLs of an icosphere with 327,680 faces, 16.4 MB each, under the
default ``service.max_upload_mb`` of 50), as an operator's page meets them after a restart.

In a fresh data dir ``cell serve`` (``config/sim-franka-rgbd.yaml``) is started, the meshes are uploaded
one after the other and the service is stopped; a new one is started on the same data dir, and the
service process's RSS (``VmRSS``, its job worker apart) is read before and after the first and the second
listing, then after ``--concurrent`` more uploads sent at once. With ``--reference DIR`` (another
checkout, e.g. ``git worktree add /tmp/ref REV`` with its compiled kernels copied in) the same is measured
there, interleaved run by run over ``--repeats`` repeats, the one that runs first alternating from repeat
to repeat (``benchmarks/interleaved.py``), and each step's figures are printed side by side: the medians
of this tree and of the reference, and the median and range of the repeats' own ratios. Before the
first repeat ``cell serve`` is started once in each tree, untimed, so that a fresh checkout's first run
does not pay for compiling its bytecode where the other tree's does not.

Prints one line per step of each run, then one line per step with the medians (and the ratio), then as
its last line JSON {"runs": {tree: [{step: value}, ...]}, "median": {tree: {step: value}}, "ratio": {step:
{"ratio": the median of the repeats' this / reference, "ratio_range": [min, max]}} or null}.

    nice .venv/bin/python benchmarks/object_uploads.py [--objects 12] [--concurrent 4] [--repeats 2]
        [--reference /tmp/ref]
"""

from __future__ import annotations

import contextlib
import json
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import trimesh
from interleaved import compared, in_turn
from options import BenchmarkParser, checkout, count, first_paragraph

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.service_process import create_key, free_port

REPO = Path(__file__).resolve().parent.parent
CELL_FILE = Path("config") / "sim-franka-rgbd.yaml"
SUBDIVISIONS = 7  # an icosphere of 20 * 4^7 = 327,680 faces: a 16.4 MB binary STL
TIMEOUT_S = 300.0


def rss_mib(pid: int) -> float:
    """The resident set of process ``pid`` [MiB] (VmRSS is in KiB)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no VmRSS for process {pid}")


def write_meshes(folder: Path, count: int) -> list[Path]:
    """``count`` binary STLs of spheres 6 to 10 cm across, in metres."""
    sphere = trimesh.creation.icosphere(subdivisions=SUBDIVISIONS, radius=1.0)
    paths = []
    for i in range(count):
        path = folder / f"sphere{i:02d}.stl"
        sphere.copy().apply_scale(0.03 + 0.02 * i / max(count - 1, 1)).export(path)
        paths.append(path)
    return paths


class Served:
    """``cell serve`` of ``tree`` on ``data_dir``, with an operator's key."""

    def __init__(self, tree: Path, data_dir: Path, key: str) -> None:
        self.port = free_port()
        cmd = [sys.executable, "-m", "cell.cli.entry", "serve", "--config", str(tree / CELL_FILE),
               "--data-dir", str(data_dir), "--port", str(self.port)]
        self.proc = subprocess.Popen(cmd, cwd=tree, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.client = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=TIMEOUT_S,
                                   headers={"Authorization": f"Bearer {key}"})
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"cell serve in {tree} exited with {self.proc.returncode}")
            with contextlib.suppress(httpx.HTTPError):
                if self.client.get("/healthz").status_code == 200:
                    return
            time.sleep(0.1)
        raise RuntimeError(f"cell serve in {tree} did not answer within {TIMEOUT_S:g} s")

    def upload(self, path: Path) -> None:
        with httpx.Client(base_url=self.client.base_url, headers=self.client.headers,
                          timeout=TIMEOUT_S) as client:
            answer = client.post("/api/v1/objects", files={"file": (path.name, path.read_bytes())})
        if answer.status_code != 201:
            raise RuntimeError(f"uploading {path.name}: HTTP {answer.status_code} {answer.text}")

    def list_s(self) -> float:
        start = time.monotonic()
        answer = self.client.get("/api/v1/objects")
        answer.raise_for_status()
        return time.monotonic() - start

    def close(self) -> None:
        self.client.close()
        self.proc.terminate()
        self.proc.wait(timeout=60)


def measure(name: str, tree: Path, meshes: list[Path], more: list[Path]) -> dict[str, float]:
    """The figures of one run in ``tree``, each printed as it comes after ``name`` (this or reference)."""
    figures: dict[str, float] = {}

    def note(step: str, value: float) -> None:
        figures[step] = value
        print(f"{name}: {step} {value:.3f}", flush=True)

    with tempfile.TemporaryDirectory() as data_dir:
        key = create_key(Path(data_dir), "operator", "bench", tree=tree)
        served = Served(tree, Path(data_dir), key)
        try:
            start = time.monotonic()
            for path in meshes:
                served.upload(path)
            note("upload_each_s", (time.monotonic() - start) / len(meshes))
        finally:
            served.close()
        served = Served(tree, Path(data_dir), key)
        try:
            time.sleep(2.0)  # the spare worker's start settles
            note("rss_after_restart_mib", rss_mib(served.proc.pid))
            note("first_list_s", served.list_s())
            note("rss_after_first_list_mib", rss_mib(served.proc.pid))
            note("second_list_s", served.list_s())
            with ThreadPoolExecutor(len(more)) as pool:
                list(pool.map(served.upload, more))
            note("rss_after_concurrent_uploads_mib", rss_mib(served.proc.pid))
            note("list_after_uploads_s", served.list_s())
            note("rss_at_end_mib", rss_mib(served.proc.pid))
        finally:
            served.close()
    return figures


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--objects", type=count, default=12)
    parser.add_argument("--concurrent", type=count, default=4)
    parser.add_argument("--repeats", type=count, default=2, help="runs of each tree, interleaved")
    parser.add_argument("--reference", type=checkout, default=None,
                        help="another checkout, measured interleaved")
    args = parser.parse_args()
    trees = {"this": REPO, **({"reference": args.reference} if args.reference else {})}
    runs: dict[str, list[dict[str, float]]] = {name: [] for name in trees}
    for tree in trees.values():  # warm-up, untimed: the bytecode compiled, the libraries in the page cache
        with tempfile.TemporaryDirectory() as data_dir:
            Served(tree, Path(data_dir), create_key(Path(data_dir), "operator", "bench", tree=tree)).close()
    with tempfile.TemporaryDirectory() as folder:
        paths = write_meshes(Path(folder), args.objects + args.concurrent)
        for repeat in range(args.repeats):
            for name in in_turn(repeat, list(trees)):
                runs[name].append(measure(name, trees[name], paths[:args.objects], paths[args.objects:]))
    steps = list(runs["this"][0])
    medians = {name: {step: round(statistics.median(run[step] for run in tree_runs), 3) for step in steps}
               for name, tree_runs in runs.items()}
    ratios = ({step: compared([run[step] for run in runs["this"]], [run[step] for run in runs["reference"]])
               for step in steps} if "reference" in runs else None)
    for step in steps:
        side_by_side = (f", reference {medians['reference'][step]:.3f}, {ratios[step].text()}"
                        if ratios is not None else "")
        print(f"{step}: this {medians['this'][step]:.3f}{side_by_side}")
    print(json.dumps({"runs": {name: [{step: round(v, 3) for step, v in run.items()} for run in tree_runs]
                               for name, tree_runs in runs.items()},
                      "median": medians,
                      "ratio": None if ratios is None else {s: c.ratios() for s, c in ratios.items()}}))


if __name__ == "__main__":
    main()
