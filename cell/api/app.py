"""The FastAPI application of ``cell serve``: ``/api/v1`` (OpenAPI at ``/api/v1/openapi.json``, docs at
``/docs``; the packing line under ``/api/v1/line``), ``/healthz``, ``/readyz`` and ``/metrics``.

The lifespan opens what the routes share: the cell's service (store, queue, workers) and the key ring,
which a background task reloads every second so that ``cell keys create`` / ``revoke`` take effect
without a restart. Shutting down stops the running job and finishes its folder, before the line's OPC UA
server closes.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
from collections.abc import AsyncIterator
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from cell import __version__
from cell.api.body_limit import BodyLimit
from cell.api.bulk import BulkReads
from cell.api.connections import ConnectionLimits
from cell.api.routes import cell as cell_routes
from cell.api.routes import clouds, health, jobs, keys, retention
from cell.api.routes import line as line_routes
from cell.api.routes.docs import add_docs
from cell.api.routes.page import add_page
from cell.service.instance import opcua_listening
from cell.service.keys import KeyRing
from cell.service.manager import CellService
from cell.service.startup import ServiceSettings, build_service
from drivers.errors import ServiceError, StoreDamaged, StoreError

KEY_REFRESH_S = 1.0
STATUS_OF = {"invalid": 422, "not found": 404, "conflict": 409, "queue full": 429, "forbidden": 403,
             "unavailable": 503}
log = logging.getLogger("cell.service")


class EchoingResponse(JSONResponse):
    """A JSON answer that may echo what the client sent (a 422's ``input``, a name a ``ServiceError``
    quotes): every character beyond ASCII goes out as a JSON escape. A lone surrogate is a valid JSON
    string (``"\\ud800"``) and so a Python ``str``, but not UTF-8: encoding it failed, a 500 for bad
    input; escaped, it comes back as the client wrote it."""

    def render(self, content: Any) -> bytes:
        return json.dumps(content, ensure_ascii=True, allow_nan=False, separators=(",", ":")).encode("ascii")


async def _refresh_keys(ring: KeyRing) -> None:
    while True:
        await asyncio.sleep(KEY_REFRESH_S)
        try:
            await asyncio.to_thread(ring.refresh)
        except StoreError as exc:
            log.warning("keys not reloaded: %s", exc)


def _line_opcua(cell: CellService, keys: KeyRing) -> contextlib.AbstractAsyncContextManager[object]:
    """The line's OPC UA server while the context runs, when the cell file has ``line.opcua``; asyncua (a
    second of imports) is loaded only then. Its connections take their share of the descriptors that the
    API's connections are capped under."""
    line_config = cell.config.line
    if cell.line is None or line_config is None or line_config.opcua is None:
        return contextlib.nullcontext()
    from cell.line.opcua import serve_opcua
    from cell.line.opcua_connections import OPCUALimits

    limits = OPCUALimits(ConnectionLimits.of_process().opcua_connections)
    return serve_opcua(cell, cell.line, line_config.opcua, keys, limits)


def create_app(settings: ServiceSettings, service: CellService | None = None) -> FastAPI:
    """The application for ``settings`` (or an already built ``service``, which it starts and closes)."""

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        cell = service if service is not None else await asyncio.to_thread(build_service, settings)
        app.state.service = cell
        app.state.keys = await asyncio.to_thread(KeyRing, cell.store)
        app.state.bulk = BulkReads()
        cell.retention.on_thread = app.state.bulk.run  # its automatic prunes too, before start() runs them
        for line in await cell.start():
            log.warning("%s", line)
        refresher = asyncio.create_task(_refresh_keys(app.state.keys))
        opcua = contextlib.AsyncExitStack()
        try:
            if await opcua.enter_async_context(_line_opcua(cell, app.state.keys)) is not None:
                # it listens: cell doctor tells its port from another program's by this (not by /healthz)
                assert cell.config.line is not None and cell.config.line.opcua is not None
                await asyncio.to_thread(opcua_listening, cell.data_dir, cell.instance,
                                        cell.config.line.opcua.endpoint)
            yield
        finally:
            refresher.cancel()
            await cell.close()  # while the OPC UA server serves: the line's PLC sees Stopping and Stopped
            await opcua.aclose()
            cell.store.close()

    # the docs page is cell.api.routes.docs's: FastAPI's own loads its scripts from a CDN
    app = FastAPI(title="cell", version=__version__, lifespan=lifespan,
                  description="An autonomous active-vision scanning cell: run, watch and stop scans.",
                  openapi_url="/api/v1/openapi.json", docs_url=None, redoc_url=None)
    app.add_middleware(BodyLimit)
    app.include_router(cell_routes.router)
    app.include_router(jobs.router)
    app.include_router(line_routes.router)
    app.include_router(health.router)
    app.include_router(clouds.router)
    app.include_router(keys.router)
    app.include_router(retention.router)
    add_page(app)  # the operator's page (cell.web) at / and /static
    add_docs(app)

    @app.exception_handler(ServiceError)
    async def service_error(_: Request, exc: ServiceError) -> JSONResponse:
        status = STATUS_OF.get(exc.reason, 409)
        if status == 422:
            detail: object = [{"loc": ["body", exc.field or "body"], "msg": str(exc), "type": "value_error"}]
        else:
            detail = str(exc)
        return EchoingResponse({"detail": detail}, status_code=status)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(_: Request, exc: RequestValidationError) -> JSONResponse:
        # as FastAPI's own answer, but a NaN or infinite number given (JSON allows neither, Python's
        # parser reads both) is echoed as text, and a lone surrogate escaped: each made FastAPI's answer
        # fail, a 500
        return EchoingResponse({"detail": _finite(jsonable_encoder(exc.errors()))}, status_code=422)

    @app.exception_handler(StoreError)
    async def store_error(_: Request, exc: StoreError) -> JSONResponse:
        log.error("job store: %s", exc)
        if isinstance(exc, StoreDamaged):
            # trying again cannot help; the store's URL and the database's words stay in the log
            return JSONResponse({"detail": "the job store is damaged (it answers, but its data is corrupt): "
                                 "an administrator restores it from a backup (docs/deploy.md, section 9)"},
                                status_code=500)
        return JSONResponse({"detail": "the job store does not answer; try again"}, status_code=503)

    return app


def _finite(value: Any) -> Any:
    """``value`` (JSON-like) with each NaN or infinite float replaced by its text."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value
