"""PackML's state model (ANSI/ISA-TR88.00.02-2015): the states and commands with their standard numbers,
the unit modes, which command each state accepts, and the stop reasons the cell reports.

Acting states (the ``-ing`` ones) end by themselves when their work is done ("state complete", SC); wait
states (Stopped, Idle, Held, Suspended, Complete, Aborted) and Execute wait for a command or, for Execute,
for the scan to end. This module is the table only; :mod:`cell.line.controller` runs it.
"""

from __future__ import annotations

from enum import IntEnum


class State(IntEnum):
    """PackML states, numbered as in TR88.00.02 and OPC 30050 (``StateCurrent``)."""

    CLEARING = 1
    STOPPED = 2
    STARTING = 3
    IDLE = 4
    SUSPENDED = 5
    EXECUTE = 6
    STOPPING = 7
    ABORTING = 8
    ABORTED = 9
    HOLDING = 10
    HELD = 11
    UNHOLDING = 12
    SUSPENDING = 13
    UNSUSPENDING = 14
    RESETTING = 15
    COMPLETING = 16
    COMPLETE = 17

    @property
    def label(self) -> str:
        """The state's name as the standard writes it (``Execute``, ``Held``)."""
        return self.name.capitalize()


class Command(IntEnum):
    """PackML commands, numbered as in TR88.00.02 (``CntrlCmd``)."""

    RESET = 1
    START = 2
    STOP = 3
    HOLD = 4
    UNHOLD = 5
    SUSPEND = 6
    UNSUSPEND = 7
    ABORT = 8
    CLEAR = 9

    @property
    def label(self) -> str:
        return self.name.capitalize()


class UnitMode(IntEnum):
    """PackML unit modes (``UnitModeCurrent``). The cell offers Production (the line drives it) and Manual
    (the operator's: API jobs, jogging); Maintenance is a standard mode the cell does not offer."""

    PRODUCTION = 1
    MAINTENANCE = 2
    MANUAL = 3

    @property
    def label(self) -> str:
        return self.name.capitalize()


OFFERED_MODES = frozenset({UnitMode.PRODUCTION, UnitMode.MANUAL})

MODE_CHANGE_STATES = frozenset({State.STOPPED, State.IDLE, State.ABORTED})
"""The wait states in which the unit mode may change: no part is on its way through the cell."""

STOPPED_BRANCH = frozenset({State.STOPPING, State.STOPPED, State.ABORTING, State.ABORTED, State.CLEARING})
"""The states a stop or an abort leads through to Stopped, where a fault shows until Reset."""

_STOPPABLE = frozenset(State) - STOPPED_BRANCH

ACCEPTS: dict[Command, frozenset[State]] = {
    Command.RESET: frozenset({State.STOPPED, State.COMPLETE}),
    Command.START: frozenset({State.IDLE}),
    Command.STOP: _STOPPABLE,
    Command.HOLD: frozenset({State.EXECUTE}),
    Command.UNHOLD: frozenset({State.HELD}),
    Command.SUSPEND: frozenset({State.EXECUTE}),
    Command.UNSUSPEND: frozenset({State.SUSPENDED}),
    Command.ABORT: frozenset(State) - {State.ABORTING, State.ABORTED},
    Command.CLEAR: frozenset({State.ABORTED}),
}
"""The states in which each command is valid (TR88.00.02-2015's state model: Stop from every state outside
the Stopped and Aborted branches, Abort from every state but Aborting and Aborted)."""

ACTING: dict[Command, State] = {
    Command.RESET: State.RESETTING, Command.START: State.STARTING, Command.STOP: State.STOPPING,
    Command.HOLD: State.HOLDING, Command.UNHOLD: State.UNHOLDING, Command.SUSPEND: State.SUSPENDING,
    Command.UNSUSPEND: State.UNSUSPENDING, Command.ABORT: State.ABORTING, Command.CLEAR: State.CLEARING,
}
"""The acting state each accepted command enters."""


def refusal(state: State, command: Command) -> str | None:
    """Why ``command`` is not valid in ``state`` (None: it is)."""
    if state in ACCEPTS[command]:
        return None
    valid = ", ".join(s.label for s in sorted(ACCEPTS[command]))
    return f"{command.label} is not valid in {state.label} (valid in: {valid})"


class StopReason(IntEnum):
    """``Admin/StopReason/ID``: why the cell last stopped or aborted (0: it has not)."""

    NONE = 0
    LINE_STOP = 1
    """the line's Stop command"""
    OPERATOR_STOP = 2
    """an operator's STOP (API, web page) or a job stopped through the API"""
    LINE_ABORT = 3
    """the line's Abort command"""
    SAFETY_STOP = 4
    """the safety layer stopped the arm (a guard refusal, a watchdog), or the service its scan's worker, which
    stopped answering (hung)"""
    ARM_FAULT = 5
    """the arm reported a fault: protective stop, emergency stop, reflex, lost connection"""
    JOB_FAILED = 6
    """the scan failed: a driver fault, a planner error, a worker that died"""
    SHUTDOWN = 7
    """the service shut down or started"""
    CLEAR_FAILED = 8
    """Clear could not recover the arm"""


ORDINARY_STOPS = frozenset({StopReason.NONE, StopReason.LINE_STOP, StopReason.LINE_ABORT,
                            StopReason.SHUTDOWN})
"""Stop reasons that are no fault of the cell: none yet, the line's own Stop or Abort (the PLC knows why),
the service's shutdown or start (a Reset is all it takes). The others (an operator's STOP, a safety stop,
an arm fault, a failed scan, a failed Clear) are what the digital I/O's ``fault_output`` shows."""
