"""Offline re-processing of a recorded job (visual-servoing paper section III-B).

The paper flushes the raw frames to disk during a scan and afterwards rebuilds the cloud "similar to the
online procedure (section II-A) ... at a higher point cloud resolution of 1 mm", registering "all the
captured point clouds simultaneously with multiway registration and pose graph optimization" (Open3D),
then compares the result with the ground truth by eq. 13. ``reprocess_job`` does that for a job folder
(layout in the job recorder, ``cell/jobs/recorder.py``):

1. frames: ``frames/NNNNNN.npz``; a depth image ``depth`` [m] (0 = no return) with intrinsics ``K`` is
   back-projected (x = (u - cx) z / fx, y = (v - cy) z / fy, pixel centres at integer (u, v)), otherwise
   the recorded ``points`` [m, sensor frame] are used; ``T_base_sensor`` is the pose the job used; a
   frame that cannot be read (a damaged file) is left out, named in ``skipped_frames`` with the reason;
2. filtering: the crop box in the sensor frame (the job's cell file's: ``cell reprocess`` refuses a job
   whose cell file it cannot find rather than guess one), then a ``voxel_m`` (1 mm) voxel filter per frame;
3. multiway registration: the point-to-plane ICP of online registration (``point_to_plane_icp``:
   coarse to fine, the paper's epsilons with PCL's meaning, pairs beyond the target's surface left out)
   between consecutive frames and between non-consecutive frames whose recorded poses are close (loop
   closures), each started from the recorded relative pose, its correction kept only along the
   directions the pair's point-to-plane residuals constrain (the degeneracy-aware acceptance of online
   registration); pairs failing the acceptance checks (fitness, size of the correction) are left out;
   information matrices of the point-to-plane residuals of the aligned pairs. Choice written down here:
   not Open3D's ICP, whose convergence criteria are relative changes of fitness and RMSE: with the
   paper's 1e-8 it ran all 20 iterations of each stage, and every iteration stepped along the directions
   that only the noise tilt of the normals constrains (the table and a box face), a random walk of
   4-9 mm over a pair of exact-pose cube frames (the paper's epsilons stop this ICP after 2-3 iterations
   there); a whole cube scan's poses moved by up to 8.8 mm and coverage fell from 82 % to 50 %. Nor
   Open3D's information matrices, which are point-to-point ones (see ``_point_to_plane_information``);
4. pose-graph optimization (Open3D, Levenberg-Marquardt): node 0 is the base frame (fixed), node k + 1
   frame k, initialised at its recorded pose. Choice written down here: besides the ICP edges (all
   uncertain, so the line process may prune them), every frame has a certain prior edge to the base
   node at its recorded pose, weighted by the FK accuracy. That keeps the result in the base frame and
   holds the directions a pair leaves unconstrained (a table plane and one box face let ICP slide);
5. each frame transformed by its optimized pose, concatenated and voxel-filtered at ``voxel_m``; written
   to ``cloud_hires.ply``;
6. eq. 13 metrics when the object and its pose are known (simulated jobs), against the same ground-truth
   sample as the online run, and their ``timeline`` as the scan went on (the paper's Fig. 5, bottom): per
   frame, its capture time from the first frame [s, the clock of ``scan_time_s``] and the figures of the
   cloud the frames up to it make, built as in step 5 with the same optimized poses; the last entry is
   the whole scan's figure (``cell.perception.metrics.metrics_timeline``), all with the ground truth
   registered to the whole cloud as the paper does, and the unregistered figures beside (``measure``);
   everything in ``result_hires.json``.

Left out from the paper's post-processing: the statistical outlier filter and segmentation (not part of
the online pipeline of this release either).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from pydantic import Field, PositiveFloat, PositiveInt

from cell.config.models import CropBoxConfig
from cell.perception.cloud import crop_voxel_downsample, cross_rows, first_voxels, voxel_downsample, write_ply
from cell.perception.hires_files import CLOUD_HIRES_FILE, RESULT_HIRES_FILE
from cell.perception.metrics import ground_truth_points, measure, metrics_timeline
from cell.perception.registration import (
    constrain_icp,
    constraint_normals,
    estimate_normals,
    kept_directions,
    point_to_plane_icp,
)
from drivers.atomic_file import write_text_atomic
from drivers.config_base import StrictModel
from drivers.depth.projection import back_project
from drivers.depth.replay import UNREADABLE_FRAME_ERRORS as FRAME_READ_ERRORS
from drivers.errors import JobError
from drivers.sim.objects import load_object
from drivers.transforms import inv_T, rotvec, transform_points

Array = NDArray[np.float64]

_reg = o3d.pipelines.registration

StageReport = Callable[[str, int, int], None]
"""(stage, done, total): how far a stage of the re-processing is."""


class MultiwayParams(StrictModel):
    """Pairwise ICP and pose-graph settings of the offline re-processing.

    ``icp_voxel_m`` [m] voxel filter of the clouds used for pairwise ICP (2.5 mm, the online resolution;
    the output cloud is at the job's ``voxel_m``); ``normal_radius_m`` [m] normal search radius (5 mm, as
    online); ``max_correspondence_m`` [m] the coarse-to-fine ICP stages, the last also the distance of the
    information matrices: 4 mm then 2 mm, narrower than online because the recorded poses are already
    the job's (FK or registered) poses, and wider first stages let overlaps dominated by planes (table,
    box faces) slide by centimetres (measured on a simulated cube scan: 20 mm first stage moved poses by
    up to 8.5 mm, 4 mm by 1.0 mm); ``point_sigma_m`` [m], ``fk_sigma_m`` [m] and ``fk_sigma_deg`` [deg] weigh
    each frame's prior edge to its recorded pose against the ICP edges (information (point / fk)^2 per
    axis), which holds the directions that ICP leaves unconstrained; ``max_iterations``
    per stage and ``epsilon`` [m^2] (paper: 20 and 1e-8, with PCL's meaning as online:
    ``point_to_plane_icp``); a pair is accepted when
    its fitness is at least ``min_fitness`` and ICP moved the recorded relative pose by at most
    ``max_correction_m`` [m] / ``max_correction_deg`` [deg]; frames form a loop-closure pair when their
    recorded sensor origins are within ``loop_max_distance_m`` [m] and their optical axes within
    ``loop_max_angle_deg`` [deg], each frame with at most ``loop_max_per_frame`` earlier ones, the
    nearest (a slow servo scan keeps most frames within 20 cm of each other, and pairs would grow with
    the square of the frame count: 3000 for an 80-frame scan, at about 0.3 s a pair);
    ``edge_prune_threshold`` and ``preference_loop_closure`` are Open3D's
    global-optimization options (line-process weight below which a loop closure is pruned; odometry vs
    loop-closure balance); ``min_constraint`` the degeneracy-aware acceptance of online registration
    (``RegistrationParams.min_constraint``, same default): a pair's correction keeps only the directions
    its point-to-plane Hessian constrains, the recorded relative pose the others;
    ``constraint_normal_radius_m`` [m] the radius of the normals of that test, as online
    (``RegistrationParams.constraint_normal_radius_m``, same default).
    """

    icp_voxel_m: float = Field(default=0.0025, ge=0.0)
    normal_radius_m: PositiveFloat = 0.005
    max_correspondence_m: tuple[PositiveFloat, ...] = Field(default=(0.004, 0.002), min_length=1)
    max_iterations: PositiveInt = 20
    epsilon: PositiveFloat = 1e-8
    min_fitness: float = Field(default=0.3, ge=0.0, le=1.0)
    max_correction_m: PositiveFloat = 0.01
    max_correction_deg: PositiveFloat = 2.0
    point_sigma_m: PositiveFloat = 0.001
    fk_sigma_m: PositiveFloat = 0.002
    fk_sigma_deg: PositiveFloat = 0.2
    loop_max_distance_m: float = Field(default=0.2, ge=0.0)
    loop_max_angle_deg: float = Field(default=60.0, ge=0.0, le=180.0)
    loop_max_per_frame: int = Field(default=4, ge=0)
    edge_prune_threshold: float = Field(default=0.25, ge=0.0, le=1.0)
    preference_loop_closure: PositiveFloat = 1.0
    min_constraint: float = Field(default=0.003, ge=0.0, le=1.0)
    constraint_normal_radius_m: PositiveFloat = 0.01


@contextmanager
def single_threaded_open3d() -> Iterator[None]:
    """Run Open3D on one thread inside the block, restoring the previous limit after it.

    Open3D's multi-threaded reductions sum in a varying order, so the pose-graph optimization of
    identical inputs can differ in the last bits from call to call; one thread makes it exactly
    repeatable (simulation must be byte-identical for a given seed). The limit is process-wide: do not
    run other Open3D work on other threads meanwhile.
    """
    previous = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(previous)


def _load_result(job_dir: Path) -> dict[str, Any]:
    path = job_dir / "result.json"
    if not job_dir.exists():
        raise JobError(f"{job_dir} does not exist")
    if not job_dir.is_dir() or not path.is_file():
        raise JobError(f"{job_dir} is not a job folder: no result.json")
    try:
        result = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise JobError(f"{path}: cannot read the job's result: {exc}") from None
    if not isinstance(result, dict):
        raise JobError(f"{path}: not a job result (expected a JSON object)")
    return result


def recorded_frames(job_dir: Path) -> list[Path]:
    """The frame files of a job folder (``frames/NNNNNN.npz``), in order."""
    return sorted((job_dir / "frames").glob("[0-9]*.npz"))


def _frame_files(job_dir: Path) -> list[Path]:
    files = recorded_frames(job_dir)
    if not files:
        raise JobError(f"{job_dir} holds no recorded frames (frames/NNNNNN.npz); nothing to re-process")
    return files


UNREADABLE_FRAME_ERRORS = (*FRAME_READ_ERRORS, TypeError)
"""What reading a damaged ``.npz`` raises (``drivers.depth.replay.UNREADABLE_FRAME_ERRORS``), and a member of
the wrong kind here (``TypeError``)."""


def _load_frame(path: Path) -> tuple[Array, Array, float]:
    """(points [m, sensor frame], T_base_sensor, capture time [s, job clock]) of one recorded frame; raises
    ``JobError`` naming the file for one that cannot be read."""
    try:
        with np.load(path) as f:
            T = np.asarray(f["T_base_sensor"], dtype=np.float64)
            t = float(f["timestamp"])
            if "depth" in f and "K" in f:
                pts = back_project(np.asarray(f["depth"]), np.asarray(f["K"], dtype=np.float64))
            else:
                pts = np.asarray(f["points"], dtype=np.float64).reshape(-1, 3)
    except UNREADABLE_FRAME_ERRORS as exc:
        raise JobError(f"{path}: not a readable frame ({type(exc).__name__}: {exc})") from None
    if T.shape != (4, 4):
        raise JobError(f"{path}: T_base_sensor has shape {T.shape}, expected (4, 4)")
    return pts, T, t


def _pairs(poses: list[Array], p: MultiwayParams) -> list[tuple[int, int, bool]]:
    """(i, j, is_loop_closure) for consecutive frames, and for each frame j its nearest earlier
    non-consecutive frames i (at most ``loop_max_per_frame``) within the loop-closure distance and angle."""
    cos_max = np.cos(np.deg2rad(p.loop_max_angle_deg))
    origins = np.array([T[:3, 3] for T in poses]).reshape(-1, 3)
    axes = np.array([T[:3, 2] for T in poses]).reshape(-1, 3)
    out = []
    for j in range(1, len(poses)):
        out.append((j - 1, j, False))
        dist = np.linalg.norm(origins[: j - 1] - origins[j], axis=1)
        close = np.flatnonzero((dist <= p.loop_max_distance_m) & (axes[: j - 1] @ axes[j] >= cos_max))
        nearest = close[np.argsort(dist[close], kind="stable")][: p.loop_max_per_frame]
        out.extend((int(i), j, True) for i in sorted(nearest))
    return out


def _point_to_plane_information(matched: Array, normals: Array) -> Array:
    """Information matrix (6, 6) of a pair edge, Open3D's order (rotation, then translation, of frame j
    about its origin): sum over the pairs of a^T a, a = [q x n, n], the rows of the point-to-plane
    residuals ICP minimised, with ``matched`` (K, 3) [m] the source points moved into frame j and
    ``normals`` (K, 3) their target normals; unit variance per residual, as Open3D's point-to-point
    ``get_information_matrix_from_point_clouds``, which would count a slide along a plane (directions
    the pair's correction keeps at the recorded pose) as measured and hold it against the FK prior."""
    rows = np.column_stack([cross_rows(matched, normals), normals])
    return rows.T @ rows


def _multiway(clouds: list[Array], poses: list[Array], p: MultiwayParams,
              progress: StageReport) -> tuple[list[Array], dict]:
    """Optimized T_base_sensor of every frame and a summary of the pose graph; ``progress`` hears of
    each pair registered and of the optimization.

    Node 0 is the base frame (fixed); node k + 1 is frame k, initialised at its recorded pose. Each frame
    has a certain "FK prior" edge to the base node (its recorded pose, information from ``fk_sigma_m`` /
    ``fk_sigma_deg``); each accepted ICP pair an uncertain edge that the line process may prune.
    """
    pts = [voxel_downsample(c, p.icp_voxel_m) if p.icp_voxel_m > 0.0 else c for c in clouds]
    normals = [estimate_normals(c, c, p.normal_radius_m) for c in pts]
    wide = [constraint_normals(c, c, p.constraint_normal_radius_m) for c in pts]
    graph = _reg.PoseGraph()
    graph.nodes.append(_reg.PoseGraphNode(np.eye(4)))
    w_rot = (p.point_sigma_m / np.deg2rad(p.fk_sigma_deg)) ** 2
    w_trans = (p.point_sigma_m / p.fk_sigma_m) ** 2
    info_fk = np.diag([w_rot] * 3 + [w_trans] * 3)  # Open3D order: rotation, then translation
    for k, T in enumerate(poses):
        graph.nodes.append(_reg.PoseGraphNode(T))
        graph.edges.append(_reg.PoseGraphEdge(k + 1, 0, T, info_fk, uncertain=False))
    n_pairs = n_loops = n_underconstrained = 0
    rejected: list[dict[str, Any]] = []
    info_dist = p.max_correspondence_m[-1]
    pairs_to_register = _pairs(poses, p)
    for n_done, (i, j, loop) in enumerate(pairs_to_register):
        progress("register pairs", n_done, len(pairs_to_register))
        if not (len(pts[i]) and len(pts[j])):
            continue
        T_init = inv_T(poses[j]) @ poses[i]  # recorded T_j_i: frame i's points into frame j
        source = transform_points(T_init, pts[i])
        icp = point_to_plane_icp(source, pts[j], normals[j], p.max_correspondence_m,
                                 max_iterations=p.max_iterations, epsilon=p.epsilon,
                                 max_tangential_m=p.normal_radius_m)
        fitness, rmse, pairs = icp.fitness, icp.rmse_m, icp.correspondences
        # the correction kept along the directions the pair constrains, as online
        C, eigval = constrain_icp(icp, source, wide[j][pairs[:, 1]], p.min_constraint)
        T = C @ T_init
        n_underconstrained += kept_directions(eigval, p.min_constraint) < 6
        corr_m = float(np.linalg.norm(T[:3, 3] - T_init[:3, 3]))
        corr_deg = float(np.degrees(np.linalg.norm(rotvec(T[:3, :3] @ T_init[:3, :3].T))))
        ok = fitness >= p.min_fitness and corr_m <= p.max_correction_m and corr_deg <= p.max_correction_deg
        if not ok:
            rejected.append({"source": i, "target": j, "loop_closure": loop, "fitness": round(fitness, 4),
                             "rmse_mm": round(rmse * 1e3, 3), "correction_mm": round(corr_m * 1e3, 3),
                             "correction_deg": round(corr_deg, 3)})
            continue
        info = _point_to_plane_information(transform_points(T, pts[i][pairs[:, 0]]), normals[j][pairs[:, 1]])
        graph.edges.append(_reg.PoseGraphEdge(i + 1, j + 1, T, info, uncertain=True))
        n_pairs += 1
        n_loops += loop
    pair_nodes = {(e.source_node_id, e.target_node_id) for e in graph.edges if e.uncertain}
    n_edges = len(graph.edges)
    progress("register pairs", len(pairs_to_register), len(pairs_to_register))
    progress("optimize the pose graph", 0, 1)
    option = _reg.GlobalOptimizationOption(max_correspondence_distance=info_dist,
                                           edge_prune_threshold=p.edge_prune_threshold,
                                           preference_loop_closure=p.preference_loop_closure,
                                           reference_node=0)
    _reg.global_optimization(graph, _reg.GlobalOptimizationLevenbergMarquardt(),
                             _reg.GlobalOptimizationConvergenceCriteria(), option)
    progress("optimize the pose graph", 1, 1)
    optimized = [np.array(node.pose) for node in graph.nodes][1:]
    kept = {(e.source_node_id, e.target_node_id) for e in graph.edges if e.uncertain}
    moves = [(float(np.linalg.norm(a[:3, 3] - b[:3, 3])),
              float(np.degrees(np.linalg.norm(rotvec(a[:3, :3] @ b[:3, :3].T)))))
             for a, b in zip(optimized, poses, strict=True)]
    summary = {
        "fk_prior_edges": len(poses),
        "pair_edges": n_pairs,
        "underconstrained_pairs": n_underconstrained,
        "loop_closure_edges": n_loops,
        "edges": n_edges,
        "edges_after_pruning": len(graph.edges),
        "pruned_edges": n_edges - len(graph.edges),
        "pruned_pairs": sorted([i - 1, j - 1] for i, j in pair_nodes - kept),
        "rejected_pairs": rejected,
        "max_pose_change_mm": round(max((m for m, _ in moves), default=0.0) * 1e3, 3),
        "max_pose_change_deg": round(max((d for _, d in moves), default=0.0), 4),
    }
    return optimized, summary


def _ground_truth(result: dict[str, Any]) -> Array | None:
    """The eq. 13 sample A of the online run (same object, scale, pose and seed), or None if not
    known."""
    name, pose = result.get("object"), result.get("object_pose")
    if not isinstance(name, str) or pose is None:
        return None
    T_base_object = np.asarray(pose, dtype=np.float64)
    if T_base_object.shape != (4, 4):
        return None
    try:
        mesh = load_object(name, float(result.get("object_scale", 1.0)))
    except (JobError, TypeError, ValueError):
        return None
    return ground_truth_points(mesh, T_base_object)


def _rounded(figures: dict[str, float]) -> dict[str, float | None]:
    """Eq. 13 figures for JSON: 6 decimals, None for the infinite distances of an empty cloud."""
    return {k: (round(v, 6) if np.isfinite(v) else None) for k, v in figures.items()}


def _silent(stage: str, done: int, total: int) -> None:
    """A ``StageReport`` that reports nowhere."""


def reprocess_job(job_dir: Path, *, crop: CropBoxConfig, crop_source: str = "given", voxel_m: float = 0.001,
                  params: MultiwayParams | None = None, frame_step: int = 1,
                  progress: StageReport = _silent, out_dir: Path | None = None,
                  result: dict[str, Any] | None = None) -> dict[str, Any]:
    """Rebuild a job's cloud at ``voxel_m`` [m] with multiway registration (paper section III-B).

    Writes ``cloud_hires.ply`` and ``result_hires.json`` (``HIRES_FILES``) into ``out_dir`` (default
    ``job_dir``), a folder the caller has checked it can write to (``cell.jobs.rebuild.output_folder``
    refuses one before any work), and returns what was written to the JSON. ``result`` is the job's
    result (default: its ``result.json``); ``crop`` is the crop box (sensor frame) of the cell file the job
    ran with and ``crop_source`` says where it came from (recorded in the output: the frames hold no crop
    box, and a guessed one, another cell's, gave another cloud without a word); ``params`` the
    registration settings; ``frame_step`` uses every n-th frame only (1 = all); ``progress`` hears how
    far each stage is (frames loaded, pairs registered, pose graph, metrics). A frame that cannot be read
    (a damaged file) is left out and listed in the output's ``skipped_frames`` (file and reason). Raises
    ``JobError`` for a folder that is not a job folder or has no readable frame.
    """

    job_dir = Path(job_dir)
    out_dir = job_dir if out_dir is None else Path(out_dir)
    if voxel_m <= 0.0:
        raise JobError(f"voxel size must be positive, got {voxel_m} m")
    if frame_step < 1:
        raise JobError(f"frame step must be at least 1, got {frame_step}")
    p = params or MultiwayParams()
    t_start = time.perf_counter()
    if result is None:
        result = _load_result(job_dir)
    files = _frame_files(job_dir)[::frame_step]

    clouds: list[Array] = []
    poses: list[Array] = []
    times: list[float] = []
    skipped: list[dict[str, str]] = []
    for n_done, path in enumerate(files):
        progress("load frames", n_done, len(files))
        try:
            pts, T, t = _load_frame(path)
        except JobError as exc:
            skipped.append({"file": str(path.relative_to(job_dir)), "reason": str(exc)})
            continue
        clouds.append(crop_voxel_downsample(pts, crop.x_m, crop.y_m, crop.z_m, voxel_m))
        poses.append(T)
        times.append(t)
    progress("load frames", len(files), len(files))
    if not clouds:
        raise JobError(f"none of the {len(files)} recorded frames of {job_dir} is readable; nothing to "
                       f"re-process (first: {skipped[0]['reason']})")
    t_loaded = time.perf_counter()

    with single_threaded_open3d():
        optimized, summary = _multiway(clouds, poses, p, progress)
    t_registered = time.perf_counter()

    per_frame = [voxel_downsample(transform_points(T, c), voxel_m) for T, c in zip(optimized, clouds,
                                                                                     strict=True)]
    cloud, first = first_voxels(per_frame, voxel_m)
    write_ply(out_dir / CLOUD_HIRES_FILE, cloud)

    gt = _ground_truth(result)
    metrics = timeline = None
    if gt is not None:
        progress("metrics", 0, 1)
        measured = measure(gt, cloud)
        metrics = _rounded(measured.as_dict())
        # the whole scan's registration places A for every step: the curve ends at the registered figure
        gt_registered = transform_points(measured.T, gt)
        steps = [_rounded(m.as_dict()) for m in metrics_timeline(gt_registered, cloud, first, len(per_frame))]
        timeline = {"t_s": [round(t - times[0], 3) for t in times],
                    **{k: [step[k] for step in steps] for k in steps[0]}}
        progress("metrics", 1, 1)
    t_measured = time.perf_counter()
    out: dict[str, Any] = {
        "n_frames": len(clouds),
        "skipped_frames": skipped,
        "frame_step": frame_step,
        "voxel_m": voxel_m,
        "crop_box": {"x_m": list(crop.x_m), "y_m": list(crop.y_m), "z_m": list(crop.z_m),
                     "source": crop_source},
        "n_cloud_points": int(cloud.shape[0]),
        "metrics": metrics,
        "metrics_online": result.get("metrics"),
        "timeline": timeline,
        "registration": summary,
        "wall_time_s": {"load": round(t_loaded - t_start, 3),
                        "registration": round(t_registered - t_loaded, 3),
                        "metrics": round(t_measured - t_registered, 3),
                        "total": round(time.perf_counter() - t_start, 3)},
    }
    write_text_atomic(out_dir / RESULT_HIRES_FILE, json.dumps(out, indent=2, allow_nan=False) + "\n")
    return out
