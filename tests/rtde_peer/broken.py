"""A controller address whose ports accept connections and then fail the handshake: another device at
the robot's address, a controller still booting, a service disabled in PolyScope.

:class:`BrokenController` listens on the controller's ports of a free ``127.0.0.N`` (threads of the test
process: ur-rtde runs in the driver's child process, so nothing here competes with it for the GIL). Each
connection is closed at once (``close``) or held open without a byte (``hang``); with ``dashboard_ok``
the dashboard port answers as a controller in remote control does, so that the handshake fails on the
next port (RTDE).
"""

from __future__ import annotations

import contextlib
import socket
import threading
from typing import Literal

from tests.loopback import free_loopback
from tests.rtde_peer.controller import DASHBOARD_PORT, POLYSCOPE_VERSION, RTDE_PORT, SCRIPT_PORT

Behaviour = Literal["close", "hang"]


class BrokenController:
    def __init__(self, behaviour: Behaviour, *, dashboard_ok: bool = False) -> None:
        self.host = free_loopback((RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT))
        self._behaviour = behaviour
        self._dashboard_ok = dashboard_ok
        self._held: list[socket.socket] = []
        self._listeners = [socket.create_server((self.host, port)) for port in
                           (RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT)]
        for listener in self._listeners:
            threading.Thread(target=self._accept, args=(listener,), daemon=True).start()

    def _accept(self, listener: socket.socket) -> None:
        port = listener.getsockname()[1]
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:  # closed by stop()
                return
            if port == DASHBOARD_PORT and self._dashboard_ok:
                threading.Thread(target=self._dashboard, args=(conn,), daemon=True).start()
            elif self._behaviour == "close":
                conn.close()
            else:
                self._held.append(conn)

    def _dashboard(self, conn: socket.socket) -> None:
        """The greeting, the PolyScope version (ur-rtde asks it on connecting), then "true" to every other
        question (remote control)."""
        with conn, contextlib.suppress(OSError):
            conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
            while line := conn.recv(1024):
                answer = POLYSCOPE_VERSION if b"polyscope" in line.lower() else "true"
                conn.sendall(f"{answer}\n".encode())

    def stop(self) -> None:
        for sock in (*self._listeners, *self._held):
            sock.close()
