"""Cost of the visual-servoing loop (visual-servoing paper section II-B, II-C, II-D).

A scene: the bunny at the Franka cell's station, six RGB-D frames around it through the perception
pipeline (5 mm occupancy map, ROI from segmentation). On it:

- ``f_eval_ms``: median time of one evaluation of f (eq. 9, 529 rays) at poses on the Z* sphere;
- ``servo_hz``: full servo iterations per second: f at r and the four displaced poses of eq. 5-6 in one
  batch, the law of eq. 1, a guard command and tick on the simulated Panda (the paper ran 30-80 Hz; the
  issue's goal is 300); ``servo_split_ms``: the median CPU time of each of those parts;
- ``global_5000_s``: median wall time to generate and score 5000 candidate views (eq. 10; the goal is
  0.5 s, the paper took 1-3 s on a 40-core Xeon), on ``threads`` OpenMP threads (OMP_NUM_THREADS, else
  the cores); barrier checks are not included;
- ``octomap_f_rel_diff``: a check, not a timing: the largest relative difference, at five poses, between
  our f and the same objective with every sample's occupancy read from an OctoMap (pyoctomap ``search``).
  Both maps are built for the check from the six frames' points with the same sensor model (the cell's
  hit / miss probabilities and clamping; no discretization nor ``keep_surface``, which OctoMap does not
  have), as ``benchmarks/map_vs_octomap.py`` builds them: their float32 log-odds are then identical
  (that benchmark finds them bit-identical), and each sample's probability is the same logistic of the
  same number in double precision (OctoMap's ``1 - 1 / (1 + exp(l))``, ours ``1 / (1 + exp(-l))``: a
  few ulp apart). The two values of f then differ only by double rounding, at most about the number of
  terms summed (529 rays x a few hundred samples in the ROI) times double's epsilon (2.2e-16), ~1e-11
  relative: the check holds when the difference is within ``OCTOMAP_F_TOLERANCE`` (1e-9), a hundredfold
  margin over that. (With the cell's own map, discretized and with ``keep_surface``, against a plain
  OctoMap at OctoMap's default clamping, the difference was 6e-3: two different maps.)

No OctoMap timing of f is reported. The check's reference loops over samples in Python, so its time
would measure the interpreter, not OctoMap. OctoMap's own C++ ray casting, ``OcTree.castRay``, is no
equivalent either: it returns the first occupied voxel along a ray, while eq. 9 needs the probability of
every voxel a ray crosses in the ROI (each sample's entropy, weighted by the chance that the voxels before
it are free). pyoctomap exposes no C++ call that reads those probabilities along a ray.

Each figure is a median of this process's CPU time (``time.process_time``, summed over its threads) and
of wall time (``*_wall*``); on a shared machine wall time also measures the other processes, so the 1-min
load average before and after the run is printed beside them. ``global_5000_s`` is wall time, the latency
a goal sample costs; ``global_5000_cpu_s`` its CPU time over all threads. The last line is JSON.

    .venv/bin/python benchmarks/servo_rate.py
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from map_vs_octomap import octomap_insert, octomap_tree
from options import BenchmarkParser
from station_rig import StationRig

from cell.config import load_config
from cell.control.servo import DualTaskServo
from cell.perception.cloud import slab_interval
from cell.perception.filters import crop_interval
from cell.perception.occupancy import OccupancyMap, binary_entropy
from cell.planning.vs.goals import sphere_views
from cell.planning.vs.objective import EntropyObjective, batch_threads
from cell.planning.vs.servo_scan import objective_rays, translated
from cell.safety.guard import MotionGuard
from drivers.arm.config import SimArmConfig
from drivers.arm.sim import SimArm
from drivers.clock import SimClock
from drivers.robots import get_robot_model

REPO = Path(__file__).resolve().parents[1]
OCTOMAP_F_TOLERANCE = 1e-9  # relative; double rounding of the same computation (module docstring)
CELL = REPO / "config" / "sim-franka-rgbd.yaml"
# Parts of a servo iteration timed apart (CPU): the five evaluations of f, the law of eq. 1, the guard's
# command and control tick, the simulated arm's step.
SERVO_STAGES = ("f", "law", "guard", "sim_arm")


def build_scene(cfg):
    """The pipeline after six frames of the bunny, and each frame's (origin, base-frame points)."""
    rig = StationRig(cfg, "bunny")
    frames = []
    with rig.sensor:
        for k in range(6):
            T = rig.view(200.0 + 25.0 * k, cfg.scan.standoff_m)
            update = rig.pipeline.process(rig.sensor.capture(), T)
            frames.append((update.T_base_sensor[:3, 3].copy(), update.points_base))
    return rig.pipeline, frames


