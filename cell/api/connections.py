"""The connections ``cell serve`` keeps: how many, how long a client may take to ask, and a log that an
exhausted descriptor table cannot flood.

uvicorn keeps a connection for as long as its client likes before the request's headers are in: a socket
that sends half a request line, or a header every few seconds, held a file descriptor for ever. 1100 of
them under systemd's default soft limit of 1024 descriptors left none for a STOP (it and ``/healthz``
timed out), and asyncio logged each failed ``accept()`` with a traceback, 112 474 times in 25 s. As nginx
and haproxy do, :func:`protocol_class` gives uvicorn a protocol (its h11 one, with these guards) where

- a connection has ``HEADER_TIMEOUT_S`` to deliver a request's headers, counted from its opening or from
  the end of its previous response: this bounds an idle keep-alive connection too (uvicorn's own
  keep-alive timeout ends one that sends nothing sooner, but not one that starts a request and stalls);
- a request's body has ``BODY_TIMEOUT_S``, and the time its length takes at ``MIN_BODY_RATE``, to
  arrive once its headers are in (unless the app answered first): 300 connections that each promised
  15 000 bytes and sent one every 2 s held every slot for as long as they liked, and a STOP got 503;
- at most :attr:`ConnectionLimits.max_connections` are open: a connection that would pass the cap
  closes the one that has waited longest for a request (none in progress: a slow or idle client), so that
  a new client, a STOP among them, always gets in. Else the oldest one still sending its body is cut (a
  slow client again, or a hostile one: nothing has answered it yet), else the oldest one whose response
  is streaming (an event stream: a browser's EventSource reconnects and resumes with ``Last-Event-ID``).
  Only when every open request is being worked on is the newcomer kept over the cap, one of at most
  :attr:`ConnectionLimits.stop_spare`, on probation: a STOP on it is served (and the connection closed
  after it), anything else answered 503 unserved. A stop is known by its request line alone, which the
  newcomer has not sent when it must be placed;
- the answers that refuse a request for want of a valid key (401) go out at most ``REFUSED_RATE`` a
  second past a burst of ``REFUSED_BURST`` (:class:`RefusalPace`): a client waits for its answer before it
  asks again, so that clients without a valid key, however many, cost the service a few dozen requests a
  second. 240 of them asking as fast as they were answered (5000 a second, a log line each) had a valid
  key's STOP answered after 0.6 s, up to 1.3 s. A connection whose refusal is held back is shed first at
  the cap, before an idle one, and one that would wait longer than ``REFUSED_MAX_WAIT_S`` is closed
  unanswered (and not logged as an error). The pace is one for the whole service: during such a flood a
  person whose key is mistyped or revoked waits for the answer, or gets a closed connection rather than a
  401 (the page then says it could not reach the cell); a bucket per client address would not tell
  clients apart behind a reverse proxy. Key hashing is untouched (one SHA-256 of a random key,
  microseconds): the time went to serving and logging the requests, whoever they came from;
- the accept loop takes at most ``backlog`` connections at a time (asyncio's loop accepts up to the
  listen backlog in one go, before any of them is counted), so that the descriptors of a burst stay
  under the limit as well.

:func:`quiet_accept_failures` makes what is left (descriptors taken by something else) one log line per
``cell.service.logs.LOG_INTERVAL_S`` with a count, not a traceback per attempt; the connections shed or
refused at the cap are logged the same way.
"""

from __future__ import annotations

import asyncio
import logging
import math
import resource
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

from starlette.types import ASGIApp, Message, Receive, Scope, Send
from uvicorn.protocols.http.h11_impl import H11Protocol

from cell.service.logs import EveryInterval

log = logging.getLogger("cell.service")

