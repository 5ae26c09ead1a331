"""systemd's service notification protocol (``sd_notify``), for ``Type=notify`` units.

The service manager passes a socket in ``NOTIFY_SOCKET`` (a path, or ``@name`` in the abstract namespace);
each notification is one datagram of ``KEY=VALUE`` lines: ``READY=1`` once the service serves,
``WATCHDOG=1`` at least every ``WATCHDOG_USEC`` microseconds while it is healthy (the manager restarts it
when they stop), ``STOPPING=1`` when it begins to shut down, ``STATUS=...`` a line for ``systemctl status``.
Without ``NOTIFY_SOCKET`` (not under systemd) every call does nothing.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping

from drivers.errors import CellError


class Notifier:
    """Sends notifications to the socket named in ``env`` (default ``os.environ``)."""

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        path = env.get("NOTIFY_SOCKET", "")
        self._address = "\0" + path[1:] if path.startswith("@") else path
        watchdog_usec = env.get("WATCHDOG_USEC", "")
        watchdog_pid = env.get("WATCHDOG_PID", "")
        # the watchdog is this process's only when the manager named it (or named no process)
        mine = not watchdog_pid or watchdog_pid == str(os.getpid())
        if watchdog_usec and mine:
            try:
                usec = int(watchdog_usec)
            except ValueError:
                raise CellError(f"WATCHDOG_USEC={watchdog_usec!r} is not a number of microseconds") from None
            self.watchdog_s: float | None = usec / 1e6 if usec > 0 else None
        else:
            self.watchdog_s = None

    @property
    def enabled(self) -> bool:
        """Whether a service manager listens."""
        return bool(self._address)

    @property
    def ping_interval_s(self) -> float | None:
        """How often to send ``WATCHDOG=1`` [s]: half the manager's timeout, as sd_watchdog_enabled(3)
        advises; None when there is no watchdog."""
        return None if self.watchdog_s is None or not self.enabled else self.watchdog_s / 2

    def notify(self, **fields: str) -> None:
        """Send ``KEY=VALUE`` lines (``notify(READY="1", STATUS="serving")``). A manager that went away is
        not an error of the service: ``OSError`` is ignored, as sd_notify(3) does. The send never waits:
        a datagram socket whose reader has fallen behind (Linux queues ``net.unix.max_dgram_qlen``, 10 by
        default) would block the event loop that sends the pings, and with it every request, Stop
        included; such a notification is dropped instead (a manager that reads no pings restarts the
        service, as it should)."""
        if not self.enabled:
            return
        message = "\n".join(f"{key}={value}" for key, value in fields.items()).encode()
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
            sock.setblocking(False)
            try:
                sock.sendto(message, self._address)
            except OSError:
                return
