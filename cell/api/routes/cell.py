"""The cell: its status, what it can run and scan, the operator's STOP, the arm and the queue."""

from __future__ import annotations

import asyncio
from functools import partial
from typing import Annotated

from fastapi import APIRouter, Form, UploadFile

from cell.api.auth import KeyFirstRoute, Reader, Recoverer, Stopper, Uploader
from cell.api.deps import Service
from cell.api.schemas import STOP_BODY, CellOut, ObjectOut, PlannerOut, RecoverOut, StopOut
from cell.api.stop_reason import StopReason
from cell.service.manager import CellService
from cell.service.objects import ObjectEntry
from cell.service.store import RUNNING_STATUSES
from drivers.errors import ServiceError
from drivers.sim.objects import DEFAULT_OBJECT

router = APIRouter(prefix="/api/v1", tags=["cell"], route_class=KeyFirstRoute)
UPLOAD_CHUNK = 1 << 20


@router.get("/cell", response_model=CellOut)
async def get_cell(cell: Service, _: Reader) -> dict[str, object]:
    """Name, mode, arm, sensor, the running job and its progress, the queue, the software version."""
    return cell.status()


@router.get("/planners", response_model=list[PlannerOut])
async def get_planners(cell: Service,
                       _: Reader) -> list[dict[str, str | bool]]:
    """The planners a job may name, the cell's default marked."""
    return cell.planners()


@router.get("/objects", response_model=list[ObjectOut])
def get_objects(cell: Service, _: Reader) -> list[ObjectOut]:
    """Sim and dry-run cells: the shipped objects and the uploaded meshes (a real cell scans real ones:
    none)."""
    if not cell.objects.virtual:
        return []
    return [_object_out(e) for e in cell.objects.entries()]


def _object_out(entry: ObjectEntry) -> ObjectOut:
    """``entry`` as the API gives it: the shipped object ``cell scan`` takes by default marked."""
    return ObjectOut(name=entry.name, source=entry.source, extents_m=entry.extents_m, licence=entry.licence,
                     default=entry.source == "shipped" and entry.name == DEFAULT_OBJECT)


def _virtual_only(cell: CellService) -> None:
    """Refuse uploaded meshes on a cell that scans real objects (409)."""
    if not cell.objects.virtual:
        raise ServiceError(f"a {cell.config.mode} cell scans real objects; meshes are for sim and dry-run "
                           "cells", reason="conflict")


@router.post("/objects", response_model=ObjectOut, status_code=201)
async def post_object(cell: Service, file: UploadFile, _: Uploader,
                      scale: Annotated[float, Form(gt=0.0, allow_inf_nan=False,
                                                   description="multiplies the mesh's coordinates into "
                                                               "metres (0.001 for millimetres)")] = 1.0,
                      ) -> ObjectOut:
    """Upload a PLY, OBJ or STL mesh, z-up (sim and dry-run cells), in metres or with the ``scale`` that
    converts it; it is named after the file. A mesh of a size the cell cannot scan is refused (422),
    saying what a scale would make of it."""
    _virtual_only(cell)
    limit = int(cell.config.service.max_upload_mb * 1e6)
    data = bytearray()
    while chunk := await file.read(UPLOAD_CHUNK):
        data += chunk
        if len(data) > limit:
            raise ServiceError(f"the file is above the cell's {limit / 1e6:g} MB", reason="invalid",
                               field="file")
    entry = await asyncio.to_thread(cell.objects.add, file.filename or "upload", bytes(data), scale)
    return _object_out(entry)


@router.delete("/objects/{name}", status_code=204)
async def delete_object(cell: Service, name: str, _: Uploader) -> None:
    """Delete an uploaded object (sim and dry-run cells). Refused (409) for a shipped object and for one
    that a queued or running job scans; 404 for an unknown one."""
    _virtual_only(cell)
    await asyncio.to_thread(cell.objects.remove, name,
                            partial(cell.store.jobs_in_status, cell.name, ("queued", *RUNNING_STATUSES)))


@router.post("/stop", response_model=StopOut, openapi_extra=STOP_BODY)
async def post_stop(cell: Service, key: Stopper, reason: StopReason) -> StopOut:
    """STOP: whatever moves is commanded to stop (through the guard) before this answers, and queued jobs
    are held until an operator resumes the queue. Every valid key may stop, with any body (``reason``
    optional; a body that does not give one stops all the same)."""
    outcome = await cell.stop_all(f"{reason} (key {key.name})")
    return StopOut(job_id=outcome.job_id, arm_commanded=outcome.arm_commanded, message=outcome.message,
                   queue_held=cell.hold_reason() is not None)


@router.post("/arm/recover", response_model=RecoverOut)
async def post_recover(cell: Service,
                       _: Recoverer) -> dict[str, object]:
    """After a protective stop (or another fault the arm reported): clear it, as `cell arm recover` does.
    Queued jobs may start again once it is cleared."""
    return await cell.recover_arm()


@router.post("/queue/resume", response_model=CellOut)
async def post_resume(cell: Service,
                      _: Recoverer) -> dict[str, object]:
    """Let queued jobs start again after a STOP (refused while the arm is faulted: recover it first)."""
    cell.resume()
    return cell.status()
