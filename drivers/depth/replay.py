"""``replay``: a recorded job folder played back, its frames as a depth sensor and its poses as a read-only
arm (:class:`drivers.arm.replay.ReplayArm`), so that a real scan can be re-run offline.

The folder layout is the job recorder's (``cell/jobs/recorder.py``): ``frames/NNNNNN.npz`` each with the
capture's ``timestamp`` [s, job clock], ``T_base_sensor`` and ``T_base_flange`` (4x4, base frame), and
either a depth image ``depth`` [m] with its intrinsics ``K`` or ``points`` [m, sensor frame] with the ToF
zones (``zone_*``); ``trajectory.csv`` holds ``t,x,y,z,qx,qy,qz,qw``, the sensor pose in the base frame at
every control tick, and ``joints.csv`` (jobs recorded since it was) ``t,q1..qN``, the joints [rad] the arm
reported at every tick.

Timing: both play on a clock given to them (the job's), in the recording's time. ``capture`` returns the
newest frame recorded at or before the clock's time that was not returned yet; when there is none it lets
the clock run (``clock.sleep``) to the next recorded frame, as a sensor makes its caller wait for the next
frame. After the last frame the sensor is gone (``DriverError``). Depth images are turned into points by
the same back-projection as the simulated camera's, so a replayed frame has exactly the recorded points.
"""

from __future__ import annotations

import csv
import math
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from drivers.clock import Clock, WallClock
from drivers.depth.base import DepthFrame, DepthSensor, SensorModel, ToFZones
from drivers.depth.projection import back_project, pinhole_fov_deg
from drivers.errors import DriverError
from drivers.local_link import LocalLink
from drivers.transforms import inv_T

Array = NDArray[np.float64]

TIME_TOLERANCE_S = 1e-9
"""Recorded times within this of the clock count as reached (times pass through float sums)."""
CSV_TIME_RESOLUTION_S = 1e-6
"""``trajectory.csv`` writes times with 6 decimals."""
JOINTS_FILE = "joints.csv"


@dataclass(frozen=True)
class RecordedFrame:
    """Where one recorded frame is: its file, recorded ``seq`` and ``timestamp`` [s, job clock]."""

    path: Path
    seq: int
    timestamp: float


UNREADABLE_FRAME_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error)
"""What reading a damaged ``.npz`` raises: a truncated file is no zip (``BadZipFile``), a damaged member
fails its CRC (``BadZipFile``) or decompression (``zlib.error``) or ends early (``EOFError``,
``ValueError``), a member may be missing (``KeyError``)."""


