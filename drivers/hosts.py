"""Host names and addresses: which of them name only this machine, whether a port can be listened on, and
reading a fixed-size message from a socket."""

from __future__ import annotations

import ipaddress
import socket


def is_loopback(host: str) -> bool:
    """Whether ``host`` names only this machine (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


INVALID_HOST_NAME = "not a valid host name: each of its dot-separated labels has 1 to 63 characters"
"""Why a name that no resolver takes cannot be listened on (``listen_problem``'s words). getaddrinfo raised
``UnicodeError`` for it, which ended ``cell serve`` and ``cell doctor`` with a traceback."""


def listen_problem(host: str | None, port: int | None) -> str | None:
    """Why a TCP server could not listen on ``host``:``port`` now (a port in use, an address that is not
    this machine's, a name that does not resolve), or None when it could. Probed as a server binds, with
    SO_REUSEADDR, on every address the name resolves to."""
    try:
        for family, kind, proto, _, address in socket.getaddrinfo(host, port, type=socket.SOCK_STREAM):
            with socket.socket(family, kind, proto) as probe:
                probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                probe.bind(address)
    except OSError as exc:
        return str(exc.strerror or exc)
    except UnicodeError:  # encoding the name (IDNA): an empty label ("a..b") or one of over 63 characters
        return INVALID_HOST_NAME
    return None


def recv_exact(sock: socket.socket, n: int) -> bytes:
    """Exactly ``n`` bytes from ``sock``; ``ConnectionError`` when the other side closes first."""
    data = bytearray()
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError(f"the other side closed the connection after {len(data)} of {n} bytes")
        data.extend(chunk)
    return bytes(data)
