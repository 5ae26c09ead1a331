"""Running under systemd: the notify protocol spoken by a real ``cell serve`` to a socket of the test's
own, the JSON log lines journald takes, and the unit file as ``systemd-analyze verify`` reads it."""

from __future__ import annotations

import asyncio
import io
import json
import logging
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from unittest import mock

import pytest
import uvicorn

from cell.api.server import NotifyingServer
from cell.deploy import DATA_DIR, SYSUSERS, UDEV_RULE, UNIT
from cell.service.logs import HumanFormatter, JsonLineFormatter, configure_logging
from cell.service.manager import CellService
from cell.service.notify import Notifier
from cell.service.store import FINISHED_STATUSES
from drivers.errors import CellError
from tests.conftest import UR5E
from tests.service_process import REPO, ServedCell

UNIT_FILE = REPO / "deploy" / UNIT
WATCHDOG_USEC = 400_000  # pings every 0.2 s


class Manager:
    """The service manager's side of ``NOTIFY_SOCKET``: a thread that reads every datagram as it comes,
    as systemd does, and keeps it with the monotonic time it arrived."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(str(path))
        self._sock.settimeout(0.05)
        self.received: list[tuple[float, dict[str, str]]] = []
        self._open = True
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while self._open:
            try:
                data = self._sock.recv(4096).decode()
            except TimeoutError:
                continue
            self.received.append((time.monotonic(), dict(line.split("=", 1) for line in data.splitlines())))

    def between(self, start: float, end: float) -> list[dict[str, str]]:
        """The messages that arrived between the monotonic times ``start`` and ``end``."""
        return [m for t, m in list(self.received) if start <= t < end]

    def close(self) -> None:
        self._open = False
        self._thread.join()
        self._sock.close()


@pytest.fixture
def manager(tmp_path):
    listening = Manager(tmp_path / "notify.sock")
    yield listening
    listening.close()


def test_serve_reports_ready_watchdog_and_stopping_and_logs_json_lines_with_the_job(tmp_path, manager):
    cell = ServedCell(UR5E, tmp_path / "data", env={"NOTIFY_SOCKET": str(manager.path),
                                                    "WATCHDOG_USEC": str(WATCHDOG_USEC)})
    try:
        answered = time.monotonic()
        # READY before the first answer: it is sent as soon as the API listens, before any request runs
        # (the 50 ms are the reading thread's, not the service's)
        time.sleep(0.05)
        first = manager.between(0.0, answered + 0.05)
        assert first and first[0]["READY"] == "1" and "serving on 127.0.0.1" in first[0]["STATUS"]
        time.sleep(1.0)
        pings = manager.between(answered, answered + 1.0)
        assert sum(m.get("WATCHDOG") == "1" for m in pings) >= 3
        with cell.client() as client:
            job = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 1.0}).json()
        cell.wait_job(job["id"], tuple(FINISHED_STATUSES))
        stopping = time.monotonic()
        # uvicorn re-raises the SIGTERM it handled once shut down; systemd counts that as a clean stop
        assert cell.stop() in (0, -signal.SIGTERM)
        time.sleep(0.2)
        assert any(m.get("STOPPING") == "1" for m in manager.between(stopping, time.monotonic()))
        log = cell.log()
    finally:
        cell.close()
    lines = [json.loads(line) for line in log.splitlines() if line.startswith("{")]
    assert lines, log
    assert all({"ts", "level", "logger", "msg"} <= line.keys() for line in lines)
    mine = [line["msg"] for line in lines if line.get("job_id") == job["id"]]
    assert any(m.startswith("job queued") for m in mine) and any(m.startswith("job started") for m in mine)
    assert any(m.startswith("job ended") for m in mine)
    assert any(line["logger"] == "uvicorn.access" for line in lines)  # uvicorn's lines are JSON too
    assert cell.keys["operator"] not in log


def test_the_watchdog_pings_stop_once_the_cell_service_can_run_no_job(manager):
    """A cell service whose job dispatcher ended on an error (``CellService.broken``) would queue jobs for
    ever: the pings stop, with the reason in STATUS, so that systemd restarts it."""
    service = mock.Mock(spec=CellService, broken=None)  # a cell service to the server, and no more
    app = SimpleNamespace(state=SimpleNamespace(service=service))
    notifier = Notifier({"NOTIFY_SOCKET": str(manager.path), "WATCHDOG_USEC": str(WATCHDOG_USEC)})
    server = NotifyingServer(uvicorn.Config(app), notifier)  # type: ignore[arg-type]

    async def ping_until_broken() -> None:
        pings = asyncio.create_task(server._ping(0.01))
        await asyncio.sleep(0.1)
        assert not pings.done()
        service.broken = "the job dispatcher stopped on an error"
        await asyncio.wait_for(pings, 30.0)

    asyncio.run(ping_until_broken())
    deadline = time.monotonic() + 30.0
    while not any("STATUS" in m for m in manager.between(0.0, time.monotonic())):
        assert time.monotonic() < deadline
        time.sleep(0.01)
    received = manager.between(0.0, time.monotonic())
    assert received[0] == {"WATCHDOG": "1"}
    assert received[-1] == {"STATUS": "not pinging the watchdog: the job dispatcher stopped on an error"}


def test_a_manager_that_reads_nothing_never_holds_a_notification(tmp_path):
    """Linux queues 10 datagrams for a reader that has fallen behind; the pings come from the API's event
    loop, so a blocking send there would hold every request. The 50 notifications return at once."""
    path = tmp_path / "notify.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as unread:
        unread.bind(str(path))
        notifier = Notifier({"NOTIFY_SOCKET": str(path)})
        sender = threading.Thread(target=lambda: [notifier.notify(WATCHDOG="1") for _ in range(50)],
                                  daemon=True)
        sender.start()
        sender.join(timeout=5.0)
        assert not sender.is_alive()
        assert unread.recv(4096) == b"WATCHDOG=1"


def test_notifier_addresses_watchdog_ownership_and_bad_values(tmp_path):
    name = f"cell-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)  # the abstract namespace, as systemd may pass it
    with sock:
        Notifier({"NOTIFY_SOCKET": "@" + name}).notify(READY="1", STATUS="up")
        sock.settimeout(1.0)
        assert sock.recv(4096) == b"READY=1\nSTATUS=up"
    assert Notifier({"NOTIFY_SOCKET": "@x", "WATCHDOG_USEC": "4000000"}).ping_interval_s == 2.0
    # the manager watches another process (a worker inherits the variables): not this one's watchdog
    other = Notifier({"NOTIFY_SOCKET": "@x", "WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "1"})
    assert other.ping_interval_s is None
    assert Notifier({}).ping_interval_s is None and not Notifier({}).enabled
    Notifier({}).notify(READY="1")  # not under systemd: nothing to tell, nothing raised
    with pytest.raises(CellError, match="WATCHDOG_USEC"):
        Notifier({"NOTIFY_SOCKET": "@x", "WATCHDOG_USEC": "soon"})


def _record(**extra: object) -> logging.LogRecord:
    record = logging.LogRecord("cell.service", logging.WARNING, __file__, 1, "job ended %s", ("failed",),
                               None)
    record.__dict__.update(extra)
    return record


def test_json_lines_carry_the_record_fields_and_the_journal_priority():
    line = json.loads(JsonLineFormatter().format(_record(job_id="ab12", status="failed")))
    assert line["msg"] == "job ended failed" and line["level"] == "warning" and line["job_id"] == "ab12"
    assert line["status"] == "failed" and line["ts"].endswith("+00:00")
    assert JsonLineFormatter(priority_prefix=True).format(_record()).startswith("<4>{")
    try:
        raise ValueError("boom")
    except ValueError:
        failed = logging.LogRecord("x", logging.ERROR, __file__, 1, "oops", None, sys.exc_info())
    assert "ValueError: boom" in json.loads(JsonLineFormatter().format(failed))["exc"]
    assert HumanFormatter().format(_record(job_id="ab12")).endswith("job ended failed [job ab12]")


def test_the_log_is_human_on_a_terminal_and_json_elsewhere():
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    controller, terminal = os.openpty()
    try:
        with os.fdopen(terminal, "w") as tty:
            configure_logging(tty)
            assert isinstance(root.handlers[0].formatter, HumanFormatter)
        configure_logging(io.StringIO())
        assert isinstance(root.handlers[0].formatter, JsonLineFormatter)
    finally:
        os.close(controller)
        root.handlers, _ = saved
        root.setLevel(saved[1])


def test_the_log_keeps_a_librarys_warnings_and_leaves_out_its_workings():
    """asyncua logs a line per node of the address space it loads as the OPC UA server starts: about a
    thousand at INFO before the certificate's fingerprint."""
    root, quiet = logging.getLogger(), logging.getLogger("asyncua")
    saved = root.handlers[:], root.level, quiet.level
    out = io.StringIO()
    try:
        configure_logging(out)
        logging.getLogger("asyncua.server.address_space").info("add_node: while adding node ...")
        logging.getLogger("asyncua.server.server").warning("endpoint not secure")
        logging.getLogger("cell.line").info("OPC UA: server certificate ...")
    finally:
        root.handlers, root.level = saved[0], saved[1]
        quiet.setLevel(saved[2])
    lines = [json.loads(line)["msg"] for line in out.getvalue().splitlines()]
    assert lines == ["endpoint not secure", "OPC UA: server certificate ..."]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed")
