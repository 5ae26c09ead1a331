"""The pipe protocol between the service and a job's worker process (``cell.service.worker``).

The service starts ``python -m cell.service.worker --job ID`` and writes JSON lines to its standard input:
first the :class:`WorkerSpec` (what to run), then commands (``{"op": "stop", "reason": ...}``). The end of
that input means the service has gone (closed, crashed or killed): the worker stops the arm at once and
finishes the job folder, since nobody could press stop any more.

The worker writes JSON lines back (its own standard output is moved to standard error first, so that a
library printing to it cannot break the protocol), each with a ``type``:

- ``loaded``: its libraries are imported (before it reads its task): a warm spare is then ready
  (``CellService.warm_worker``, ``/readyz``);
- ``started``: ``pid``;
- ``alive``: a beat, every :data:`WORKER_BEAT_S` from when it started its task to its end, from a thread
  of its own: a worker silent for long is hung (``cell.service.manager.WORKER_SILENT_S``);
- ``progress``: ``progress``, a ``cell.jobs.progress.JobProgress`` as a dict;
- ``stop``: the answer to a stop command, after the arm was commanded to stop: ``effect`` (a
  ``cell.jobs.control.StopEffect`` value: commanded, or the job had not moved yet, or its motion had
  ended), ``reason``;
- ``recovered``: the answer to a recover spec: ``ok``, ``message``, ``arm`` (the state after);
- ``ended``: ``status``, ``termination``, ``result`` (the job's result.json, None when the job ended
  before its folder existed) and ``ticks`` (the control loop's final tick histogram).

Progress lines may be dropped when the service does not read fast enough; nothing else is.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from typing import Any

WORKER_MODULE = "cell.service.worker"
WORKER_BEAT_S = 0.5
"""How often a worker that has its task says it is alive [s]: a small fraction of the seconds a hung job
may be left before it is stopped, and a line every half second costs the worker nothing."""


@dataclass(frozen=True)
class WorkerSpec:
    """One task of a worker. ``op`` ``scan``: run the job (``config`` is the cell file's parsed YAML, which
    the worker validates again, ``config_file`` the service's copy of it in the data dir, named in messages
    and, relative to the job folder, in the job's result, :func:`cell.service.startup.keep_cell_file`;
    ``object`` a shipped name or a mesh path, or a label on a real cell; ``object_pose`` x [m], y [m],
    yaw [deg] from the station; ``folder`` the job folder to create; ``part_id`` and ``submitted_by`` the
    job's, kept in its job.json). ``op`` ``recover``: connect the cell's arm, clear
    a recoverable fault, report its state and disconnect (operator action)."""

    op: str
    job_id: str
    config: dict[str, Any]
    config_file: str
    object: str = "unknown"
    object_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    planner: str | None = None
    seed: int = 0
    max_time_s: float | None = None
    folder: str = ""
    part_id: str | None = None
    submitted_by: str | None = None

    def line(self) -> bytes:
        return (json.dumps(asdict(self)) + "\n").encode()

    @classmethod
    def parse(cls, line: str) -> WorkerSpec:
        data = json.loads(line)
        data["object_pose"] = tuple(data["object_pose"])
        return cls(**data)


def stop_command(reason: str, *, operator: bool = True) -> bytes:
    """The line that asks a worker to stop its job; ``operator``: someone asked for the stop (the job ends
    ``operator stop: <reason>``), else the service stops the job itself (a hung worker, its own failure:
    ``safety stop: <reason>``)."""
    return (json.dumps({"op": "stop", "reason": reason, "operator": operator}) + "\n").encode()


def finite_json(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None: result.json may hold NaN (a metric with no
    ground truth), which strict JSON (responses, PostgreSQL's JSON type) cannot carry."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite_json(v) for v in value]
    return value
