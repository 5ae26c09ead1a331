"""A small client of the service's ``/api/v1`` for the command line: JSON requests and a job's event stream.

:class:`ApiClient` sends ``Authorization: Bearer KEY`` with every request and turns what can go wrong into
two errors that read as one line: :class:`ApiError` (the server answered with an HTTP error: its status
and ``detail``, a 422's fields named) and :class:`ServerUnreachable` (no answer at the URL). The key is
never part of a message.

:meth:`ApiClient.follow` reads ``GET /api/v1/jobs/{id}/events`` (Server-Sent Events, parsed here: ``id:``,
``event:``, ``data:`` lines, comments ignored, a blank line ends an event). When the stream breaks it
reconnects with ``Last-Event-ID`` for up to :data:`RECONNECT_WINDOW_S` without an event, so that no event
is lost or repeated and a service restarted meanwhile is waited for; it ends after the job's ``result``
event.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any
from urllib.parse import quote

import httpx

from drivers.errors import CellError

JOB_STATUSES = ("queued", "running", "stopping", "completed", "no_object", "failed", "stopped", "cancelled",
                "interrupted")
"""Every status a job can be in, in the order of its life: the service's own list
(``cell.service.store.JOB_STATUSES``; a test holds them equal), which the command line does not import: the
store's module loads SQLAlchemy, a third of a second of every ``cell jobs``."""
FINISHED = frozenset(JOB_STATUSES[3:])
"""The statuses a job never leaves: all but queued, running and stopping."""
REQUEST_TIMEOUT_S = 30.0
STREAM_IDLE_S = 40.0
"""An event stream silent this long [s] is taken as broken (the server sends a keep-alive every 15 s)."""
RECONNECT_WINDOW_S = 60.0
"""How long [s] a broken event stream is reconnected without an event before giving up: a service that
systemd restarts (``RestartSec=5``, then a start of 10-20 s) is back within it, and the job's record then
says how it ended (``interrupted``); five tries in a row, 12 s, had given up before."""
GATEWAY_AWAY = frozenset({502, 503, 504})
"""What a reverse proxy before the service answers while the service restarts (bad gateway, unavailable,
gateway timeout): a broken stream to reconnect within :data:`RECONNECT_WINDOW_S`, as a refused
connection is."""
RECONNECT_DELAY_S = 0.5
"""The wait before the n-th reconnection in a row is n times this [s], at most ``MAX_RECONNECT_DELAY_S``."""
MAX_RECONNECT_DELAY_S = 5.0


class ApiError(CellError):
    """The server answered ``status`` with ``detail`` (a 422's fields and messages as ``field: msg``)."""

    def __init__(self, status: int, detail: str) -> None:
        self.status = status
        self.detail = detail
        super().__init__(f"{status} {detail}")


class ServerUnreachable(CellError):
    """No answer from the server (refused, unknown host, timed out, connection broken)."""


class WaitTimeout(CellError):
    """A job did not end within the time given to wait for it."""


@dataclass(frozen=True)
class ServerEvent:
    """One Server-Sent Event: ``id`` (None if the server sent none), ``event`` (``message`` if unnamed) and
    its ``data`` decoded from JSON."""

    id: int | None
    event: str
    data: Any


def _field(loc: object) -> str:
    """The field a 422 ``loc`` names: its last name, with the indices after it (``object_pose[2]``)."""
    parts = list(loc) if isinstance(loc, list | tuple) else [loc]
    indices: list[str] = []
    while parts and isinstance(parts[-1], int):
        indices.insert(0, f"[{parts.pop()}]")
    name = str(parts[-1]) if parts else "body"
    return name + "".join(indices)


def describe_detail(body: object, fallback: str) -> str:
    """The ``detail`` of an error body in one line: a string as is, a list of validation errors as
    ``field: msg; field: msg``; ``fallback`` when there is none."""
    detail = body.get("detail") if isinstance(body, dict) else None
    if isinstance(detail, str) and detail:
        text = detail
    elif isinstance(detail, list) and detail:
        text = "; ".join(f"{_field(item.get('loc'))}: {item.get('msg', '')}" if isinstance(item, dict)
                         else str(item) for item in detail)
    elif detail is not None:
        text = json.dumps(detail)
    else:
        text = fallback
    return " ".join(text.split())


def _api_error(response: httpx.Response) -> ApiError:
    try:
        body: object = response.json()
    except ValueError:
        body = None
    text = response.text.strip().splitlines()[0][:200] if body is None and response.text.strip() else ""
    return ApiError(response.status_code, describe_detail(body, text or response.reason_phrase or "error"))


