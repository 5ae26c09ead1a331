"""The connections the line's OPC UA server keeps: how many, how many from one address, and how long a
client may take to say Hello.

asyncua's server accepts every TCP connection (up to a thousand) and keeps one that never speaks until
its watchdog sees no activated session, 30 s later. It runs on the event loop of ``cell serve``'s HTTP
server, in its process: a broken or hostile client on the line's network could hold connections until
the process had no file descriptor left, and an operator's STOP could not be accepted. As the HTTP
guard (:mod:`cell.api.connections`) does for the API, :class:`GuardedServer` keeps

- at most :attr:`OPCUALimits.max_connections` open, a share of the descriptors the HTTP guard budgets
  (``cell.api.connections.ConnectionLimits.opcua_connections``): a connection that would pass the cap
  closes the oldest one that has not said Hello (a silent client), so that the PLC gets in; with none
  such the newcomer is refused with OPC UA's ``Bad_TcpServerTooBusy``;
- at most :attr:`OPCUALimits.per_peer` from one address: a new one closes that address's oldest (a PLC
  that rebooted leaves its old connections behind it; a client that opens more than its share only
  crowds out itself);
- a connection whose client has not sent its Hello, the first message of OPC UA's TCP protocol (OPC
  10000-6, 7.1), within :attr:`OPCUALimits.hello_timeout_s` is closed (one that said Hello and activates
  no session is left to asyncua's watchdog);
- the listen backlog at :attr:`OPCUALimits.backlog`: asyncio accepts up to it in one go, before any of
  the connections is counted.

asyncua has no parameter for its listener's class or protocol: ``Server.start`` builds a
``BinaryServer`` and starts it at once. :class:`GuardedServer` puts a :class:`GuardedBinaryServer` in
its place as ``start`` assigns it (asyncua's own start is kept whole: its certificate check, its nodes);
that one makes :class:`GuardedProtocol` for each connection and listens with the backlog. Only this
server's listener is changed; asyncua's classes are not patched. The connections closed by the guard are
logged in one line per ``cell.service.logs.LOG_INTERVAL_S`` with their count.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from typing import Any

from asyncua import Server, ua
from asyncua.common.connection import TransportLimits
from asyncua.common.utils import Buffer
from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
from asyncua.server.internal_server import InternalServer
from asyncua.ua.ua_binary import uatcp_to_binary

from cell.service.logs import EveryInterval

log = logging.getLogger("cell.line")

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
        self._deadline: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        loop = asyncio.get_running_loop()
        self.host, self.opened_at = str(transport.get_extra_info("peername")[0]), loop.time()
        others = [c for c in self.clients if isinstance(c, GuardedProtocol) and c.transport is not None
                  and not c.transport.is_closing()]
        same_peer = [c for c in others if c.host == self.host]
        silent = [c for c in others if not c.said_hello]
        if len(same_peer) >= self._guard.per_peer:
            min(same_peer, key=_age).cut(f"{self.host} opened more than its {self._guard.per_peer} "
                                           "connections: its oldest closed")
        elif len(others) >= self._guard.max_connections and silent:
            min(silent, key=_age).cut(f"at the cap of {self._guard.max_connections} connections: the "
                                        "oldest without a Hello closed")
        elif len(others) >= self._guard.max_connections:
            self._cuts.event(loop, f"at the cap of {self._guard.max_connections} connections, each past "
                                  f"its Hello: {self.host} refused")
            transport.write(TOO_BUSY)  # type: ignore[attr-defined]
            transport.close()
            return
        super().connection_made(transport)
        if self.transport is not None:
            timeout_s = self._guard.hello_timeout_s
            why = f"{self.host} sent no Hello within {timeout_s:g} s"
            self._deadline = loop.call_later(timeout_s, self.cut, why)

    def connection_lost(self, ex: BaseException | None) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
        super().connection_lost(ex)

    async def _process_one_msg(self, header: Any, buf: Buffer) -> bool:
        # asyncua's one place that sees each message whole, with its type (were it renamed, every connection
        # would be cut at the deadline: tests/test_line_opcua_connections.py's PLC would be)
        if header.MessageType == ua.MessageType.Hello and self._deadline is not None:
            self._deadline.cancel()
            self.said_hello = True
        return await super()._process_one_msg(header, buf)

    def cut(self, why: str) -> None:
        """Close the connection now (what is queued for its client is dropped), ``why`` logged."""
        if self.transport is not None and not self.transport.is_closing():
            self._cuts.event(asyncio.get_running_loop(), why)
            self.transport.abort()


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

    @property
    def bserver(self) -> GuardedBinaryServer | None:
        """The listener."""
        return self._bserver

    @bserver.setter
    def bserver(self, plain: BinaryServer | None) -> None:
        # asyncua's start assigns the listener it built, not started yet: this one listens in its place
        self._bserver = None if plain is None else GuardedBinaryServer(plain.iserver, plain.hostname,
                                                                       plain.port, plain.limits, self._guard)
