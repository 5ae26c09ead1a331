"""A job's cloud for a browser: the binary answer of ``GET /api/v1/jobs/{id}/cloud``.

The cloud is the final ``cloud.ply`` once the job has ended (its ``result.json`` is written after it), and
while it runs the snapshot the job keeps (``cell.jobs.live_cloud``). It goes out quantized: 200,000 points
in 1.2 MB, a step of at most 1/65535 of the cloud's extent per axis (8 um over 0.5 m).

Format, little-endian, a 40-byte header then the points:

=======  ===========  ==========================================================================
offset   type         field
=======  ===========  ==========================================================================
0        4 bytes      magic ``CLD1``
4        uint32       ``n``: points in this answer
8        uint32       ``total``: points in the job's cloud (``n`` < ``total`` when subsampled)
12       uint32       ``final``: 1 for the job's final cloud, 0 for a running job's snapshot
16       float32[3]   ``lo``: the box's minimum corner (x, y, z) [m], base frame
28       float32[3]   ``hi``: its maximum corner [m]
40       uint16[n,3]  each point's x, y, z: ``lo + q * (hi - lo) / 65535``
=======  ===========  ==========================================================================
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cell.jobs.live_cloud import LIVE_CLOUD_FILE, read_live_cloud
from cell.perception.cloud import read_ply

MAGIC = b"CLD1"
HEADER = struct.Struct("<4sIII3f3f")
LEVELS = 65535
DEFAULT_MAX_POINTS = 200_000
MAX_POINTS = 1_000_000

Array = NDArray[np.float64]


@dataclass(frozen=True)
class JobCloud:
    """A job's accumulated cloud (N, 3) [m], base frame, and whether it is the final one."""

    points: Array
    final: bool


def job_cloud(folder: Path) -> JobCloud:
    """The cloud of the job in ``folder``: ``cloud.ply`` once ``result.json`` exists (final); while it
    runs, its snapshot; as it ends, ``cloud.ply`` not yet final: a job removes its snapshot, then writes
    ``cloud.ply``, then ``result.json`` once its metrics are measured (seconds later), and in that time
    its cloud is ``cloud.ply``, not none. No points before the first perception update, or for a folder
    that is gone (or, for a moment, one whose snapshot is gone and whose ``cloud.ply`` is not yet
    whole)."""
    ended = (folder / "result.json").is_file()
    if not ended:
        live = read_live_cloud(folder / LIVE_CLOUD_FILE)
        if live is not None:
            return JobCloud(live, final=False)
    try:
        return JobCloud(read_ply(folder / "cloud.ply"), final=ended)
    except (OSError, ValueError):
        pass
    live = read_live_cloud(folder / LIVE_CLOUD_FILE) if ended else None  # a killed worker's last snapshot
    return JobCloud(np.zeros((0, 3)) if live is None else live, final=False)


def encode_cloud(cloud: JobCloud, max_points: int = DEFAULT_MAX_POINTS) -> bytes:
    """The answer (module docstring) for ``cloud``: every point, or ``max_points`` of them evenly spread
    over the cloud's order (deterministic)."""
    points = np.asarray(cloud.points, dtype=np.float64).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    total = points.shape[0]
    if total > max_points:
        points = points[np.arange(max_points) * total // max_points]
    if points.shape[0] == 0:
        lo = hi = np.zeros(3, dtype=np.float32)
    else:
        lo, hi = points.min(axis=0).astype(np.float32), points.max(axis=0).astype(np.float32)
    # lo and hi as the reader gets them (float32); the points quantized against those, clipped for the
    # rounding of the box to float32
    span = np.where(hi > lo, hi.astype(np.float64) - lo, 1.0)
    q = np.rint((points - lo.astype(np.float64)) / span * LEVELS)
    q = np.clip(q, 0, LEVELS).astype("<u2")
    header = HEADER.pack(MAGIC, points.shape[0], total, int(cloud.final), *lo.tolist(), *hi.tolist())
    return header + q.tobytes()


def decode_cloud(data: bytes) -> tuple[Array, int, bool]:
    """The points (N, 3) [m], the job's total and whether it is final, from an answer of
    :func:`encode_cloud` (what the page's ``cloud.js`` does); ``ValueError`` for anything else."""
    if len(data) < HEADER.size:
        raise ValueError(f"a cloud answer has a {HEADER.size}-byte header; got {len(data)} bytes")
    magic, n, total, final, *box = HEADER.unpack_from(data)
    if magic != MAGIC or len(data) != HEADER.size + 6 * n:
        raise ValueError(f"not a cloud answer: magic {magic!r}, {n} points in {len(data)} bytes")
    lo, hi = np.array(box[:3], dtype=np.float64), np.array(box[3:], dtype=np.float64)
    q = np.frombuffer(data, dtype="<u2", offset=HEADER.size).reshape(-1, 3).astype(np.float64)
    return lo + q * (hi - lo) / LEVELS, int(total), bool(final)
