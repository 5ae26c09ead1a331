"""Occupancy map vs OctoMap on the same recorded frames, at the same resolution, in one run.

Records a short simulated scan (Franka + RGB-D, bunny), then for every frame: depth image -> points in the
sensor frame (x = (u - cx) z / fx, y = (v - cy) z / fy, z), crop box of the paper (x, y in +-0.15 m,
z in (0.05, 0.40) m, sensor frame), 2.5 mm voxel filter, transform to the base frame; integrates the
points into ``OccupancyMap`` and into pyoctomap's ``OcTree.insertPointCloud`` (discretize=false) at 5 mm.
Only integration is timed: per repeat, both maps start empty and take the frames in turn (ours, then
OctoMap, frame by frame), so that load from other processes on a shared machine falls on both alike;
each side's time of a repeat is the sum over the frames, its figure the median over the repeats, and
``speedup`` the ratio of the two medians (OctoMap's / ours). Agreement: share of voxels known to both
maps on which the occupied/free classification agrees (OctoMap's state read back from its own ``.bt``
file).

Last line: JSON {"speedup", "agreement", "ours_ms_per_frame", "octomap_ms_per_frame", "repeats", ...}.

    .venv/bin/python benchmarks/map_vs_octomap.py [--frames-dir DIR] [--max-time 10] [--repeat 9]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from cell.perception.cloud import crop_box, voxel_downsample
from cell.perception.occupancy import OccupancyMap, OccupancyParams
from cell.perception.octomap_io import read_bt
from drivers.transforms import transform_points

ROOT = Path(__file__).resolve().parents[1]
RES_M = 0.005
VOXEL_FILTER_M = 0.0025
BOX = ((-0.15, 0.15), (-0.15, 0.15), (0.05, 0.40))


def record(out: Path, max_time_s: float) -> Path:
    from cell.config import load_config
    from cell.jobs.runner import ScanRequest, run_scan

    cfg_path = ROOT / "config" / "sim-franka-rgbd.yaml"
    cfg = load_config(str(cfg_path))
    outcome = run_scan(ScanRequest(config=cfg, config_path=str(cfg_path), object="bunny",
                                   max_time_s=max_time_s, out=out / "job"))
    return outcome.folder / "frames"


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
        frames.append((T[:3, 3].copy(), transform_points(T, pts)))
    return frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames-dir", type=Path, default=None, help="recorded frames/ (default: record a scan)")
    ap.add_argument("--max-time", type=float, default=10.0, help="scan time to record [s]")
    ap.add_argument("--repeat", type=int, default=9, help="interleaved timed repetitions of each (>= 5)")
    args = ap.parse_args()
    if args.repeat < 5:
        ap.error("--repeat must be at least 5")
    try:
        import pyoctomap
    except ImportError:
        sys.exit("pyoctomap is missing: .venv/bin/pip install pyoctomap")

    with tempfile.TemporaryDirectory() as tmp:
        frames_dir = args.frames_dir or record(Path(tmp), args.max_time)
        frames = load_frames(frames_dir)
        n_rays = sum(p.shape[0] for _, p in frames)
        print(f"{len(frames)} frames, {n_rays} rays ({n_rays / max(len(frames), 1):.0f} per frame), "
              f"resolution {RES_M * 1000:.1f} mm")

        ours_s, octo_s = [], []
        for _ in range(args.repeat):
            occ = OccupancyMap(OccupancyParams(resolution_m=RES_M))
            tree = pyoctomap.OcTree(RES_M)
            ours_t = octo_t = 0.0
            # interleaved frame by frame, so that a burst of load from other processes falls on both
            for origin, pts in frames:
                t0 = time.perf_counter()
                occ.integrate(origin, pts)
                t1 = time.perf_counter()
                tree.insertPointCloud(pts, origin, -1.0)
                t2 = time.perf_counter()
                ours_t, octo_t = ours_t + t1 - t0, octo_t + t2 - t1
            ours_s.append(ours_t)
            octo_s.append(octo_t)

        bt = Path(tmp) / "octomap.bt"
        tree.writeBinary(str(bt))
        ref = read_bt(bt)

    ours_keys, ours_lo = occ.known_keys()
    ours_occ = occ.classify_logodds(ours_lo)
    ref_keys, ref_lo = ref.known_keys()
    ref_occ = ref.classify_logodds(ref_lo)

    def pack(k: np.ndarray) -> np.ndarray:
        k = k + (1 << 20)
        return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]

    common, i_ours, i_ref = np.intersect1d(pack(ours_keys), pack(ref_keys), return_indices=True)
    agree = float(np.mean(ours_occ[i_ours] == ref_occ[i_ref])) if common.size else float("nan")
    n = max(len(frames), 1)
    ours_ms, octo_ms = float(np.median(ours_s)) / n * 1e3, float(np.median(octo_s)) / n * 1e3
    print(f"ours:    {ours_ms:8.2f} ms/frame median of {len(ours_s)} ({ours_keys.shape[0]} known voxels, "
          f"{int(ours_occ.sum())} occupied)")
    print(f"octomap: {octo_ms:8.2f} ms/frame median of {len(octo_s)} ({ref_keys.shape[0]} known voxels, "
          f"{int(ref_occ.sum())} occupied)")
    print(f"known to both: {common.size}; only ours {ours_keys.shape[0] - common.size}, "
          f"only octomap {ref_keys.shape[0] - common.size}; occupied/free agreement {agree:.4f}")
    print(json.dumps({"speedup": round(octo_ms / ours_ms, 3), "agreement": round(agree, 5),
                      "ours_ms_per_frame": round(ours_ms, 2), "octomap_ms_per_frame": round(octo_ms, 2),
                      "repeats": args.repeat, "frames": len(frames), "rays_per_frame": round(n_rays / n),
                      "resolution_m": RES_M}))


if __name__ == "__main__":
    main()
