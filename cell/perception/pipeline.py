"""The one per-frame perception pipeline, used by every planner in sim and on hardware (visual-servoing
paper section II-A and Fig. 2): filter, register, accumulate (cloud and occupancy map), segment.

``PerceptionPipeline.process`` handles one frame synchronously; in sim the job calls it at the
configured rate of sim time, so a run is deterministic. ``AsyncPerception`` runs the same pipeline in
its own thread for real mode, asynchronously from control as in the paper: the newest frame waits in a
one-slot mailbox (older ones are dropped, the pipeline never lags behind), and the newest update is read
without blocking the control loop. An exception in the worker is kept and re-raised to the reader.
"""

from __future__ import annotations

import copy
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from cell.config.models import PerceptionConfig
from cell.perception import filters
from cell.perception.cloud import CloudAccumulator
from cell.perception.entropy_form import EntropyForm
from cell.perception.occupancy import OccupancyMap
from cell.perception.registration import RegistrationResult, RegistrationTarget
from cell.perception.seen_obstacles import SeenCells, SeenObstacles, sample_pitch_rad
from cell.perception.segmentation import ROI, ObjectExtent, SegmentationResult, segment_object
from drivers.depth.base import DepthFrame
from drivers.depth.projection import back_project
from drivers.scheduling import ordinary_scheduling
from drivers.transforms import transform_points

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PerceptionUpdate:
    """What planners see after a frame: its pose after registration, its filtered points in the base
    frame, the ends of the rays it carved free (its ToF zones with no target, out to the sensor's range or
    the crop box's far side, :func:`carved_lengths`; (0, 3) for a camera), the segmented object and its
    ROI, ``extent`` the box (min, max) [m] of every ROI so far (``ObjectExtent``), H_ROI (eq. 12) over
    that box in the form ``h_roi_entropy`` (the pipeline's), the occupancy map, and ``seen`` the cells of
    every return standing on the table so far, crop box or not, but the object's
    (``cell.perception.seen_obstacles``: the guard's obstacles). ``roi``, ``centroid``, ``extent`` and
    ``h_roi`` are None until an object has been found. ``map`` is the pipeline's own map when frames are
    processed in the planner's thread (later frames update it), and a copy taken right after this frame
    when they are processed asynchronously (``AsyncPerception``), so that a planner never reads a map the
    worker is writing."""

    seq: int
    timestamp: float
    T_base_sensor: Array
    registration: RegistrationResult
    points_base: Array
    free_ends_base: Array
    object_points: Array
    roi: ROI | None
    centroid: Array | None
    extent: tuple[Array, Array] | None
    h_roi: float | None
    h_roi_entropy: EntropyForm
    map: OccupancyMap
    seen: SeenCells


class StageTimes:
    """Wall and CPU time [ms] of each stage of the last frame, in order (diagnostics; printed by
    benchmarks/perception_cycle.py). CPU time is the calling thread's (``time.thread_time``): in real
    mode, the perception thread's own, without the control loop's."""

    def __init__(self) -> None:
        self.last: dict[str, tuple[float, float]] = {}
        self._wall = self._cpu = 0.0

    def start(self) -> None:
        self.last = {}
        self._wall, self._cpu = time.perf_counter(), time.thread_time()

    def lap(self, stage: str) -> None:
        """Close ``stage``: the time since the previous lap (or the start)."""
        wall, cpu = time.perf_counter(), time.thread_time()
        self.last[stage] = ((wall - self._wall) * 1e3, (cpu - self._cpu) * 1e3)
        self._wall, self._cpu = wall, cpu


