"""uvicorn's server for ``cell serve``, telling systemd how it is (:mod:`cell.service.notify`).

``READY=1`` once the API listens (after the cell's service started: store, queue, line), ``WATCHDOG=1``
every half watchdog period from the event loop itself, so that a loop that hangs stops the pings and
systemd restarts the service (as does a cell service that can run no more jobs: its job dispatcher ended on
an error, ``CellService.broken``; the pings stop then, with the reason in ``STATUS``), and ``STOPPING=1``
as soon as a shutdown begins. The running job's arm is then commanded to stop at once
(``CellService.stop_for_shutdown``), before uvicorn waits for open requests (event streams, which end
within a second of it, ``cell.api.routes.jobs``): it used to be stopped by the app's lifespan, after that
wait, and moved on for its 2 s. The lifespan then finishes the job's folder, which may take
``service.shutdown_timeout_s``. A failing ``accept()`` is logged once in a while, not once per attempt
(``cell.api.connections.quiet_accept_failures``).
"""

from __future__ import annotations

import asyncio
import contextlib
import socket

import uvicorn

from cell.api.connections import quiet_accept_failures
from cell.service.manager import CellService
from cell.service.notify import Notifier


class NotifyingServer(uvicorn.Server):
    """A uvicorn server that notifies ``notifier``'s service manager."""

    def __init__(self, config: uvicorn.Config, notifier: Notifier) -> None:
        super().__init__(config)
        self._notifier = notifier
        self._pings: asyncio.Task[None] | None = None

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        quiet_accept_failures(asyncio.get_running_loop())
        await super().startup(sockets)
        if not self.started:
            return
        self._notifier.notify(READY="1", STATUS=f"serving on {self.config.host}:{self.config.port}")
        interval = self._notifier.ping_interval_s
        if interval is not None:
            self._pings = asyncio.create_task(self._ping(interval))

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        self._notifier.notify(STOPPING="1", STATUS="stopping: the running job stops and finishes its folder")
        service = self._service()
        try:
            try:
                if service is not None:  # the arm first, before uvicorn waits for open requests
                    await service.stop_for_shutdown()
            finally:
                await super().shutdown(sockets)
        finally:
            if self._pings is not None:
                self._pings.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await self._pings

    async def _ping(self, interval_s: float) -> None:
        while (broken := self._broken()) is None:
            self._notifier.notify(WATCHDOG="1")
            await asyncio.sleep(interval_s)
        self._notifier.notify(STATUS=f"not pinging the watchdog: {broken}")

    def _broken(self) -> str | None:
        """Why the app's cell service can run no more jobs, or None."""
        service = self._service()
        return None if service is None else service.broken

    def _service(self) -> CellService | None:
        """The app's cell service (``app.state.service``), once its lifespan has started it."""
        service = getattr(getattr(self.config.app, "state", None), "service", None)
        return service if isinstance(service, CellService) else None
