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
@router.head("/healthz", operation_id="healthz_head")  # its own id: one shared with the GET is a duplicate
async def healthz(cell: Service) -> dict[str, str]:
    """The process answers (no key needed): liveness, whether or not a job would run; ``instance`` the id
    of this start (``cell.service.instance``: random, it says nothing of the cell), by which ``cell doctor``
    tells the ports this cell's running service holds from another program's. HEAD too, as uptime
    monitors send."""
    return {"status": "ok", "instance": cell.instance}


@router.get("/readyz", responses={503: {"description": "a job submitted now would not run: body says why"}})
@router.head("/readyz", operation_id="readyz_head",
             responses={503: {"description": "a job submitted now would not run: GET's body says why"}})
async def readyz(response: Response, cell: Service,
                 _: Reader) -> dict[str, str]:
    """A job submitted now would run: the service has started, its store answers (to a write too, when the
    newest write failed: ``Store.probe_write``), and nothing keeps the
    next job from starting (``CellService.not_ready``: the queue held, also by a store found damaged, here
    or by any call before, which answers other reads all the same; no worker process can be started, the
    jobs folder not writable or without room for a job); else 503 with the reason as ``status``.
    ``warm_worker`` says whether the next job's worker has loaded its libraries
    (``CellService.warm_worker``: off, none, loading, loaded); a service whose spare is still loading
    takes jobs all the same (the first then waits for the imports), so it does not make the answer 503;
    ``placement_checks`` whether the dispatcher has loaded them (``CellService.placement_checks``:
    loading, loaded), which it does once, about a second after the start, before it starts any job."""
    # first: a deleted file's pool may make an empty one in its place, which answers no read
    lost = await asyncio.to_thread(cell.store.check_file)
    try:
        await asyncio.to_thread(cell.store.count_by_status, cell.name)
    except StoreError:
        if not cell.store.damaged and lost is None:  # else not_ready says how to restore the store
            response.status_code = 503
            return {"status": "the job store does not answer"}
    # a write probe only while the newest write failed: a store that reads but refuses writes (a lock
    # another process holds) takes no job
    whole = not cell.store.damaged and lost is None
    if whole and await asyncio.to_thread(cell.store.probe_write) is not None:
        response.status_code = 503
        return {"status": "the job store does not answer: it takes no write (the log says why)"}
    # off the event loop: it asks the file system about the jobs folder (access, free space)
    if (reason := await asyncio.to_thread(cell.not_ready)) is not None:
        response.status_code = 503
        return {"status": reason}
    return {"status": "ready", "warm_worker": cell.warm_worker, "placement_checks": cell.placement_checks}


@router.get("/metrics", response_class=Response, responses={200: {"content": {CONTENT_TYPE: {}}}})
def metrics(cell: Service, _: Reader) -> Response:
    """Prometheus text format (``cell.service.metrics``)."""
    return Response(cell.metrics.render(), media_type=CONTENT_TYPE)
