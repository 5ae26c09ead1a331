"""Free loopback addresses for the tests' protocol peers (RTDE controller, franky-sim, Franka connect peer):
127.0.0.N with N in FIRST_HOST..LAST_HOST; the addresses below FIRST_HOST are the dry run's own
(``test_dry_run``)."""

from __future__ import annotations

import contextlib
import os
import socket
from collections.abc import Sequence

FIRST_HOST, LAST_HOST = 20, 250
# Each test process starts at its own address, so that concurrent runs rarely probe the same one.
_next_host = FIRST_HOST + os.getpid() % (LAST_HOST - FIRST_HOST + 1)


def free_loopback(ports: Sequence[int], *, reuse_address: bool = True) -> str:
    """A 127.0.0.N on which every port of ``ports`` could be listened on, probed as the peer binds: with
    SO_REUSEADDR or, for a peer that does not set it (it cannot listen on a port still in TIME_WAIT),
    without. Consecutive calls move on to the next address, so a peer never inherits the last one's."""
    global _next_host
    for _ in range(LAST_HOST - FIRST_HOST + 1):
        host = f"127.0.0.{_next_host}"
        _next_host = FIRST_HOST if _next_host >= LAST_HOST else _next_host + 1
        if all(_port_free(host, port, reuse_address) for port in ports):
            return host
    raise RuntimeError(f"no free 127.0.0.N address for ports {list(ports)}")


def _port_free(host: str, port: int, reuse_address: bool) -> bool:
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as probe:
        if reuse_address:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError:
            return False
    return True
