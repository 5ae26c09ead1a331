"""Retention: what ``service.retention`` deletes now (any key) and pruning on demand (admin keys)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from cell.api.auth import KeyFirstRoute, Purger, Reader
from cell.api.deps import Bulk, Service
from cell.api.schemas import PrunedOut, RetentionOut
from cell.service.retention import GB, PrunedJob, PrunePlan

router = APIRouter(prefix="/api/v1/retention", tags=["retention"], route_class=KeyFirstRoute)


def _out(cell: Service, plan: PrunePlan, jobs: list[PrunedJob]) -> RetentionOut:
    config = cell.retention.config
    return RetentionOut(days=config.days, max_gb=config.max_gb, total_gb=plan.total_bytes / GB,
                        freed_gb=sum(j.size_bytes for j in jobs) / GB, unmet=plan.unmet,
                        unknown_folders=len(plan.unknown), unknown_gb=plan.unknown_bytes / GB,
                        jobs=[PrunedOut(id=j.job_id, ended_at=j.ended_at, size_mb=j.size_bytes / 1e6,
                                        reason=j.reason) for j in jobs])


@router.get("", response_model=RetentionOut)
async def preview(request: Request, cell: Service, bulk: Bulk, _: Reader) -> Response:
    """The ended jobs that pruning would delete now (a dry run: nothing is deleted)."""

    def planned() -> bytes:  # every job of the store and every file of the jobs folder: a bulk answer
        plan = cell.retention.plan_now()
        return _out(cell, plan, list(plan.jobs)).model_dump_json().encode()

    return await bulk.answer(request, planned)


@router.post("/prune", response_model=RetentionOut)
async def prune_now(cell: Service, _: Purger) -> RetentionOut:
    """Prune now, as the service does by itself every ``service.retention.interval_h`` hours; the answer
    lists the jobs deleted."""
    plan, done = await cell.retention.prune()
    return _out(cell, plan, done)
