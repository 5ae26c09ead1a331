"""The connection guard of the line's OPC UA server (``cell.line.opcua_connections``).

A real ``cell serve`` under a soft limit of 256 descriptors (its OPC UA server may keep 8 connections, 2
from one address) flooded with 300 TCP connections that start a Hello and never finish it: the server
never holds more than its cap, the silent ones are closed at the Hello deadline, an operator's STOP is
answered meanwhile and the PLC (an asyncua client) connects and stays. Without the guard the server held
242 of them, every descriptor it had, and the STOP was not answered in 20 s.

Then the rules one by one on an asyncua server of the guard's own on loopback, with small limits and raw
OPC UA TCP messages: an address's oldest connection makes room for its new one, at the cap the oldest
silent one does, with none silent the newcomer is refused with ``Bad_TcpServerTooBusy``, and a connection
that says Hello is not closed at the deadline.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import os
import socket
import struct
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.ua.ua_binary import uatcp_to_binary

from cell.api import connections
from cell.api.connections import ConnectionLimits
from cell.line.opcua_connections import GuardedServer, OPCUALimits
from tests.conftest import UR5E
from tests.service_process import ServedCell, closed_by_server, free_port, opcua_cell_file

WAIT_S = 60.0  # a bound on waiting, never a timed check [s]
LONG_S = 600.0  # a deadline no test reaches [s]
STOP_WAIT_S = 15.0  # a bound on waiting for the STOP's answer [s]
FEW_FDS = 256  # the service's soft descriptor limit: 64 HTTP connections, 8 OPC UA ones (2 per address)
OPCUA_CAP, PER_PEER = 8, 2
FLOOD = 300  # more connections than the service has descriptors
ADDRESSES = [f"127.0.0.{i}" for i in range(2, 32)]  # the flood's sources, ten connections each
NAMESPACE = "urn:cell:packml"
HELLO = uatcp_to_binary(ua.MessageType.Hello, ua.Hello(EndpointUrl=""))  # type: ignore[arg-type]


def held(pid: int, port: int) -> collections.Counter[str]:
    """The TCP connections process ``pid`` holds open on its local ``port``, by the client's address."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        with contextlib.suppress(FileNotFoundError):  # closed since listed
            link = os.readlink(f"/proc/{pid}/fd/{fd}")
            if link.startswith("socket:["):
                inodes.add(link[len("socket:["):-1])
    peers: collections.Counter[str] = collections.Counter()
    for row in Path(f"/proc/{pid}/net/tcp").read_text().splitlines()[1:]:
        _, local, remote, state, *_, inode = row.split()[:10]
        if int(local.split(":")[1], 16) == port and state != "0A" and inode in inodes:  # 0A: listening
            peers[socket.inet_ntoa(struct.pack("<I", int(remote.split(":")[0], 16)))] += 1
    return peers


