"""Answers that carry a lot of the cell's data (a page of up to 500 jobs with their results, a job folder's
listing of thousands of frames) or read a lot of it (retention's preview: every job of the store and
every file of the jobs folder): read, built and written out as JSON on a worker thread, one at a time.

Such an answer is pure Python work (the store's rows, a pydantic model per job, its JSON: about 0.3 s of
CPU for a page of 500 jobs), and it holds the GIL for all of it, on whichever thread it runs. Built on the
event loop, and read on as many of asyncio's worker threads as there were clients, 40 viewers listing 500
jobs at a time left the loop about one turn in seven of the GIL, and a STOP was answered after 29 s (the
arm of the running job moved on meanwhile). One at a time on one thread, the loop shares the GIL with one
other thread at most, and a bulk answer waiting for its turn costs the loop nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable

from fastapi import Response

BULK_AT_ONCE = 1
"""Bulk answers built at once. One keeps the loop's share of the GIL at half or more; the others wait
their turn on the loop, idle."""


class BulkReads:
    """The app's bulk answers (``app.state.bulk``, made in its lifespan, on its event loop)."""

    def __init__(self) -> None:
        self._turns = asyncio.Semaphore(BULK_AT_ONCE)

    @contextlib.asynccontextmanager
    async def turn(self) -> AsyncIterator[None]:
        """A bulk read's turn: what the context does on worker threads runs with no other bulk read."""
        async with self._turns:
            yield

    async def json(self, build: Callable[[], bytes]) -> Response:
        """The JSON answer whose body ``build`` reads and writes out (on a worker thread, in its turn); an
        ``HTTPException`` or ``ServiceError`` it raises is answered as from the route."""
        async with self.turn():
            body = await asyncio.to_thread(build)
        return Response(body, media_type="application/json")