def octomap_f(tree, T, rays_cam, roi_min, roi_max, crop, res) -> float:
    """Eq. 9 at pose T with each sample's probability read from the OcTree (unknown: 0.5)."""
    R, o = T[:3, :3], T[:3, 3]
    d = rays_cam @ R.T
    t_in, t_out = slab_interval(o, d, roi_min, roi_max)
    c_in, c_out = crop_interval(rays_cam, crop)
    t_in, t_out = np.maximum(np.maximum(t_in, c_in), 0.0), np.minimum(t_out, c_out)
    total = 0.0
    for k in range(rays_cam.shape[0]):
        n = max(int(np.ceil((t_out[k] - t_in[k]) / res - 0.5)), 0)
        if n == 0:
            continue
        pts = o + (t_in[k] + (np.arange(n) + 0.5) * res)[:, None] * d[k]
        p = np.empty(n)
        for i, q in enumerate(pts):
            node = tree.search(q)
            p[i] = 0.5 if node is None else node.getOccupancy()
        log_free = np.log1p(-p)
        total += float(np.sum(np.exp(np.cumsum(log_free) - log_free) * binary_entropy(p)))
    return total / rays_cam.shape[0]


def median_ms(fn, repeat: int) -> tuple[float, float]:
    """Median (CPU, wall) time of ``fn()`` [ms] over ``repeat`` calls."""
    cpu, wall = [], []
    for _ in range(repeat):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return float(np.median(cpu) * 1e3), float(np.median(wall) * 1e3)