class JobRecording:
    """The frames and poses of a job folder (see the module docstring); raises ``DriverError`` for a
    folder that holds no readable recording. A frame file that cannot be read whole (a damaged file: each
    one's members are checked against their CRC) is left out of :attr:`frames` and listed in
    :attr:`unreadable` with the reason, for the caller to warn of or to refuse."""

    def __init__(self, job_dir: str | Path) -> None:
        self.job_dir = Path(job_dir)
        self.device = f"replay {self.job_dir}"
        files = sorted((self.job_dir / "frames").glob("[0-9]*.npz"))
        if not files:
            raise DriverError("no recorded frames (frames/NNNNNN.npz): not a job folder", device=self.device)
        frames = []
        self.unreadable: list[tuple[Path, str]] = []
        """(file, reason) of each frame file that cannot be read, left out of :attr:`frames`."""
        T_flange_sensor: Array | None = None
        for path in files:
            try:
                with np.load(path) as f:
                    damaged = f.zip.testzip() if f.zip is not None else None
                    if damaged is not None:
                        raise zipfile.BadZipFile(f"member {damaged} fails its CRC check")
                    frame = RecordedFrame(path, int(path.stem), float(f["timestamp"]))
                    T_fs = inv_T(np.asarray(f["T_base_flange"])) @ np.asarray(f["T_base_sensor"])
            except UNREADABLE_FRAME_ERRORS as exc:
                self.unreadable.append((path, f"{type(exc).__name__}: {exc}"))
                continue
            frames.append(frame)
            if T_flange_sensor is None:
                T_flange_sensor = T_fs
        if T_flange_sensor is None:
            path, reason = self.unreadable[0]
            raise DriverError(f"none of the {len(files)} recorded frames is readable (first: {path.name}: "
                              f"{reason})", device=self.device)
        self.frames: list[RecordedFrame] = sorted(frames, key=lambda r: r.timestamp)
        self.T_flange_sensor: Array = T_flange_sensor
        """The hand-eye transform the job used, recovered from its first readable frame."""

    def _open(self, path: Path) -> np.lib.npyio.NpzFile:
        try:
            return np.load(path)
        except UNREADABLE_FRAME_ERRORS as exc:
            raise DriverError(f"{path}: not a readable frame ({type(exc).__name__}: {exc})",
                              device=self.device) from None

    def load(self, index: int) -> tuple[DepthFrame, Array, Array]:
        """Frame ``index`` (in time order) as captured, with its T_base_sensor and T_base_flange."""
        rec = self.frames[index]
        try:
            with self._open(rec.path) as f:
                T_base_sensor = np.asarray(f["T_base_sensor"], dtype=np.float64)
                T_base_flange = np.asarray(f["T_base_flange"], dtype=np.float64)
                depth = K = zones = None
                if "depth" in f and "K" in f:
                    depth = np.asarray(f["depth"], dtype=np.float32)
                    K = np.asarray(f["K"], dtype=np.float64)
                    points = back_project(depth, K)
                else:
                    points = np.asarray(f["points"], dtype=np.float64).reshape(-1, 3)
                if "zone_status" in f:
                    zones = ToFZones(distance_m=f["zone_distance_m"], sigma_m=f["zone_sigma_m"],
                                     status=f["zone_status"], nb_targets=f["zone_nb_targets"],
                                     reflectance_pct=f["zone_reflectance_pct"],
                                     directions=f["zone_directions"])
        except KeyError as exc:
            raise DriverError(f"{rec.path}: missing {exc}", device=self.device) from None
        except UNREADABLE_FRAME_ERRORS as exc:
            raise DriverError(f"{rec.path}: not a readable frame ({type(exc).__name__}: {exc})",
                              device=self.device) from None
        frame = DepthFrame(seq=rec.seq, timestamp=rec.timestamp, points=points, depth=depth, intrinsics=K,
                           zones=zones)
        return frame, T_base_sensor, T_base_flange

    def flange_track(self) -> tuple[Array, Array]:
        """Recorded flange poses in time order: times (K,) [s] and T_base_flange (K, 4, 4).

        The frames' own flange poses (exact) and ``trajectory.csv``'s sensor poses (every control tick,
        times to 1 us, poses to 9 decimals) taken back to the flange through :attr:`T_flange_sensor`. A
        trajectory row within ``CSV_TIME_RESOLUTION_S`` / 2 of a frame is left out, so that the pose read
        at a capture's time is exactly the one the capture used.
        """
        frame_t = np.array([rec.timestamp for rec in self.frames])
        times = [frame_t]
        poses = [np.stack([self._flange_of(rec) for rec in self.frames])]
        traj = self.job_dir / "trajectory.csv"
        if traj.is_file():
            rows = self._trajectory_rows(traj)
            if rows:
                values = np.asarray(rows, dtype=np.float64)
                near = np.abs(values[:, 0, None] - frame_t[None, :]).min(axis=1) <= CSV_TIME_RESOLUTION_S / 2
                values = values[~near]
                T = np.zeros((len(values), 4, 4))
                T[:, :3, :3] = Rotation.from_quat(values[:, 4:8]).as_matrix()
                T[:, :3, 3] = values[:, 1:4]
                T[:, 3, 3] = 1.0
                times.append(values[:, 0])
                poses.append(T @ inv_T(self.T_flange_sensor))
        t = np.concatenate(times)
        order = np.argsort(t, kind="stable")
        return t[order], np.concatenate(poses)[order]

    def joint_track(self) -> tuple[Array, Array] | None:
        """The recorded joints in time order: times (K,) [s] and joints (K, N) [rad], from ``joints.csv``;
        None for a job recorded without it. A last line cut short (a job killed mid-write) is left out;
        ``DriverError`` names a row that is not numbers."""
        path = self.job_dir / JOINTS_FILE
        if not path.is_file():
            return None
        text = path.read_text()
        lines = text.splitlines()
        if lines and not text.endswith("\n"):
            lines.pop()
        try:
            values = np.array([[float(v) for v in row] for row in csv.reader(lines[1:])], dtype=np.float64)
        except ValueError as exc:
            raise DriverError(f"{path}: not a row of joints ({exc})", device=self.device) from None
        if values.ndim != 2 or values.shape[0] == 0:
            return None
        return values[:, 0], values[:, 1:]

    def _trajectory_rows(self, path: Path) -> list[list[float]]:
        """The pose rows of ``trajectory.csv`` (t, x, y, z, qx, qy, qz, qw). The job appends a row at every
        control tick: a job killed mid-write leaves its last line without its line end, and that line is
        left out; any other row that is not eight numbers raises ``DriverError`` naming its line."""
        text = path.read_text()
        lines = text.splitlines()
        if lines and not text.endswith("\n"):
            lines.pop()  # cut short by the job's end
        rows = []
        for number, row in enumerate(csv.reader(lines[1:]), start=2):
            try:
                if len(row) != 8:
                    raise ValueError(f"{len(row)} fields, expected 8")
                rows.append([float(v) for v in row])
            except ValueError as exc:
                raise DriverError(f"{path} line {number}: not a pose row ({exc})",
                                  device=self.device) from None
        return rows

    def _flange_of(self, rec: RecordedFrame) -> Array:
        with self._open(rec.path) as f:
            return np.asarray(f["T_base_flange"], dtype=np.float64)