def silent_connections(port: int, source: str) -> list[socket.socket]:
    """``FLOOD / len(ADDRESSES)`` connections to ``port`` from ``source``, each with the first byte of a
    Hello and no more. (A byte, not nothing: a connection that the listen backlog had no room for is
    established for its client alone, for ever; what it sends is answered with a reset.)"""
    opened = []
    for _ in range(FLOOD // len(ADDRESSES)):
        opened.append(socket.create_connection(("127.0.0.1", port), timeout=WAIT_S,
                                               source_address=(source, 0)))
        opened[-1].sendall(HELLO[:1])
    return opened


def test_a_flood_of_silent_connections_leaves_stop_answering_and_the_plc_connecting(tmp_path: Path) -> None:
    config, port = opcua_cell_file(tmp_path, UR5E)
    url = f"opc.tcp://127.0.0.1:{port}/cell"
    with ServedCell(config, tmp_path / "data", nofile=FEW_FDS) as cell:
        assert cell.proc is not None
        flood: list[socket.socket] = []
        try:
            # one thread per address: a connect that waits for room in the listen backlog (its SYN
            # dropped, sent again a second later) does not hold up the others
            with ThreadPoolExecutor(len(ADDRESSES)) as threads:
                for opened in threads.map(lambda source: silent_connections(port, source), ADDRESSES):
                    flood += opened
            # a bound, not a timed check: answered within milliseconds, unless the flood took every
            # descriptor (then until asyncua's own watchdog closes its connections, 30 s after they opened)
            with cell.client("operator", timeout_s=STOP_WAIT_S) as http:
                stop = http.post("/api/v1/stop", json={"reason": "flooded"})
            assert stop.status_code == 200, stop.text
            # counted once the server's loop has served the STOP: it has taken in every connection of the
            # flood by then (up to its backlog of them may still be uncounted while it accepts)
            peers = held(cell.proc.pid, port)
            assert sum(peers.values()) <= OPCUA_CAP and max(peers.values(), default=0) <= PER_PEER, peers

            async def plc() -> None:
                client = Client(url, timeout=WAIT_S / 2)
                client.set_user("test-line")
                client.set_password(cell.keys["line"])
                async with client:
                    ns = (await client.get_namespace_array()).index(NAMESPACE)
                    state = client.get_node(ua.NodeId("PackTags.Status.StateCurrent", ns))
                    assert await state.read_value() >= 0
                    # a silent connection opened after the PLC's: once the guard closed it, the PLC's own
                    # deadline has passed too
                    canary = socket.create_connection(("127.0.0.1", port), timeout=WAIT_S)
                    canary.sendall(HELLO[:1])
                    with canary:
                        assert await asyncio.to_thread(closed_by_server, canary)
                    closed = await asyncio.to_thread(lambda: sum(closed_by_server(sock) for sock in flood))
                    assert closed == FLOOD
                    assert await state.read_value() >= 0  # the PLC said Hello: it stays

            asyncio.run(plc())
        finally:
            for sock in flood:
                sock.close()
        log = cell.log()
    assert "Traceback" not in log and "out of system resource" not in log, log[-2000:]
    assert "connections closed or refused by the connection guard" in log, log[-2000:]


# ------------------------------------------------------------------------------------------------ rules


@pytest.mark.parametrize("soft", [64, 256, 1024, 4096])
def test_both_servers_connections_fit_in_the_descriptors_they_share(monkeypatch: pytest.MonkeyPatch,
                                                                    soft: int) -> None:
    """Each HTTP connection may hold two descriptors, the backlogs are accepted in one go, a few more may
    only stop: what is left of the soft limit (``FD_SHARE``: 30 %) is the store's, the worker's, the logs'."""
    monkeypatch.setattr(connections.resource, "getrlimit", lambda _: (soft, soft))
    http = ConnectionLimits.of_process()
    opcua = OPCUALimits(http.opcua_connections)
    most_http = 2 * http.max_connections + http.backlog + http.stop_spare
    assert most_http + opcua.max_connections + opcua.backlog <= 0.71 * soft


@contextlib.asynccontextmanager
async def guarded(limits: OPCUALimits) -> AsyncIterator[str]:
    """An asyncua server on loopback under ``limits`` while the context runs; yields its endpoint."""
    url = f"opc.tcp://127.0.0.1:{free_port()}/guard"
    server = GuardedServer(limits)
    await server.init()
    server.iserver.max_pending_activation_seconds = 0  # asyncua's watchdog off: only the guard closes
    server.set_endpoint(url)
    await server.start()
    try:
        yield url
    finally:
        await server.stop()


class Raw:
    """A TCP connection to an OPC UA server from ``source``, speaking its messages by hand."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer

    @classmethod
    async def open(cls, url: str, source: str) -> Raw:
        port = int(url.rsplit(":", 1)[1].split("/")[0])
        return cls(*await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0)))

    async def hello(self) -> bytes:
        """Say Hello; the type of the server's answer (``ACK``, ``ERR``)."""
        self.writer.write(HELLO)
        return await self.answer()

    async def answer(self) -> bytes:
        header = await asyncio.wait_for(self.reader.readexactly(8), WAIT_S)
        await self.reader.readexactly(struct.unpack("<I", header[4:])[0] - 8)
        return header[:3]

    async def closed(self) -> bool:
        """Whether the server closes the connection (within ``WAIT_S``)."""
        try:
            return await asyncio.wait_for(self.reader.read(), WAIT_S) == b""
        except ConnectionResetError:
            return True
        except TimeoutError:
            return False

    def close(self) -> None:
        self.writer.close()


def test_a_new_connection_closes_its_addresses_oldest_and_at_the_cap_a_silent_one_first() -> None:
    async def scenario() -> None:
        async with guarded(OPCUALimits(4, hello_timeout_s=LONG_S)) as url:
            first, second = [await Raw.open(url, "127.0.0.2") for _ in range(2)]
            third = await Raw.open(url, "127.0.0.2")  # past the address's share of 2
            assert await first.closed()
            assert await second.hello() == b"ACK" and await third.hello() == b"ACK"
            silent = await Raw.open(url, "127.0.0.3")
            talker = await Raw.open(url, "127.0.0.4")
            assert await talker.hello() == b"ACK"  # 4 open: second, third, silent, talker
            newcomer = await Raw.open(url, "127.0.0.5")
            assert await silent.closed()
            assert await newcomer.hello() == b"ACK"
            # every open one said Hello, none logged in: the oldest of the address that holds the most
            sixth = await Raw.open(url, "127.0.0.6")
            assert await second.closed()
            for raw in (third, talker, newcomer, sixth):
                assert await raw.hello() == b"ACK"  # all still served
                raw.close()

    asyncio.run(scenario())


def test_a_logged_in_client_is_never_closed_to_make_room_and_a_newcomer_then_is_refused() -> None:
    """A PLC's session (here asyncua's client, from 127.0.0.1) outlives the connections its address opens
    past its share; with both of the address's slots logged in, the next is refused."""
    async def scenario() -> None:
        async with guarded(OPCUALimits(4, hello_timeout_s=LONG_S)) as url:
            plc = Client(url, timeout=WAIT_S)
            await plc.connect()
            raw = await Raw.open(url, "127.0.0.1")
            assert await raw.hello() == b"ACK"
            again = await Raw.open(url, "127.0.0.1")  # past the share: the raw one goes, not the PLC
            assert await raw.closed()
            async with Client(url, timeout=WAIT_S) as second_plc:  # past it again: `again` goes
                assert await again.closed()
                refused = await Raw.open(url, "127.0.0.1")
                assert await refused.answer() == b"ERR" and await refused.closed()
                assert await second_plc.nodes.server_state.read_value() == ua.ServerState.Running
            assert await plc.nodes.server_state.read_value() == ua.ServerState.Running
            await plc.disconnect()

    asyncio.run(scenario())


def test_a_first_message_that_is_no_hello_or_a_chunk_past_the_buffer_is_cut() -> None:
    """A client may claim any size in a header, and asyncua would keep (and copy at every read) what it
    sends towards it: a Hello claiming 4 GB, a first message that is no Hello, and after a Hello a chunk
    larger than the receive buffer the server acknowledged are each cut at once."""
    async def scenario() -> None:
        async with guarded(OPCUALimits(8, hello_timeout_s=LONG_S)) as url:
            huge = await Raw.open(url, "127.0.0.2")
            huge.writer.write(b"HELF" + struct.pack("<I", 0xFFFFFFF0) + bytes(1000))
            other = await Raw.open(url, "127.0.0.3")
            other.writer.write(b"MSGF" + struct.pack("<I", 100) + bytes(92))
            chunk = await Raw.open(url, "127.0.0.4")
            assert await chunk.hello() == b"ACK"
            chunk.writer.write(b"MSGF" + struct.pack("<I", 1 << 20) + bytes(1000))
            talker = await Raw.open(url, "127.0.0.5")
            assert await talker.hello() == b"ACK"
            for raw in (huge, other, chunk):
                assert await raw.closed()
            assert await talker.hello() == b"ACK"
            talker.close()

    asyncio.run(scenario())


def test_a_connection_without_a_hello_is_closed_at_the_deadline_and_one_with_it_is_not() -> None:
    async def scenario() -> None:
        async with guarded(OPCUALimits(4, hello_timeout_s=0.5)) as url:
            talker = await Raw.open(url, "127.0.0.1")
            assert await talker.hello() == b"ACK"
            silent = await Raw.open(url, "127.0.0.2")  # its deadline is after the talker's
            assert await silent.closed()
            assert await talker.hello() == b"ACK"
            talker.close()

    asyncio.run(scenario())
