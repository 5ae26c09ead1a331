"""Which of the sim ToF cell's errors keep the packing estimate from 1 cm (issue 24): the packing grid
(``benchmarks/packing_grid.py``) on the shipped cell and on copies of it with one error source switched
off, side by side.

Variants of ``config/sim-ur5e-tof.yaml`` (written to OUT/cells):

- ``shipped``: as shipped (the calibration error of ``drivers.sim.errors`` and the sensor's range noise);
- ``no-hand-eye``: ``sim.error.hand_eye_std_m`` and ``hand_eye_std_deg`` 0;
- ``no-depth-offset``: ``sim.error.depth_offset_std_m`` 0;
- ``exact``: ``sim.exact`` (no calibration error at all);
- ``no-range-noise``: the range noise std 0.5 mm at every range (``sensor.noise``), the calibration error
  as shipped.

Each variant's scans differ in their paths too (the planners see other points), so a single scan's box
moves either way for that reason alone; the counts over the grid are what compares. Prints, per variant,
the scans whose every dimension lies within 1 cm of the truth, per object and planner and in all, as a
table; then per object, planner and variant the estimate's error, mean and std over the seeds (L W H):
a mean that stays with every error source off is the estimator's own bias; then JSON {variant:
within_dims_error} as its last line.

Run: ``nice .venv/bin/python benchmarks/packing_error_sources.py [--out DIR] [packing_grid options]``
(default options: ``--objects flange --objects gripper --planners lr-nbv --planners nbv --jobs 2
--limit-directions 0``, seeds 0-4: about 2 min a variant on 2 cores).
"""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from options import BenchmarkParser, first_paragraph

from cell.templates import template_path

DEFAULT_OPTIONS = ["--objects", "flange", "--objects", "gripper", "--planners", "lr-nbv", "--planners", "nbv",
                   "--jobs", "2", "--limit-directions", "0"]
# The quiet sensor's range noise [m]: small against the 2.5 mm voxel filter, not zero (the packing's
# noise bands divide by it).
QUIET_SIGMA_M = 0.0005


def variants(cell: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The cell files of the module docstring's variants, from the shipped one ``cell`` (parsed YAML)."""

    def changed(*edits: tuple[str, Any]) -> dict[str, Any]:
        out = copy.deepcopy(cell)
        for dotted, value in edits:
            *path, key = dotted.split(".")
            node = out
            for part in path:
                node = node[part]
            node[key] = value
        return out

    return {
        "shipped": cell,
        "no-hand-eye": changed(("sim.error.hand_eye_std_m", 0.0), ("sim.error.hand_eye_std_deg", 0.0)),
        "no-depth-offset": changed(("sim.error.depth_offset_std_m", 0.0)),
        "exact": changed(("sim.exact", True)),
        "no-range-noise": changed(("sensor.noise", {"sigma0_m": QUIET_SIGMA_M, "k_per_m": 0.0})),
    }


def _count(counts: list[int]) -> str:
    return f"{counts[0]} / {counts[1]}"


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--out", type=Path, default=Path("/tmp/packing_error_sources"))
    args, rest = parser.parse_known_args()
    cell = yaml.safe_load(template_path("sim-ur5e-tof").read_text())
    (args.out / "cells").mkdir(parents=True, exist_ok=True)
    grid = Path(__file__).with_name("packing_grid.py")
    within: dict[str, dict[str, list[int]]] = {}
    error_stats: dict[str, dict[str, list[list[float]]]] = {}
    for name, variant in variants(cell).items():
        path = args.out / "cells" / f"{name}.yaml"
        path.write_text(yaml.safe_dump({**variant, "name": f"{cell['name']}-{name}"}, sort_keys=False))
        command = [sys.executable, str(grid), "--out", str(args.out / name), "--config", str(path),
                   *(rest or DEFAULT_OPTIONS)]
        done = subprocess.run(command, check=False, capture_output=True, text=True)
        if done.returncode:
            sys.exit(f"{name}: packing_grid.py failed ({done.returncode}):\n{done.stderr[-2000:]}")
        boxes = json.loads(done.stdout.strip().splitlines()[-1])["boxes"]
        within[name], error_stats[name] = boxes["within_dims_error"], boxes["dims_error_mean_std_m"]
    groups = sorted({group for counts in within.values() for group in counts})
    print(f"{'within 1 cm':<24}" + "".join(f"{name:>17}" for name in within))
    for group in groups:
        print(f"{group:<24}" + "".join(f"{_count(c.get(group, [0, 0])):>17}" for c in within.values()))
    total = {name: [sum(c[0] for c in counts.values()), sum(c[1] for c in counts.values())]
             for name, counts in within.items()}
    print(f"{'all':<24}" + "".join(f"{_count(t):>17}" for t in total.values()))
    print(f"\n{'estimate error [mm]':<41}" + "".join(f"{dim:>16}" for dim in "LWH"))
    for group in groups:
        for name, stats in error_stats.items():
            if group in stats:
                cells = zip(*(np.array(v) * 1e3 for v in stats[group]), strict=True)
                print(f"{group:<24}{name:<17}" + "".join(f"{m:>+9.1f} +- {s:<4.1f}" for m, s in cells))
    print(json.dumps(within))


if __name__ == "__main__":
    main()