def test_the_unit_file_verifies(tmp_path):
    # verify wants ExecStart's program to exist: point it at this venv's cell instead of /opt/cell's
    cell = Path(sys.executable).parent / "cell"
    unit = tmp_path / "cell.service"
    unit.write_text(UNIT_FILE.read_text().replace("/opt/cell/venv/bin/cell", str(cell)))
    out = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stderr == "", out.stderr


def test_the_unit_the_users_and_the_udev_rule_agree():
    unit = dict(line.split("=", 1) for line in UNIT_FILE.read_text().splitlines() if "=" in line
                and not line.startswith("#"))
    assert unit["Type"] == "notify" and int(unit["WatchdogSec"]) > 0 and unit["NotifyAccess"] == "main"
    assert f"--data-dir {DATA_DIR}" in unit["ExecStart"] and unit["StateDirectory"] == "cell"
    assert "--config /etc/cell/" in unit["ExecStart"] and unit["ConfigurationDirectory"] == "cell"
    group = unit["SupplementaryGroups"]
    sysusers = (REPO / "deploy" / SYSUSERS).read_text()
    assert f"m {unit['User']} {group}" in sysusers
    rules = [line for line in (REPO / "deploy" / UDEV_RULE).read_text().splitlines()
             if line.startswith("SUBSYSTEM")]
    assert rules and all(f'GROUP="{group}"' in line and 'SYMLINK+="vl53l8cx"' in line for line in rules)
    # the rule matches exactly the USB ids the firmware's README says the boards report
    matched = {re.search(r'idVendor}=="(\w+)", ATTRS{idProduct}=="(\w+)"', line).groups() for line in rules}
    readme = (REPO / "deploy" / "firmware" / "README.md").read_text()
    stated = set(re.findall(r"\*\*(\w{4}):(\w{4})\*\*", readme))
    assert matched == stated and stated


def test_a_service_that_fails_at_every_start_is_not_restarted_for_ever():
    """Restart=on-failure with RestartSec=5 restarted a broken cell file every 5 s, for ever: the start
    limit must be reachable by a service that fails at once, each try RestartSec apart."""
    text = UNIT_FILE.read_text()
    unit_section = text[text.index("[Unit]"):text.index("[Service]")]
    limits = dict(line.split("=", 1) for line in unit_section.splitlines() if "=" in line
                  and not line.startswith("#"))
    service = dict(line.split("=", 1) for line in text.splitlines()
                   if "=" in line and not line.startswith("#"))
    burst, interval = int(limits["StartLimitBurst"]), int(limits["StartLimitIntervalSec"])
    assert service["Restart"] == "on-failure" and burst >= 3
    assert burst * int(service["RestartSec"]) < interval