MAX_CONNECTIONS = 256
"""The most connections the service keeps open. Its clients are a few operator pages (a browser holds
up to six connections to a host, and one event stream per job it follows), the line's PLC, the command
line and a metrics scraper: a few dozen; 256 is ten times that."""
FD_SHARE = 4
"""The connections take at most 1/FD_SHARE of the process's soft descriptor limit: each may hold a second
descriptor (a job file being sent, an upload's temporary file), the accept backlog adds half as many
again and the connections on probation an eighth; the line's OPC UA server takes an eighth as many again
and its backlog a sixteenth (:attr:`ConnectionLimits.opcua_connections`). That leaves 30 % of the limit
to the store, the job's worker and its pipes and the logs (the cap is 256 under the usual soft limit of
1024, 64 under 256; 720 descriptors at most for the connections of both servers under 1024)."""
HEADER_TIMEOUT_S = 10.0
"""How long a connection has to deliver a request's headers [s], from its opening or from the end of its
previous response; haproxy's usual ``timeout http-request``. A client on loopback or a LAN sends them in
one packet, in well under a millisecond; ten seconds is room for a congested wireless link."""
BODY_TIMEOUT_S = 10.0
"""How long a request's body may take to arrive after its headers [s], besides ``MIN_BODY_RATE``'s share:
a JSON body comes in one packet with its headers, or just after them."""
MIN_BODY_RATE = 125_000
"""The slowest a body with a length is owed time for [bytes/s]: 1 Mbit/s, a poor wireless link. The
largest, a mesh upload of ``service.max_upload_mb``, 50 MB, then has 410 s; a job's 16 KiB, 10.1 s."""
REFUSED_RATE = 20.0
"""The answers refusing a request for want of a valid key (401) the service gives per second past
``REFUSED_BURST`` [1/s]: a person who mistyped a key, or a page whose key was revoked, asks a few times;
what asks faster than this is a flood, and each of its requests cost the service about 0.3 ms."""
REFUSED_BURST = 40
"""How many 401 answers go out at once before ``REFUSED_RATE`` paces them: a page's dozen calls when its
key is revoked, a script that tries every route without a key."""
REFUSED_MAX_WAIT_S = HEADER_TIMEOUT_S
"""The longest a 401 answer is held back [s]; a request that would wait longer has its connection closed
unanswered, so that a flood of new connections neither queues answers nor pushes the pace ever later."""
ACCEPT_FAILURE = "socket.accept() out of system resource"
"""What asyncio's event loop reports when ``accept()`` fails for want of descriptors or memory."""
BUSY = b"every connection has a request in progress"
BUSY_HEADERS = [(b"content-type", b"text/plain; charset=utf-8"), (b"connection", b"close")]
BUSY_ANSWER = b"".join((b"HTTP/1.1 503 Service Unavailable\r\n", *(b"%s: %s\r\n" % h for h in BUSY_HEADERS),
                        b"content-length: %d\r\n\r\n" % len(BUSY), BUSY))
"""The answer to a connection over the cap when no open one can be closed for it, and to a request on
probation that is not a stop."""


