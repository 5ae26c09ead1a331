"""A bound on request bodies, checked before anything reads them.

FastAPI reads and parses a JSON body before a route's dependencies run, and parses it on the event loop:
a large one held the loop (and so a STOP) for a second. A request without a valid key never gets this
far (``cell.api.auth.KeyFirstRoute`` answers it 401 unread); a keyed one's body is bounded here:
a JSON one (a job, a command) is well under ``JSON_MAX_BYTES``; a mesh upload (``POST /api/v1/objects``,
multipart, parsed into a temporary file) under the cell's ``service.max_upload_mb`` and
``MULTIPART_SLACK_BYTES`` of form fields and boundaries; a stop is not bounded here, as it reads only the
start of its body (``cell.api.stop_reason``). A larger body is answered 413 unread, or as soon as what has
arrived passes the bound when the request does not give its length.
"""

from __future__ import annotations

from typing import Any

from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from cell.api.connections import is_stop

JSON_MAX_BYTES = 16 << 10
"""16 KiB [bytes]. The largest JSON body a route takes is a job request: three names of at most 64, 128
and 64 characters (6 bytes each when written as ``\\uXXXX`` escapes: under 2 KiB) and four numbers; a
line command or a mode is smaller. 16 KiB leaves room for pretty-printed JSON and fields to come, and
parsing it costs the event loop well under a millisecond (at 1 MiB, eight clients slowed a STOP from
milliseconds to 0.5-0.9 s)."""
MULTIPART_SLACK_BYTES = 1 << 20
"""What an upload's form adds to its file: the boundaries, the headers of its parts, the scale field."""
UPLOAD_PATH = "/api/v1/objects"


class BodyLimit:
    """ASGI middleware: 413 for a request body over its bound (the module docstring)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or is_stop(scope):
            await self.app(scope, receive, send)
            return
        bound = _bound(scope)
        length = dict(scope["headers"]).get(b"content-length", b"")
        if length.isdigit() and int(length) > bound:
            await _refuse(scope, receive, send, bound)
            return
        received = 0
        over = started = False

        async def counted() -> Message:
            # past the bound the app is told the client left: a raised error would be caught by FastAPI's
            # body reading and answered 400 there
            nonlocal received, over
            if over:
                return {"type": "http.disconnect"}
            message = await receive()
            received += len(message.get("body", b""))
            over = received > bound
            return {"type": "http.disconnect"} if over else message

        async def sending(message: Message) -> None:
            nonlocal started
            if not over:
                started = True
                await send(message)

        try:
            await self.app(scope, counted, sending)
        except Exception:
            if not over:
                raise
        if over and not started:
            await _refuse(scope, receive, send, bound)


def _bound(scope: Scope) -> int:
    """The most bytes the request's body may have: a mesh upload's (the cell's ``max_upload_mb``, and
    the form around it), else a JSON body's."""
    if scope.get("method") == "POST" and scope.get("path") == UPLOAD_PATH:
        config = scope["app"].state.service.config
        return int(config.service.max_upload_mb * 1e6) + MULTIPART_SLACK_BYTES
    return JSON_MAX_BYTES


async def _refuse(scope: Scope, receive: Receive, send: Send, bound: int) -> None:
    response: Any = JSONResponse({"detail": f"the request's body is over {bound} bytes"}, status_code=413)
    await response(scope, receive, send)
