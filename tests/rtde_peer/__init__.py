"""A UR controller peer for tests: the real ur-rtde client talks to it on loopback.

:class:`ControllerPeer` starts ``python -m tests.rtde_peer`` in its own process (ur-rtde's constructors
hold the GIL, so a peer in the test's process would starve), in the real-time class where the machine
allows it (as a controller's cycle runs; a starved peer falls silent), on a free ``127.0.0.N`` (the
controller's ports are fixed), and drives it over its JSON control port: inject faults, read what the
client sent; and stops its process to play a controller gone silent with its connections open
(``frozen``).
Disconnect the client before stopping the peer.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from tests.loopback import free_loopback
from tests.rtde_peer.controller import CONTROL_PORT, PORTS

REPO = Path(__file__).resolve().parents[2]
START_ATTEMPTS = 5


class ControllerPeer:
    """Handle on one running peer process."""

    def __init__(self, *, remote_control: bool = True, q: Sequence[float] | None = None,
                 start_timeout_s: float = 30.0) -> None:
        """``q``: the arm's start joints [rad] (default: the peer's UR home pose, the flange at x < 0).
        A concurrent test run may take the probed address first; then the next free one is tried."""
        args = [] if remote_control else ["--no-remote-control"]
        if q is not None:
            args += ["--q", ",".join(repr(float(v)) for v in q)]
        for _ in range(START_ATTEMPTS):
            self.host = free_loopback(PORTS)
            cmd = [sys.executable, "-m", "tests.rtde_peer", "--host", self.host, "--exit-on-stdin-eof", *args]
            # the peer's standard error goes to a file, shown when the peer stops (a pipe nobody reads
            # could fill up and block it); it lives as long as the peer, closed by _take_stderr
            self._stderr = tempfile.TemporaryFile("w+")  # noqa: SIM115
            self._proc = subprocess.Popen(cmd, cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                          stderr=self._stderr, text=True)
            assert self._proc.stdout is not None
            line = self._proc.stdout.readline()
            if line.startswith("ready"):
                break
            self._proc.communicate()
            stderr = self._take_stderr()
            if "Address already in use" not in stderr:
                raise RuntimeError(f"controller peer did not start: {line!r}\n{stderr}")
        else:
            raise RuntimeError(f"controller peer did not start: every address tried was taken ({self.host})")
        self._sock = socket.create_connection((self.host, CONTROL_PORT), timeout=start_timeout_s)
        self._reader = self._sock.makefile("r")

    @property
    def pid(self) -> int:
        return self._proc.pid

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

    def pulse_digital_input(self, index: int, duration_s: float) -> float:
        """Input ``index`` high for ``duration_s`` of the controller's time (its RTDE timestamp); returns
        when it falls, on that clock [s]."""
        return float(self.call("digital_pulse", index=index, duration_s=duration_s)["ends_s"])

    def drop_clients(self) -> None:
        self.call("disconnect")

    @contextlib.contextmanager
    def frozen(self) -> Iterator[None]:
        """The controller stops with every connection open, as a hung controller or a network path that no
        longer delivers: the peer's process is stopped (SIGSTOP), so it sends nothing, and what clients
        send waits in its sockets until the block ends (SIGCONT) and it reads it all at once. Do not call
        the peer inside the block."""
        os.kill(self._proc.pid, signal.SIGSTOP)
        try:
            yield
        finally:
            os.kill(self._proc.pid, signal.SIGCONT)

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
        sys.stderr.write(self._take_stderr())

    def _take_stderr(self) -> str:
        """What the peer process wrote to standard error; closes the file."""
        self._stderr.seek(0)
        text = self._stderr.read()
        self._stderr.close()
        return text
