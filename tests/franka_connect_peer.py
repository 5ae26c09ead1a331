"""A Franka control unit that speaks only the research interface's connect handshake, for version tests.

It listens on the robot's command port (TCP 1337) of a free ``127.0.0.N`` and answers every Connect
request as libfranka reads the reply: the command header ``<III`` (command 0, the request's command id,
the message size including the header), then ``<B`` status (0 success, 1 incompatible library version)
and ``<H`` the server's research-interface version. Offered a version other than its own, it refuses with
status 1 and its version, as a robot on older firmware does; then it closes the connection. It records
the versions the clients offered. It streams no state, so it is for the connect step only; franky-sim is
the peer for everything after it.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import threading

from drivers.hosts import recv_exact
from tests.loopback import free_loopback

COMMAND_PORT = 1337
HEADER = struct.Struct("<III")
REQUEST = struct.Struct("<HH")
REPLY = struct.Struct("<BH")
CMD_CONNECT = 0
STATUS_SUCCESS, STATUS_INCOMPATIBLE = 0, 1


class FrankaConnectPeer:
    """A thread that answers Connect requests with server version ``version``; stop with :meth:`stop`."""

    def __init__(self, version: int) -> None:
        self.version = version
        self.offered: list[int] = []
        self.host = free_loopback([COMMAND_PORT])
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind((self.host, COMMAND_PORT))
        self._listener.listen(4)
        self._thread = threading.Thread(target=self._serve, daemon=True, name="franka-connect-peer")
        self._thread.start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self._listener.accept()
            except OSError:
                return  # stopped
            conn.settimeout(5.0)
            with conn, contextlib.suppress(OSError, ConnectionError):
                self._answer(conn)

    def _answer(self, conn: socket.socket) -> None:
        command, command_id, size = HEADER.unpack(recv_exact(conn, HEADER.size))
        body = recv_exact(conn, size - HEADER.size)
        if command != CMD_CONNECT:
            return  # nothing but the handshake is spoken here: drop the connection
        offered, _udp_port = REQUEST.unpack(body[:REQUEST.size])
        self.offered.append(offered)
        status = STATUS_SUCCESS if offered == self.version else STATUS_INCOMPATIBLE
        reply = REPLY.pack(status, self.version)
        conn.sendall(HEADER.pack(CMD_CONNECT, command_id, HEADER.size + len(reply)) + reply)

    def stop(self) -> None:
        with contextlib.suppress(OSError):  # wakes the blocked accept (close alone does not)
            self._listener.shutdown(socket.SHUT_RDWR)
        self._listener.close()
        self._thread.join(timeout=5)

