"""The accumulated cloud of a running job, for whoever watches it: ``cloud_live.npy`` in the job folder.

The final ``cloud.ply`` is written when the job ends; while it runs, a watcher (the operator's page, via
the service's cloud endpoint) reads this snapshot instead: the accumulated cloud in the base frame [m],
(N, 3) float32, in NumPy's ``.npy`` format, at most ``LIVE_CLOUD_PERIOD_S`` of wall time old.

The control thread only hands over a reference (:meth:`LiveCloudWriter.offer`, O(1): the accumulator
publishes each cloud complete and never changes it afterwards, ``cell.perception.cloud.CloudAccumulator``,
even while the perception worker adds the next frame on the wall clock); a thread of its own
converts and writes it, to a temporary file renamed over the snapshot (``drivers.atomic_file``), so a
reader sees the previous snapshot or the next one, never a part of one. The snapshot is removed when
the job ends.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from drivers.atomic_file import atomic_open, temporary_path
from drivers.scheduling import ordinary_scheduling

LIVE_CLOUD_FILE = "cloud_live.npy"
LIVE_CLOUD_PERIOD_S = 1.0
"""Shortest wall time between two snapshots [s]."""
JOIN_TIMEOUT_S = 5.0


class LiveCloudWriter:
    """Writes ``path`` (see the module docstring) from a daemon thread started here; ``log`` takes a
    message when a write fails (the job goes on: the snapshot is only for watching)."""

    def __init__(self, path: Path, log: Callable[[str], None],
                 period_s: float = LIVE_CLOUD_PERIOD_S) -> None:
        self._path = path
        self._log = log
        self._period_s = period_s
        self._latest: NDArray[np.float64] | None = None
        self._written: NDArray[np.float64] | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.n_written = 0
        self._thread = threading.Thread(target=self._run, name="live-cloud", daemon=True)
        self._thread.start()

    def offer(self, points: NDArray[np.float64]) -> None:
        """The accumulated cloud now, (N, 3) [m] base frame, as the accumulator holds it (not copied; it
        must not be changed afterwards). Returns at once; the thread writes the newest one offered."""
        self._latest = points
        self._wake.set()

    def close(self) -> None:
        """Stop the thread (what was offered since the last write is dropped) and remove the snapshot."""
        self._stop.set()
        self._wake.set()
        self._thread.join(JOIN_TIMEOUT_S)
        temporary_path(self._path).unlink(missing_ok=True)  # a write the join did not wait for
        self._path.unlink(missing_ok=True)

    def _run(self) -> None:
        ordinary_scheduling()  # never at a realtime priority inherited from the control thread
        while not self._stop.is_set():
            self._wake.wait()
            self._wake.clear()
            points = self._latest
            if self._stop.is_set() or points is None or points is self._written:
                continue
            self._write(points)
            self._written = points
            self._stop.wait(self._period_s)

    def _write(self, points: NDArray[np.float64]) -> None:
        try:
            with atomic_open(self._path) as f:
                np.save(f, np.asarray(points, dtype=np.float32).reshape(-1, 3))
            self.n_written += 1
        except OSError as exc:
            self._log(f"live cloud snapshot not written: {exc}")


def read_live_cloud(path: Path) -> NDArray[np.float64] | None:
    """The snapshot at ``path`` as (N, 3) float64 [m], or None when there is none (or it is unreadable)."""
    try:
        points = np.load(path, allow_pickle=False)
    except (OSError, ValueError):
        return None
    if points.ndim != 2 or points.shape[1] != 3:
        return None
    return np.asarray(points, dtype=np.float64)
