"""The child process that holds a UR5e's ur-rtde clients: ``python -m drivers.arm.ur_rtde_child CONN LIFE``.

:class:`~drivers.arm.ur_rtde_process.RTDEProcess` starts it with two file descriptors: ``CONN``, a socket
carrying :class:`multiprocessing.connection.Connection` requests ``(seq, op, args)`` answered with
``(seq, "ok", value)`` or ``(seq, "error", text)``, and ``LIFE``, the read end of the driver's lifeline
pipe. It has
no policy of its own: the driver decides what to send; the child runs ur-rtde and reports.

A dropped connection ends the child (exit code ``EXIT_LOST``, no answer). ur-rtde 1.6.5's receive
interface stays disconnected once the controller closed its connection, but its control interface
reconnects by itself, from its receive thread (and keeps two receive threads on one socket, which soon
crashes the process), and a command whose send fails reconnects and is sent again within the same call:
against the RTDE peer, a ``speedL`` called 100 ms after a drop returned True and reached the controller
through a new connection and a new control script. So the receive interface's connection is the
tripwire: it is checked before every operation that reads the state or sends to the controller, so
nothing is sent through a control interface that reconnected by itself, and a monitor thread checks it
every ``MONITOR_PERIOD_S``, also while a command runs (ur-rtde's methods release the GIL; only its
constructors hold it), so that the child is gone before a reconnection, which takes ur-rtde a script
upload and at least 10 ms of waiting, can re-send anything. The driver latches the loss and starts a
fresh child only when an operator recovers the arm.

Requests (``op``: arguments → value):

- ``dashboard_connect``: host, timeout [ms]; ``dashboard``: a command name from ``DASHBOARD_COMMANDS``
  → its answer.
- ``receive_connect``: host, frequency [Hz], output variable names; ``control_connect``: host,
  frequency [Hz] (uploads ur-rtde's control script).
- ``snapshot``: kick (bool; kick the RTDE watchdog first when the control script runs) → a dict of the
  state (see :meth:`Clients.snapshot`).
- ``control``: a command name from ``CONTROL_COMMANDS``, its arguments → ur-rtde's answer.
- ``set_outputs``: host, ``[(index, level), ...]`` → the first output the controller refused, or None.
  RTDE IO is opened for the change and closed while the controller still answers: ur-rtde's IO interface
  writes to its socket in its destructor, which ends the process when the controller has dropped it.
- ``close``: disconnect every client, answer, exit with ``EXIT_CLOSED``.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

import dashboard_client
import rtde_control
import rtde_io
import rtde_receive

from drivers.arm.ur_rtde_process import EXIT_CLOSED, EXIT_LOST, EXIT_PARENT_GONE

DASHBOARD_COMMANDS = frozenset({"isInRemoteControl", "closeSafetyPopup", "unlockProtectiveStop", "powerOn",
                                "brakeRelease", "safetystatus"})
CONTROL_COMMANDS = frozenset({"speedL", "speedStop", "servoJ", "servoStop", "stopL", "setWatchdog",
                              "setTcp", "setPayload", "reuploadScript", "stopScript"})
# how often the monitor thread checks the receive interface's connection [s]
MONITOR_PERIOD_S = 0.002


class Clients:
    """The ur-rtde clients of one connection to a controller, and the operations on them."""

    def __init__(self) -> None:
        self.dash: dashboard_client.DashboardClient | None = None
        self.recv: rtde_receive.RTDEReceiveInterface | None = None
        self.ctl: rtde_control.RTDEControlInterface | None = None
        self.closing = False

    def check_connected(self) -> None:
        """End the process at once when the controller has closed the connection (module docstring)."""
        if self.closing:
            return
        if (self.recv is not None and not self.recv.isConnected()) or \
                (self.ctl is not None and not self.ctl.isConnected()):
            os._exit(EXIT_LOST)

    def monitor(self) -> None:
        while True:
            self.check_connected()
            time.sleep(MONITOR_PERIOD_S)

    def handle(self, op: str, args: tuple[Any, ...]) -> object:
        if op == "dashboard_connect":
            host, timeout_ms = args
            self.dash = dashboard_client.DashboardClient(host)
            self.dash.connect(int(timeout_ms))
            return None
        if op == "dashboard":
            (name,) = args
            if name not in DASHBOARD_COMMANDS or self.dash is None:
                raise ValueError(f"dashboard command {name!r} is not available")
            return getattr(self.dash, name)()
        if op == "receive_connect":
            host, frequency, variables = args
            self.recv = rtde_receive.RTDEReceiveInterface(host, float(frequency), list(variables))
            threading.Thread(target=self.monitor, daemon=True, name="connection-monitor").start()
            return None
        if op == "control_connect":
            host, frequency = args
            self.ctl = rtde_control.RTDEControlInterface(host, float(frequency),
                                                         rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT)
            return None
        if op == "close":
            self.close()
            return None
        self.check_connected()
        if op == "snapshot":
            (kick,) = args
            return self.snapshot(bool(kick))
        if op == "control":
            name, values = args
            if name not in CONTROL_COMMANDS or self.ctl is None:
                raise ValueError(f"control command {name!r} is not available")
            return getattr(self.ctl, name)(*values)
        if op == "set_outputs":
            host, outputs = args
            return self.set_outputs(host, outputs)
        raise ValueError(f"unknown operation {op!r}")

    def snapshot(self, kick: bool) -> dict[str, object]:
        """The receive interface's state and whether the control script runs; units as ur-rtde's."""
        recv, ctl = self.recv, self.ctl
        if recv is None:
            raise ValueError("the receive interface is not connected")
        running = ctl is not None and ctl.isProgramRunning()
        if kick and running:
            assert ctl is not None
            ctl.kickWatchdog()
        return {
            "timestamp": recv.getTimestamp(), "q": list(recv.getActualQ()), "qd": list(recv.getActualQd()),
            "tcp_pose": list(recv.getActualTCPPose()), "tcp_speed": list(recv.getActualTCPSpeed()),
            "robot_mode": recv.getRobotMode(), "safety_mode": recv.getSafetyMode(),
            "emergency_stopped": recv.isEmergencyStopped(), "protective_stopped": recv.isProtectiveStopped(),
            "digital_inputs": int(recv.getActualDigitalInputBits()), "control": ctl is not None,
            "program_running": running,
        }

    def set_outputs(self, host: str, outputs: list[tuple[int, bool]]) -> int | None:
        io = rtde_io.RTDEIOInterface(host)
        try:
            for index, level in outputs:
                if not io.setStandardDigitalOut(index, level):
                    return index
            return None
        finally:
            with contextlib.suppress(RuntimeError):  # raises when the controller dropped the connection
                io.disconnect()

    def close(self) -> None:
        self.closing = True
        for client in (self.ctl, self.recv, self.dash):
            if client is not None:
                with contextlib.suppress(RuntimeError):  # a socket the controller dropped raises; closed
                    client.disconnect()


def _exit_with_parent(lifeline: int) -> None:
    """End the process when the driver's process ends (its end of the lifeline closes)."""
    while os.read(lifeline, 1):
        pass
    os._exit(EXIT_PARENT_GONE)


def main(conn_fd: int, lifeline_fd: int) -> None:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)  # the driver ends this process (module docstring)
    threading.Thread(target=_exit_with_parent, args=(lifeline_fd,), daemon=True, name="lifeline").start()
    conn = Connection(conn_fd)
    clients = Clients()
    while True:
        try:
            seq, op, args = conn.recv()
        except EOFError:
            os._exit(EXIT_PARENT_GONE)
        try:
            reply: tuple[int, str, object] = (seq, "ok", clients.handle(op, args))
        except (RuntimeError, ValueError, TypeError) as exc:  # ur-rtde raises RuntimeError
            reply = (seq, "error", str(exc))
        conn.send(reply)
        if op == "close":
            sys.stdout.flush()
            os._exit(EXIT_CLOSED)


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]))
