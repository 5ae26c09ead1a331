"""A job folder whose ``result.json`` is missing: the process that ran the job was killed before it
could write it (a power cut, ``kill -9``), or the file was deleted. ``cell reprocess`` rebuilds it from
what the folder still holds, so that the folder is a job folder again: what the job was asked
(``job.json``, written when the folder was made) and the frames it recorded.

The rebuilt result says ``status`` ``interrupted`` (the job's own outcome is unknown) and carries the
identity of the job (planner, object, its scale and pose, seed, cell file), the number of frames, and no
metrics: ``cell reprocess`` then computes its own from the frames (``result_hires.json``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from cell.jobs.recorder import JOB_FILE, RESULT_FILE
from cell.perception.reprocess import recorded_frames
from drivers.errors import JobError

IDENTITY = ("planner", "object", "object_scale", "object_pose", "config", "seed")
"""The fields of ``job.json`` that the rebuilt result keeps."""


def rebuild_result(job_dir: Path) -> dict[str, Any] | None:
    """Write the ``result.json`` of a job folder that has lost it and return it; None when the folder has
    one. Raises ``JobError`` when the folder holds no recorded frame (not a job folder)."""
    if (job_dir / RESULT_FILE).exists():
        return None
    frames = recorded_frames(job_dir)
    if not frames:
        raise JobError(f"{job_dir} is not a job folder: no result.json and no recorded frames")
    try:
        asked = json.loads((job_dir / JOB_FILE).read_text())
    except (OSError, ValueError):
        asked = {}  # a folder made before job.json existed: the job's identity is lost
    known = {key: asked[key] for key in IDENTITY if isinstance(asked, dict) and key in asked}
    result: dict[str, Any] = {
        **known,
        "status": "interrupted",
        "termination": f"the job ended without writing its result; rebuilt by cell reprocess from "
                       f"{len(frames)} recorded frames" + ("" if known else f" (no readable {JOB_FILE})"),
        "n_captures": len(frames),
        "metrics": {"chamfer_mm": None, "hausdorff_mm": None, "coverage_pct": None},
    }
    (job_dir / RESULT_FILE).write_text(json.dumps(result, indent=2) + "\n")
    if (job_dir / "log.txt").is_file():
        with (job_dir / "log.txt").open("a") as log:
            log.write(f"[reprocess] {RESULT_FILE} was missing: rebuilt, status interrupted\n")
    return result
