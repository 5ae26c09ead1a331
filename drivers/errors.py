"""The one error hierarchy of the project.

It lives in the lowest layer so that drivers and the application raise the same types; ``cell`` imports
it from here. Each error carries the facts a person needs to act on it.
"""

from __future__ import annotations


class CellError(Exception):
    """Base of every error the cell raises on purpose."""


class ConfigError(CellError):
    """A configuration file or value is invalid; raised before anything moves.

    ``file`` is the YAML file, ``field`` the dotted path of the offending value and ``allowed`` what
    would have been accepted.
    """

    def __init__(self, message: str, *, file: str | None = None, field: str | None = None,
                 allowed: str | None = None) -> None:
        self.file = file
        self.field = field
        self.allowed = allowed
        parts = [p for p in (file, field) if p]
        prefix = ": ".join(parts)
        text = f"{prefix}: {message}" if prefix else message
        if allowed:
            text += f" (allowed: {allowed})"
        super().__init__(text)


class DriverError(CellError):
    """A device could not be reached or misbehaved. ``device`` names it (e.g. ``arm sim``)."""

    def __init__(self, message: str, *, device: str) -> None:
        self.device = device
        super().__init__(f"{device}: {message}")


class DeviceFault(DriverError):
    """A device latched a fault (its link gone, it stopped answering): every use fails until it is
    reconnected, so retrying cannot help and a job that needs it ends."""


ARM_FAULT = "arm fault: "
"""How the reason of a stop for a fault the arm latched (a ``RobotFault``) begins, the fault's words
following: the arm stays faulted until recovered."""
OPERATOR_STOP = "operator stop: "
"""How the reason of a stop someone asked for (the guard's ``request_stop``, an interrupt) begins: a job
it ends was stopped by a person or a client, not by the safety layer."""
SHUTDOWN_STOP = "shutdown stop: "
"""How the reason of a stop the service makes as it is shut down (SIGTERM or Ctrl-C of ``cell serve``, a
system shutdown) begins: asked for, not the safety layer's, but by no operator of the job, and kept so in its
termination (it read ``operator stop``)."""
SAFETY_STOP = "safety stop: "
"""How the termination of a job its safety layer stopped by itself begins (a guard refusal, the watchdog, an
arm fault, a worker that stopped answering): the reason follows."""


def stop_cause(reason: str, operator: bool) -> str:
    """The reason a stop is made with: ``operator stop: <reason>`` for a stop someone asked for, the
    reason as it is for the service's shutdown (it begins ``shutdown stop:``; a client's reason never does,
    ``cell.api.stop_reason``) and for one the safety layer or the service made by itself
    (``stop_termination`` then reads it as a safety stop)."""
    if reason.startswith(SHUTDOWN_STOP):  # the service's shutdown says so itself
        return reason
    return f"{OPERATOR_STOP}{reason}" if operator else reason


def stop_termination(reason: str) -> str:
    """The termination of a job a stop ended: an operator stop as it is (``operator stop: <reason>``), as is
    the service's shutdown (``shutdown stop: <reason>``), the
    safety layer's own (a refusal, the watchdog, an arm fault) as ``safety stop: <reason>``. An operator's
    stop was reported as a safety stop, and a line or a person reading it looked for a fault."""
    return reason if reason.startswith((OPERATOR_STOP, SHUTDOWN_STOP)) else f"{SAFETY_STOP}{reason}"


COMMAND_LINE_REASON = "requested from the command line"
"""A stop's reason when the command line is given none (``cell stop``, ``cell jobs stop``): the job's
termination already says that it was an operator stop (``operator stop: <reason> (key NAME)``), which a
default of "operator stop" repeated."""


class RobotFault(DriverError):
    """The arm reports a fault (protective stop, reflex, joint limit, disconnect); motion has stopped."""

    def __init__(self, message: str, *, device: str, fault: str) -> None:
        self.fault = fault
        super().__init__(message, device=device)


class KinematicsError(CellError):
    """A kinematic query has no acceptable answer (unreachable pose, wrong joint vector length)."""


class SafetyStop(CellError):
    """The safety layer refused or stopped a motion; ``reason`` is recorded in the job."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(reason)


class PlanningError(CellError):
    """A planner cannot produce a next view or a motion."""


class NoObjectFound(PlanningError):
    """The planner's views show no object above the table, so it has nothing to scan: the job ends
    ``no_object`` (not a failure of the cell; an empty table, a part that did not arrive)."""


class CalibrationError(CellError):
    """A calibration cannot give a trustworthy answer (too few views, an axis the views cannot observe,
    a target not seen); the message says which and what to change."""


class JobError(CellError):
    """A scan job cannot start or continue (missing object, unwritable folder, ...)."""


class StoreError(CellError):
    """The job store cannot be opened, migrated or written (a bad ``--db`` URL, a database that does not
    answer, a schema newer than this software)."""


class StoreDamaged(StoreError):
    """The job store answers, but its data is damaged (an SQLite file that is "malformed" or "not a
    database", a PostgreSQL page or index reported corrupt, a broken constraint): trying again cannot
    help; the store is restored from a backup (docs/deploy.md, section 9)."""


class ServiceError(CellError):
    """The service refuses a request. ``reason`` is one of ``invalid`` (``field`` names the offending
    input), ``not found``, ``conflict`` (not in a state that allows it), ``queue full``, ``forbidden``
    (the caller's key may not do it), ``unavailable`` (what it needs is gone: the job store's file); the API
    turns it into its HTTP status (422, 404, 409, 429, 403, 503)."""

    def __init__(self, message: str, *, reason: str, field: str | None = None) -> None:
        self.reason = reason
        self.field = field
        super().__init__(message)
