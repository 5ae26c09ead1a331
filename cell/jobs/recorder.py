"""The job folder, readable without the service.

- ``job.json``: what the job was asked, written when the folder is made (planner, object, its scale and
  pose, seed, cell file); what ``cell reprocess`` rebuilds ``result.json`` from when that is missing
  (``cell.jobs.rebuild``);
- ``result.json``: the job's outcome (see ``cell.jobs.runner``);
- ``cloud.ply``: the accumulated cloud, base frame [m], binary little-endian float64 x, y, z;
- ``trajectory.csv``: ``t,x,y,z,qx,qy,qz,qw``, the sensor pose in the base frame at every control tick;
- ``joints.csv``: ``t,q1..qN``, the joints the arm reported [rad] at every control tick, exactly (the
  shortest decimal that reads back as the same float): a replay's arm reports them
  (``drivers.arm.replay``), and the planner's joint-limit and singularity rows see what the live one did;
- ``frames/NNNNNN.npz``: each capture's raw data with ``T_base_sensor`` (reported), ``T_base_flange`` and
  the timestamp: for a depth camera the depth image [m] and its intrinsics ``K`` (the points follow from
  them, see ``DepthFrame``) and its grey ``intensity`` image when it gives one, otherwise the points in
  the sensor frame, plus the ToF zones;
  ``frames/index.csv`` lists them;
- ``map.bt``: the occupancy map in OctoMap's binary format (octovis and pyoctomap open it);
- ``log.txt``: what happened, stamped with job time;
- ``planner_requests.csv``: the moves, reach checks and retraces the planner asked for and the twists the
  guard refused, with the cell's answers and the guard's reasons (a replayed job's: every request,
  twists and holds too; ``cell.jobs.requests``);
- ``STOP``: written by ``cell stop`` while the job runs (an operator stop, ``cell.jobs.stop_file``; the
  job removes it).
- ``cloud_live.npy``: while a watched job runs, its accumulated cloud (``cell.jobs.live_cloud``; removed
  when it ends).

Every file that is written whole (a frame, ``job.json``, ``result.json``, the clouds, the map) is written
to a temporary name beside it and renamed (``drivers.atomic_file``): a job killed or a disk filled up
mid-write leaves no truncated file under a final name. ``job.json`` and ``result.json`` are also flushed
to the disk (``fsync``) before they are renamed (they say the job began and ended); the frames are not:
measured, writing a frame through a temporary name costs what writing it in place does (a ToF frame
2.0-2.7 ms, a 640 x 480 depth image of noise 98-126 ms, either way, 50-300 frames each, the spread
run-to-run noise), and an ``fsync`` per frame would add a disk's latency to every capture. The logs and
CSV files grow a line at a time: ``log.txt``, ``frames/index.csv`` and ``planner_requests.csv`` flushed at
each line, ``trajectory.csv`` and ``joints.csv`` (a row per control tick) buffered, and all of them flushed
to the disk before ``result.json`` is written: a folder whose ``result.json`` exists holds every row.
"""

from __future__ import annotations

import csv
import json
import os
import threading
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from numpy.typing import NDArray

from cell.jobs.requests import COLUMNS, REQUESTS_FILE, request_row
from cell.perception.cloud import write_ply
from cell.perception.occupancy import OccupancyMap
from cell.perception.octomap_io import write_bt
from cell.safety.events import Refusal
from drivers.atomic_file import atomic_open, write_text_atomic
from drivers.depth.base import DepthFrame
from drivers.depth.replay import JOINTS_FILE
from drivers.errors import JobError
from drivers.transforms import quat_xyzw

Array = NDArray[np.float64]

JOB_FILE = "job.json"
RESULT_FILE = "result.json"


def holds_job(folder: Path) -> bool:
    """Whether ``folder`` already holds a job (its ``frames/``), which ``JobRecorder`` refuses."""
    return (folder / "frames").exists()