class ApiClient:
    """The API of the service at ``server`` (``http://host:port``) with ``key``. Use as a context manager
    or call :meth:`close`. ``transport`` replaces httpx's own (tests: ``httpx.MockTransport``)."""

    def __init__(self, server: str, key: str, *, timeout_s: float = REQUEST_TIMEOUT_S,
                 transport: httpx.BaseTransport | None = None) -> None:
        self.server = server.rstrip("/")
        if not self.server.startswith(("http://", "https://")):
            raise CellError(f"the server URL must start with http:// or https://, got {server!r}")
        if not key.isascii() or not key.isprintable() or not key.strip():
            raise CellError("the API key is not a valid key (printable ASCII expected)")
        self._http = httpx.Client(base_url=self.server, headers={"Authorization": f"Bearer {key.strip()}"},
                                  timeout=timeout_s, transport=transport)

    def __enter__(self) -> ApiClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _unreachable(self, exc: httpx.TransportError) -> ServerUnreachable:
        if isinstance(exc, httpx.ConnectError | httpx.ConnectTimeout):
            return ServerUnreachable(f"the server did not answer at {self.server} ({_reason(exc)})")
        if isinstance(exc, httpx.TimeoutException):
            return ServerUnreachable(f"the server at {self.server} did not answer in time ({_reason(exc)})")
        return ServerUnreachable(f"the connection to {self.server} failed ({_reason(exc)})")

    def request(self, method: str, path: str, *, json_body: object = None,
                params: dict[str, Any] | None = None) -> Any:
        """``method path`` and its decoded JSON answer (None for an empty one); ``ApiError`` for an HTTP
        error, ``ServerUnreachable`` when there is no answer."""
        try:
            response = self._http.request(method, path, json=json_body, params=params)
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from None
        if response.is_error:
            raise _api_error(response)
        if not response.content:
            return None
        try:
            return response.json()
        except ValueError:
            raise ApiError(response.status_code, f"the answer to {method} {path} is not JSON") from None

    # --- the job routes ---------------------------------------------------------------------------------

    def submit(self, body: dict[str, Any]) -> dict[str, Any]:
        result: dict[str, Any] = self.request("POST", "/api/v1/jobs", json_body=body)
        return result

    def jobs(self, params: dict[str, Any]) -> dict[str, Any]:
        result: dict[str, Any] = self.request("GET", "/api/v1/jobs", params=params)
        return result

    def job(self, job_id: str) -> dict[str, Any]:
        result: dict[str, Any] = self.request("GET", f"/api/v1/jobs/{_segment(job_id)}")
        return result

    def stop(self, job_id: str, reason: str) -> dict[str, Any]:
        result: dict[str, Any] = self.request("POST", f"/api/v1/jobs/{_segment(job_id)}/stop",
                                              json_body={"reason": reason})
        return result

    def stop_all(self, reason: str) -> dict[str, Any]:
        result: dict[str, Any] = self.request("POST", "/api/v1/stop", json_body={"reason": reason})
        return result

    def resume(self) -> dict[str, Any]:
        """Let queued jobs start again after a STOP; the cell's state as the service then gives it."""
        result: dict[str, Any] = self.request("POST", "/api/v1/queue/resume")
        return result

    def keep(self, job_id: str, keep: bool) -> dict[str, Any]:
        result: dict[str, Any] = self.request("PUT", f"/api/v1/jobs/{_segment(job_id)}/keep",
                                              json_body={"keep": keep})
        return result

    def retention(self, prune: bool) -> dict[str, Any]:
        result: dict[str, Any] = (self.request("POST", "/api/v1/retention/prune") if prune
                                  else self.request("GET", "/api/v1/retention"))
        return result

    # --- the line's digital I/O ---------------------------------------------------------------------------

    def line_dio(self) -> dict[str, Any]:
        result: dict[str, Any] = self.request("GET", "/api/v1/line/dio")
        return result

    def set_line_input(self, name: str, level: bool) -> dict[str, Any]:
        result: dict[str, Any] = self.request("PUT", f"/api/v1/line/dio/inputs/{_segment(name)}",
                                              json_body={"level": level})
        return result

    # --- the event stream ---------------------------------------------------------------------------------

    def events(self, job_id: str, last_id: int, idle_s: float,
               check: Callable[[], None] | None = None) -> Iterator[ServerEvent]:
        """One connection to the job's event stream, resuming after ``last_id`` (0: from the start): its
        events until the server ends the stream. ``check`` is called at every line received (keep-alives
        too; it may raise to give up). ``ApiError`` if the stream is refused; httpx's transport errors
        (a read idle for ``idle_s`` [s] included) pass through."""
        headers = {"Accept": "text/event-stream", "Cache-Control": "no-cache"}
        if last_id > 0:
            headers["Last-Event-ID"] = str(last_id)
        timeout = httpx.Timeout(REQUEST_TIMEOUT_S, read=idle_s)
        with self._http.stream("GET", f"/api/v1/jobs/{_segment(job_id)}/events", headers=headers,
                               timeout=timeout) as response:
            if response.is_error:
                response.read()
                raise _api_error(response)
            lines = response.iter_lines()
            if check is not None:
                lines = _checked(lines, check)
            yield from parse_events(lines)

    def follow(self, job_id: str, timeout_s: float | None = None) -> Iterator[ServerEvent]:
        """Every event of the job from its start, until its ``result`` event (the last one yielded).

        A broken stream (also a reverse proxy's :data:`GATEWAY_AWAY` answer) is reopened with
        ``Last-Event-ID`` (for up to :data:`RECONNECT_WINDOW_S` without
        an event; a first connection that fails is ``ServerUnreachable`` at once);
        one the server ended without a result (e.g. a restarted service that no longer has the events) is
        completed from the job's record: a ``result`` event with its status is made up once it ended.
        ``WaitTimeout`` once ``timeout_s`` [s] passed, ``ServerUnreachable`` when reconnecting failed."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s

        def check() -> None:
            _check_deadline(deadline, job_id, timeout_s)

        last_id, failures, received, broken_since = 0, 0, False, 0.0
        while True:
            idle = STREAM_IDLE_S
            if deadline is not None:
                idle = min(idle, max(deadline - time.monotonic(), 0.0) + 0.05)
            problem: str | None = None
            try:
                for event in self.events(job_id, last_id, idle, check):
                    failures, received = 0, True
                    if event.id is not None:
                        last_id = event.id
                    yield event
                    if event.event == "result":
                        return
            except httpx.TransportError as exc:
                check()
                if not received:  # never connected: no server there, nothing to resume
                    raise self._unreachable(exc) from None
                problem = _reason(exc)
            except ApiError as exc:
                if exc.status not in GATEWAY_AWAY or not received:
                    raise
                problem = str(exc)
            check()
            if problem is None:
                try:
                    job = self.job(job_id)
                except ServerUnreachable as exc:
                    problem = str(exc)
                except ApiError as exc:
                    if exc.status not in GATEWAY_AWAY:
                        raise
                    problem = str(exc)
                else:
                    if job["status"] in FINISHED:
                        yield from _ended_events(job)
                        return
                    problem = "the server ended the event stream before the job ended"
            failures += 1
            if failures == 1:
                broken_since = time.monotonic()
            elif time.monotonic() - broken_since > RECONNECT_WINDOW_S:
                raise ServerUnreachable(f"lost the event stream of job {job_id}: reconnecting to "
                                        f"{self.server} failed for {RECONNECT_WINDOW_S:g} s ({problem})")
            time.sleep(min(RECONNECT_DELAY_S * failures, MAX_RECONNECT_DELAY_S))


def parse_events(lines: Iterator[str]) -> Iterator[ServerEvent]:
    """Server-Sent Events from a stream's lines (the WHATWG rules this API needs: ``id``, ``event`` and
    ``data`` fields, several ``data`` lines joined by newlines, ``:`` comments skipped, an event dispatched
    at a blank line, one without data dropped). ``data`` is decoded from JSON when it is JSON."""
    event_id: int | None = None
    kind = ""
    data: list[str] = []
    for raw in lines:
        line = raw.rstrip("\r\n")
        if not line:
            if data:
                text = "\n".join(data)
                try:
                    value: Any = json.loads(text)
                except ValueError:
                    value = text
                yield ServerEvent(event_id, kind or "message", value)
            kind, data = "", []
            continue
        if line.startswith(":"):
            continue
        name, _, value_text = line.partition(":")
        value_text = value_text.removeprefix(" ")
        if name == "data":
            data.append(value_text)
        elif name == "event":
            kind = value_text
        elif name == "id" and value_text.isdigit():
            event_id = int(value_text)


def _ended_events(job: dict[str, Any]) -> Iterator[ServerEvent]:
    """The last two events of an ended job, made from its record (they have no id)."""
    yield ServerEvent(None, "state", {"status": job["status"], "termination": job.get("termination")})
    yield ServerEvent(None, "result", {"status": job["status"], "result": job.get("result")})


def _checked(lines: Iterator[str], check: Callable[[], None]) -> Iterator[str]:
    for line in lines:
        check()
        yield line


def _check_deadline(deadline: float | None, job_id: str, timeout_s: float | None) -> None:
    if deadline is not None and time.monotonic() >= deadline:
        raise WaitTimeout(f"job {job_id} did not end within {timeout_s:g} s")


def _segment(job_id: str) -> str:
    """``job_id`` as one path segment (quoted: an id with a '/' cannot reach another route)."""
    return quote(job_id, safe="")


def _reason(exc: httpx.TransportError) -> str:
    """Why a connection failed, in a few words (httpx's message, or its kind when it has none)."""
    text = " ".join(str(exc).split())
    return text or type(exc).__name__
