"""What a client asks of a scan job, checked against the cell before it is queued.

Every check that ``cell scan`` would make before anything moves is made here, at submission, so that a
bad request is answered at once (naming the field) instead of failing later on the arm: the planner is
registered, the object is known, of a size the cell scans and stands on the table at the pose asked
(``"none"``: an empty table), clear of the arm at its home joints and seen by one of the planner's search
views (an upload's by the points on its surface the service keeps of it), the seed and the time budget are
in range. The job's worker repeats all of these, and makes the one that needs an upload's mesh, which the
service does not keep (only its outline): its placement clear of the arm.
"""

from __future__ import annotations

from dataclasses import dataclass

from cell.config.models import CellConfig
from cell.jobs.inputs import check_seed
from cell.jobs.placement import check_object_size, check_on_table
from cell.planning.registry import check_planner
from cell.service.arm_clearance import ArmClearance
from cell.service.objects import ObjectLibrary
from cell.service.search_views import SearchViews
from drivers.errors import JobError, PlanningError, ServiceError
from drivers.sim.objects import EMPTY_TABLE, ObjectMesh

MAX_TIME_BUDGET_S = 3600.0
"""The longest time budget a job may ask for [s]: an hour, twenty times the papers' longest scans."""


@dataclass(frozen=True)
class JobRequest:
    """A client's request; None takes the cell's default (``object`` has none on a sim or dry-run cell).
    ``object_pose`` is (x [m], y [m], yaw [deg]) from the station."""

    planner: str | None = None
    object: str | None = None
    object_pose: tuple[float, float, float] | None = None
    seed: int | None = None
    max_time_s: float | None = None
    part_id: str | None = None


@dataclass(frozen=True)
class ValidJob:
    """A request with the cell's defaults filled in; ``object_source`` is what the worker loads (a
    shipped name or an uploaded file's path; the label on a real cell)."""

    planner: str
    object: str | None
    object_source: str
    object_pose: tuple[float, float, float]
    seed: int
    max_time_s: float | None
    part_id: str | None


def _invalid(message: str, field: str) -> ServiceError:
    return ServiceError(message, reason="invalid", field=field)


def validate(config: CellConfig, objects: ObjectLibrary, arm: ArmClearance, views: SearchViews,
             req: JobRequest) -> ValidJob:
    """The request completed with the cell's defaults, or ``ServiceError`` (invalid) naming the field;
    ``arm`` checks a shipped object's placement against the arm, ``views`` in the planner's search views.
    Slow at the first call that checks a placement, or names a planner (``ArmClearance``,
    ``SearchViews``): call it off the event loop."""
    planner = req.planner or config.scan.planner
    try:
        check_planner(planner)
    except PlanningError as exc:
        raise _invalid(str(exc), "planner") from None
    seed = 0 if req.seed is None else req.seed
    try:
        check_seed(seed)
    except JobError as exc:
        raise _invalid(str(exc), "seed") from None
    if req.max_time_s is not None and not 0.0 < req.max_time_s <= MAX_TIME_BUDGET_S:
        raise _invalid(f"max_time_s must be above 0 and at most {MAX_TIME_BUDGET_S:g} s, got "
                       f"{req.max_time_s}", "max_time_s")
    pose = req.object_pose or (0.0, 0.0, 0.0)
    if not objects.virtual:
        label = req.object or "unknown"
        return ValidJob(planner, req.object, label, pose, seed, req.max_time_s, req.part_id)
    if req.object is None:
        raise _invalid(f"a {config.mode} cell scans a virtual object: name one (GET /api/v1/objects)",
                       "object")
    if req.object == EMPTY_TABLE:
        return ValidJob(planner, req.object, EMPTY_TABLE, pose, seed, req.max_time_s, req.part_id)
    source = objects.source(req.object)
    # an upload's outline, with its surface points: the service reads no uploaded mesh
    shape = objects.shape(req.object, surface=True)
    try:
        check_object_size(config, shape, option="uploading it again with scale")
    except JobError as exc:  # an upload kept from before the cell checked sizes
        raise _invalid(str(exc), "object") from None
    try:
        check_on_table(config, shape, pose)
        if isinstance(shape, ObjectMesh):  # a shipped mesh; an upload's outline has no faces to test
            arm.check(shape, pose)
        views.check(shape, pose, planner)
    except JobError as exc:
        raise _invalid(str(exc), "object_pose") from None
    return ValidJob(planner, req.object, source, pose, seed, req.max_time_s, req.part_id)