def main() -> None:
    BenchmarkParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
                    ).parse_args()  # no options: --help
    try:
        import pyoctomap
    except ImportError:
        sys.exit("pyoctomap is missing: .venv/bin/pip install pyoctomap")
    load_before = os.getloadavg()[0]
    cfg = load_config(CELL)
    pipeline, frames = build_scene(cfg)
    roi = pipeline.latest.roi
    assert roi is not None, "the bunny was not segmented"
    rays = objective_rays(cfg)
    crop = cfg.perception.crop_box
    f = EntropyObjective(pipeline.map, roi.aabb_min, roi.aabb_max, crop, rays)
    rng = np.random.default_rng(2)
    u = rng.normal(size=(5000, 3))
    u[:, 2] = np.abs(u[:, 2])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    views = sphere_views(roi.centroid, cfg.scan.standoff_m, u)

    singles = iter(views)
    f_eval_ms, f_eval_wall_ms = median_ms(lambda: f(next(singles)), 300)

    # One servo iteration as the loop runs it, on a simulated Panda behind the guard.
    model = get_robot_model(cfg.arm.model)
    clock = SimClock()
    assert isinstance(cfg.arm, SimArmConfig)  # the benchmark's cell files simulate the arm
    arm = SimArm(cfg.arm, model, clock)
    arm.connect()
    guard = MotionGuard.from_config(arm, model, cfg, clock)
    sc = cfg.planners.vs.servo
    servo = DualTaskServo(standoff_m=cfg.scan.standoff_m, lambda_0=sc.lambda_0, lambda_inf=sc.lambda_inf,
                          lambda_0_slope=sc.lambda_0_slope, lambda_g=sc.lambda_g,
                          e_converged_m=sc.e_converged_m)
    servo.secondary_active = True
    d = cfg.planners.vs_local.delta_m
    offsets = np.array([[0, 0, 0], [d, 0, 0], [-d, 0, 0], [0, d, 0], [0, -d, 0]], dtype=float)
    alpha = cfg.planners.vs_local.alpha
    poses = iter(views)
    split: dict[str, list[float]] = {stage: [] for stage in SERVO_STAGES}

    def iteration() -> None:
        c = [time.process_time()]
        T = next(poses)
        values = f(translated(T, offsets))
        c.append(time.process_time())
        g = np.zeros(6)
        g[:2] = alpha * np.array([values[1] - values[2], values[3] - values[4]]) / (2 * d)
        out = servo.step(T[:3, :3].T @ (roi.centroid - T[:3, 3]), g)
        c.append(time.process_time())
        guard.command_twist(out.v * 1e-3)  # the law's twist, scaled so the arm stays where it is
        guard.tick()
        c.append(time.process_time())
        clock.sleep(1.0 / cfg.scan.control_rate_hz)
        c.append(time.process_time())
        for stage, t0, t1 in zip(SERVO_STAGES, c[:-1], c[1:], strict=True):
            split[stage].append(t1 - t0)

    servo_hz, servo_wall_hz = (1e3 / ms for ms in median_ms(iteration, 300))
    servo_split_ms = {stage: round(float(np.median(t)) * 1e3, 4) for stage, t in split.items()}
    global_cpu_ms, global_wall_ms = median_ms(
        lambda: f(sphere_views(roi.centroid, cfg.scan.standoff_m, u)), 5)

    # the check's two maps: the same points, the same sensor model, what OctoMap does
    params = cfg.perception.occupancy.model_copy(update={"discretize": False, "keep_surface": False})
    check_map, tree = OccupancyMap(params), octomap_tree(pyoctomap, params)
    for origin, pts in frames:
        check_map.integrate(origin, pts)
        octomap_insert(tree, origin, np.ascontiguousarray(pts, dtype=np.float64))
    tree.updateInnerOccupancy()
    res = params.resolution_m
    octo_values = [octomap_f(tree, T, rays, roi.aabb_min, roi.aabb_max, crop, res) for T in views[:5]]
    ours = EntropyObjective(check_map, roi.aabb_min, roi.aabb_max, crop, rays)(views[:5])
    rel = float(np.max(np.abs(np.array(octo_values) - ours) / np.abs(ours)))
    holds = rel <= OCTOMAP_F_TOLERANCE

    load_after = os.getloadavg()[0]
    threads = batch_threads()
    extent = np.round(roi.aabb_max - roi.aabb_min, 3).tolist()
    print(f"map: {pipeline.map.n_known} known voxels; ROI {extent} m; {rays.shape[0]} rays")
    print(f"load average (1 min) {load_before:.2f} before, {load_after:.2f} after; {threads} OpenMP threads")
    print("                         CPU        wall")
    print(f"f evaluation        {f_eval_ms:8.3f}    {f_eval_wall_ms:8.3f} ms (median of 300 poses)")
    print(f"servo iteration     {servo_hz:8.1f}    {servo_wall_hz:8.1f} Hz (5 evaluations, eq. 1, guard; "
          "goal >= 300 Hz)")
    print("  of which (CPU, ms): " + ", ".join(f"{k} {v:.3f}" for k, v in servo_split_ms.items()))
    print(f"5000 candidates     {global_cpu_ms / 1e3:8.3f}    {global_wall_ms / 1e3:8.3f} s (goal <= 0.5 s)")
    print(f"f on an OctoMap of the same frames (per-sample search, untimed): max rel. diff {rel:.2e}, "
          f"{'within' if holds else 'NOT within'} {OCTOMAP_F_TOLERANCE:g} (double rounding)")
    print(json.dumps({"f_eval_ms": round(f_eval_ms, 4), "f_eval_wall_ms": round(f_eval_wall_ms, 4),
                      "servo_hz": round(servo_hz, 1), "servo_wall_hz": round(servo_wall_hz, 1),
                      "servo_split_ms": servo_split_ms,
                      "global_5000_s": round(global_wall_ms / 1e3, 4),
                      "global_5000_cpu_s": round(global_cpu_ms / 1e3, 4), "threads": threads,
                      "octomap_f_rel_diff": rel, "octomap_f_tolerance": OCTOMAP_F_TOLERANCE,
                      "octomap_f_check_holds": holds,
                      "load_avg_1min": [round(load_before, 2), round(load_after, 2)]}))

if __name__ == "__main__":
    main()
