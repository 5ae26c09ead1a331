"""The service's log: one line per event on standard error, for a person or for journald.

On a terminal a line reads ``2026-11-24 12:00:00 INFO    cell.service: job ended completed [job 3f..]``;
anywhere else (a pipe, a file, systemd's journal) it is one JSON object: ``ts`` (UTC, ISO 8601),
``level``, ``logger``, ``msg``, the record's own fields (``job_id``, ``part_id``, ``status``, ... given with
``extra=``) and ``exc`` (a traceback) when there is one. When standard error is the journal's stream
(``JOURNAL_STREAM``), each line starts with the syslog priority (``<6>``) so that journald files it at
the record's level.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import sys
from collections.abc import Callable
from datetime import UTC, datetime
from typing import IO, Any

# The attributes every LogRecord has; anything else on a record came from ``extra=``.
_STANDARD = frozenset(logging.LogRecord("", 0, "", 0, "", None, None).__dict__) | {"message", "asctime",
                                                                                  "color_message", "taskName"}
_SYSLOG_PRIORITY = {logging.CRITICAL: 2, logging.ERROR: 3, logging.WARNING: 4, logging.INFO: 6,
                    logging.DEBUG: 7}
UVICORN_LOGGERS = ("uvicorn", "uvicorn.error", "uvicorn.access")
# Libraries whose INFO records are their own workings, not the service's events: asyncua's OPC UA server
# logs a line for each of about a thousand nodes of the standard address space it loads as it starts,
# burying the line with the certificate's fingerprint that a line's commissioning needs.
QUIET_LOGGERS = ("asyncua",)
LOG_INTERVAL_S = 10.0
"""At most one line per this interval [s] for an event that a flood repeats (:class:`EveryInterval`): the
accept failures, the connections shed or refused at the caps of the HTTP and OPC UA servers, each line
with how many there were."""


def _fields(record: logging.LogRecord) -> dict[str, Any]:
    return {k: v for k, v in record.__dict__.items() if k not in _STANDARD and not k.startswith("_")}


class JsonLineFormatter(logging.Formatter):
    """A record as one JSON object on one line (see the module docstring)."""

    def __init__(self, priority_prefix: bool = False) -> None:
        super().__init__()
        self._prefix = priority_prefix

    def format(self, record: logging.LogRecord) -> str:
        line: dict[str, Any] = {
            "ts": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname.lower(), "logger": record.name, "msg": record.getMessage()}
        line |= _fields(record)
        if record.exc_info:
            line["exc"] = self.formatException(record.exc_info)
        text = json.dumps(line, default=str, ensure_ascii=False)
        if self._prefix:
            level = max((lv for lv in _SYSLOG_PRIORITY if lv <= record.levelno), default=logging.DEBUG)
            text = f"<{_SYSLOG_PRIORITY[level]}>{text}"
        return text


class HumanFormatter(logging.Formatter):
    """Time, level, logger and message; the job's id, if the record has one, in brackets."""

    def __init__(self) -> None:
        super().__init__("%(asctime)s %(levelname)-7s %(name)s: %(message)s", datefmt="%Y-%m-%d %H:%M:%S")

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        job_id = getattr(record, "job_id", None)
        return f"{text} [job {job_id}]" if job_id else text


def _is_journal(stream: IO[str]) -> bool:
    """Whether ``stream`` is the connection to journald that systemd gave this service."""
    expected = os.environ.get("JOURNAL_STREAM", "")
    try:
        st = os.fstat(stream.fileno())
    except (OSError, ValueError):
        return False
    return expected == f"{st.st_dev}:{st.st_ino}"


def configure_logging(stream: IO[str] | None = None, level: int = logging.INFO) -> None:
    """Send every logger's records (uvicorn's included) to ``stream`` (default: standard error), as JSON
    lines unless it is a terminal."""
    stream = sys.stderr if stream is None else stream
    handler = logging.StreamHandler(stream)
    tty = stream.isatty()
    handler.setFormatter(HumanFormatter() if tty else JsonLineFormatter(priority_prefix=_is_journal(stream)))
    root = logging.getLogger()
    root.handlers = [handler]
    root.setLevel(level)
    for name in QUIET_LOGGERS:
        logging.getLogger(name).setLevel(max(level, logging.WARNING))
    for name in UVICORN_LOGGERS:  # uvicorn's own handlers would print a second, unstructured copy
        logger = logging.getLogger(name)
        logger.handlers = []
        logger.propagate = True


class EveryInterval:
    """Counts events and logs them in one line at most every ``LOG_INTERVAL_S``: the first event at once,
    the ones after it in a line with their count at the end of the interval."""

    def __init__(self, line: Callable[[int, str], None]) -> None:
        """``line(count, detail)`` logs the line, ``detail`` being the newest event's."""
        self._line = line
        self._count = 0
        self._detail = ""
        self._last: float | None = None
        self._pending: asyncio.TimerHandle | None = None

    def event(self, loop: asyncio.AbstractEventLoop, detail: str = "") -> None:
        """One more event, on ``loop`` (whose clock times the interval)."""
        self._count, self._detail = self._count + 1, detail
        if self._pending is not None:
            return
        wait_s = 0.0 if self._last is None else self._last + LOG_INTERVAL_S - loop.time()
        if wait_s <= 0.0:
            self._emit(loop)
        else:
            self._pending = loop.call_later(wait_s, self._emit, loop)

    def _emit(self, loop: asyncio.AbstractEventLoop) -> None:
        self._line(self._count, self._detail)
        self._count, self._last, self._pending = 0, loop.time(), None