class PerceptionPipeline:
    """Filter -> register -> accumulate -> integrate -> segment, one frame at a time.

    ``table_z_m`` is the table height in the base frame [m]; ``range_max_m`` the sensor's maximum range
    [m], up to which ToF zones with no target carve free space (no further than the crop box).
    ``h_roi_entropy``: the form of each update's H_ROI, which the update carries; a job passes its
    objective's (``planners.vs.objective.entropy``), so that what it reports is what the servo planners'
    termination judges (``ServoScanPlanner.entropy_settled``), computed once per capture. A servo planner
    refuses an update in another form (``PlanningError``), so a pipeline built with the default ``paper``
    cannot silently change that termination. ``reach_m``: the arm's reach [m] from the base frame's
    origin, within which what stands on the table is kept for the guard (``cell.perception.seen_obstacles``;
    None: anywhere)."""

    def __init__(self, config: PerceptionConfig, *, table_z_m: float, range_max_m: float,
                 rng: np.random.Generator, h_roi_entropy: EntropyForm = "paper",
                 reach_m: float | None = None) -> None:
        self.config = config
        self.table_z_m = table_z_m
        self.reach_m = reach_m
        self.range_max_m = range_max_m
        self.h_roi_entropy: EntropyForm = h_roi_entropy
        self.cloud = CloudAccumulator(config.voxel_m)
        self.map = OccupancyMap(config.occupancy)
        self._target = RegistrationTarget(config.registration)
        self.extent = ObjectExtent()
        self.seen = SeenObstacles(config.seen_obstacle_voxel_m, table_z_m,
                                  config.segmentation.plane_distance_m, reach_m)
        self._rng = rng
        self.latest: PerceptionUpdate | None = None
        self.stage_times = StageTimes()

    def empty_like(self, rng: np.random.Generator) -> PerceptionPipeline:
        """A pipeline that has seen nothing, of this one's settings (configuration, table, range, H_ROI
        form), segmenting with ``rng``: what a rebuild of this one's captures starts from."""
        return PerceptionPipeline(self.config, table_z_m=self.table_z_m, range_max_m=self.range_max_m,
                                  rng=rng, h_roi_entropy=self.h_roi_entropy, reach_m=self.reach_m)

    def _returns(self, frame: DepthFrame) -> tuple[Array, Array | None]:
        """The frame's returns (N, 3) [m, sensor frame], for the ToF only its zones that hold a range
        (the cell file's ``perception.filters.valid_tof_statuses``), and their range sigmas (N,) [m] when
        the sensor reports them."""
        if frame.zones is None:
            return frame.points, None
        return filters.valid_tof_returns(frame, self.config.filters.valid_tof_statuses)

    def _see(self, frame: DepthFrame, returns: Array, sigma: Array | None, T_base_sensor: Array) -> None:
        """Add a frame's returns and sigmas (:meth:`_returns`), seen from ``T_base_sensor``, to what stands
        on the table (``cell.perception.seen_obstacles``); a camera's without the farther pixel at each jump
        of its depth image (:func:`filters.continuous_depth_mask`): the flying pixels between an edge and
        what lies behind it, which no crop box or outlier filter takes off outside the crop box."""
        pitch = sample_pitch_rad(frame)
        if frame.depth is not None and frame.intrinsics is not None:
            keep = filters.continuous_depth_mask(frame.depth, pitch)
            returns = back_project(np.where(keep, frame.depth, 0.0), frame.intrinsics)
        self.seen.add(returns, T_base_sensor, pitch, sigma)

    def filter_frame(self, points: Array) -> Array:
        """Of a frame's returns ``points`` (:meth:`_returns`), those worth keeping, sensor frame: crop box,
        voxel filter and statistical outlier removal (section II-A, "Filtering")."""
        c = self.config
        return filters.filter_frame(points, crop=c.crop_box, voxel_m=c.voxel_m, params=c.filters)

    def survey(self, frame: DepthFrame, T_base_sensor_fk: Array) -> SeenCells:
        """Take in a frame only for what stands on the table (``cell.perception.seen_obstacles``): a look
        from where the arm stands before it first moves, whose cells are all obstacles (no object has been
        found yet). It adds nothing to the cloud, the map or registration, whose frames are the scan's."""
        returns, sigma = self._returns(frame)
        self._see(frame, returns, sigma, np.asarray(T_base_sensor_fk, dtype=float))
        return self.seen.outside(None)

    def process(self, frame: DepthFrame, T_base_sensor_fk: Array) -> PerceptionUpdate:
        """Process one frame captured at the pose the arm reported (FK and hand-eye)."""
        T_fk = np.asarray(T_base_sensor_fk, dtype=float)
        if T_fk.shape != (4, 4) or not np.all(np.isfinite(T_fk)):
            raise ValueError(f"T_base_sensor_fk is not a finite 4x4 pose: {T_fk.tolist()}")
        clock = self.stage_times
        clock.start()
        returns, sigma = self._returns(frame)
        points = self.filter_frame(returns)
        clock.lap("filter")
        reg = self._target.register(points, T_fk)
        clock.lap("register")
        T = reg.T_base_sensor
        points_base = transform_points(T, points)
        free_ends = np.zeros((0, 3))
        if frame.zones is not None:
            directions = filters.no_target_directions(frame)
            length = filters.carved_lengths(directions, self.config.crop_box, self.range_max_m)
            carves = length > 0.0
            free_ends = T[:3, 3] + (directions[carves] @ T[:3, :3].T) * length[carves, None]
        seg, extent = self.add_capture(T, points_base, free_ends)
        roi = seg.roi
        self._see(frame, returns, sigma, T)
        # a frame whose segmentation lost the object: the box of every ROI so far, not none
        seen = self.seen.outside((roi.aabb_min, roi.aabb_max) if roi is not None else extent)
        clock.lap("seen")
        aware = self.h_roi_entropy == "observation_aware"
        h_roi = self.map.mean_entropy_in_box(*extent, observation_aware=aware) if extent is not None else None
        clock.lap("h_roi")
        update = PerceptionUpdate(seq=frame.seq, timestamp=frame.timestamp, T_base_sensor=T, registration=reg,
                                  points_base=points_base, free_ends_base=free_ends,
                                  object_points=seg.object_points, roi=roi,
                                  centroid=roi.centroid if roi is not None else None, extent=extent,
                                  h_roi=h_roi, h_roi_entropy=self.h_roi_entropy, map=self.map,
                                  seen=seen)
        self.latest = update
        return update

    def add_capture(self, T_base_sensor: Array, points_base: Array, free_ends: Array,
                    ) -> tuple[SegmentationResult, tuple[Array, Array] | None]:
        """Accumulate one capture's filtered points ``points_base`` (K, 3) [m, base frame], seen from the
        sensor pose ``T_base_sensor`` (after registration), into the cloud and the occupancy map, carving
        free the rays to ``free_ends`` (J, 3) [m] (the zones with no target, up to the sensor's range or the
        crop box), segment the map and add the object's ROI to ``extent``: the segmentation and the box of
        every ROI so far (None until an object has been found)."""
        clock = self.stage_times
        self.cloud.add(points_base)
        clock.lap("accumulate")
        if self.config.registration.enabled:
            self._target.update(self.cloud.points, new=self.cloud.new, viewpoint_base=T_base_sensor[:3, 3])
        clock.lap("normals")
        origin = T_base_sensor[:3, 3]
        self.map.integrate(origin, points_base)
        if free_ends.shape[0]:
            self.map.integrate(origin, free_ends, free_only=np.ones(free_ends.shape[0], dtype=bool))
        clock.lap("integrate")
        seg = segment_object(self.map.occupied_centers(), self.config.segmentation, self._rng,
                             table_z=self.table_z_m)
        clock.lap("segment")
        return seg, self.extent.add(seg.roi) if seg.roi is not None else None