class JobRecorder:
    """Writes one job folder; every file is flushed as the job goes (the per-tick CSV files at the latest
    before ``result.json``), so a crash loses nothing recorded under a result."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        try:
            (folder / "frames").mkdir(parents=True, exist_ok=False)
        except FileExistsError:
            raise JobError(f"job folder {folder} already holds a job; choose another --out") from None
        except OSError as exc:
            raise JobError(f"cannot create job folder {folder}: {exc}") from None
        self._log: TextIO = (folder / "log.txt").open("w")
        self._log_lock = threading.Lock()
        self._traj: TextIO = (folder / "trajectory.csv").open("w", newline="")
        self._traj_writer = csv.writer(self._traj)
        self._traj_writer.writerow(["t", "x", "y", "z", "qx", "qy", "qz", "qw"])
        self._index: TextIO = (folder / "frames" / "index.csv").open("w", newline="")
        self._index_writer = csv.writer(self._index)
        self._index_writer.writerow(["seq", "t", "file", "n_points"])
        self._requests: TextIO | None = None
        self._joints: TextIO | None = None
        self._unsaved: dict[str, str] = {}  # a growing file whose rows could not all be written: why

    def log(self, t: float, message: str) -> None:
        """One line of ``log.txt`` (any thread: the perception worker logs too on the wall clock)."""
        with self._log_lock:
            try:
                self._log.write(f"[{t:9.3f}] {message}\n")
                self._log.flush()
            except OSError as exc:  # a full disk: the job goes on, its result says the log is short
                self._lost(self._log, exc)

    def pose(self, t: float, T_base_sensor: Array) -> None:
        p = T_base_sensor[:3, 3]
        q = quat_xyzw(T_base_sensor)
        self._traj_writer.writerow([f"{t:.6f}", *(f"{v:.9f}" for v in p), *(f"{v:.9f}" for v in q)])

    def joints(self, t: float, q: Array) -> None:
        """One row of ``joints.csv``: job time [s] and the joints [rad] (created with the first row)."""
        if self._joints is None:
            self._joints = (self.folder / JOINTS_FILE).open("w", newline="")
            self._joints_writer = csv.writer(self._joints)
            self._joints_writer.writerow(["t", *(f"q{k + 1}" for k in range(len(q)))])
        self._joints_writer.writerow([f"{t:.6f}", *(repr(float(v)) for v in q)])

    def frame(self, frame: DepthFrame, T_base_sensor: Array, T_base_flange: Array,
              extra: dict[str, Array]) -> None:
        name = f"{frame.seq:06d}.npz"
        arrays: dict[str, Any] = {"timestamp": np.array(frame.timestamp), "T_base_sensor": T_base_sensor,
                                  "T_base_flange": T_base_flange, **extra}
        if frame.depth is not None and frame.intrinsics is not None:
            arrays.update(depth=frame.depth, K=frame.intrinsics)
        else:
            arrays["points"] = frame.points
        if frame.intensity is not None:
            arrays["intensity"] = frame.intensity
        if frame.zones is not None:
            z = frame.zones
            arrays.update(zone_distance_m=z.distance_m, zone_sigma_m=z.sigma_m, zone_status=z.status,
                          zone_nb_targets=z.nb_targets, zone_reflectance_pct=z.reflectance_pct,
                          zone_directions=z.directions)
        with atomic_open(self.folder / "frames" / name) as f:
            np.savez_compressed(f, **arrays)
        self._index_writer.writerow([frame.seq, f"{frame.timestamp:.6f}", name, frame.points.shape[0]])
        self._index.flush()

    def planner_request(self, t: float, kind: str, T_base_sensor: Array | None = None,
                        v_sensor: Array | None = None, answer: str = "", t_done: float | None = None,
                        refusal: Refusal | None = None) -> None:
        """One row of ``planner_requests.csv`` (created with the first request; ``cell.jobs.requests``)."""
        if self._requests is None:
            self._requests = (self.folder / REQUESTS_FILE).open("w", newline="")
            csv.writer(self._requests).writerow(COLUMNS)
        csv.writer(self._requests).writerow(request_row(t, kind, T_base_sensor, v_sensor, answer, t_done,
                                                        refusal))
        self._requests.flush()

    def cloud(self, points: Array) -> None:
        write_ply(self.folder / "cloud.ply", points)

    def occupancy_map(self, occupancy: OccupancyMap) -> None:
        write_bt(occupancy, self.folder / "map.bt")

    def job(self, job: dict[str, Any]) -> None:
        """Write ``job.json``: what the job was asked."""
        write_text_atomic(self.folder / JOB_FILE, json.dumps(job, indent=2) + "\n", durable=True)

    def result(self, result: dict[str, Any]) -> None:
        """Write ``result.json``, whole and on the disk (see the module docstring), once the files that
        grow a row at a time are on the disk too: ``trajectory.csv`` and ``joints.csv`` buffer their rows
        (one per control tick), and a process killed between ``result.json`` and :meth:`close` lost their
        tail under a result that said the job was whole. One that cannot be (a full disk, an I/O error)
        does not keep ``result.json`` from being written: it says which files lack rows and why
        (``files_incomplete``, file name -> the error)."""
        with self._log_lock:  # the perception worker may log meanwhile
            for f in self._growing():
                try:
                    f.flush()
                    os.fsync(f.fileno())
                except OSError as exc:
                    self._lost(f, exc)
        if self._unsaved:
            result = {**result, "files_incomplete": dict(self._unsaved)}
        text = json.dumps(result, indent=2, sort_keys=False, allow_nan=True)
        write_text_atomic(self.folder / RESULT_FILE, text + "\n", durable=True)

    def close(self) -> None:
        """Close the growing files; one whose rows cannot be written is closed all the same (its buffer
        dropped), as :meth:`result` has said in ``files_incomplete``, and the others are closed too."""
        for f in self._growing():
            try:
                f.close()
            except OSError as exc:
                self._lost(f, exc)

    def _lost(self, f: TextIO, exc: OSError) -> None:
        """Note that rows of ``f`` could not be written, and why (the first error per file)."""
        self._unsaved.setdefault(Path(f.name).name, exc.strerror or str(exc))

    def _growing(self) -> list[TextIO]:
        """The files that grow a row at a time, open ones only."""
        return [f for f in (self._traj, self._joints, self._index, self._requests, self._log)
                if f is not None and not f.closed]
