"""Request and response bodies of ``/api/v1``, apart from the service's own records.

Units are in the field names (``_m``, ``_s``, ``_deg``); poses are in the robot base frame.
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Any

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    StrictStr,
    field_validator,
)

from cell.api.stop_reason import DEFAULT_REASON, MAX_LENGTH
from cell.jobs.inputs import MAX_SEED
from cell.jobs.placement import MAX_YAW_DEG
from cell.line.config import PART_ID_MAX, PART_ID_PATTERN
from cell.service.store import JobRecord
from cell.service.submission import MAX_TIME_BUDGET_S, JobRequest


class JobSubmit(BaseModel):
    """A scan to run. Everything but ``object`` (on sim and dry-run cells) defaults to the cell's own:
    its planner, pose (0, 0, 0) at the station, seed 0, the cell file's time budget."""

    model_config = ConfigDict(extra="forbid")

    planner: str | None = Field(None, max_length=64, description="planner name (GET /api/v1/planners)")
    object: str | None = Field(None, max_length=128, description="object name (GET /api/v1/objects); on a "
                                                                 "real cell, an optional label")
    object_pose: tuple[StrictFloat, StrictFloat, StrictFloat] | None = Field(
        None, description=f"[x_m, y_m, yaw_deg] on the table, from the cell's station; "
                          f"|yaw_deg| <= {MAX_YAW_DEG:g}")
    seed: StrictInt | None = Field(None, ge=0, le=MAX_SEED)
    max_time_s: StrictFloat | None = Field(None, gt=0.0, le=MAX_TIME_BUDGET_S, description="time budget [s]")
    part_id: str | None = Field(None, min_length=1, max_length=PART_ID_MAX, pattern=PART_ID_PATTERN,
                                description="the line's identifier of the part (printable ASCII)")

    @field_validator("object_pose")
    @classmethod
    def _finite(cls, pose: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
        if pose is not None and not all(math.isfinite(v) for v in pose):
            raise ValueError("every value must be a finite number")
        return pose

    def request(self) -> JobRequest:
        return JobRequest(planner=self.planner, object=self.object, object_pose=self.object_pose,
                          seed=self.seed, max_time_s=self.max_time_s, part_id=self.part_id)


class JobOut(BaseModel):
    """A job: what was asked, where it is, and once it ended the whole ``result.json`` under ``result``.
    ``progress`` is the newest progress of a running job (the last one of an ended job)."""

    id: str
    cell: str
    status: str
    planner: str
    object: str | None
    object_pose: tuple[float, float, float] | None
    seed: int
    max_time_s: float | None
    part_id: str | None
    submitted_by: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    termination: str | None
    progress: dict[str, Any] | None
    result: dict[str, Any] | None
    keep: bool
    links: dict[str, str]

    @classmethod
    def of(cls, job: JobRecord) -> JobOut:
        base = f"/api/v1/jobs/{job.id}"
        links = {"self": base, "events": f"{base}/events", "files": f"{base}/files", "stop": f"{base}/stop"}
        return cls(id=job.id, cell=job.cell, status=job.status, planner=job.planner, object=job.object,
                   object_pose=job.object_pose, seed=job.seed, max_time_s=job.max_time_s, part_id=job.part_id,
                   submitted_by=job.submitted_by, created_at=job.created_at, started_at=job.started_at,
                   finished_at=job.finished_at, termination=job.termination, progress=job.progress,
                   result=job.result, keep=job.keep, links=links)


class JobPage(BaseModel):
    """One page of jobs, newest first; ``total`` counts every job the filters match."""

    items: list[JobOut]
    total: int
    limit: int
    offset: int


class FileOut(BaseModel):
    """A file of a job folder: its name relative to the folder, size [bytes] and download link."""

    name: str
    size_bytes: int
    url: str


class WhoAmIOut(BaseModel):
    """The calling key: its name, role (viewer, operator, line, admin) and what that role may do."""

    name: str
    role: str
    permissions: list[str]


class KeepIn(BaseModel):
    """Whether retention must never delete the job (``service.retention``)."""

    model_config = ConfigDict(extra="forbid")

    keep: bool


class PrunedOut(BaseModel):
    """An ended job that retention deletes: when it ended, its folder's size [MB] and why."""

    id: str
    ended_at: datetime
    size_mb: float
    reason: str


class RetentionOut(BaseModel):
    """Retention's limits (``service.retention``; None: no limit of that kind), the size of the cell's job
    folders before pruning [GB], the jobs pruning deletes (or deleted) and what that frees [GB], and why
    the size limit still is not met, if it is not; and how many entries of the jobs folder are no job of
    the cell's store and their size [GB]: retention neither counts them against its limit nor deletes
    them (the service's log names them)."""

    days: float | None
    max_gb: float | None
    total_gb: float
    freed_gb: float
    jobs: list[PrunedOut]
    unmet: str | None
    unknown_folders: int
    unknown_gb: float


class StopIn(BaseModel):
    """Why the stop: recorded in the job's termination with the key's name. Documentation only: the stop
    routes read any body (``cell.api.stop_reason``)."""

    reason: str = Field(DEFAULT_REASON, description=f"one line, at most {MAX_LENGTH} characters kept")


STOP_BODY: dict[str, Any] = {"requestBody": {"required": False, "content": {"application/json": {
    "schema": StopIn.model_json_schema()}}}}
"""The stop routes' body in the OpenAPI document, which their reading it themselves leaves out."""


class StopOut(BaseModel):
    """What a stop did: the job it reached (None: nothing ran), whether that job's arm had been commanded
    to stop when this answer was sent, in words, and whether queued jobs are held."""

    job_id: str | None
    arm_commanded: bool
    message: str
    queue_held: bool


class RecoverOut(BaseModel):
    ok: bool
    message: str
    arm: dict[str, Any]


class ObjectOut(BaseModel):
    """An object the cell can scan: bounding box (x, y, z) [m]; ``source`` shipped or uploaded;
    ``default`` marks the object ``cell scan`` takes when none is named, which the page preselects."""

    name: str
    source: str
    extents_m: tuple[float, float, float]
    licence: str | None
    default: bool


class PlannerOut(BaseModel):
    name: str
    description: str
    default: bool


class ArmOut(BaseModel):
    """The arm: ``state`` idle, moving, protective stop, emergency stop, fault or disconnected; ``tcp``
    the flange pose (``xyz_m``, ``quat_xyzw``), None until known."""

    type: str
    model: str
    connected: bool
    state: str
    protective_stop: bool
    faults: list[str]
    tcp: dict[str, list[float]] | None


class QueueOut(BaseModel):
    length: int
    max: int
    held: str | None = Field(description="why queued jobs do not start, or null")
    held_at: datetime | None = Field(description="since when the queue is held until an operator resumes "
                                                 "it (kept across restarts), or null")


class CycleResultOut(BaseModel):
    """One part's result as the line reads it: lengths [m] of the packing box (length >= width), its upper
    bound from the sensor's error model (``upper_*``, what the container is chosen for), the container
    chosen (empty: none fits) with the smallest clearance [m] between the upper bound and its walls or
    lid, and whether the part fits; ``status`` the scan job's, or ``rejected`` when no scan ran;
    ``scan_time_s`` [s] the scan's time on the cell (its job's ``sim_time_s``) and ``converged`` whether it
    completed by its planner's own rule, not its time budget (:class:`cell.line.result.CycleResult`)."""

    job_id: str
    part_id: str
    status: str
    length_m: float
    width_m: float
    height_m: float
    container: str
    clearance_m: float
    fits: bool
    message: str
    upper_length_m: float = 0.0
    upper_width_m: float = 0.0
    upper_height_m: float = 0.0
    scan_time_s: float = 0.0
    converged: bool = False


class StopReasonOut(BaseModel):
    id: int = Field(description="0 none, 1 line Stop, 2 operator STOP, 3 line Abort, 4 safety stop, 5 arm "
                                "fault, 6 scan failed, 7 service shut down, 8 Clear failed")
    message: str


class LineOut(BaseModel):
    """The packing line's PackML state machine: state and unit mode (numbers and names), the part id
    the next Start scans, the cycle's job, the counters, the last stop reason and result, the outcome
    of the last command."""

    state: int
    state_name: str
    mode: int
    mode_name: str
    part_id: str
    job_id: str | None
    processed: int
    defective: int
    stop_reason: StopReasonOut
    result: CycleResultOut | None
    message: str


class LineCommandIn(BaseModel):
    """A PackML command by name (``start``) or number (2); ``part_id`` sets the part the next Start scans
    (sim and dry-run cells: a shipped or uploaded object, optionally ``NAME@x_m,y_m,yaw_deg``)."""

    model_config = ConfigDict(extra="forbid")

    # strict: a true given as the command was taken for 1, Reset
    command: StrictStr | StrictInt = Field(description="reset 1, start 2, stop 3, hold 4, unhold 5, "
                                                       "suspend 6, unsuspend 7, abort 8, clear 9")
    part_id: str | None = Field(None, min_length=1, max_length=PART_ID_MAX, pattern=PART_ID_PATTERN)


class LineCommandOut(BaseModel):
    message: str
    line: LineOut


class LineModeIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    mode: StrictStr | StrictInt = Field(description="production 1 or manual 3")


class LineDioPinOut(BaseModel):
    """One wired signal of the digital-I/O handshake: its name (``trigger_input``, ``busy_output``, ...),
    its standard digital index (DI/DO 0-7) and its level: an input's as the handshake counts it (after the
    debounce filter), an output's as last written; null before the link first connected."""

    name: str
    pin: int
    level: bool | None


class LineDioOut(BaseModel):
    """The line's digital I/O: whether its link is connected, whether it is a sim cell's simulated UR5e
    (whose inputs ``PUT /api/v1/line/dio/inputs/{name}`` sets), and each wired input and output."""

    connected: bool
    simulated: bool
    sampled_s: float | None = Field(description="when the device sampled the inputs the levels were counted "
                                                "from [s, on its clock: a UR controller's RTDE timestamp]; "
                                                "null while the link is not connected")
    inputs: list[LineDioPinOut]
    outputs: list[LineDioPinOut]


class LineDioInputIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    level: StrictBool = Field(description="true: high, false: low")


class LineTransitionOut(BaseModel):
    """One recorded transition: its id (for paging), when, the PackML states before and after, the unit
    mode after, and why."""

    id: int
    at: datetime
    from_state: int
    from_name: str
    to_state: int
    to_name: str
    mode: int
    cause: str


class CellOut(BaseModel):
    """The cell now: name, mode (sim, dry-run, real, replay), a job's time budget when its submission gives
    none [s], arm, sensor, running job, queue, version, and the packing line's state when the cell has
    one."""

    name: str
    mode: str
    version: str
    max_time_s: float
    arm: ArmOut
    sensor: dict[str, Any]
    job: dict[str, Any] | None
    queue: QueueOut
    line: LineOut | None
