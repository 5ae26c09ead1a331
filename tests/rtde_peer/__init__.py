"""A UR controller peer for tests: the real ur-rtde client talks to it on loopback.

:class:`ControllerPeer` starts ``python -m tests.rtde_peer`` in its own process (ur-rtde's constructors
hold the GIL, so a peer in the test's process would starve) on a free ``127.0.0.N`` (the controller's
ports are fixed), and drives it over its JSON control port: inject faults, read what the client sent.
Disconnect the client before stopping the peer.
"""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from tests.rtde_peer.controller import CONTROL_PORT, RTDE_PORT

REPO = Path(__file__).resolve().parents[2]
_next_host = 20


def _free_host() -> str:
    """A loopback address whose RTDE port is free (another test's or engineer's peer may hold one)."""
    global _next_host
    for _ in range(200):
        host = f"127.0.0.{_next_host}"
        _next_host = 20 if _next_host >= 250 else _next_host + 1
        probe = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            probe.bind((host, RTDE_PORT))
            return host
        except OSError:
            continue
        finally:
            probe.close()
    raise RuntimeError("no free 127.0.0.N address for a controller peer")


class ControllerPeer:
    """Handle on one running peer process."""

    def __init__(self, *, remote_control: bool = True, start_timeout_s: float = 30.0) -> None:
        self.host = _free_host()
        cmd = [sys.executable, "-m", "tests.rtde_peer", "--host", self.host, "--exit-on-stdin-eof"]
        if not remote_control:
            cmd.append("--no-remote-control")
        self._proc = subprocess.Popen(cmd, cwd=REPO, stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, text=True)
        assert self._proc.stdout is not None
        line = self._proc.stdout.readline()
        if not line.startswith("ready"):
            self._proc.kill()
            raise RuntimeError(f"controller peer did not start: {line!r}")
        self._sock = socket.create_connection((self.host, CONTROL_PORT), timeout=start_timeout_s)
        self._reader = self._sock.makefile("r")

    def call(self, op: str, **args: Any) -> dict[str, Any]:
        self._sock.sendall((json.dumps({"op": op, **args}) + "\n").encode())
        reply: dict[str, Any] = json.loads(self._reader.readline())
        if "error" in reply:
            raise RuntimeError(reply["error"])
        return reply

    def state(self) -> dict[str, Any]:
        return self.call("state")

    def records(self, name: str | None = None) -> list[dict[str, Any]]:
        recs = self.call("records")["records"]
        return [r for r in recs if name is None or r["name"] == name]

    def protective_stop(self) -> None:
        self.call("protective_stop")

    def emergency_stop(self) -> None:
        self.call("emergency_stop")

    def release_emergency_stop(self) -> None:
        self.call("release_emergency_stop")

    def set_digital_input(self, index: int, value: bool) -> None:
        self.call("digital_input", index=index, value=value)

    def drop_clients(self) -> None:
        self.call("disconnect")

    def wait_for(self, predicate: Any, timeout_s: float = 20.0, what: str = "condition") -> dict[str, Any]:
        """Poll the peer's state until ``predicate(state)`` holds (a bound on waiting, not a timed check)."""
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.state()
            if predicate(st):
                return st
            if time.monotonic() > deadline:
                raise AssertionError(f"peer never reached {what}: {st}")
            time.sleep(0.02)

    def stop(self) -> None:
        with contextlib.suppress(OSError, ValueError):  # the peer may be gone already
            self.call("shutdown")
        self._reader.close()
        self._sock.close()
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        for pipe in (self._proc.stdin, self._proc.stdout):
            if pipe is not None:
                pipe.close()
