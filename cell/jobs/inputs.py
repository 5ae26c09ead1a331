"""The checks of a scan's inputs that need no device: each raises ``JobError`` with a one-line reason, so
that ``run_scan`` refuses bad input before the job's folder exists and the service before it queues.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from drivers.errors import JobError
from drivers.file_access import read_only_problem, user_name

MAX_SEED = 2**63 - 1
"""The largest seed a job takes: the store keeps it as a signed 64-bit integer; numpy's seed sequence
takes any non-negative integer."""


def check_seed(seed: int) -> None:
    if not 0 <= seed <= MAX_SEED:
        raise JobError(f"seed must be between 0 and {MAX_SEED}, got {seed}")


def check_time_budget(max_time_s: float) -> None:
    if not (math.isfinite(max_time_s) and max_time_s > 0.0):
        raise JobError(f"time budget must be a positive number of seconds, got {max_time_s}")


def parse_pose(text: str) -> tuple[float, float, float]:
    """An object pose written ``x,y,yaw_deg`` (x [m], y [m], yaw [deg]): three finite numbers; raises
    ``JobError`` saying what it expected."""
    try:
        pose = tuple(float(part) for part in text.split(","))
    except ValueError:  # not a number
        pose = ()
    if len(pose) != 3 or not all(math.isfinite(v) for v in pose):
        raise JobError(f"expected x,y,yaw_deg (three finite numbers), got {text!r}")
    return pose[0], pose[1], pose[2]


def check_pose(pose: tuple[float, float, float]) -> None:
    """An object pose (x [m], y [m], yaw [deg]) from the station: three finite numbers."""
    if not all(math.isfinite(v) for v in pose):
        raise JobError(f"object pose must be three finite numbers x, y, yaw_deg, got {list(pose)}")


def _nearest_existing(folder: Path) -> Path:
    """``folder`` or its nearest ancestor that exists."""
    for candidate in (folder, *folder.absolute().parents):
        if candidate.exists():
            return candidate
    return Path(folder.absolute().anchor)


CHOOSE_OUT = "choose another --out"
"""What a job folder that cannot be made asks of ``cell scan``'s user (the service says its own)."""


def check_job_folder(folder: Path, choose: str = CHOOSE_OUT) -> None:
    """A new job's folder: one that does not exist yet but can be made (its nearest existing ancestor a
    folder this process may write to on a writable file system, ``os.access`` and ``statvfs``: nothing is
    made to try), or an empty one. A folder that holds a job is refused (its result would be overwritten),
    and so is any other non-empty folder (the job's files would land among someone's own). ``choose``
    says what to do instead, in the caller's words (its option that chooses the folder)."""
    if not folder.exists():
        parent = _nearest_existing(folder)
        if not parent.is_dir():
            raise JobError(f"cannot create job folder {folder}: {parent} is a file; {choose}")
        read_only = read_only_problem(parent, "folder", choose)
        if read_only is not None:
            raise JobError(f"cannot create job folder {folder}: {read_only}")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise JobError(f"cannot create job folder {folder}: user {user_name()} may not write in "
                           f"{parent}; {choose}")
        return
    if not folder.is_dir():
        raise JobError(f"job folder {folder} is a file; {choose}")
    if (folder / "frames").exists() or (folder / "result.json").exists():
        raise JobError(f"job folder {folder} already holds a job; {choose}")
    if any(folder.iterdir()):
        raise JobError(f"{folder} is not empty and holds no job: a job writes its own folder; {choose} "
                       "(a new or empty folder)")
