"""The connection guards of ``cell serve`` (``cell.api.connections``), on a uvicorn server of their own on
loopback with small limits, serving a small ASGI app: a connection that does not deliver its headers, or
its body, in time is closed; at the cap the connection idle longest (else the oldest still sending its
body, else the oldest stream) makes room for a new client, and with every request being worked on a
newcomer may still stop; a failing ``accept()`` is logged once per interval, not once per attempt.

``test_service_process`` floods a real ``cell serve`` under a low descriptor limit."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import time
from typing import Any

import pytest

from cell.api import connections
from cell.api.connections import ACCEPT_FAILURE, ConnectionLimits, RefusalPace, quiet_accept_failures
from cell.service import logs
from tests.service_process import closed_by_server, serving_guarded, until

WAIT_S = 30.0  # a bound on waiting for the server, never a timed check [s]; the sockets' timeout
LONG_S = 600.0  # a deadline no test reaches [s]
WORKING: list[dict[str, Any]] = []
"""The requests ``app`` is working on for ever (``/work``), once it has their whole body."""


async def app(scope: dict[str, Any], receive: Any, send: Any) -> None:
    """``/stream``: a response that never ends (a chunk every 50 ms); ``/body``: answers once the whole
    body is in; ``/work``: once the whole body is in, works for ever (never answers); ``/refused``: a
    401, as to a request without a valid key; anything else, ``/api/v1/stop`` among them: ``ok``."""
    if scope["path"] == "/refused":
        await send({"type": "http.response.start", "status": 401, "headers": [(b"content-length", b"2")]})
        await send({"type": "http.response.body", "body": b"no"})
        return
    if scope["path"] in ("/body", "/work"):
        while (await receive()).get("more_body"):
            pass
    if scope["path"] == "/work":
        WORKING.append(scope)
        await asyncio.sleep(LONG_S)
    length = [] if scope["path"] == "/stream" else [(b"content-length", b"2")]
    await send({"type": "http.response.start", "status": 200, "headers": length})
    if scope["path"] == "/stream":
        while True:
            await send({"type": "http.response.body", "body": b"tick\n", "more_body": True})
            await asyncio.sleep(0.05)
    await send({"type": "http.response.body", "body": b"ok"})


def serving(limits: ConnectionLimits) -> contextlib.AbstractContextManager[int]:
    """A uvicorn server of ``app`` with the guards under ``limits``, in a thread; yields its port."""
    return serving_guarded(app, limits, WAIT_S, lifespan="off", timeout_keep_alive=int(LONG_S))


def connect(port: int, request: bytes = b"") -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=WAIT_S)
    sock.sendall(request)
    return sock


def still_open(sock: socket.socket) -> bool:
    """Whether the connection answers another request."""
    sock.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
    try:
        return until(sock, b"ok").endswith(b"ok")
    except ConnectionResetError:
        return False


def test_a_connection_that_does_not_deliver_its_headers_in_time_is_closed() -> None:
    """Half a request line, a connection that sends nothing, and a kept-alive one that starts its next
    request and stalls are each closed at the header deadline; a request in time is answered."""
    with serving(ConnectionLimits(16, header_timeout_s=0.5)) as port:
        slow = connect(port, b"GET / HTTP/1.1\r\nHost: x\r\n")
        silent = connect(port)
        kept = connect(port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        assert until(kept, b"ok").endswith(b"ok")
        kept.sendall(b"GET / HTTP/1.1\r\n")
        for sock in (slow, silent, kept):
            with sock:
                assert closed_by_server(sock)
        with connect(port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n") as prompt:
            assert until(prompt, b"ok").startswith(b"HTTP/1.1 200 ")


def test_at_the_cap_the_connection_idle_longest_makes_room_for_a_new_client() -> None:
    with serving(ConnectionLimits(4, header_timeout_s=LONG_S)) as port:
        idle = []
        for _ in range(4):  # one request each, in turn: idle[0] has waited longest since
            idle.append(connect(port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n"))
            assert until(idle[-1], b"ok").endswith(b"ok")
        with connect(port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n") as newcomer:
            assert until(newcomer, b"ok").startswith(b"HTTP/1.1 200 ")
            assert closed_by_server(idle[0])
            assert all(still_open(sock) for sock in idle[1:])
        for sock in idle:
            sock.close()


def test_at_the_cap_with_every_request_in_progress_a_stream_is_cut_else_the_newcomer_refused() -> None:
    """With no idle connection, the oldest streaming response is cut for the new client (an event stream
    resumes with Last-Event-ID); with none streaming either, the new client is answered 503."""
    with serving(ConnectionLimits(4, header_timeout_s=LONG_S)) as port:
        streams = []
        for _ in range(4):
            streams.append(connect(port, b"GET /stream HTTP/1.1\r\nHost: x\r\n\r\n"))
            assert b"tick" in until(streams[-1], b"tick")
        with connect(port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n") as newcomer:
            assert until(newcomer, b"ok").startswith(b"HTTP/1.1 200 ")
            assert closed_by_server(streams[0])
        for sock in streams[1:]:
            assert b"tick" in until(sock, b"tick")  # still streaming
            sock.close()
    with serving(ConnectionLimits(4, header_timeout_s=LONG_S)) as port:
        # every one being worked on: the newcomer may only stop, and one at a time (a cap of 4 spares 1)
        WORKING.clear()
        working = [connect(port, b"POST /work HTTP/1.1\r\nHost: x\r\nContent-Length: 2\r\n\r\nab")
                   for _ in range(4)]
        deadline = time.monotonic() + WAIT_S
        while len(WORKING) < 4:
            assert time.monotonic() < deadline, "the requests were never worked on"
            time.sleep(0.01)
        with connect(port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n") as refused:
            answer = until(refused, b"progress")
            assert answer.startswith(b"HTTP/1.1 503 "), answer
            assert closed_by_server(refused)
        stop = b"POST /api/v1/stop HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\n\r\n"
        with connect(port) as stopping, connect(port, stop) as over:
            assert until(over, b"progress").startswith(b"HTTP/1.1 503 ")  # past the spare
            stopping.sendall(stop)
            answer = until(stopping, b"ok")
            assert answer.startswith(b"HTTP/1.1 200 ") and b"connection: close" in answer.lower(), answer
            assert closed_by_server(stopping)  # its place given back
        for sock in working:
            sock.settimeout(0.2)
            assert not closed_by_server(sock)  # none was cut: each is being answered
            sock.close()


def test_a_body_that_does_not_arrive_in_time_is_closed() -> None:
    """300 connections each promising a body and sending a byte of it every 2 s held every place for as
    long as they liked (a STOP was answered 503): a body has a deadline from its headers, as long again
    as its length takes at the slowest rate owed; one that comes in time is answered."""
    with serving(ConnectionLimits(16, header_timeout_s=LONG_S, body_timeout_s=0.5)) as port:
        late = connect(port, b"POST /body HTTP/1.1\r\nHost: x\r\nContent-Length: 10\r\n\r\n01234")
        with connect(port, b"POST /body HTTP/1.1\r\nHost: x\r\nContent-Length: 10\r\n\r\n01234") as prompt:
            prompt.sendall(b"56789")
            assert until(prompt, b"ok").startswith(b"HTTP/1.1 200 ")
        with late:
            assert closed_by_server(late)
    limits = ConnectionLimits(16, body_timeout_s=0.5)
    assert limits.body_deadline_s(0) == 0.5
    assert limits.body_deadline_s(50_000_000) == pytest.approx(0.5 + 50_000_000 / connections.MIN_BODY_RATE)


def test_at_the_cap_the_oldest_connection_still_sending_its_body_makes_room_before_a_stream() -> None:
    """With no idle connection, one still sending its body is cut for a newcomer (the oldest), before any
    event stream: a slow body (or a hostile one) never holds a place a STOP needs."""
    with serving(ConnectionLimits(4, header_timeout_s=LONG_S, body_timeout_s=LONG_S)) as port:
        stream = connect(port, b"GET /stream HTTP/1.1\r\nHost: x\r\n\r\n")
        assert b"tick" in until(stream, b"tick")
        bodies = []
        for _ in range(3):  # the 100 Continue comes once the app reads the body: its request is in progress
            bodies.append(connect(port, b"POST /body HTTP/1.1\r\nHost: x\r\nContent-Length: 10\r\n"
                                        b"Expect: 100-continue\r\n\r\n"))
            assert until(bodies[-1], b"\r\n\r\n").startswith(b"HTTP/1.1 100 ")
        with connect(port, b"POST /api/v1/stop HTTP/1.1\r\nHost: x\r\n\r\n") as newcomer:
            assert until(newcomer, b"ok").startswith(b"HTTP/1.1 200 ")
            assert closed_by_server(bodies[0])
        assert b"tick" in until(stream, b"tick")  # still streaming
        for sock in bodies[1:]:
            sock.sendall(b"0123456789")
            assert until(sock, b"ok").startswith(b"HTTP/1.1 200 ")
            sock.close()
        stream.close()


def test_a_failing_accept_is_logged_once_per_interval_with_its_count(
        caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    """asyncio reported every failed ``accept()`` with a traceback (112 474 in 25 s, 57 MB of log); it is
    one line, then one line with the count at the end of the interval. Other reports go on as before."""
    monkeypatch.setattr(logs, "LOG_INTERVAL_S", 0.05)
    loop = asyncio.new_event_loop()
    try:
        quiet_accept_failures(loop)
        with caplog.at_level(logging.INFO):
            for _ in range(1000):
                loop.call_exception_handler({"message": ACCEPT_FAILURE,
                                             "exception": OSError(24, "Too many open files")})
            assert [r.getMessage() for r in caplog.records if r.name == "cell.service"] == [
                "accept() failed 1 times: out of file descriptors or memory ([Errno 24] Too many open "
                "files); the service accepts again a second later"]
            loop.run_until_complete(asyncio.sleep(0.5))  # past the interval's end
            lines = [r.getMessage() for r in caplog.records if r.name == "cell.service"]
            assert len(lines) == 2 and lines[1].startswith("accept() failed 999 times")
            assert not any(r.exc_info for r in caplog.records)
            loop.call_exception_handler({"message": "something else"})
            assert any(r.name == "asyncio" and r.getMessage() == "something else" for r in caplog.records)
    finally:
        loop.close()


def test_refusals_go_out_at_once_up_to_the_burst_then_at_the_rate_and_none_waits_past_the_bound() -> None:
    """``RefusalPace`` on a clock of its own (no time passes unless the test says so): a burst of 4 at once,
    then one every 0.1 s; an answer that would wait past 0.35 s is not counted, so that later ones do not
    wait for it; as time passes the burst comes back."""
    pace = RefusalPace(rate=10.0, burst=4, max_wait_s=0.35)
    waits = [pace.wait_s(100.0) for _ in range(7)]
    assert waits == pytest.approx([0.0, 0.0, 0.0, 0.0, 0.1, 0.2, 0.3])
    assert pace.wait_s(100.0) is None
    assert pace.wait_s(100.1) == pytest.approx(0.3)  # the refused one took no place
    assert pace.wait_s(200.0) == 0.0


def test_refusals_past_the_pace_s_bound_are_closed_without_an_error_or_a_500_logged(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """A refusal that would wait past the bound is closed unanswered; uvicorn had logged "ASGI callable
    returned without starting response" and an access line of a 500 for each, a log flood of its own."""
    monkeypatch.setattr(connections, "RefusalPace", lambda: RefusalPace(rate=1.0, burst=2, max_wait_s=0.5))
    caplog.set_level(logging.INFO)
    with serving(ConnectionLimits(16)) as port:
        answers = []
        for _ in range(6):
            with connect(port, b"GET /refused HTTP/1.1\r\nHost: x\r\n\r\n") as sock:
                try:
                    answers.append(until(sock, b"no").split(b"\r\n")[0])
                except ConnectionResetError:
                    answers.append(b"")
    assert answers.count(b"HTTP/1.1 401 Unauthorized") >= 2 and b"" in answers, answers
    logged = [record.getMessage() for record in caplog.records]
    assert not any("without starting response" in m or " 500" in m for m in logged), logged


def test_at_the_cap_a_connection_held_for_its_refusal_goes_before_an_idle_one(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A client waiting for its paced 401 is shed first: a legitimate idle keep-alive connection, older,
    had gone in its place."""
    monkeypatch.setattr(connections, "RefusalPace", lambda: RefusalPace(rate=0.1, burst=1, max_wait_s=LONG_S))
    with serving(ConnectionLimits(2, header_timeout_s=LONG_S)) as port:
        legit = connect(port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        assert until(legit, b"ok").endswith(b"ok")
        with connect(port, b"GET /refused HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n") as first:
            assert until(first, b"no").startswith(b"HTTP/1.1 401 ")  # the burst, at once
        held = connect(port, b"GET /refused HTTP/1.1\r\nHost: x\r\n\r\n")  # waits 10 s for its 401
        time.sleep(0.3)  # its request is in: held, not idle (no timed check: the order is what is asserted)
        with connect(port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n") as newcomer:
            assert until(newcomer, b"ok").startswith(b"HTTP/1.1 200 ")
            assert closed_by_server(held)
            assert still_open(legit)
        held.close()
        legit.close()
