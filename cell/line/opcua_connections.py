"""The connections the line's OPC UA server keeps: how many, how many from one address, and how long a
client may take to say Hello.

asyncua's server accepts every TCP connection (up to a thousand) and keeps one that never speaks until
its watchdog sees no activated session, 30 s later. It runs on the event loop of ``cell serve``'s HTTP
server, in its process: a broken or hostile client on the line's network could hold connections until
the process had no file descriptor left, and an operator's STOP could not be accepted. As the HTTP
guard (:mod:`cell.api.connections`) does for the API, :class:`GuardedServer` keeps

- at most :attr:`OPCUALimits.max_connections` open, a share of the descriptors the HTTP guard budgets
  (``cell.api.connections.ConnectionLimits.opcua_connections``), and at most :attr:`OPCUALimits.per_peer`
  from one address. A connection that would pass either closes one that holds no activated session (a
  client logged in with a key is never closed to make room): one that has not said Hello first, from the
  address that holds the most of them (a flood's, not the PLC's one), the oldest there (:func:`_to_close`).
  With every one logged in, the newcomer is refused with OPC UA's ``Bad_TcpServerTooBusy``;
- a connection whose client has not sent its whole Hello, the first message of OPC UA's TCP protocol
  (OPC 10000-6, 7.1), within :attr:`OPCUALimits.hello_timeout_s` is closed, and so is one that begins
  with anything else or a Hello longer than :data:`HELLO_MAX_BYTES`, or later sends a message chunk longer
  than the receive buffer the server acknowledged (:meth:`GuardedProtocol.data_received`); one that said
  Hello and activates no session is closed by asyncua's watchdog after :data:`ACTIVATION_TIMEOUT_S`;
- the listen backlog at :attr:`OPCUALimits.backlog`: asyncio accepts up to it in one go, before any of
  the connections is counted.

asyncua has no parameter for its listener's class or protocol: ``Server.start`` builds a
``BinaryServer`` and starts it at once. :class:`GuardedServer` puts a :class:`GuardedBinaryServer` in
its place as ``start`` assigns it (asyncua's own start is kept whole: its certificate check, its nodes);
that one makes :class:`GuardedProtocol` for each connection and listens with the backlog. Only this
server's listener is changed; asyncua's classes are not patched, but the guard reads what asyncua 2.1
keeps of a connection (its protocol's ``_buffer`` and ``processor.session``, its listener's ``clients``),
which is why asyncua is pinned to 2.1. The connections closed by the guard are
logged in one line per ``cell.service.logs.LOG_INTERVAL_S`` with their count.
"""

from __future__ import annotations

import asyncio
import collections
import logging
from dataclasses import dataclass
from typing import Any

from asyncua import Server, ua
from asyncua.common.connection import TransportLimits
from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
from asyncua.server.internal_server import InternalServer
from asyncua.ua.ua_binary import uatcp_to_binary

from cell.service.logs import EveryInterval

log = logging.getLogger("cell.line")

HELLO_MAX_BYTES = 4096 + 32
"""The largest Hello a client may send [bytes]: its fixed fields (32 bytes with the header) and an
endpoint URL of at most 4096 bytes (OPC 10000-6, 7.1.2.3)."""
ACTIVATION_TIMEOUT_S = 10.0
"""How long a connection may go without an activated session [s] before asyncua's watchdog closes it
(asyncua's default: 30 s): a PLC opens and activates its session within a second of its Hello; a client
that only said Hello holds a slot no longer."""
HELLO_TIMEOUT_S = 5.0
"""How long a new connection has to deliver its Hello [s]. A client sends it in the packet after the TCP
handshake: within milliseconds on the line's LAN; five seconds are room for a congested link."""
TOO_BUSY = uatcp_to_binary(
    ua.MessageType.Error,  # type: ignore[arg-type]  # asyncua's annotation is the class of these bytes
    ua.ErrorMessage(ua.StatusCode(ua.UInt32(ua.StatusCodes.BadTcpServerTooBusy)),
                    ua.String("every connection of the cell's OPC UA server is in use")))