class AsyncPerception:
    """Runs a ``PerceptionPipeline`` in its own thread (real mode). ``submit`` never blocks: a frame not
    yet picked up is replaced by the newer one. ``on_update(frame, T_base_sensor_fk, update)`` runs on the
    worker after each frame (e.g. to record it). ``latest`` returns the newest update, or raises what the
    worker raised."""

    def __init__(self, pipeline: PerceptionPipeline,
                 on_update: Callable[[DepthFrame, Array, PerceptionUpdate], None] | None = None) -> None:
        self.pipeline = pipeline
        self._on_update = on_update
        self._cond = threading.Condition()
        self._pending: tuple[DepthFrame, Array] | None = None
        self._latest: PerceptionUpdate | None = None
        self._error: BaseException | None = None
        self._stop = False
        self.n_dropped = 0
        self._thread = threading.Thread(target=self._run, name="perception", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def submit(self, frame: DepthFrame, T_base_sensor_fk: Array) -> None:
        with self._cond:
            if self._pending is not None:
                self.n_dropped += 1
            self._pending = (frame, T_base_sensor_fk)
            self._cond.notify()

    def latest(self) -> PerceptionUpdate | None:
        with self._cond:
            if self._error is not None:
                raise self._error
            return self._latest

    def _run(self) -> None:
        ordinary_scheduling()  # never at a realtime priority inherited from the control thread
        while True:
            with self._cond:
                while self._pending is None and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                assert self._pending is not None
                frame, pose = self._pending
                self._pending = None
            try:
                update = replace(self.pipeline.process(frame, pose), map=copy.deepcopy(self.pipeline.map))
                if self._on_update is not None:
                    self._on_update(frame, pose, update)
            except BaseException as exc:
                with self._cond:
                    self._error = exc
                return
            with self._cond:
                self._latest = update

    def stop(self, timeout_s: float = 5.0) -> None:
        """Ask the worker to finish after its current frame and wait for it."""
        with self._cond:
            self._stop = True
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
