"""Liveness (no key), readiness and Prometheus metrics."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, Response

from cell.api.auth import KeyFirstRoute, Reader
from cell.api.deps import Service
from cell.service.metrics import CONTENT_TYPE
from drivers.errors import StoreError

router = APIRouter(tags=["health"], route_class=KeyFirstRoute)


@router.get("/healthz")
async def healthz() -> dict[str, str]:
    """The process answers (no key needed)."""
    return {"status": "ok"}


@router.get("/readyz", responses={503: {"description": "not taking jobs"}})
async def readyz(response: Response, cell: Service,
                 _: Reader) -> dict[str, str]:
    """Taking jobs: the service has started and its store answers. ``warm_worker`` says whether the next
    job's worker has loaded its libraries (``CellService.warm_worker``: off, none, loading, loaded); a
    service whose spare is still loading takes jobs all the same (the first then waits for the imports),
    so it does not make the answer 503."""
    try:
        await asyncio.to_thread(cell.store.count_by_status, cell.name)
    except StoreError:
        response.status_code = 503
        return {"status": "the job store does not answer"}
    if not cell.ready:
        response.status_code = 503
        return {"status": "not taking jobs (starting or shutting down)"}
    return {"status": "ready", "warm_worker": cell.warm_worker}


@router.get("/metrics", response_class=Response, responses={200: {"content": {CONTENT_TYPE: {}}}})
def metrics(cell: Service, _: Reader) -> Response:
    """Prometheus text format (``cell.service.metrics``)."""
    return Response(cell.metrics.render(), media_type=CONTENT_TYPE)
