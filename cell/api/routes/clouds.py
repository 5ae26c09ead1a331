"""A job's cloud, compactly, for the page's 3D view (format: ``cell.service.clouds``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response

from cell.api.auth import KeyFirstRoute, Reader
from cell.api.deps import Bulk, Service
from cell.service.clouds import DEFAULT_MAX_POINTS, MAX_POINTS, encode_cloud, job_cloud

router = APIRouter(prefix="/api/v1/jobs", tags=["jobs"], route_class=KeyFirstRoute)
MEDIA_TYPE = "application/octet-stream"


@router.get("/{job_id}/cloud", response_class=Response, responses={200: {"content": {MEDIA_TYPE: {}}}})
async def get_cloud(request: Request, job_id: str, cell: Service, bulk: Bulk, _: Reader,
                    max_points: Annotated[int, Query(ge=1, le=MAX_POINTS)] = DEFAULT_MAX_POINTS) -> Response:
    """The job's accumulated cloud, base frame: the final one once it ended, the newest snapshot (at
    most about a second old) while it runs. Binary: a 40-byte header (magic ``CLD1``, uint32 points
    sent, uint32 points in the cloud, uint32 1 if final, float32 box min and max [m]) then uint16 x, y, z
    per point within the box, little-endian; at most ``max_points`` points, evenly subsampled."""
    folder = Path((await cell.job(job_id)).folder)
    # a final cloud.ply read and subsampled: a bulk answer (cell.api.bulk)
    return await bulk.answer(request, lambda: encode_cloud(job_cloud(folder), max_points), MEDIA_TYPE,
                             {"Cache-Control": "no-store"})
