"""Jobs: submit, list, read, cancel or purge, stop, follow live (Server-Sent Events), download files."""

from __future__ import annotations

import asyncio
import json
import mimetypes
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Header, HTTPException, Query, Request, Response
from fastapi.responses import FileResponse, StreamingResponse
from pydantic import AwareDatetime, TypeAdapter

from cell.api.auth import Canceller, Keeper, KeyFirstRoute, Reader, Stopper, Submitter, forbidden
from cell.api.deps import Bulk, Service
from cell.api.schemas import STOP_BODY, FileOut, JobOut, JobPage, JobSubmit, KeepIn, StopOut
from cell.api.stop_reason import StopReason
from cell.service.keys import KeyRing, Permission, allowed
from cell.service.recovery import folder_files
from cell.service.store import FINISHED_STATUSES, JOB_STATUSES, JobRecord

router = APIRouter(prefix="/api/v1/jobs", tags=["jobs"], route_class=KeyFirstRoute)
KEEP_ALIVE_S = 15.0
"""An event stream with nothing to say sends a comment this often [s], so proxies keep it open."""
KEY_CHECK_S = 1.0
"""How often an open event stream checks that its key is still active [s], at least: at each event and
after this long without one. The service reloads the keys every second (``cell.api.app``), so a stream
whose key is revoked ends within about two seconds, as the key's other requests are refused."""
FILE_LIST = TypeAdapter(list[FileOut])
CONTENT_TYPES = {".json": "application/json", ".csv": "text/csv; charset=utf-8",
                 ".txt": "text/plain; charset=utf-8", ".png": "image/png", ".ply": "application/octet-stream",
                 ".bt": "application/octet-stream", ".npz": "application/octet-stream"}


@router.post("", response_model=JobOut, status_code=201)
async def submit(body: JobSubmit, response: Response, cell: Service,
                 key: Submitter) -> JobOut:
    """Queue a scan. 201 with the job and its ``Location``; 422 naming the field for invalid input; 429
    when the queue is full."""
    job = await cell.submit(body.request(), submitted_by=key.name)
    response.headers["Location"] = f"/api/v1/jobs/{job.id}"
    return JobOut.of(job)


STATUS_FILTER = Query(description="any of " + ", ".join(JOB_STATUSES))
CREATED_FILTER = Query(description="a date and time with its timezone (ISO 8601, e.g. 2026-01-01T00:00:00Z "
                                   "or 2026-01-01T08:00:00+08:00)")


@router.get("", response_model=JobPage)
async def list_jobs(request: Request, cell: Service, bulk: Bulk, _: Reader,
                    status: Annotated[list[str] | None, STATUS_FILTER] = None,
                    planner: str | None = None, part_id: str | None = None,
                    created_after: Annotated[AwareDatetime | None, CREATED_FILTER] = None,
                    created_before: Annotated[AwareDatetime | None, CREATED_FILTER] = None,
                    limit: Annotated[int, Query(ge=1, le=500)] = 50,
                    offset: Annotated[int, Query(ge=0, le=10**9)] = 0) -> Response:
    """This cell's jobs, newest first, filtered and paginated. ``created_after`` and ``created_before`` need
    their timezone: a time without one is refused (422, "Input should have timezone info") rather than
    taken as UTC, since the cell's PC, its store and the person asking may keep different zones, and a
    guess would shift the answer by hours without a word."""
    # A time without its zone was a 500. A bulk answer (cell.api.bulk): a page of 500 jobs, built on the
    # event loop, kept a STOP out for 29 s under 40 viewers.
    unknown = sorted(set(status or ()) - set(JOB_STATUSES))
    if unknown:
        message = f"unknown status {unknown[0]!r}; one of {', '.join(JOB_STATUSES)}"
        raise HTTPException(422, [{"loc": ["query", "status"], "type": "value_error", "msg": message}])

    def page() -> bytes:
        jobs, total = cell.store.list_jobs(
            cell=cell.name, statuses=status, planner=planner, part_id=part_id, created_after=created_after,
            created_before=created_before, limit=limit, offset=offset)
        return JobPage(items=[JobOut.of(cell.as_now(j)) for j in jobs], total=total, limit=limit,
                       offset=offset).model_dump_json().encode()

    return await bulk.answer(request, page)


@router.get("/{job_id}", response_model=JobOut)
async def get_job(job_id: str, cell: Service, _: Reader) -> JobOut:
    """Status, progress, times and, once it ended, the whole result.json under ``result``."""
    return JobOut.of(await cell.job(job_id))


@router.delete("/{job_id}", response_model=JobOut | None)
async def delete_job(job_id: str, cell: Service,
                     key: Canceller) -> JobOut | None:
    """A queued job becomes ``cancelled``. An ended job is purged (its folder and record deleted; admin
    keys only)."""
    job = await cell.job(job_id)
    if job.status in FINISHED_STATUSES:
        if not allowed(key.role, Permission.PURGE):
            raise forbidden(key.role, "purge an ended job")
        await cell.purge(job_id)
        return None
    return JobOut.of(await cell.cancel(job_id, f"cancelled by key {key.name}"))


@router.put("/{job_id}/keep", response_model=JobOut)
async def keep_job(job_id: str, body: KeepIn, cell: Service, _: Keeper) -> JobOut:
    """Mark the job kept (``service.retention`` never deletes it) or release it."""
    return JobOut.of(await cell.set_keep(job_id, body.keep))


