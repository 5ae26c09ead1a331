"""The service the routes call, taken from the app (opened in its lifespan).

Every dependency of the API is a coroutine that does no blocking I/O, so that it runs on the event loop:
FastAPI runs a plain ``def`` one in anyio's thread pool, 40 threads shared with every sync route, and a
STOP (whose routes take the service) waited 27 s behind 45 clients polling a slow sync route.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from cell.api.bulk import BulkReads
from cell.service.manager import CellService


async def service(request: Request) -> CellService:
    cell: CellService = request.app.state.service
    return cell


Service = Annotated[CellService, Depends(service)]


async def bulk(request: Request) -> BulkReads:
    reads: BulkReads = request.app.state.bulk
    return reads


Bulk = Annotated[BulkReads, Depends(bulk)]