def _sensor_model(frame: DepthFrame, range_m: tuple[float, float]) -> SensorModel:
    """Viewing geometry of a recorded frame: a depth image's size and intrinsics, or the ToF zones' grid
    and the field of view their central rays span."""
    lo, hi = range_m
    if frame.depth is not None and frame.intrinsics is not None:
        h, w = frame.depth.shape
        fov_x, fov_y = pinhole_fov_deg(frame.intrinsics, w, h)
        return SensorModel(kind="rgbd", width=w, height=h, fov_x_deg=fov_x, fov_y_deg=fov_y, range_min_m=lo,
                           range_max_m=hi)
    if frame.zones is not None:
        res = math.isqrt(frame.zones.status.size)
        d0 = frame.zones.directions[0]
        # zone 0's central ray sits half a zone inside the corner: angle = -fov/2 (1 - 1/res)
        fov = float(np.degrees(-2.0 * np.arctan2(d0[0], d0[2]) / (1.0 - 1.0 / res)))
        return SensorModel(kind="tof", width=res, height=res, fov_x_deg=fov, fov_y_deg=fov, range_min_m=lo,
                           range_max_m=hi)
    raise DriverError("a recorded frame with neither a depth image nor ToF zones", device="replay")


class PlaybackClock:
    """The wall clock [s], shifted to start at ``start_s`` (e.g. a recording's first frame), for playing
    a recording in real time without waiting for the moments before its first frame."""

    def __init__(self, start_s: float) -> None:
        self._wall = WallClock()
        self._start = float(start_s)

    def now(self) -> float:
        return self._start + self._wall.now()

    def sleep(self, dt: float) -> None:
        self._wall.sleep(dt)


class ReplaySensor(LocalLink, DepthSensor):
    """The frames of a :class:`JobRecording` as a depth sensor on ``clock`` (see the module docstring).
    ``range_m`` (min, max) [m] is the recorded sensor's range, which the job folder does not hold."""

    name = "replay"

    def __init__(self, recording: JobRecording, clock: Clock, range_m: tuple[float, float]) -> None:
        self.recording = recording
        self._clock = clock
        self._range = range_m
        self._next = 0
        self._model = _sensor_model(recording.load(0)[0], range_m)

    @property
    def model(self) -> SensorModel:
        return self._model

    @property
    def device(self) -> str:
        return self.recording.device

    @property
    def remaining(self) -> int:
        """Frames not yet played."""
        return len(self.recording.frames) - self._next

    @property
    def next_timestamp(self) -> float | None:
        """When the next frame not yet played was recorded [s, job clock], None after the last one."""
        return self.recording.frames[self._next].timestamp if self.remaining else None

    def capture(self) -> DepthFrame:
        self._require_connected("capture", self.recording.device)
        frames = self.recording.frames
        if self._next >= len(frames):
            raise DriverError(f"replay ended: all {len(frames)} recorded frames were played",
                              device=self.recording.device)
        now = self._clock.now()
        due = self._next
        while due + 1 < len(frames) and frames[due + 1].timestamp <= now + TIME_TOLERANCE_S:
            due += 1
        wait = frames[due].timestamp - now
        if wait > TIME_TOLERANCE_S:
            self._clock.sleep(wait)
        self._next = due + 1
        return self.recording.load(due)[0]
