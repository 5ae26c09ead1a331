"""What the line reads after a cycle, and what a part id says in a sim or dry-run cell.

In sim and dry-run cells the part id names what the simulated feeder puts on the table: a shipped object
or an uploaded mesh, optionally with a placement ``NAME@x_m,y_m,yaw_deg`` (from the station, as
``cell scan --object-pose``). On a real cell the part id is only recorded.
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass
from typing import Any

from cell.line.config import PART_ID_MAX, PART_ID_PATTERN
from drivers.errors import ServiceError

PLACEMENT_SEPARATOR = "@"


def check_part_id(part_id: str) -> str:
    """``part_id`` if a line may send it (1 to :data:`PART_ID_MAX` characters of
    :data:`PART_ID_PATTERN`, printable ASCII), else ``ServiceError`` (invalid, field ``part_id``)."""
    if not 0 < len(part_id) <= PART_ID_MAX:
        why = f"got {len(part_id)}"
    elif re.fullmatch(PART_ID_PATTERN, part_id) is None:
        why = f"got {part_id!r}"
    else:
        return part_id
    raise ServiceError(f"a part id is 1 to {PART_ID_MAX} printable ASCII characters, {why}", reason="invalid",
                       field="part_id")


def feeder_part(part_id: str) -> tuple[str, tuple[float, float, float] | None]:
    """The object and placement (x [m], y [m], yaw [deg], or None: the cell's default) a sim or dry-run
    cell's feeder puts on the table for ``part_id``; ``ServiceError`` (invalid, field ``part_id``) for an
    object name that is empty or holds a space (no object's name does) or a placement that is not three
    finite numbers. Whether the object exists is the catalogue's to say, when the scan is submitted."""
    name, sep, placement = part_id.partition(PLACEMENT_SEPARATOR)
    if not name or any(c.isspace() for c in name):
        where = " before '@'" if sep else ""
        raise ServiceError(f"part id {part_id!r}: the object name{where} must be one word, no spaces",
                           reason="invalid", field="part_id")
    if not sep:
        return name, None
    try:
        x, y, yaw = (float(v) for v in placement.split(","))
    except ValueError:
        raise ServiceError(f"part id {part_id!r}: the placement after '@' must be x_m,y_m,yaw_deg",
                           reason="invalid", field="part_id") from None
    if not all(math.isfinite(v) for v in (x, y, yaw)):
        raise ServiceError(f"part id {part_id!r}: the placement must be finite numbers", reason="invalid",
                           field="part_id")
    return name, (x, y, yaw)


@dataclass(frozen=True)
class CycleResult:
    """One part's result as the line reads it (``Result/...``).

    ``status`` is the job's (``completed``, ``no_object``: nothing on the table) or ``rejected`` when no scan
    ran (an unknown part): only a cycle that reaches Complete has a result; ``length_m`` >= ``width_m`` and
    ``height_m`` the packing box's estimate [m] (0 when none was measured) and ``upper_length_m``,
    ``upper_width_m``, ``upper_height_m`` its upper bound [m] from the sensor's error model, the box the
    container is chosen for (0 when none was measured); ``container`` the chosen container's name ("" when
    none fits); ``clearance_m`` the smallest gap [m] between the upper bound and the container's walls or lid
    (0 when none fits); ``fits`` whether a container was chosen (a part that fits none is defective, not a
    fault); ``message`` why, in words; ``scan_time_s`` [s] the scan job's time on the cell (its
    ``result.json``'s ``sim_time_s``: the job's clock from its start, the move to the first view included,
    simulated in a sim cell, the wall clock's on a dry-run or real cell; the clock the time budget counts;
    0 when no scan ran); ``converged`` whether the scan completed by its planner's own termination rule
    (false when the time budget ran out, ``result.json``'s ``limit_reached``, and when no part was
    measured)."""

    job_id: str
    part_id: str
    status: str
    length_m: float = 0.0
    width_m: float = 0.0
    height_m: float = 0.0
    container: str = ""
    clearance_m: float = 0.0
    fits: bool = False
    message: str = ""
    upper_length_m: float = 0.0
    upper_width_m: float = 0.0
    upper_height_m: float = 0.0
    scan_time_s: float = 0.0
    converged: bool = False

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CycleResult:
        return cls(**data)


def rejected(part_id: str, reason: str) -> CycleResult:
    """The result of a part the cell would not scan (no job ran)."""
    return CycleResult(job_id="", part_id=part_id, status="rejected", message=reason)


def cycle_result(job_id: str, part_id: str, status: str, termination: str | None,
                 result: dict[str, Any] | None) -> CycleResult:
    """The line's view of a finished job: its ``result.json``'s ``packing`` section (dimensions, container),
    its time and how it ended; a job that found no object gives a no-part result (no dimensions, no
    container)."""
    job = result or {}
    ended: dict[str, Any] = {"scan_time_s": float(job.get("sim_time_s") or 0.0),
                             "converged": status == "completed" and job.get("limit_reached") is False}
    if status == "no_object":
        return CycleResult(job_id=job_id, part_id=part_id, status=status, message=termination or status,
                           **ended)
    packing = (result or {}).get("packing") or {}
    dims = packing.get("dims_m")
    container = packing.get("container") or {}
    reason = str(container.get("reason") or termination or status)
    if not dims:
        return CycleResult(job_id=job_id, part_id=part_id, status=status, message=reason, **ended)
    length, width = sorted(dims[:2], reverse=True)
    height = dims[2]
    upper = packing.get("dims_upper_m") or dims
    # an unbounded face (no container then) leaves the upper bound at 0: not measured
    up_length, up_width, up_height = (0.0, 0.0, 0.0) if None in upper else \
        (*sorted(upper[:2], reverse=True), upper[2])
    inner = container.get("inner_dims_m")
    if not container.get("name") or not inner:
        return CycleResult(job_id, part_id, status, length, width, height, message=reason,
                           upper_length_m=up_length, upper_width_m=up_width, upper_height_m=up_height,
                           **ended)
    in_plane = sorted(inner[:2], reverse=True)
    # the box stands on the container's floor: gaps on each side in the plane, and above it
    clearance = min((in_plane[0] - up_length) / 2.0, (in_plane[1] - up_width) / 2.0, inner[2] - up_height)
    return CycleResult(job_id, part_id, status, length, width, height, str(container["name"]),
                       round(clearance, 6), True, reason, up_length, up_width, up_height, **ended)
