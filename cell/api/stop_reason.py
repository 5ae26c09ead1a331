"""The reason a STOP gives, taken from whatever body the request has: a stop is never refused for its body.

STOP must work for every valid key whatever else it sends, so the stop routes read no model: a body that
is missing, not JSON, too large, or whose ``reason`` is not a string (or is empty, or an extra field sits
beside it) stops as a body of ``{"reason": DEFAULT_REASON}`` does. A reason is recorded in the job's
termination and its ``log.txt``, so it is kept to one line of printable characters (a newline or an
escape sequence in it would forge a line of the log) and ``MAX_LENGTH`` characters. Only the first
``MAX_BODY_BYTES`` of a body are read: no body, however large, costs a stop time or memory.
"""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import Depends, Request

DEFAULT_REASON = "requested over the API"
MAX_LENGTH = 200
"""Characters of a reason that are kept."""
MAX_BODY_BYTES = 4096
"""A stop's body beyond this is not read, and the default reason stands."""


async def stop_reason(request: Request) -> str:
    """The request's ``reason``, one printable line of at most ``MAX_LENGTH`` characters, or the default
    (the module docstring)."""
    raw = bytearray()
    async for chunk in request.stream():
        raw += chunk
        if len(raw) > MAX_BODY_BYTES:
            return DEFAULT_REASON
    try:
        body: Any = json.loads(raw) if raw else None
    except (ValueError, RecursionError):
        return DEFAULT_REASON
    reason = body.get("reason") if isinstance(body, dict) else None
    if not isinstance(reason, str):
        return DEFAULT_REASON
    line = " ".join("".join(c if c.isprintable() else " " for c in reason).split())
    return line[:MAX_LENGTH] or DEFAULT_REASON


StopReason = Annotated[str, Depends(stop_reason)]
