"""The process that holds a UR5e's ur-rtde connections, seen from the driver (see :mod:`drivers.arm.ur5e`).

:class:`RTDEProcess` starts ``python -m drivers.arm.ur_rtde_child`` and talks to it over a socket pair
with :class:`multiprocessing.connection.Connection` (pickled ``(seq, op, args)`` requests, ``(seq, "ok",
value)`` or ``(seq, "error", text)`` replies, one at a time; the sequence number pairs them, so that the
late reply to a call that was interrupted, e.g. by Ctrl-C, is not taken for the next call's). The driver
never creates a ur-rtde object itself, so what ur-rtde does after a dropped connection (reconnecting by
itself, a second receive thread, a crash in a destructor) happens in a process the driver can end.

The child ends with the driver's process: it holds the read end of a pipe (the lifeline) whose write end
only the driver holds, and exits when that pipe reaches end of file, even in the middle of a ur-rtde call.
It ignores SIGINT and SIGTERM, so that a Ctrl-C in a terminal reaches the driver, which still stops the
arm through the child, and not the child first.

Exit codes of the child that the driver tells apart: ``EXIT_LOST`` (ur-rtde lost the connection, closed by
the controller or given up on after its silence: the child ended itself at once, before ur-rtde could
reconnect, see :mod:`drivers.arm.ur_rtde_child`),
``EXIT_PARENT_GONE`` and ``EXIT_CLOSED`` (asked to close).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path

EXIT_CLOSED = 0
EXIT_LOST = 3
EXIT_PARENT_GONE = 4
CHILD_MODULE = "drivers.arm.ur_rtde_child"
# the folder that holds the ``drivers`` package, so that the child imports the same code
SOURCE_ROOT = Path(__file__).resolve().parents[2]
# how long a closing child may take to disconnect from the controller before it is killed [s]
CLOSE_TIMEOUT_S = 5.0


class ClientError(Exception):
    """ur-rtde raised in the child; the text is ur-rtde's. The driver turns it into its own errors."""


class ClientGone(Exception):
    """The child ended or did not answer in time; it has been killed. The text says which."""


def exit_words(returncode: int) -> str:
    """Why a child that ended with ``returncode`` ended, in words."""
    if returncode == EXIT_LOST:
        return ("the controller closed the connection, or sent nothing for so long that ur-rtde gave up on "
                "it (its control interface does after about 2.5 s); the ur-rtde process ended itself so that "
                "ur-rtde cannot reconnect and resume motion")
    if returncode == EXIT_PARENT_GONE:
        return "the ur-rtde process lost its driver"
    if returncode < 0:
        name = signal.strsignal(-returncode)
        return f"the ur-rtde process was killed by signal {-returncode}" + (f" ({name})" if name else "")
    return f"the ur-rtde process ended with exit code {returncode}"


class RTDEProcess:
    """One child process holding ur-rtde clients; :meth:`call` runs an operation in it."""

    def __init__(self) -> None:
        self._proc: subprocess.Popen[bytes] | None = None
        self._conn: Connection | None = None
        self._lifeline: int | None = None
        self._lock = threading.Lock()
        self._seq = 0

    def start(self) -> None:
        """Start the child (it imports ur-rtde and waits for requests)."""
        ours, theirs = socket.socketpair()
        life_r, life_w = os.pipe()  # non-inheritable: only the child gets the read end, by pass_fds
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(SOURCE_ROOT), env.get("PYTHONPATH")) if p)
        try:
            # ur-rtde prints progress to standard output: it goes to standard error, not into the
            # driver's own output (e.g. what ``cell arm status`` prints)
            self._proc = subprocess.Popen(
                [sys.executable, "-m", CHILD_MODULE, str(theirs.fileno()), str(life_r)],
                pass_fds=(theirs.fileno(), life_r), stdin=subprocess.DEVNULL, stdout=2, env=env)
        finally:
            theirs.close()
            os.close(life_r)
        self._conn = Connection(ours.detach())
        self._lifeline = life_w

    @property
    def pid(self) -> int | None:
        """The child's process id while it runs."""
        return self._proc.pid if self._proc is not None and self._proc.poll() is None else None

    def call(self, op: str, *args: object, timeout_s: float) -> object:
        """Run ``op`` in the child and return its value. ``ClientError`` when ur-rtde raised there;
        ``ClientGone`` when the child has ended or gave no answer within ``timeout_s`` [s] (then it is
        killed: whatever it was doing, it does no more)."""
        with self._lock:
            if self._conn is None or self._proc is None:
                raise ClientGone("the ur-rtde process is not running")
            self._seq += 1
            deadline = time.monotonic() + timeout_s
            try:
                self._conn.send((self._seq, op, args))
                while True:
                    if not self._conn.poll(max(0.0, deadline - time.monotonic())):
                        self.kill()
                        raise ClientGone(f"the ur-rtde process did not answer {op} within {timeout_s:g} s "
                                         "and was killed")
                    seq, status, value = self._conn.recv()
                    if seq == self._seq:
                        break
            except (EOFError, OSError):
                raise ClientGone(exit_words(self._reap())) from None
        if status == "error":
            raise ClientError(str(value))
        return value

    def close(self) -> None:
        """Ask the child to disconnect from the controller and end; kill it if it does not."""
        if self._proc is None:
            return
        try:
            self.call("close", timeout_s=CLOSE_TIMEOUT_S)
            self._proc.wait(timeout=CLOSE_TIMEOUT_S)
        except (ClientGone, ClientError, subprocess.TimeoutExpired):
            pass  # killed below, or already gone
        self.kill()

    def _reap(self) -> int:
        """The exit code of a child whose connection ended (killed if it lingers)."""
        assert self._proc is not None
        try:
            returncode = self._proc.wait(timeout=CLOSE_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            returncode = self._proc.wait()
        self._release()
        return returncode

    def kill(self) -> None:
        """End the child at once (SIGKILL) and wait for it. Safe to call twice."""
        if self._proc is not None and self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()
        self._release()

    def _release(self) -> None:
        if self._conn is not None:
            self._conn.close()
        if self._lifeline is not None:
            os.close(self._lifeline)
        self._conn = None
        self._lifeline = None
        self._proc = None
