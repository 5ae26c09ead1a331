"""The reason a STOP gives, taken from whatever body the request has: a stop is never refused for its body.

STOP must work for every valid key whatever else it sends, so the stop routes read no model: a body that
is missing, not JSON, too large, or whose ``reason`` is not a string (or is empty, or an extra field sits
beside it) stops as a body of ``{"reason": DEFAULT_REASON}`` does. A reason is recorded in the job's
termination and its ``log.txt``, so it is kept to one line of printable characters (a newline or an
escape sequence in it would forge a line of the log) and ``MAX_LENGTH`` characters, without a stop's
kind at its start (``STOP_KINDS``: the service says who stopped). Only the first
``MAX_BODY_BYTES`` of a body are read: no body, however large, costs a stop time or memory.

Nor does a body that is slow to come, or never comes: a stop acts on its headers. The reason is taken
from a body that is in within ``REASON_WAIT_S`` of them; a body that is still arriving then, or whose
client has left, stops with the default reason (the stop used to wait for the whole body, for ever, and
a client that left before sending it had its stop dropped).
"""

from __future__ import annotations

import asyncio
import json
from typing import Annotated, Any

from fastapi import Depends, Request
from starlette.requests import ClientDisconnect

from drivers.errors import OPERATOR_STOP, SAFETY_STOP, SHUTDOWN_STOP

DEFAULT_REASON = "requested over the API"
STOP_KINDS = tuple(kind.strip() for kind in (OPERATOR_STOP, SHUTDOWN_STOP, SAFETY_STOP))
"""How a termination says who stopped the job: a reason that begins so has it taken off (a client's
``shutdown stop: ...`` was recorded as the service's shutdown, not as the operator stop it was)."""
MAX_LENGTH = 200
"""Characters of a reason that are kept."""
MAX_BODY_BYTES = 4096
"""A stop's body beyond this is not read, and the default reason stands."""
REASON_WAIT_S = 0.2
"""The longest a stop waits for the rest of its body [s], and so the most a stop is delayed, only ever
for a client that sent its headers without its body. A body sent with its headers is read without
waiting, one written just after them (httpx writes the two apart) within milliseconds; the bound leaves
room for an event loop kept from running for a moment on a loaded machine. A stop is worth more than
its reason: nothing longer is waited for."""


async def stop_reason(request: Request) -> str:
    """The request's ``reason``, one printable line of at most ``MAX_LENGTH`` characters, or the default
    (the module docstring)."""
    try:
        raw = await asyncio.wait_for(_body_start(request), REASON_WAIT_S)
    except (TimeoutError, ClientDisconnect):
        return DEFAULT_REASON
    if raw is None:
        return DEFAULT_REASON
    try:
        body: Any = json.loads(raw) if raw else None
    except (ValueError, RecursionError):
        return DEFAULT_REASON
    reason = body.get("reason") if isinstance(body, dict) else None
    if not isinstance(reason, str):
        return DEFAULT_REASON
    line = " ".join("".join(c if c.isprintable() else " " for c in reason).split())
    while line.startswith(STOP_KINDS):  # a stop's kind is the service's word, never the client's
        line = line.partition(":")[2].strip()
    return line[:MAX_LENGTH] or DEFAULT_REASON


async def _body_start(request: Request) -> bytes | None:
    """The request's body, or None once it is over ``MAX_BODY_BYTES`` (the rest is not read)."""
    raw = bytearray()
    async for chunk in request.stream():
        raw += chunk
        if len(raw) > MAX_BODY_BYTES:
            return None
    return bytes(raw)


StopReason = Annotated[str, Depends(stop_reason)]
