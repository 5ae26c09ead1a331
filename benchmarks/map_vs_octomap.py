"""Occupancy map vs OctoMap on the same recorded frames, at the same resolution and sensor model, in one
run.

Records a short simulated scan (Franka + RGB-D, bunny), then for every frame: depth image -> points in the
sensor frame (x = (u - cx) z / fx, y = (v - cy) z / fy, z), crop box of the paper (x, y in +-0.15 m,
z in (0.05, 0.40) m, sensor frame), 2.5 mm voxel filter, transform to the base frame; integrates the
points into ``OccupancyMap`` and into an OctoMap at 5 mm with our hit / miss probabilities and clamping
thresholds (``OccupancyParams``: 0.7 / 0.4, 0.12 / 0.97; OctoMap's own default clamping is 0.1192 /
0.971), full rays, no discretization.

The reference is OctoMap's own C++ ``insertPointCloud`` through the binding's fastest path. In pyoctomap
1.2.2 (``.venv/lib/python3.11/site-packages/pyoctomap``), ``OcTree.insertPointCloud`` builds the C++
``Pointcloud`` row by row through a Python ndarray slice (``point = point_cloud[i]``) and, unless
``lazy_eval``, then runs a whole-tree ``updateInnerOccupancy()`` after every frame on top of OctoMap's own
inner-node updates; ``ColorOcTree.insertPointCloud`` fills the ``Pointcloud`` in a C loop over a
C-contiguous float64 memoryview (no Python work per point) and calls the same
``OccupancyOcTreeBase::insertPointCloud``. The reference is a ``ColorOcTree`` (an occupancy octree whose
nodes also carry an unused colour) with ``lazy_eval=True`` per frame and one ``updateInnerOccupancy()``
after the last frame, timed as part of its integration. (On the recorded frames a lazy ``OcTree`` took
about 5 % more CPU time than the lazy ``ColorOcTree``.)

Timing: per repeat, both maps start empty and take the frames in turn, frame by frame, ours first in even
repeats and OctoMap first in odd ones (``benchmarks/interleaved.py``), so that load from other processes
on a shared machine falls on both alike. Each side's time of a repeat is the sum over its frames
(OctoMap's with its final ``updateInnerOccupancy``), in CPU time of the process (``time.process_time``)
and wall time; its figure is the median over the repeats, and ``speedup`` the median of the repeats' own
ratios (OctoMap's / ours), for CPU and wall, with their range.

Agreement, on the maps of the last repeat: OctoMap's log-odds per voxel read back from the tree (every
leaf, a pruned one expanded to its voxels), against ours. ``max_abs_dlogodds`` over the voxels known to
both; ``agreement`` the share of the UNION of known voxels on which the occupied / free classification
(p > 0.5) agrees, a voxel known to only one map counting as a disagreement (``only_ours``,
``only_octomap``). Goal (the occupancy issue): integration at least 5x OctoMap's speed (CPU time) at an
agreement of at least 0.99.

Last line: JSON {"speedup_cpu", "speedup_wall", "speedup_range": {"cpu": [min, max], "wall": [...]},
"agreement", "max_abs_dlogodds", "only_ours", "only_octomap", "goal_met", ...}.

    .venv/bin/python benchmarks/map_vs_octomap.py [--frames-dir DIR] [--max-time 10] [--repeat 10]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from interleaved import compared, in_turn
from options import BenchmarkParser, at_least, positive

from cell.perception.cloud import crop_box, voxel_downsample
from cell.perception.occupancy import OccupancyMap, OccupancyParams
from drivers.transforms import transform_points

ROOT = Path(__file__).resolve().parents[1]
RES_M = 0.005
VOXEL_FILTER_M = 0.0025
BOX = ((-0.15, 0.15), (-0.15, 0.15), (0.05, 0.40))
GOAL_SPEEDUP = 5.0  # the occupancy issue's goal: integration at least 5x OctoMap's speed ...
GOAL_AGREEMENT = 0.99  # ... at an occupied/free agreement of at least 0.99
FIRST_FRAME_S = 3.0  # about when the recorded scan takes its first frame, after the approach [s]


def record(out: Path, max_time_s: float) -> Path:
    from cell.config import load_config
    from cell.jobs.runner import ScanRequest, run_scan

    cfg_path = ROOT / "config" / "sim-franka-rgbd.yaml"
    cfg = load_config(str(cfg_path))
    outcome = run_scan(ScanRequest(config=cfg, config_path=str(cfg_path), object="bunny",
                                   max_time_s=max_time_s, out=out / "job"))
    return outcome.folder / "frames"


def frames_problem(frames_dir: Path) -> str | None:
    """Why ``frames_dir`` (a job's ``frames/``) gives this benchmark nothing to integrate, or None: not a
    folder, no recorded frame in it, or frames without a depth image (a ToF sensor's: points and zones)."""
    if not frames_dir.is_dir():
        return f"{frames_dir} is not a folder"
    first = next(iter(sorted(frames_dir.glob("*.npz"))), None)
    if first is None:
        return f"{frames_dir} holds no recorded frames (*.npz, a job's frames/)"
    if "depth" not in np.load(first).files:
        return f"{frames_dir} holds no RGB-D depth frames ({first.name} has no depth image: a ToF scan's?)"
    return None


def load_frames(frames_dir: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """(origin_base (3,), points_base (N, 3)) per frame."""
    frames = []
    for f in sorted(frames_dir.glob("*.npz")):
        d = np.load(f)
        depth, K, T = d["depth"].astype(np.float64), d["K"], d["T_base_sensor"]
        v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
        z = depth[v, u]
        pts = np.column_stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])
        pts = voxel_downsample(crop_box(pts, *BOX), VOXEL_FILTER_M)
        # C-contiguous float64: what the reference's insertPointCloud takes without a copy
        frames.append((T[:3, 3].copy(), np.ascontiguousarray(transform_points(T, pts), dtype=np.float64)))
    return frames


def octomap_tree(pyoctomap: Any, params: OccupancyParams) -> Any:
    """An empty ``ColorOcTree`` (see the module docstring) at ``params``' resolution, with its hit / miss
    probabilities, clamping thresholds and occupancy threshold."""
    tree = pyoctomap.ColorOcTree(params.resolution_m)
    tree.setProbHit(params.p_hit)
    tree.setProbMiss(params.p_miss)
    tree.setClampingThresMin(params.clamp_min)
    tree.setClampingThresMax(params.clamp_max)
    tree.setOccupancyThres(params.occupied_threshold)
    return tree


def octomap_logodds(tree: Any, resolution_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Keys floor(x / resolution_m) (K, 3) and log-odds (K,) of every voxel the tree knows (its leaves, a
    pruned leaf expanded to all its voxels), as ``OccupancyMap.known_keys`` gives ours."""
    keys, logodds = [], []
    for leaf in tree.begin_leafs():
        size = leaf.getSize()
        corner = np.rint((np.asarray(leaf.getCoordinate()) - size / 2.0) / resolution_m).astype(np.int64)
        n = round(size / resolution_m)
        block = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
        keys.append(corner + block)
        logodds.append(np.full(n ** 3, leaf.current_node.getLogOdds()))
    if not keys:
        return np.empty((0, 3), dtype=np.int64), np.empty(0)
    return np.concatenate(keys), np.concatenate(logodds)


def octomap_insert(tree: Any, origin: np.ndarray, points: np.ndarray) -> None:
    """One frame, ``points`` (N, 3) [m] seen from ``origin`` (3,) [m], into the reference: full rays, no
    range limit, the inner nodes left for one ``updateInnerOccupancy`` at the end (``lazy_eval``)."""
    tree.insertPointCloud(points, origin, -1.0, True)


def timed(total: np.ndarray, fn: Callable[..., object], *fn_args: object) -> None:
    """Call ``fn(*fn_args)``, adding its CPU time (of the process) and wall time [s] to ``total`` (2,)."""
    c0, w0 = time.process_time(), time.perf_counter()
    fn(*fn_args)
    total += (time.process_time() - c0, time.perf_counter() - w0)


def pack(keys: np.ndarray) -> np.ndarray:
    """Voxel keys (K, 3) as one int64 each (21 bits an axis)."""
    k = keys + (1 << 20)
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


def compare(occ: OccupancyMap, ref_keys: np.ndarray, ref_lo: np.ndarray) -> dict[str, Any]:
    """Our map against OctoMap's voxels: the largest |log-odds difference| on the voxels both know, the
    share of the union of known voxels classified alike (one known to a single map disagrees), and the
    counts known to both, to ours only and to OctoMap only."""
    ours_keys, ours_lo = occ.known_keys()
    common, i_ours, i_ref = np.intersect1d(pack(ours_keys), pack(ref_keys), return_indices=True)
    union = ours_keys.shape[0] + ref_keys.shape[0] - common.size
    same = occ.classify_logodds(ours_lo[i_ours]) == occ.classify_logodds(ref_lo[i_ref])
    delta = np.abs(ours_lo[i_ours].astype(np.float64) - ref_lo[i_ref])
    return {"both": int(common.size), "only_ours": int(ours_keys.shape[0] - common.size),
            "only_octomap": int(ref_keys.shape[0] - common.size),
            "agreement": float(np.sum(same)) / union if union else float("nan"),
            "max_abs_dlogodds": float(delta.max()) if common.size else float("nan"),
            "occupied_ours": int(occ.classify_logodds(ours_lo).sum()),
            "occupied_octomap": int(occ.classify_logodds(ref_lo).sum())}


def main() -> None:
    ap = BenchmarkParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames-dir", type=Path, default=None, help="recorded frames/ (default: record a scan)")
    ap.add_argument("--max-time", type=positive, default=10.0, help="scan time to record [s]")
    ap.add_argument("--repeat", type=at_least(5), default=10,
                    help="interleaved timed repetitions of each (>= 5)")
    args = ap.parse_args()
    if args.frames_dir is not None and (problem := frames_problem(args.frames_dir)):
        ap.error(f"--frames-dir: {problem}")
    try:
        import pyoctomap
    except ImportError:
        sys.exit("pyoctomap is missing: .venv/bin/pip install pyoctomap")

    with tempfile.TemporaryDirectory() as tmp:
        frames_dir = args.frames_dir or record(Path(tmp), args.max_time)
        if args.frames_dir is None and frames_problem(frames_dir):  # a given folder was checked above
            ap.error(f"the scan recorded in --max-time {args.max_time:g} s took no frame: give --max-time "
                     f"{FIRST_FRAME_S + 1:g} or more (its first frame comes about {FIRST_FRAME_S:g} s in)")
        frames = load_frames(frames_dir)
    n_rays = sum(p.shape[0] for _, p in frames)
    n = len(frames)
    print(f"{len(frames)} frames, {n_rays} rays ({n_rays / n:.0f} per frame), "
          f"resolution {RES_M * 1000:.1f} mm")

    params = OccupancyParams(resolution_m=RES_M)
    spent: dict[str, list[np.ndarray]] = {"ours": [], "octomap": []}  # per repeat: (CPU, wall) [s]
    for r in range(args.repeat):
        occ, tree = OccupancyMap(params), octomap_tree(pyoctomap, params)
        total = {side: np.zeros(2) for side in spent}
        sides: list[tuple[str, Callable[..., object]]] = [("ours", occ.integrate),
                                                           ("octomap", partial(octomap_insert, tree))]
        for origin, pts in frames:
            for side, integrate in in_turn(r, sides):
                timed(total[side], integrate, origin, pts)
        timed(total["octomap"], tree.updateInnerOccupancy)
        for side, t in total.items():
            spent[side].append(t)

    ref_keys, ref_lo = octomap_logodds(tree, RES_M)
    agreement = compare(occ, ref_keys, ref_lo)
    # (CPU, wall) [ms per frame]
    med = {side: np.median(np.array(t), axis=0) / n * 1e3 for side, t in spent.items()}
    speedup = {kind: compared([t[i] for t in spent["octomap"]], [t[i] for t in spent["ours"]])
               for i, kind in enumerate(("cpu", "wall"))}
    speedup_cpu, speedup_wall = speedup["cpu"].ratio, speedup["wall"].ratio
    met = speedup_cpu >= GOAL_SPEEDUP and agreement["agreement"] >= GOAL_AGREEMENT
    print(f"median of {args.repeat} interleaved repeats, ms per frame      CPU      wall")
    for side, label in (("ours", "ours (OccupancyMap.integrate)"),
                        ("octomap", "OctoMap (ColorOcTree, lazy)")):
        print(f"  {label:44s} {med[side][0]:8.2f} {med[side][1]:9.2f}")
    print(f"  speedup (OctoMap / ours)                     {speedup_cpu:8.2f} {speedup_wall:9.2f}")
    print(f"  speedup over the repeats: CPU {speedup['cpu'].text(2)}, wall {speedup['wall'].text(2)}")
    print(f"voxels known to both {agreement['both']}, only ours {agreement['only_ours']}, only OctoMap "
          f"{agreement['only_octomap']}; occupied {agreement['occupied_ours']} ours, "
          f"{agreement['occupied_octomap']} OctoMap")
    print(f"max |delta log-odds| on voxels known to both {agreement['max_abs_dlogodds']:.3g}; "
          f"occupied/free agreement over the union of known voxels {agreement['agreement']:.5f}")
    print(f"goal: integration >= {GOAL_SPEEDUP:g}x OctoMap (CPU) at agreement >= {GOAL_AGREEMENT}: "
          f"{'met' if met else 'NOT met'}")
    print(json.dumps({"speedup_cpu": round(speedup_cpu, 3), "speedup_wall": round(speedup_wall, 3),
                      "speedup_range": {kind: c.ratios()["ratio_range"] for kind, c in speedup.items()},
                      **{k: round(v, 6) if isinstance(v, float) else v for k, v in agreement.items()},
                      "goal": {"speedup": GOAL_SPEEDUP, "agreement": GOAL_AGREEMENT}, "goal_met": met,
                      **{f"{side}_ms_per_frame": {"cpu": round(m[0], 3), "wall": round(m[1], 3)}
                         for side, m in med.items()},
                      "repeats": args.repeat, "frames": len(frames), "rays_per_frame": round(n_rays / n),
                      "resolution_m": RES_M, "load_avg_1min": round(os.getloadavg()[0], 2)}))


if __name__ == "__main__":
    main()
