"""The packing line's digital-I/O handshake on the UR5e's standard I/O (the simplest line: one input, two
outputs).

- A rising edge on ``trigger_input`` in Idle is Start (the part id is ``line.dio.part_id``, or
  ``part-<n>``): a digital input carries none.
- ``busy_output`` is high in Execute; ``done_output`` is high in Complete, until the PLC acknowledges the
  result, which is Reset. Both of a PLC's usual patterns work (:func:`trigger_commands`): a trigger held
  until done acknowledges by falling (Complete: Reset); a pulsed trigger, whose fall during Execute does
  nothing, acknowledges with the next part's rising edge (Complete: Reset, then Start). An edge the state
  does not accept is refused as any command is, and logged.
- The trigger is debounced: a new level counts once it has held for ``line.dio.debounce_s``. The level
  found at start is the baseline, not an edge (a trigger left high does not start a scan on a restart).

A thread of its own polls the inputs at ``line.dio.poll_hz`` and writes the outputs when the state
changes, through :class:`drivers.arm.ur_io.URDigitalIO`; commands go to the service's loop. A lost link
is logged and reconnected every ``RECONNECT_S``; the outputs are written again once it is back.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time

from cell.line.config import DigitalIOConfig
from cell.line.controller import LineController, LineSnapshot
from cell.line.packml import Command, State
from drivers.arm.config import UR5eArmConfig
from drivers.arm.ur_io import URDigitalIO
from drivers.errors import DriverError, ServiceError

RECONNECT_S = 2.0
"""How long a lost I/O link waits before connecting again [s]."""

log = logging.getLogger("cell.line")


class Debouncer:
    """A digital level that changes only after the raw input has held the new level for ``hold_s`` [s]."""

    def __init__(self, level: bool, hold_s: float) -> None:
        self.level = level
        self._hold_s = hold_s
        self._candidate_since: float | None = None

    def update(self, raw: bool, now: float) -> bool | None:
        """The raw level at time ``now`` [s]; returns the new debounced level when it changes, else None."""
        if raw == self.level:
            self._candidate_since = None
            return None
        if self._candidate_since is None:
            self._candidate_since = now
        if now - self._candidate_since >= self._hold_s:
            self.level, self._candidate_since = raw, None
            return raw
        return None


def trigger_commands(state: State, rising: bool) -> tuple[Command, ...]:
    """What an edge of the trigger does in ``state``, in order: a rise is Start, in Complete after Reset
    (the next part's trigger acknowledges the last part's result); a fall is Reset in Complete (a held
    trigger acknowledges) and nothing elsewhere (a pulse's fall, or a held trigger's during the scan)."""
    if rising:
        return (Command.RESET, Command.START) if state is State.COMPLETE else (Command.START,)
    return (Command.RESET,) if state is State.COMPLETE else ()


class DigitalIOHandshake:
    """The handshake of one cell (see the module docstring); :meth:`start` on the service's loop."""

    def __init__(self, line: LineController, arm: UR5eArmConfig, config: DigitalIOConfig) -> None:
        assert arm.trigger_input is not None and arm.busy_output is not None and arm.done_output is not None
        self._line = line
        self._config = config
        self._trigger, self._busy, self._done = arm.trigger_input, arm.busy_output, arm.done_output
        self._io = URDigitalIO(arm)
        self._wanted: list[tuple[int, bool]] = self._outputs(line.state)
        self._written: list[tuple[int, bool]] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="line digital io", daemon=True)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._edges: asyncio.Lock | None = None  # one edge at a time, in the order they came

    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._edges = asyncio.Lock()
        self._line.subscribe(self._on_change)
        self._thread.start()

    async def close(self) -> None:
        """Stop polling, set both outputs low and disconnect."""
        self._stop.set()
        await asyncio.to_thread(self._thread.join)

    def _outputs(self, state: State) -> list[tuple[int, bool]]:
        return [(self._busy, state is State.EXECUTE), (self._done, state is State.COMPLETE)]

    def _on_change(self, snapshot: LineSnapshot) -> None:
        self._wanted = self._outputs(snapshot.state)

    def _run(self) -> None:
        period = 1.0 / self._config.poll_hz
        debounced: Debouncer | None = None
        while not self._stop.is_set():
            try:
                if debounced is None:
                    self._io.connect()
                    debounced = Debouncer(self._io.inputs()[self._trigger], self._config.debounce_s)
                    log.info("line: digital I/O connected (trigger DI%d, busy DO%d, done DO%d)",
                             self._trigger, self._busy, self._done)
                assert debounced is not None
                wanted = self._wanted
                if wanted != self._written:
                    self._io.set_outputs(wanted)
                    self._written = wanted
                edge = debounced.update(self._io.inputs()[self._trigger], time.monotonic())
                if edge is not None:
                    self._post(edge)
            except DriverError as exc:
                log.error("line: digital I/O: %s; connecting again in %g s", exc, RECONNECT_S)
                self._io.close()
                debounced, self._written = None, None
                self._stop.wait(RECONNECT_S)
                continue
            self._stop.wait(period)
        try:
            self._io.set_outputs([(self._busy, False), (self._done, False)])
        except DriverError as exc:
            log.warning("line: digital outputs not cleared at shutdown: %s", exc)
        self._io.close()

    def _post(self, rising: bool) -> None:
        assert self._loop is not None
        asyncio.run_coroutine_threadsafe(self._edge(rising), self._loop)

    async def _edge(self, rising: bool) -> None:
        assert self._edges is not None
        line = self._line
        source = f"digital input DI{self._trigger} {'rising' if rising else 'falling'}"
        async with self._edges:
            await line.settle()
            for command in trigger_commands(line.state, rising):
                part_id = None
                if command is Command.START:
                    part_id = self._config.part_id or f"part-{line.snapshot().processed + 1}"
                try:
                    await line.command(command, source, part_id=part_id)
                except ServiceError as exc:
                    log.warning("line: %s refused: %s", source, exc)
                    return
                await line.settle()  # Start after Reset meets Idle