@dataclass(frozen=True)
class ConnectionLimits:
    """The guards of :func:`protocol_class` (see the module docstring)."""

    max_connections: int
    """Connections open at once."""
    header_timeout_s: float = HEADER_TIMEOUT_S
    """How long a connection has to deliver a request's headers [s]."""

    body_timeout_s: float = BODY_TIMEOUT_S
    """How long a request's body has to arrive after its headers [s], besides ``MIN_BODY_RATE``'s share."""

    @property
    def stop_spare(self) -> int:
        """The most connections kept over the cap on probation (a STOP served, nothing else): an eighth of
        it, within the descriptors ``FD_SHARE`` leaves (the accept backlog's half is more)."""
        return max(1, self.max_connections // 8)

    def body_deadline_s(self, length: int) -> float:
        """How long a body of ``length`` bytes (0: not given, chunked) has after its headers [s]."""
        return self.body_timeout_s + length / MIN_BODY_RATE

    @property
    def backlog(self) -> int:
        """The listen backlog, and so the most connections asyncio accepts in one go: half the cap."""
        return max(1, self.max_connections // 2)

    @property
    def opcua_connections(self) -> int:
        """The most connections the line's OPC UA server keeps open (:mod:`cell.line.opcua_connections`),
        out of the same descriptors: an eighth of the cap, 32 under a soft limit of 1024, 8 under 256. A
        line's OPC UA clients are its PLC, an HMI or a SCADA server reading the tags and an engineer's
        client at commissioning: a handful, each one connection (one descriptor; no files)."""
        return max(1, self.max_connections // 8)

    @classmethod
    def of_process(cls) -> ConnectionLimits:
        """``MAX_CONNECTIONS``, or less when this process's soft descriptor limit is low (``FD_SHARE``)."""
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        share = MAX_CONNECTIONS if soft == resource.RLIM_INFINITY else soft // FD_SHARE
        return cls(max(1, min(MAX_CONNECTIONS, share)))


class RefusalPace:
    """When the next 401 answer may go out: ``REFUSED_RATE`` a second past a burst of ``REFUSED_BURST``
    (the generic cell rate algorithm, one pace for every connection of the service)."""

    def __init__(self, rate: float = REFUSED_RATE, burst: int = REFUSED_BURST,
                 max_wait_s: float = REFUSED_MAX_WAIT_S) -> None:
        self._interval = 1.0 / rate
        self._tolerance = (burst - 1) * self._interval  # the burst's first answer is due at once
        self._max_wait_s = max_wait_s
        self._due = -math.inf
        """When the answers given so far would all have gone out at the rate (the loop's clock [s])."""

    def wait_s(self, now: float) -> float | None:
        """How long an answer due at ``now`` (the loop's clock [s]) waits [s], counted as given; None, and
        not counted, if that is longer than ``max_wait_s``."""
        due = max(self._due, now)
        wait = max(0.0, due - now - self._tolerance)
        if wait > self._max_wait_s:
            return None
        self._due = due + self._interval
        return wait


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with header and body deadlines and a connection cap (the module docstring);
    made with its limits by :func:`protocol_class`. h11 is what uvicorn's ``auto`` chooses here (httptools
    is not installed); naming it keeps the guards should httptools ever be."""

    limits: ClassVar[ConnectionLimits]
    at_cap: ClassVar[EveryInterval]
    refusals: ClassVar[RefusalPace]

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._deadline: asyncio.TimerHandle | None = None
        self._body_of: object = None
        """The request whose body the deadline is counting for (its cycle), if any."""
        self.waiting_since = 0.0
        """When this connection began to wait for a request's headers (the loop's clock [s]); kept while
        the request is in progress."""
        self.on_probation = False
        """Kept over the cap: it may stop, nothing else (the module docstring)."""
        self.refusing = False
        """Its request's 401 answer is held back (:class:`RefusalPace`): shed like an idle connection."""

    @property
    def busy(self) -> bool:
        """Whether a request is in progress: its headers are in and its response is not complete."""
        return self.cycle is not None and not self.cycle.response_complete

    @property
    def receiving(self) -> bool:
        """Whether a request in progress is still sending its body, nothing answered yet."""
        return self.busy and self.cycle.more_body and not self.cycle.response_started

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._await_request()
        self.app = _paced_refusals(self.app, self)
        # the connections on probation are over the cap: neither counted nor shed (each serves one request
        # within the header deadline)
        others = [c for c in self.connections if c is not self and not c.transport.is_closing()
                  and isinstance(c, GuardedH11Protocol)]
        counted = [c for c in others if not c.on_probation]
        if len(counted) < self.limits.max_connections:
            return
        refusing = [c for c in counted if c.refusing]
        idle = [c for c in counted if not c.busy]
        receiving = [c for c in counted if c.receiving]
        streaming = [c for c in counted if c.busy and c.cycle.response_started]
        sheddable = refusing or idle or receiving or streaming
        if sheddable:
            _drop(min(sheddable, key=lambda c: c.waiting_since).transport)
        elif len(others) - len(counted) < self.limits.stop_spare:
            self.on_probation = True
            self.app = _stop_only(self.app)
        else:
            self.transport.write(BUSY_ANSWER)
            self.transport.close()
        self.at_cap.event(self.loop)

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_waiting()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self.receiving:
            if self._body_of is not self.cycle:
                self._body_of = self.cycle
                length = dict(self.cycle.scope["headers"]).get(b"content-length", b"")
                self._set_deadline(self.limits.body_deadline_s(int(length) if length.isdigit() else 0),
                                   self._body_late)
        elif self.busy:
            self._stop_waiting()

    def handle_websocket_upgrade(self, event: Any) -> None:
        self._stop_waiting()  # the connection is the WebSocket protocol's from now on
        super().handle_websocket_upgrade(event)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.busy and not self.transport.is_closing():
            self._await_request()

    def _await_request(self) -> None:
        self.waiting_since = self.loop.time()
        self._set_deadline(self.limits.header_timeout_s, lambda: _drop(self.transport))

    def _body_late(self) -> None:
        # an answer started before the body is in (a stream, a stop) did not wait for the body: it is not
        # cut for it (the deadline moves at the answer's end)
        if self.receiving:
            _drop(self.transport)

    def _set_deadline(self, after_s: float, callback: Callable[[], None]) -> None:
        self._stop_waiting()
        self._deadline = self.loop.call_later(after_s, callback)

    def _stop_waiting(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None


def is_stop(scope: Scope) -> bool:
    """Whether a request is a stop (``POST /api/v1/stop``, ``POST /api/v1/jobs/{id}/stop``)."""
    return scope.get("method") == "POST" and str(scope.get("path", "")).endswith("/stop")


def _stop_only(app: ASGIApp) -> ASGIApp:
    """``app`` for a connection on probation: a stop is served (and the connection closed after it, to give
    its place back), anything else is answered 503 without reaching ``app``."""

    async def stop_only(scope: Scope, receive: Receive, send: Send) -> None:
        if not is_stop(scope):
            await send({"type": "http.response.start", "status": 503, "headers": BUSY_HEADERS})
            await send({"type": "http.response.body", "body": BUSY})
            return

        async def closing(message: Message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", []), (b"connection", b"close")]}
            await send(message)

        await app(scope, receive, closing)

    return stop_only


def _paced_refusals(app: ASGIApp, connection: GuardedH11Protocol) -> ASGIApp:
    """``app`` on ``connection`` with its 401 answers paced by the service's :class:`RefusalPace`: held
    back meanwhile (the connection marked ``refusing``), or the connection closed unanswered."""

    async def paced(scope: Scope, receive: Receive, send: Send) -> None:
        closed = False

        async def pacing(message: Message) -> None:
            nonlocal closed
            if message["type"] == "http.response.start" and message["status"] == 401:
                wait_s = connection.refusals.wait_s(connection.loop.time())
                if wait_s is None:
                    closed = True
                    # said disconnected, uvicorn logs no "returned without starting response" error and
                    # sends no 500 for the answer the app did not give
                    connection.cycle.disconnected = True
                    _drop(connection.transport)
                elif wait_s > 0.0:
                    connection.refusing = True
                    try:
                        await asyncio.sleep(wait_s)
                    finally:
                        connection.refusing = False
            if not closed:  # the rest of an answer whose connection was closed goes nowhere
                await send(message)

        await app(scope, receive, pacing)

    return paced


def _drop(transport: asyncio.Transport) -> None:
    """Close a connection now: a plain close waits until what is queued for the client has been sent,
    which a client that does not read never lets happen."""
    if transport.get_write_buffer_size():
        transport.abort()
    else:
        transport.close()


def protocol_class(limits: ConnectionLimits) -> type[GuardedH11Protocol]:
    """The protocol for ``uvicorn.Config(http=...)`` under ``limits``."""

    def line(count: int, _: str) -> None:
        log.warning("connections at the cap of %d: %d more came; for each, the one idle longest was closed "
                    "(with none idle, the oldest still sending its body, else the oldest streaming response "
                    "cut; with none either, the new one may only stop, or is answered 503)",
                    limits.max_connections, count)

    class Limited(GuardedH11Protocol):
        pass

    Limited.limits, Limited.at_cap, Limited.refusals = limits, EveryInterval(line), RefusalPace()
    return Limited


def quiet_accept_failures(loop: asyncio.AbstractEventLoop) -> None:
    """Make the event loop's report of a failed ``accept()`` one line per ``LOG_INTERVAL_S`` (of
    :mod:`cell.service.logs`) with a count (asyncio logs a traceback for every attempt, up to the
    backlog's number each time it retries); every other report goes where it went."""
    previous = loop.get_exception_handler()

    def line(count: int, failure: str) -> None:
        log.error("accept() failed %d times: out of file descriptors or memory (%s); the service accepts "
                  "again a second later", count, failure)

    failures = EveryInterval(line)

    def handler(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        if context.get("message") == ACCEPT_FAILURE:
            failures.event(loop, str(context.get("exception", "")))
        elif previous is not None:
            previous(loop, context)
        else:
            loop.default_exception_handler(context)

    loop.set_exception_handler(handler)