"""OPC UA's error message to a connection refused at the cap (a client reports its status code)."""


@dataclass(frozen=True)
class OPCUALimits:
    """The guards of :class:`GuardedServer` (see the module docstring)."""

    max_connections: int
    """Connections open at once."""
    hello_timeout_s: float = HELLO_TIMEOUT_S
    """How long a connection has to deliver its Hello [s]."""

    @property
    def per_peer(self) -> int:
        """The most connections from one address: a quarter of the cap, at least two (a client that
        reconnects before its old connection is closed), 8 under a soft descriptor limit of 1024."""
        return min(self.max_connections, max(2, self.max_connections // 4))

    @property
    def backlog(self) -> int:
        """The listen backlog, and so the most connections asyncio accepts in one go: half the cap."""
        return max(1, self.max_connections // 2)


class GuardedProtocol(OPCUAProtocol):
    """asyncua's protocol of one connection, under :class:`OPCUALimits` (the module docstring)."""

    def __init__(self, *args: Any, guard: OPCUALimits, cuts: EveryInterval, **kwargs: Any) -> None:
        """asyncua's arguments; ``guard`` the limits, ``cuts`` counts the connections the guard closes."""
        super().__init__(*args, **kwargs)
        self._guard, self._cuts = guard, cuts
        self.host = ""
        """The client's address."""
        self.opened_at = 0.0
        """When the connection was made (the loop's clock [s])."""
        self.said_hello = False
        """Whether the client's whole Hello has arrived."""
        self._head = b""
        self._received = 0
        self._deadline: asyncio.TimerHandle | None = None

    @property
    def activated(self) -> bool:
        """Whether the connection holds an activated session (a client logged in with a key): what the
        guard never closes to make room (asyncua's own watchdog asks the same)."""
        session = self.processor.session if self.processor is not None else None
        return session is not None and session.is_activated()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        loop = asyncio.get_running_loop()
        peer = transport.get_extra_info("peername")
        self.host, self.opened_at = str(peer[0]) if peer else "?", loop.time()
        others = [c for c in self.clients if isinstance(c, GuardedProtocol) and c.transport is not None
                  and not c.transport.is_closing()]
        same_peer = [c for c in others if c.host == self.host]
        if len(same_peer) >= self._guard.per_peer:
            room = _to_close(same_peer, f"{self.host} opened more than its {self._guard.per_peer} "
                                        "connections")
        elif len(others) >= self._guard.max_connections:
            room = _to_close(others, f"at the cap of {self._guard.max_connections} connections")
        else:
            room = None
        if room is not None and room[0] is None:
            self._cuts.event(loop, f"{room[1]}, each logged in: {self.host} refused")
            transport.write(TOO_BUSY)  # type: ignore[attr-defined]
            transport.close()
            return
        if room is not None and room[0] is not None:
            room[0].cut(room[1])
        super().connection_made(transport)
        if self.transport is not None:
            timeout_s = self._guard.hello_timeout_s
            why = f"{self.host} sent no Hello within {timeout_s:g} s"
            self._deadline = loop.call_later(timeout_s, self.cut, why)

    def connection_lost(self, ex: BaseException | None) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
        super().connection_lost(ex)

    def data_received(self, data: bytes) -> None:
        """asyncua's, once the message that ``data`` starts or goes on is one the client may send: first a
        Hello of at most ``HELLO_MAX_BYTES``, then message chunks of at most the receive buffer the server
        acknowledged (``limits.max_recv_buffer``). asyncua keeps a message's bytes until the size its
        header claims has arrived, copying them at every read: a header that claimed 4 GB held the event
        loop up to 65 ms a connection (measured). The Hello counts as said once it has arrived whole."""
        if not self.said_hello:
            self._head += data[:max(0, 8 - len(self._head))]
            self._received += len(data)
            if len(self._head) == 8:
                kind, size = self._head[:3], int.from_bytes(self._head[4:8], "little")
                if kind != b"HEL" or size > HELLO_MAX_BYTES:
                    self.cut(f"{self.host} began with a {kind!r} message of {size} bytes, not a Hello of at "
                             f"most {HELLO_MAX_BYTES}")
                    return
                if self._received >= size:
                    self.said_hello = True
                    if self._deadline is not None:
                        self._deadline.cancel()
        super().data_received(data)
        pending = self._buffer  # asyncua's: the start of a message not whole yet, from its header
        if self.said_hello and len(pending) >= 8 and self.transport is not None:
            size = int.from_bytes(pending[4:8], "little")
            if size > self.limits.max_recv_buffer:
                self.cut(f"{self.host} sent a message chunk of {size} bytes, more than the "
                         f"{self.limits.max_recv_buffer} acknowledged")

    def cut(self, why: str) -> None:
        """Close the connection now (what is queued for its client is dropped), ``why`` logged."""
        if self.transport is not None and not self.transport.is_closing():
            self._cuts.event(asyncio.get_running_loop(), why)
            self.transport.abort()


def _to_close(connections: list[GuardedProtocol], why: str) -> tuple[GuardedProtocol | None, str]:
    """Which of ``connections`` to close to make room for a new one, and why (with ``why``, the rule):
    never one with an activated session (None when every one has); of the others, those that have not
    said Hello first, from the address that holds the most of them (a flood's, not a PLC's one), the oldest
    there."""
    open_ = [c for c in connections if not c.activated]
    if not open_:
        return None, why
    silent = [c for c in open_ if not c.said_hello]
    pool = silent or open_
    by_host = collections.Counter(c.host for c in pool)
    most = max(by_host.values())
    oldest = min((c for c in pool if by_host[c.host] == most), key=_age)
    return oldest, f"{why}: {oldest.host}'s oldest {'without a Hello' if silent else 'not logged in'} closed"


def _age(connection: GuardedProtocol) -> float:
    return connection.opened_at


class GuardedBinaryServer(BinaryServer):
    """asyncua's TCP listener, its connections under ``guard``."""

    def __init__(self, iserver: InternalServer, hostname: str, port: int, limits: TransportLimits,
                 guard: OPCUALimits) -> None:
        super().__init__(iserver, hostname, port, limits)
        self.guard = guard

        def line(count: int, latest: str) -> None:
            log.warning("OPC UA: %d connections closed or refused by the connection guard; the latest: %s",
                        count, latest)

        self._cuts = EveryInterval(line)

    def _make_protocol(self) -> GuardedProtocol:
        return GuardedProtocol(iserver=self.iserver, policies=self._policies, clients=self.clients,
                               closing_tasks=self.closing_tasks, limits=self.limits, guard=self.guard,
                               cuts=self._cuts)

    async def start(self) -> None:
        """Listen (asyncua's start, with the guard's backlog: asyncio's default of 100 would take that many
        descriptors at once; asyncua's also reads back a port 0 the system chose, where a line's endpoint
        names its port)."""
        self._server = await asyncio.get_running_loop().create_server(
            self._make_protocol, self.hostname, self.port, backlog=self.guard.backlog)
        self.cleanup_task = asyncio.create_task(self._close_task_loop())


class GuardedServer(Server):
    """asyncua's server whose listener is a :class:`GuardedBinaryServer` under ``guard``."""

    def __init__(self, guard: OPCUALimits, **kwargs: Any) -> None:
        """``kwargs`` are asyncua's."""
        self._guard = guard
        self._bserver: GuardedBinaryServer | None = None
        super().__init__(**kwargs)
        self.iserver.max_pending_activation_seconds = ACTIVATION_TIMEOUT_S

    @property
    def bserver(self) -> GuardedBinaryServer | None:
        """The listener."""
        return self._bserver

    @bserver.setter
    def bserver(self, plain: BinaryServer | None) -> None:
        # asyncua's start assigns the listener it built, not started yet: this one listens in its place
        self._bserver = None if plain is None else GuardedBinaryServer(plain.iserver, plain.hostname,
                                                                       plain.port, plain.limits, self._guard)
