"""Perception on the wall clock (``mode: real`` and ``dry-run``): asynchronous from control, as in the
visual-servoing paper (section II-A: perception at about 1 Hz, servoing at 30-80 Hz).

Two threads besides the control loop:

- the capture thread reads the sensor as fast as it delivers (so the device's own queue never holds
  stale frames), pairs each frame with the flange pose the control loop recorded at the frame's time
  (:class:`PoseHistory`; the arm is only ever talked to by the control loop) and hands the pair to
- the perception worker (:class:`cell.perception.pipeline.AsyncPerception`): a one-slot mailbox, so a
  frame not yet picked up is replaced by a newer one and perception never lags; it processes the frame
  and records it in the job folder.

The control loop polls :meth:`LivePerception.poll` every tick for the newest update. A capture that
fails is retried after a short pause and counted; a sensor that latched a fault (``DeviceFault``: its
link gone or silent, which no retry clears) and an error in the worker end the job at the next poll,
naming the device, rather than after the perception watchdog's age limit.
"""

from __future__ import annotations

import bisect
import threading
from collections import deque
from collections.abc import Callable

import numpy as np

from cell.perception.pipeline import AsyncPerception, PerceptionPipeline, PerceptionUpdate
from drivers.depth.base import DepthFrame, DepthSensor
from drivers.errors import DeviceFault, DriverError
from drivers.scheduling import ordinary_scheduling
from drivers.transforms import inv_T, rotation_from_rotvec, rotvec

Array = np.ndarray

CAPTURE_RETRY_S = 0.05
"""Pause after a failed capture before the capture thread tries again [s]."""
JOIN_TIMEOUT_S = 5.0


class PoseHistory:
    """Flange poses the control loop recorded, with their job times, for pairing frames captured on
    another thread. Thread-safe; keeps the last ``maxlen`` poses (at 500 Hz, 4096 are 8 s)."""

    def __init__(self, maxlen: int = 4096) -> None:
        self._lock = threading.Lock()
        self._times: deque[float] = deque(maxlen=maxlen)
        self._poses: deque[Array] = deque(maxlen=maxlen)

    def add(self, t: float, T_base_flange: Array) -> None:
        with self._lock:
            self._times.append(t)
            self._poses.append(T_base_flange.copy())

    def latest(self) -> Array:
        """The newest pose (4x4); raises ``DriverError`` before the first."""
        with self._lock:
            if not self._poses:
                raise DriverError("no arm pose recorded yet", device="pose history")
            return self._poses[-1].copy()

    def at(self, t: float) -> Array:
        """T_base_flange at job time ``t`` [s]: interpolated between the recorded poses around it
        (linear in position, along the geodesic in rotation), the first or the newest outside them."""
        with self._lock:
            if not self._poses:
                raise DriverError("no arm pose recorded yet", device="pose history")
            k = bisect.bisect_right(self._times, t)
            if k == 0:
                return self._poses[0].copy()
            if k == len(self._times):
                return self._poses[-1].copy()
            t0, t1 = self._times[k - 1], self._times[k]
            T0, T1 = self._poses[k - 1], self._poses[k]
        s = (t - t0) / (t1 - t0) if t1 > t0 else 1.0
        T = np.eye(4)
        step = rotvec(T0[:3, :3].T @ T1[:3, :3])
        T[:3, :3] = T0[:3, :3] @ rotation_from_rotvec(s * step)
        T[:3, 3] = (1.0 - s) * T0[:3, 3] + s * T1[:3, 3]
        return T


class LivePerception:
    """The capture thread and the perception worker of one stretch of continuous capture (see the
    module docstring). ``record(frame, T_base_flange, update)`` runs on the worker after each frame
    (writing the job folder); ``log`` takes a message (thread-safe)."""

    def __init__(self, sensor: DepthSensor, pipeline: PerceptionPipeline, poses: PoseHistory,
                 T_flange_sensor: Array, record: Callable[[DepthFrame, Array, PerceptionUpdate], None],
                 log: Callable[[str], None]) -> None:
        self._sensor = sensor
        self._poses = poses
        self._T_fs = T_flange_sensor
        self._T_sf = inv_T(T_flange_sensor)
        self._log = log
        self._worker = AsyncPerception(pipeline, on_update=lambda frame, T_fk, update: record(
            frame, T_fk @ self._T_sf, update))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._capture_loop, name="capture", daemon=True)
        self._last_seq: int | None = None
        self._fault: DeviceFault | None = None
        self.n_capture_failures = 0

    def start(self) -> None:
        self._worker.start()
        self._thread.start()

    def stop(self) -> None:
        """Stop capturing, let the worker finish its frame, and wait for both threads."""
        self._stop.set()
        self._thread.join(JOIN_TIMEOUT_S)
        self._worker.stop(JOIN_TIMEOUT_S)

    @property
    def n_dropped(self) -> int:
        """Frames replaced in the mailbox by a newer one before perception took them."""
        return self._worker.n_dropped

    def poll(self) -> PerceptionUpdate | None:
        """The newest update if it is new since the last poll, else None; re-raises a worker error or the
        sensor's latched fault."""
        if self._fault is not None:
            raise self._fault
        update = self._worker.latest()
        if update is None or update.seq == self._last_seq:
            return None
        self._last_seq = update.seq
        return update

    def _capture_loop(self) -> None:
        ordinary_scheduling()  # never at a realtime priority inherited from the control thread
        while not self._stop.is_set():
            try:
                frame = self._sensor.capture()
                T_fk = self._poses.at(frame.timestamp) @ self._T_fs
            except DriverError as exc:
                self.n_capture_failures += 1
                self._log(f"capture failed: {exc}")
                if isinstance(exc, DeviceFault):  # latched: no retry clears it
                    self._fault = exc
                    return
                self._stop.wait(CAPTURE_RETRY_S)
                continue
            self._worker.submit(frame, T_fk)