@router.post("/{job_id}/stop", response_model=StopOut, openapi_extra=STOP_BODY)
async def stop_job(job_id: str, cell: Service, key: Stopper, reason: StopReason) -> StopOut:
    """Stop this job: the arm is commanded to stop before this answers. Every valid key may stop a running
    job, with any body (``reason`` optional, as for STOP); a queued job is cancelled, which needs a key
    that may cancel (403 for a viewer's)."""
    outcome = await cell.stop_job(job_id, f"{reason} (key {key.name})",
                                  may_cancel=allowed(key.role, Permission.CANCEL))
    return StopOut(job_id=outcome.job_id, arm_commanded=outcome.arm_commanded, message=outcome.message,
                   queue_held=cell.hold_reason() is not None)


@router.get("/{job_id}/events", response_class=StreamingResponse,
            responses={200: {"content": {"text/event-stream": {}}}})
async def job_events(job_id: str, request: Request, cell: Service, key: Reader,
                     last_event_id: Annotated[int | None, Header(ge=0)] = None) -> StreamingResponse:
    """Server-Sent Events: ``state`` (queued, running, stopping, completed, failed, stopped, cancelled,
    interrupted), ``progress`` at each perception update, and a final ``result``. Reconnect with
    ``Last-Event-ID`` to resume where the stream broke off. The stream ends once its key is revoked
    (within about two seconds, ``KEY_CHECK_S``; a reconnection with it is then refused, 401), and within
    about a second once the service begins to shut down."""
    log = await cell.job_events(job_id)
    metrics = cell.metrics
    ring: KeyRing = request.app.state.keys

    async def stream() -> AsyncIterator[str]:
        metrics.sse_clients.inc()
        quiet_s = 0.0  # since the last thing sent [s]
        try:
            async for event in log.follow(last_event_id or 0, KEY_CHECK_S):
                # nor does it outlast a shutdown's wait for open requests (2 s), which would cut it with an
                # error logged: the client resumes from the restarted service with Last-Event-ID
                if not ring.active(key) or cell.closing:
                    return
                if event is not None:
                    quiet_s = 0.0
                    yield f"id: {event.id}\nevent: {event.kind}\ndata: {json.dumps(event.data)}\n\n"
                elif (quiet_s := quiet_s + KEY_CHECK_S) >= KEEP_ALIVE_S:
                    quiet_s = 0.0
                    yield ": keep-alive\n\n"
        finally:
            metrics.sse_clients.dec()

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


def _inside(folder: Path, name: str) -> Path | None:
    """The file ``name`` of a job folder; None for anything that is not a file inside it, nor a name the
    file system refuses (too long: ``ENAMETOOLONG``, which was a 500). It reads the file system: run it
    on a thread."""
    # a NUL byte is refused before resolving: os.path.realpath raises ValueError on one (a 500)
    if "\0" in name:
        return None
    try:
        root = folder.resolve()
        path = (root / name).resolve()
        inside = path.is_relative_to(root) and path != root and path.is_file()
    except OSError:
        return None
    return path if inside else None


def _folder(job: JobRecord) -> Path:
    """The folder of ``job``; 410 when the job ran but its folder is missing (the data dir was moved or
    restored without it, or it was deleted), which a listing must not show as a folder with no files. It
    reads the file system: run it on a thread."""
    folder = Path(job.folder)
    if job.status in FINISHED_STATUSES - {"cancelled"} and not folder.is_dir():
        raise HTTPException(410, f"the folder of job {job.id} is missing from the data dir (jobs/{job.id}): "
                                 "it was moved or deleted; restore it there to serve its files")
    return folder


def _job_file(job: JobRecord, name: str) -> Path | None:
    """The file ``name`` of ``job``'s folder (:func:`_inside` of :func:`_folder`, 410 for an ended job's
    missing folder): one trip to a thread for both."""
    return _inside(_folder(job), name)


def _listing(job: JobRecord) -> bytes:
    """Every file of a job's folder, as the JSON of a list of ``FileOut`` (none while it does not exist
    yet: a job that has not started, or never will; 410 for an ended job's: :func:`_folder`). It walks
    the folder and stats each file (a scan's thousands of frames): run it on a thread, never on the event
    loop, where it delayed a STOP by up to 2 s under 100 viewers."""
    folder, job_id = _folder(job), job.id
    files: list[FileOut] = []
    if folder.is_dir():
        root = folder.resolve()
        files = [FileOut(name=str(p.relative_to(root)), size_bytes=p.stat().st_size,
                         url=f"/api/v1/jobs/{job_id}/files/{p.relative_to(root)}")
                 for p in folder_files(root)]
    return FILE_LIST.dump_json(files)


@router.get("/{job_id}/files", response_model=list[FileOut])
async def list_files(request: Request, job_id: str, cell: Service, bulk: Bulk,
                     _: Reader) -> Response:
    """Every file of the job folder (frames included)."""
    job = await cell.job(job_id)
    return await bulk.answer(request, lambda: _listing(job))  # thousands of frames: a bulk answer


@router.get("/{job_id}/files/{name:path}", response_class=FileResponse)
async def get_file(job_id: str, name: str, cell: Service,
                   _: Reader) -> FileResponse:
    """One file of the job folder (``result.json``, ``cloud.ply``, ``map.bt``, ``trajectory.csv``,
    ``servo.png``, ``path.png``, ``log.txt``, ``frames/000000.npz``, ...); nothing outside it."""
    path = await asyncio.to_thread(_job_file, await cell.job(job_id), name)
    if path is None:
        raise HTTPException(404, f"no file {name!r} in this job's folder")
    media = CONTENT_TYPES.get(path.suffix) or mimetypes.guess_type(path.name)[0] or "application/octet-stream"
    return FileResponse(path, media_type=media, filename=path.name, content_disposition_type="inline")
