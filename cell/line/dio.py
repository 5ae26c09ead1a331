"""The packing line's digital-I/O handshake on the UR5e's standard I/O (the simplest line: one input, two
outputs; optionally a second input and two more outputs). The pins are the arm section's.

- A rising edge on ``trigger_input`` in Idle is Start. A digital input carries no part id: the part is
  ``line.dio.part_id`` if the cell file gives one, else the one the line set for it over OPC UA or REST
  since the last Start, else ``part-<n>`` (:meth:`DigitalIOHandshake._part_id`).
- ``busy_output`` is high in Execute; ``done_output`` is high in Complete, until the PLC acknowledges the
  result, which is Reset. Both of a PLC's usual patterns work (:func:`trigger_commands`): a trigger held
  until done acknowledges by falling (Complete: Reset); a pulsed trigger, whose fall during Execute does
  nothing, acknowledges with the next part's rising edge (Complete: Reset, then Start). An edge the state
  does not accept is refused as any command is, and logged.
- ``reset_input`` (optional): a rising edge is Clear in Aborted and Reset elsewhere (valid in Stopped and
  Complete, refused and logged in the other states), so that a line wired only to digital I/O can bring
  the cell back from Stopped (after every start of the service) and Aborted.
- ``ready_output`` and ``fault_output`` (optional; :func:`output_levels`): ready is high in Idle in
  Production mode (a trigger starts a part); fault is high in Held, and in the Stopped and Aborted
  branches for a stop the line did not command (:data:`cell.line.packml.ORDINARY_STOPS`), until Reset.
- An input is debounced: a new level counts once it has held for ``line.dio.debounce_s``, on the clock of
  the device that sampled it (the UR controller's RTDE timestamp): a sample the service reads late or
  twice (it, or its RTDE link, descheduled on a loaded PC) does not stretch a bounce into a level. The
  level found at start is the baseline, not an edge (a trigger left high does not start a scan on a
  restart).

A thread of its own polls the inputs at ``line.dio.poll_hz`` and writes the outputs when they change,
through :class:`drivers.arm.ur_io.URDigitalIO` (a UR5e) or :class:`drivers.arm.sim_io.SimDigitalIO` (a sim
cell's simulated UR5e, whose inputs REST sets: :meth:`DigitalIOHandshake.simulated`); commands go to the
service's loop. A lost link is logged and reconnected every ``RECONNECT_S``; the outputs are written again
once it is back. :meth:`DigitalIOHandshake.levels` says what the handshake last saw and wrote.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import threading
from collections.abc import AsyncIterator, Coroutine
from dataclasses import dataclass
from typing import Any

from cell.line.config import DigitalIOConfig
from cell.line.controller import LineController, LineSnapshot
from cell.line.packml import ORDINARY_STOPS, STOPPED_BRANCH, Command, State, UnitMode
from drivers.arm.config import LINE_INPUTS, LINE_OUTPUTS, ArmConfig, LinePinsConfig, UR5eArmConfig
from drivers.arm.sim_io import DigitalIO, SimDigitalIO
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


def reset_command(state: State) -> Command:
    """What a rising edge of the reset input asks for in ``state``: Clear in Aborted, else Reset (which the
    state machine refuses outside Stopped and Complete)."""
    return Command.CLEAR if state is State.ABORTED else Command.RESET



def output_levels(snapshot: LineSnapshot) -> dict[str, bool]:
    """The level of each output (:data:`drivers.arm.config.LINE_OUTPUTS`) for the line's ``snapshot``:
    ``busy_output`` in Execute, ``done_output`` in Complete, ``ready_output`` in Idle in Production mode,
    ``fault_output`` in Held, and in :data:`cell.line.packml.STOPPED_BRANCH` when the stop reason is not
    one of :data:`cell.line.packml.ORDINARY_STOPS` (it stays high through Clear, until Reset)."""
    state = snapshot.state
    return {"busy_output": state is State.EXECUTE, "done_output": state is State.COMPLETE,
            "ready_output": state is State.IDLE and snapshot.mode is UnitMode.PRODUCTION,
            "fault_output": state is State.HELD or (state in STOPPED_BRANCH
                                                    and snapshot.stop_reason_id not in ORDINARY_STOPS)}


@dataclass(frozen=True)
class Signal:
    """One wired signal of the handshake: its ``name`` (of :data:`LINE_INPUTS`, :data:`LINE_OUTPUTS`), the
    digital index it is wired to (``pin``) and its ``level``: an input's as the handshake counts it
    (debounced; None before the link first connected), an output's as last written (None: not written
    since the link connected)."""

    name: str
    pin: int
    level: bool | None


@dataclass(frozen=True)
class DigitalLevels:
    """What :meth:`DigitalIOHandshake.levels` says: whether the link is ``connected``, whether the I/O is
    ``simulated`` (a sim cell's, whose inputs may be set), the device's time of the inputs' sample the
    levels were counted from (``sampled_s`` [s, the controller's RTDE timestamp; a sim cell's: the
    service's monotonic clock]; None while the link is not connected), and each wired input and output."""

    connected: bool
    simulated: bool
    sampled_s: float | None
    inputs: tuple[Signal, ...]
    outputs: tuple[Signal, ...]


def digital_io(arm: ArmConfig) -> DigitalIO:
    """The digital I/O the handshake of a cell with ``arm`` uses: a UR5e's over RTDE, else (the config's
    check: a simulated UR5e) a simulated one."""
    return URDigitalIO(arm) if isinstance(arm, UR5eArmConfig) else SimDigitalIO()


def _wired(arm: LinePinsConfig, names: tuple[str, ...]) -> dict[str, int]:
    """The pins of ``names`` that ``arm`` wires: name -> digital index."""
    return {name: index for name, index in arm.line_pins(names).items() if index is not None}


def _log_failure(done: concurrent.futures.Future[None]) -> None:
    """Log an edge's handling that failed (it runs on the service's loop, where nobody waits for it)."""
    if not done.cancelled() and (exc := done.exception()) is not None:
        log.error("line: a digital input's edge was not handled: %s: %s", type(exc).__name__, exc,
                  exc_info=exc)


class DigitalIOHandshake:
    """The handshake of one cell (see the module docstring); :meth:`start` on the service's loop."""

    def __init__(self, line: LineController, arm: LinePinsConfig, config: DigitalIOConfig,
                 io: DigitalIO) -> None:
        assert arm.trigger_input is not None  # the config's check: line.dio needs it (and busy, done)
        self._line = line
        self._config = config
        self._trigger, self._reset = arm.trigger_input, arm.reset_input
        self._inputs, self._pins = _wired(arm, LINE_INPUTS), _wired(arm, LINE_OUTPUTS)
        self._io = io
        self._wanted: list[tuple[int, bool]] = self._outputs(line.snapshot())
        self._written: list[tuple[int, bool]] | None = None
        # the debounced inputs by index and the device's time of the sample they were counted from, while
        # connected: one tuple, replaced whole, so a reader never pairs one sample's levels with another's
        self._seen: tuple[dict[int, bool], float] | None = None
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
        """Stop polling, set every output low and disconnect."""
        self._stop.set()
        await asyncio.to_thread(self._thread.join)

    @property
    def simulated(self) -> SimDigitalIO | None:
        """The simulated I/O of a sim cell, whose inputs may be set; None for a UR5e's."""
        return self._io if isinstance(self._io, SimDigitalIO) else None

    def levels(self) -> DigitalLevels:
        """Each wired input as the handshake counts it and each output as it last wrote it."""
        seen, written = self._seen, self._written
        wrote = dict(written) if written is not None else {}
        levels, sampled_s = (None, None) if seen is None else seen
        return DigitalLevels(
            connected=seen is not None, simulated=self.simulated is not None, sampled_s=sampled_s,
            inputs=tuple(Signal(name, index, None if levels is None else levels[index])
                         for name, index in self._inputs.items()),
            outputs=tuple(Signal(name, index, wrote.get(index)) for name, index in self._pins.items()))

    def _outputs(self, snapshot: LineSnapshot) -> list[tuple[int, bool]]:
        levels = output_levels(snapshot)
        return [(index, levels[name]) for name, index in self._pins.items()]

    def _on_change(self, snapshot: LineSnapshot) -> None:
        self._wanted = self._outputs(snapshot)

    def _wiring(self) -> str:
        inputs = [f"trigger DI{self._trigger}"] + ([] if self._reset is None else [f"reset DI{self._reset}"])
        return ", ".join(inputs + [f"{name} DO{index}" for name, index in self._pins.items()])

    def _run(self) -> None:
        period = 1.0 / self._config.poll_hz
        trigger: Debouncer | None = None
        reset: Debouncer | None = None
        while not self._stop.is_set():
            try:
                if trigger is None:
                    self._io.connect()
                    levels, now = self._io.inputs()
                    trigger = Debouncer(levels[self._trigger], self._config.debounce_s)
                    if self._reset is not None:
                        reset = Debouncer(levels[self._reset], self._config.debounce_s)
                    # the baseline is what is counted until the next sample, which comes after the outputs
                    # are written (the first write connects RTDE IO, seconds on a loaded PC)
                    self._publish(trigger, reset, now)
                    log.info("line: digital I/O connected (%s)", self._wiring())
                assert trigger is not None
                wanted = self._wanted
                if wanted != self._written:
                    self._io.set_outputs(wanted)
                    self._written = wanted
                levels, now = self._io.inputs()  # now: the device's clock [s]
                edge = trigger.update(levels[self._trigger], now)
                if edge is not None:
                    self._post(self._trigger_edge(edge))
                if reset is not None and self._reset is not None and reset.update(levels[self._reset], now):
                    self._post(self._reset_edge())  # its fall does nothing
                # after the edges are posted: a level seen here has had its command sent to the line
                self._publish(trigger, reset, now)
            except DriverError as exc:
                log.error("line: digital I/O: %s; connecting again in %g s", exc, RECONNECT_S)
                self._io.close()
                trigger, reset, self._written, self._seen = None, None, None, None
                self._stop.wait(RECONNECT_S)
                continue
            self._stop.wait(period)
        try:
            self._io.set_outputs([(index, False) for index in self._pins.values()])
        except DriverError as exc:
            log.warning("line: digital outputs not cleared at shutdown: %s", exc)
        self._io.close()

    def _publish(self, trigger: Debouncer, reset: Debouncer | None, sampled_s: float) -> None:
        """Publish the inputs as counted from the device's sample at ``sampled_s`` [s, its clock]."""
        seen = {self._trigger: trigger.level}
        if reset is not None and self._reset is not None:
            seen[self._reset] = reset.level
        self._seen = (seen, sampled_s)  # whole: the event loop reads it from this thread's side

    def _post(self, edge: Coroutine[Any, Any, None]) -> None:
        assert self._loop is not None
        asyncio.run_coroutine_threadsafe(edge, self._loop).add_done_callback(_log_failure)

    async def _trigger_edge(self, rising: bool) -> None:
        source = f"digital input DI{self._trigger} {'rising' if rising else 'falling'}"
        async with self._one_edge():
            for command in trigger_commands(self._line.state, rising):
                part_id = None
                if command is Command.START:
                    part_id = self._part_id()
                if not await self._give(command, source, part_id):
                    return

    def _part_id(self) -> str:
        """What a trigger's Start scans: ``line.dio.part_id``; else the part id the line set for this part
        (OPC UA, REST) since the last Start; else ``part-<n>``, n the count of parts processed, plus one."""
        line = self._line
        return self._config.part_id or line.pending_part_id or f"part-{line.snapshot().processed + 1}"

    async def _reset_edge(self) -> None:
        async with self._one_edge():
            await self._give(reset_command(self._line.state), f"digital input DI{self._reset} rising")

    @contextlib.asynccontextmanager
    async def _one_edge(self) -> AsyncIterator[None]:
        """Edges one at a time, in the order they came, each meeting the state the one before led to."""
        assert self._edges is not None
        async with self._edges:
            await self._line.settle()
            yield

    async def _give(self, command: Command, source: str, part_id: str | None = None) -> bool:
        """Give the line ``command``; whether it was accepted (a refusal is logged, and said by the line).
        Returns once the acting state it entered has done its work (Start after Reset meets Idle)."""
        try:
            await self._line.command(command, source, part_id=part_id)
        except ServiceError as exc:
            log.warning("line: %s from %s refused: %s", command.label, source, exc)
            return False
        await self._line.settle()
        return True
