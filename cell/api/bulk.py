"""Answers that carry a lot of the cell's data (a page of up to 500 jobs with their results, a job folder's
listing of thousands of frames, a thousand of the line's transitions, a job's cloud) or read a lot of it
(retention's plan: every job of the store and every file of the jobs folder): read, built and written out
on a worker thread, one at a time.

Such an answer is pure Python work (the store's rows, a pydantic model per job, its JSON: about 0.3 s of
CPU for a page of 500 jobs), and it holds the GIL for all of it, on whichever thread it runs. Built on the
event loop, and read on as many of asyncio's worker threads as there were clients, 40 viewers listing 500
jobs at a time left the loop about one turn in seven of the GIL, and a STOP was answered after 29 s (the
arm of the running job moved on meanwhile); 40 viewers reading the line's history (65-330 ms each)
delayed it by 4-7 s. One at a time on one thread, the loop shares the GIL with one other thread at most,
and a bulk answer waiting for its turn costs the loop nothing.

uvicorn does not cancel a handler whose client went away: a request whose client has gone by its turn is
skipped (200 clients that asked for 500 jobs and closed at once made another viewer wait 18 s), and at
most ``BULK_WAITING`` wait for a turn (the others are answered 503 at once, with ``Retry-After``).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import TypeVar

from fastapi import HTTPException, Request, Response

BULK_AT_ONCE = 1
"""Bulk answers built at once. One keeps the loop's share of the GIL at half or more; the others wait
their turn on the loop, idle."""
BULK_WAITING = 32
"""Requests that may wait for a bulk turn. A browser holds up to six connections to a host
(``cell.api.connections.MAX_CONNECTIONS``), so five operator pages with every connection on a bulk read
wait 30; the 32nd is answered within about 32 x 0.3 s (the largest answer, 500 jobs), 10 s, as long as a
client has to send its headers (``cell.api.connections.HEADER_TIMEOUT_S``). More are not pages but a
client looping on them, which would hold every other viewer's answer back by 0.3 s each."""
RETRY_AFTER_S = 1
"""The ``Retry-After`` of a bulk read refused for the queue's length [s]: about three answers' time."""
CLIENT_GONE = 499
"""The status logged for a bulk read skipped because its client closed the connection (nginx's "client
closed request"; nothing is sent)."""
T = TypeVar("T")


class BulkReads:
    """The app's bulk answers (``app.state.bulk``, made in its lifespan, on its event loop)."""

    def __init__(self, waiting: int = BULK_WAITING) -> None:
        self._turns = asyncio.Semaphore(BULK_AT_ONCE)
        self._most_waiting = waiting
        self._waiting = 0

    async def run(self, work: Callable[[], T]) -> T:
        """``work()`` on a worker thread in its turn."""
        await self._turns.acquire()
        return await self._in_turn(work)

    async def _in_turn(self, work: Callable[[], T]) -> T:
        """``work()`` on a worker thread, the turn (taken) given back once the thread has finished, even
        when the caller is cancelled meanwhile: the thread cannot be stopped, and two would overlap."""
        done = asyncio.ensure_future(asyncio.to_thread(work))
        done.add_done_callback(lambda _: self._turns.release())
        return await asyncio.shield(done)

    async def answer(self, request: Request, build: Callable[[], bytes], media_type: str = "application/json",
                     headers: dict[str, str] | None = None) -> Response:
        """The answer to ``request`` whose body ``build`` reads and writes out, in its turn; an
        ``HTTPException`` or ``ServiceError`` it raises is answered as from the route. 503 when
        ``BULK_WAITING`` requests wait already; nothing is built when the client has gone by its turn."""
        if self._waiting >= self._most_waiting:
            raise HTTPException(503, f"{self._waiting} requests for large answers (job lists, file lists, "
                                "the line's history, clouds, retention) are waiting already: ask again later",
                                headers={"Retry-After": str(RETRY_AFTER_S)})
        self._waiting += 1
        try:
            await self._turns.acquire()
        finally:
            self._waiting -= 1
        try:
            gone = await request.is_disconnected()
        except BaseException:
            self._turns.release()
            raise
        if gone:
            self._turns.release()
            return Response(status_code=CLIENT_GONE)
        body = await self._in_turn(build)
        return Response(body, media_type=media_type, headers=headers)
