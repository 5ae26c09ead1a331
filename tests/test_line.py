"""The packing line's PackML state machine through REST (in process; each scan in a real worker), the
digital-I/O handshake against the RTDE controller peer, and the pieces: the state table, the part id,
the result a line reads, the debouncer."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from asyncua import Client, ua
from fastapi.testclient import TestClient
from pydantic import ValidationError

from cell.api.app import create_app
from cell.api.schemas import LineCommandIn
from cell.config.models import CellConfig
from cell.line.config import DigitalIOConfig
from cell.line.controller import LineSnapshot
from cell.line.dio import Debouncer, output_levels
from cell.line.packml import ACCEPTS, Command, State, StopReason, UnitMode, refusal
from cell.line.result import check_part_id, cycle_result, feeder_part
from cell.service.keys import create_key
from cell.service.startup import ServiceSettings
from cell.service.store import FINISHED_STATUSES, open_data_store, sqlite_url
from drivers.arm.config import LINE_INPUTS, LINE_NEEDS, LINE_OUTPUTS, UR5eArmConfig
from drivers.errors import ServiceError
from tests.rtde_peer import ControllerPeer
from tests.service_process import free_port

from .conftest import CONFIG_DIR, REPO, wait_started

TOF = CONFIG_DIR / "sim-ur5e-tof.yaml"
DRY_RUN = CONFIG_DIR / "dryrun-ur5e-peer.yaml"
# A line scan's time budget here [s]: the line needs a scan's result (a box, a container), not a full
# scan's accuracy, which the planners' own tests judge; but a box whose ends no view saw inside its frame
# has no upper bound and no container (LR-NBV sees the 30 cm box's ends after 15-25 s).
SCAN_S = 25.0
# How long a test waits for the line at most [s]: a bound on waiting (a scan's worker started on a loaded
# machine), never a timed check. A PLC's level is held until the handshake counted it (``drive``), not for
# a guessed time: a 0.2 s, then a 0.5 s pulse was missed by a digital I/O thread starved under load.
WAIT_S = 120.0
ROLES = ("viewer", "operator", "line", "admin")


class Line:
    """A served cell with a line, and a key of each role."""

    def __init__(self, client: TestClient, keys: dict[str, str]) -> None:
        self.client, self.keys = client, keys

    def auth(self, role: str) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.keys[role]}"}

    def state(self) -> dict[str, Any]:
        return self.client.get("/api/v1/line", headers=self.auth("viewer")).json()

    def command(self, command: str, part_id: str | None = None, role: str = "line") -> Any:
        body = {"command": command} | ({"part_id": part_id} if part_id is not None else {})
        return self.client.post("/api/v1/line/command", json=body, headers=self.auth(role))

    def wait(self, states: set[str], timeout_s: float = WAIT_S) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while (now := self.state())["state_name"] not in states:
            assert time.monotonic() < deadline, f"the line stayed {now['state_name']}: {now}"
            time.sleep(0.05)
        return now

    def job(self, job_id: str) -> dict[str, Any]:
        return self.client.get(f"/api/v1/jobs/{job_id}", headers=self.auth("viewer")).json()

    def dio(self) -> dict[str, Any]:
        """The digital-I/O handshake's signals (``GET /api/v1/line/dio``)."""
        answer: dict[str, Any] = self.client.get("/api/v1/line/dio", headers=self.auth("viewer")).json()
        return answer

    def counted(self, name: str, level: bool) -> dict[str, Any]:
        """Wait until the handshake counts input ``name`` at ``level`` (past its debounce filter)."""
        deadline = time.monotonic() + WAIT_S
        while True:
            dio = self.dio()
            if {s["name"]: s["level"] for s in dio["inputs"]}[name] is level:
                return dio
            assert time.monotonic() < deadline, f"the handshake never counted {name} {level}: {dio}"
            time.sleep(0.02)

    def message(self, start: str) -> str:
        """Wait until the line's last command message starts with ``start``."""
        deadline = time.monotonic() + WAIT_S
        while not (message := self.state()["message"]).startswith(start):
            assert time.monotonic() < deadline, message
            time.sleep(0.05)
        return message


def _cell_file(tmp_path: Path, base: Path, line: dict[str, Any], **changes: Any) -> Path:
    data = yaml.safe_load(base.read_text())
    data["line"] = line
    data.update(changes)
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@contextlib.contextmanager
def served_line(tmp_path: Path, config: Path) -> Iterator[Line]:
    data = tmp_path / "data"
    store = open_data_store(data, sqlite_url(data))
    keys = {role: create_key(store, role, role)[1] for role in ROLES}
    store.close()
    with TestClient(create_app(ServiceSettings(config_file=config, data_dir=data))) as client:
        yield Line(client, keys)


@pytest.fixture
def line(tmp_path: Path) -> Iterator[Line]:
    config = _cell_file(tmp_path, TOF, {"initial_mode": "production", "max_time_s": SCAN_S})
    with served_line(tmp_path, config) as served:
        yield served


# ---------------------------------------------------------------------- the pieces


def test_the_state_table_is_packmls():
    assert refusal(State.IDLE, Command.START) is None
    assert refusal(State.EXECUTE, Command.START) == ("Start is not valid in Execute (valid in: Idle)")
    assert ACCEPTS[Command.RESET] == {State.STOPPED, State.COMPLETE}
    assert ACCEPTS[Command.CLEAR] == {State.ABORTED}
    # Stop from every state outside the Stopped and Aborted branches; Abort from all but Aborting/Aborted
    assert State.CLEARING not in ACCEPTS[Command.STOP] and State.COMPLETE in ACCEPTS[Command.STOP]
    assert set(State) - ACCEPTS[Command.ABORT] == {State.ABORTING, State.ABORTED}
    assert [int(s) for s in (State.CLEARING, State.EXECUTE, State.COMPLETE)] == [1, 6, 17]
    assert [int(c) for c in (Command.RESET, Command.START, Command.CLEAR)] == [1, 2, 9]


def test_part_ids():
    assert feeder_part("bunny") == ("bunny", None)
    assert feeder_part("horizontal_box@0.01,-0.02,20") == ("horizontal_box", (0.01, -0.02, 20.0))
    for bad in ("cube@1,2", "cube@a,b,c", "cube@nan,0,0", "cube@abc", "cube@0.01,0"):
        with pytest.raises(ServiceError, match="placement") as err:
            feeder_part(bad)
        assert err.value.field == "part_id"
    for bad in ("cube @0,0,0", "@0,0,0", " cube", "big box"):  # no object's name holds a space
        with pytest.raises(ServiceError, match=r"object name.* one word") as err:
            feeder_part(bad)
        assert err.value.field == "part_id"
    assert check_part_id("x" * 64) == "x" * 64
    for bad in ("würfel部品", "", "x" * 65, "tab\there"):
        with pytest.raises(ServiceError, match="1 to 64 printable ASCII"):
            check_part_id(bad)
        # one rule for every way in: REST's command, the digital I/O's part id, OPC UA (check_part_id)
        with pytest.raises(ValidationError):
            LineCommandIn(command="start", part_id=bad)
        with pytest.raises(ValidationError):
            DigitalIOConfig(part_id=bad)


def test_the_result_a_line_reads():
    packing = {"dims_m": [0.10, 0.20, 0.05], "container": {
        "name": "medium", "inner_dims_m": [0.25, 0.20, 0.15], "rotated": True, "reason": "smallest"}}
    result = cycle_result("j", "p", "completed", "done", {"packing": packing})
    # length is the longer side; the clearance is the smallest gap: (0.20 - 0.10) / 2 across
    assert (result.length_m, result.width_m, result.height_m) == (0.20, 0.10, 0.05)
    assert result.fits and result.container == "medium" and result.clearance_m == pytest.approx(0.025)
    assert (result.upper_length_m, result.upper_width_m, result.upper_height_m) == (0.20, 0.10, 0.05)
    # with an upper bound, the clearance is the upper bound's: (0.20 - 0.14) / 2 across
    upper = {**packing, "dims_upper_m": [0.14, 0.22, 0.08]}
    bounded = cycle_result("j", "p", "completed", "done", {"packing": upper})
    assert (bounded.length_m, bounded.upper_length_m, bounded.upper_width_m) == (0.20, 0.22, 0.14)
    assert bounded.clearance_m == pytest.approx(0.015)
    no_bound = {**packing, "dims_upper_m": [None, None, 0.06], "container": {"name": None, "reason": "none"}}
    unbounded = cycle_result("j", "p", "completed", "done", {"packing": no_bound})
    assert not unbounded.fits and unbounded.upper_length_m == 0.0 and unbounded.length_m == 0.20
    none = {"dims_m": [0.6, 0.5, 0.4], "container": {"name": None, "reason": "none fits: no container"}}
    defective = cycle_result("j", "p", "completed", "done", {"packing": none})
    assert not defective.fits and defective.container == "" and defective.length_m == 0.6
    assert defective.message == "none fits: no container"
    # the scan's time on the cell and whether its planner ended it, or its time budget
    budget = {"packing": packing, "sim_time_s": 20.000004, "limit_reached": True}
    assert cycle_result("j", "p", "completed", "time budget of 20 s used up", budget).scan_time_s == 20.000004
    assert not cycle_result("j", "p", "completed", "time budget of 20 s used up", budget).converged
    own = cycle_result("j", "p", "completed", "raster complete", budget | {"limit_reached": False})
    assert own.converged and own.fits and own.scan_time_s == 20.000004
    assert not result.converged and result.scan_time_s == 0.0  # a result.json that does not say
    # nothing on the table: a no-part result, whatever the packing section holds
    empty = cycle_result("j", "p", "no_object", "no object found: ...",
                         {"packing": packing, "sim_time_s": 3.5, "limit_reached": False})
    assert (empty.status, empty.fits, empty.length_m, empty.container) == ("no_object", False, 0.0, "")
    assert (empty.scan_time_s, empty.converged) == (3.5, False)
    assert empty.message == "no object found: ..."


def test_the_debouncer_ignores_bounces_shorter_than_its_hold():
    trigger = Debouncer(False, hold_s=0.02)
    assert trigger.update(True, 0.000) is None
    assert trigger.update(False, 0.010) is None  # a bounce: back before 20 ms
    assert trigger.update(True, 0.015) is None
    assert trigger.update(True, 0.030) is None
    assert trigger.update(True, 0.036) is True and trigger.level
    assert trigger.update(True, 0.100) is None


# ---------------------------------------------------------------------- through REST


def test_whole_cycles_with_results_and_counters(line: Line):
    assert line.state()["state_name"] == "Stopped"
    refused = line.command("start", "cube")
    assert refused.status_code == 409 and "valid in: Idle" in refused.json()["detail"]
    # a command is a name or a number, not a boolean (true was taken for 1, Reset)
    assert line.client.post("/api/v1/line/command", json={"command": True}, headers=line.auth("line")
                            ).status_code == 422
    assert line.command("reset").json()["line"]["state_name"] in {"Resetting", "Idle"}
    line.wait({"Idle"})
    parts = ["horizontal_box@0.01,-0.02,20", "unicorn", "none", "cube@-0.02,0.01,45"]
    for n, part in enumerate(parts, start=1):
        assert line.command("start", part).status_code == 200
        done = line.wait({"Complete"})
        result = done["result"]
        assert result["part_id"] == part and done["processed"] == n
        # Complete shows the job that produced its result (none for a part rejected before a scan)
        assert done["job_id"] == (result["job_id"] or None), done
        if part == "unicorn":  # the feeder has no such part: defective, not a fault
            assert result["status"] == "rejected" and not result["fits"]
            assert "unknown object" in result["message"]
        elif part == "none":  # the feeder put nothing on the table: a no-part result, not a fault
            assert line.job(result["job_id"])["status"] == "no_object"
            assert result["status"] == "no_object" and not result["fits"] and result["length_m"] == 0.0
            assert result["message"].startswith("no object found: ")
        else:
            job = line.job(result["job_id"])
            assert job["status"] == "completed" and job["part_id"] == part
            scanned = job["result"]
            assert result["scan_time_s"] == scanned["sim_time_s"] > 0
            # LR-NBV uses up its SCAN_S here: a part that fits, from a scan its time budget ended
            assert scanned["termination"] == f"time budget of {SCAN_S:g} s used up"
            assert scanned["limit_reached"] and not result["converged"]
            assert result["fits"] and result["container"] and result["clearance_m"] > 0
            assert result["length_m"] >= result["width_m"] > 0 and result["height_m"] > 0
        assert line.command("reset").status_code == 200
        assert line.wait({"Idle"})["job_id"] is None  # Reset ends the cycle
    assert line.state()["defective"] == 2
    history = line.client.get("/api/v1/line/history?limit=1000", headers=line.auth("viewer")).json()
    walk = [(h["from_name"], h["to_name"]) for h in reversed(history)]
    assert walk[:3] == [("Stopped", "Stopped"), ("Stopped", "Resetting"), ("Resetting", "Idle")]
    assert walk.count(("Completing", "Complete")) == 4
    assert line.client.get("/api/v1/line/history", headers={}).status_code == 401
    # a row id past the store's 64-bit integers is refused, not an overflow in the store (a 500)
    assert line.client.get(f"/api/v1/line/history?before_id={2**63}", headers=line.auth("viewer")
                           ).status_code == 422


def test_a_malformed_part_id_is_refused_when_it_is_given_not_scanned_as_a_defective_part(line: Line):
    line.command("reset")
    line.wait({"Idle"})
    for bad in ("cube@abc", "cube@0.01,0", "cube @0,0,0"):
        refused = line.command("start", bad)
        assert refused.status_code == 422 and f"part id {bad!r}" in refused.text, refused.text
        state = line.state()
        assert (state["state_name"], state["processed"], state["defective"]) == ("Idle", 0, 0)
    # a dry-run cell's line.dio.part_id, the feeder's part at every trigger, is checked when it is loaded
    dry_run = yaml.safe_load(DRY_RUN.read_text()) | {"line": {"dio": {"part_id": "cube@0.01,0"}}}
    why = "line.dio.part_id: part id 'cube@0.01,0': the placement"
    with pytest.raises(ValidationError, match=re.escape(why)):
        CellConfig.model_validate(dry_run)
    # the catalogue's check stays at Start: an unknown object is a defective part
    assert line.command("start", "unicorn@0,0,0").status_code == 200
    assert line.wait({"Complete"})["defective"] == 1


def test_a_part_placed_where_no_search_view_sees_it_is_rejected_at_start_with_the_reason(tmp_path):
    """The Franka cell's vs-local looks from 2 views: a part at 0.5,0,0 was scanned, and its job failed with
    0 captures (a fault); it is a defective part saying why, and no scan runs."""
    config = _cell_file(tmp_path, CONFIG_DIR / "sim-franka-rgbd.yaml", {"initial_mode": "production"})
    with served_line(tmp_path, config) as line:
        line.command("reset")
        line.wait({"Idle"})
        assert line.command("start", "bunny@0.5,0,0").status_code == 200
        done = line.wait({"Complete"})
        result = done["result"]
        assert (result["status"], result["job_id"], done["defective"]) == ("rejected", "", 1), done
        message = result["message"]
        assert message.startswith("object_pose: object pose [0.5, 0.0, 0.0] puts bunny (footprint"), message
        assert "where none of the 2 views vs-local looks for an object from sees it" in message, message
        assert line.client.get("/api/v1/jobs", headers=line.auth("viewer")).json()["total"] == 0


def test_stop_during_execute_stops_the_scan_and_a_start_there_is_refused(line: Line):
    line.command("reset")
    line.wait({"Idle"})
    line.command("start", "bunny")
    running = line.wait({"Execute"})
    again = line.command("start", "cube")
    assert again.status_code == 409 and "not valid in Execute" in again.json()["detail"]
    after = line.state()
    assert after["state_name"] == "Execute" and after["job_id"] == running["job_id"]
    assert after["part_id"] == "bunny"  # the refused Start's part id is not taken either
    refused = line.command("stop", role="viewer")
    assert (refused.status_code, refused.json()["detail"]) == (403, "a viewer key may not drive the line")
    assert line.command("stop").status_code == 200
    stopped = line.wait({"Stopped"})
    assert stopped["stop_reason"] == {"id": 1, "message": "Stop from REST (key line)"}
    job = line.job(running["job_id"])
    assert job["status"] == "stopped" and stopped["job_id"] == running["job_id"]
    # the job says who stopped the line, as the stop reason does
    assert job["termination"].startswith("operator stop: the line: Stopping (Stop from REST (key line))")
    assert stopped["processed"] == 0 and stopped["result"] is None  # only a Complete writes a result


def test_a_job_stopped_through_the_api_stops_the_line_it_does_not_abort_it(line: Line):
    line.command("reset")
    line.wait({"Idle"})
    line.command("start", "bunny")
    job_id = line.wait({"Execute"})["job_id"]
    stop = line.client.post(f"/api/v1/jobs/{job_id}/stop", json={"reason": "wrong part"},
                            headers=line.auth("operator"))
    assert stop.status_code == 200
    ended = line.wait({"Stopped", "Aborted"})
    assert ended["state_name"] == "Stopped", ended
    assert ended["stop_reason"]["id"] == 2 and "wrong part" in ended["stop_reason"]["message"]
    history = line.client.get("/api/v1/line/history?limit=2", headers=line.auth("viewer")).json()
    assert [(h["from_name"], h["to_name"]) for h in reversed(history)] == [
        ("Execute", "Stopping"), ("Stopping", "Stopped")]


def _started_scan(line: Line, part: str) -> str:
    """The job id of ``part``'s scan, once its worker has started it (its first progress)."""
    line.command("reset")
    line.wait({"Idle"})
    line.command("start", part)
    job_id: str = line.wait({"Execute"})["job_id"]
    wait_started(line.client, line.auth("viewer"), job_id)
    return job_id


def test_an_operators_stop_of_a_line_scan_whose_worker_is_starting_keeps_the_operators_cause(tmp_path: Path):
    """``POST /api/v1/stop`` while the line's scan's worker still loads: the line's own stop of its scan
    follows the operator's within the same turns of the loop; the job ends with the operator's reason
    (it ended "the line: Stopping", the second stop's, overwriting the first)."""
    config = _cell_file(tmp_path, TOF, {"initial_mode": "production", "max_time_s": SCAN_S},
                        service={"warm_worker": False})
    with served_line(tmp_path, config) as line:
        service = line.client.app.state.service  # type: ignore[attr-defined]
        line.command("reset")
        line.wait({"Idle"})
        line.command("start", "bunny")
        job_id = line.wait({"Execute"})["job_id"]
        deadline = time.monotonic() + 30.0
        while service._running is None or service._running.proc is None:  # handed its job, still loading
            assert time.monotonic() < deadline, "the worker was never handed its job"
            time.sleep(0.005)
        stop = line.client.post("/api/v1/stop", json={"reason": "hands in"}, headers=line.auth("operator"))
        assert stop.status_code == 200, stop.text
        line.wait({"Stopped", "Aborted"})
        job = line.job(job_id)
        while job["status"] not in FINISHED_STATUSES:
            assert time.monotonic() < deadline + 60.0, job
            time.sleep(0.05)
            job = line.job(job_id)
        # the operator's own words first, not the line's stop that names them
        assert job["termination"].startswith("operator stop: hands in (key "), job["termination"]


def test_a_job_stopped_through_the_api_whose_worker_is_killed_is_still_an_operators_stop(tmp_path: Path):
    """A worker that does not confirm the stop is killed: the line still reads an operator's stop (2), and
    its message says so and that the worker was killed (it said "safety stop")."""
    config = _cell_file(tmp_path, TOF, {"initial_mode": "production", "max_time_s": SCAN_S},
                        service={"stop_confirm_timeout_s": 1e-6})  # no worker answers in a microsecond
    with served_line(tmp_path, config) as line:
        job_id = _started_scan(line, "bunny")
        stop = line.client.post(f"/api/v1/jobs/{job_id}/stop", json={"reason": "wrong part"},
                                headers=line.auth("operator"))
        assert stop.status_code == 200 and "was killed" in stop.json()["message"]
        ended = line.wait({"Stopped", "Aborted"})
        assert ended["state_name"] == "Stopped" and ended["stop_reason"]["id"] == 2, ended
        message = ended["stop_reason"]["message"]
        assert message.startswith(f"scan {job_id} stopped: operator stop: wrong part (key operator)"), message
        assert message.endswith("and was killed)"), message


def test_a_hung_scan_is_a_safety_stop_not_an_operators(line: Line):
    """The service's own stop of a worker that stopped answering is a safety stop (4, Aborted), not a stop
    someone asked for (it was 2, Stopped)."""
    job_id = _started_scan(line, "bunny")
    store = line.client.app.state.service.store  # type: ignore[attr-defined]
    pid = store.get_job(job_id).worker_pid
    os.kill(pid, signal.SIGSTOP)
    try:
        ended = line.wait({"Stopped", "Aborted"}, timeout_s=60.0)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)
    assert ended["state_name"] == "Aborted" and ended["stop_reason"]["id"] == 4, ended
    message = ended["stop_reason"]["message"]
    assert message.startswith(f"scan {job_id} stopped: safety stop: ") and "hung" in message, message


def test_hold_stops_the_scan_and_unhold_scans_the_part_again(line: Line):
    line.command("reset")
    line.wait({"Idle"})
    line.command("start", "cube@0.01,0.0,15")
    first = line.wait({"Execute"})["job_id"]
    assert line.command("hold").status_code == 200
    held = line.wait({"Held"})
    assert line.job(first)["status"] == "stopped" and held["job_id"] == first
    assert line.command("start", "bunny").status_code == 409  # Held waits for Unhold (or Stop, Abort)
    assert line.state()["part_id"] == "cube@0.01,0.0,15"
    line.command("unhold")
    again = line.wait({"Execute"})["job_id"]
    assert again != first and line.job(again)["part_id"] == "cube@0.01,0.0,15"
    done = line.wait({"Complete"})
    assert done["result"]["job_id"] == done["job_id"] == again and done["processed"] == 1
    history = line.client.get("/api/v1/line/history?limit=1000", headers=line.auth("viewer")).json()
    walk = [h["to_name"] for h in reversed(history)]
    assert walk[walk.index("Holding"):walk.index("Complete") + 1] == [
        "Holding", "Held", "Unholding", "Execute", "Completing", "Complete"]


def test_an_arm_fault_aborts_and_clear_then_reset_recover(tmp_path: Path):
    config = _cell_file(tmp_path, TOF, {}, sim={"table_size_m": [1.2, 1.2], "table_center_xy_m": [0.4, 0.0],
                                               "faults": [{"at_s": 2.0, "kind": "protective stop"}]})
    with served_line(tmp_path, config) as line:
        line.command("reset")
        line.wait({"Idle"})
        line.command("start", "bunny")
        aborted = line.wait({"Aborted"})
        assert aborted["stop_reason"]["id"] == 5 and "protective stop" in aborted["stop_reason"]["message"]
        refused = line.command("reset")
        assert refused.status_code == 409 and "valid in: Stopped, Complete" in refused.json()["detail"]
        assert line.state()["state_name"] == "Aborted"
        line.command("clear")
        line.wait({"Stopped"})
        cell = line.client.get("/api/v1/cell", headers=line.auth("viewer")).json()
        assert not cell["arm"]["faults"] and cell["line"]["state_name"] == "Stopped"
        line.command("reset")
        line.wait({"Idle"})


def test_the_line_and_operators_never_drive_the_cell_at_once(line: Line):
    op = line.auth("operator")
    refused = line.client.post("/api/v1/jobs", json={"object": "cube"}, headers=op)
    assert refused.status_code == 409 and "Production mode" in refused.json()["detail"]
    manual = line.client.post("/api/v1/line/mode", json={"mode": "manual"}, headers=op)
    assert manual.status_code == 200 and manual.json()["line"]["mode_name"] == "Manual"
    line.command("reset")
    line.wait({"Idle"})
    start = line.command("start", "cube")
    assert start.status_code == 409 and "Manual mode" in start.json()["detail"]
    job = line.client.post("/api/v1/jobs", json={"object": "bunny"}, headers=op).json()
    back = line.client.post("/api/v1/line/mode", json={"mode": 1}, headers=line.auth("line"))
    assert back.status_code == 409 and "operator jobs" in back.json()["detail"]
    line.client.post(f"/api/v1/jobs/{job['id']}/stop", headers=op)
    deadline = time.monotonic() + 30
    while line.client.post("/api/v1/line/mode", json={"mode": "production"},
                           headers=line.auth("line")).status_code != 200:
        assert time.monotonic() < deadline
        time.sleep(0.1)
    assert line.state()["mode_name"] == "Production"
    maintenance = line.client.post("/api/v1/line/mode", json={"mode": 2}, headers=line.auth("line"))
    assert maintenance.status_code == 422 and "not offered" in maintenance.text


def test_an_operator_stop_stops_the_line_and_the_counters_outlive_a_restart(tmp_path: Path):
    config = _cell_file(tmp_path, TOF, {"max_time_s": SCAN_S})
    with served_line(tmp_path, config) as line:
        line.command("reset")
        line.wait({"Idle"})
        line.command("start", "baseball")
        line.wait({"Complete"})
        line.command("reset")
        line.wait({"Idle"})
        line.command("start", "bunny")
        line.wait({"Execute"})
        stop = line.client.post("/api/v1/stop", json={"reason": "hands in the cell"},
                                headers=line.auth("viewer"))
        assert stop.status_code == 200
        stopped = line.wait({"Stopped"})
        assert stopped["stop_reason"]["id"] == 2 and "hands in the cell" in stopped["stop_reason"]["message"]
        # the STOP holds the queue until an operator resumes it: the line's Reset may not release it
        refused = line.command("reset")
        assert refused.status_code == 409 and "POST /api/v1/queue/resume" in refused.json()["detail"]
        cell = line.client.get("/api/v1/cell", headers=line.auth("viewer")).json()
        assert cell["queue"]["held"] and cell["line"]["state_name"] == "Stopped"
        assert line.client.post("/api/v1/queue/resume", headers=line.auth("operator")).status_code == 200
        line.command("reset")
        line.wait({"Idle"})
        assert line.client.get("/api/v1/cell", headers=line.auth("viewer")).json()["queue"]["held"] is None
        manual = line.client.post("/api/v1/line/mode", json={"mode": "manual"}, headers=line.auth("line"))
        assert manual.status_code == 200
        keys = line.keys
    with _reopen(tmp_path, config, keys) as line:
        state = line.state()
        assert state["state_name"] == "Stopped" and state["processed"] == 1
        assert state["result"]["part_id"] == "baseball" and state["stop_reason"]["id"] == 7
        # line.initial_mode (production) is a new line's: a cell left in Manual stays in Manual
        assert state["mode_name"] == "Manual"


def test_a_shutdown_stops_the_line_and_the_restart_says_so_from_its_last_state(tmp_path: Path):
    config = _cell_file(tmp_path, TOF, {})
    with served_line(tmp_path, config) as line:
        line.command("reset")
        line.wait({"Idle"})
        line.command("start", "unicorn")  # no scan: a defective part, Complete at once
        assert line.wait({"Complete"})["stop_reason"]["id"] == 0
        keys = line.keys
    with _reopen(tmp_path, config, keys) as line:
        state = line.state()
        assert state["state_name"] == "Stopped" and state["processed"] == 1
        assert state["stop_reason"] == {"id": 7, "message": "the service started (the line was Stopped)"}
        history = line.client.get("/api/v1/line/history?limit=4", headers=line.auth("viewer")).json()
        assert [(h["from_name"], h["to_name"], h["cause"]) for h in history] == [
            ("Stopped", "Stopped", "the service started"),
            ("Stopping", "Stopped", "no scan was running"),
            ("Complete", "Stopping", "the service is shutting down"),  # the PLC saw the shutdown
            ("Completing", "Complete", "the result is written (defective)")]


@contextlib.contextmanager
def _reopen(tmp_path: Path, config: Path, keys: dict[str, str]) -> Iterator[Line]:
    """The same data dir served again, with the keys made the first time."""
    with TestClient(create_app(ServiceSettings(config_file=config, data_dir=tmp_path / "data"))) as client:
        yield Line(client, keys)


def test_a_cell_without_a_line_says_so(tmp_path: Path):
    data = tmp_path / "data"
    store = open_data_store(data, sqlite_url(data))
    key = create_key(store, "line", "l")[1]
    store.close()
    with TestClient(create_app(ServiceSettings(config_file=TOF, data_dir=data))) as client:
        res = client.get("/api/v1/line", headers={"Authorization": f"Bearer {key}"})
        assert res.status_code == 404 and "no packing line" in res.json()["detail"]
        assert client.get("/api/v1/cell", headers={"Authorization": f"Bearer {key}"}).json()["line"] is None


# ---------------------------------------------------------------------- the robot's digital I/O


DioLine = tuple[Line, ControllerPeer, dict[str, Any]]


@contextlib.contextmanager
def dio_line(tmp_path: Path, caplog: pytest.LogCaptureFixture, dio: dict[str, Any],
             max_time_s: float = SCAN_S, opcua: dict[str, Any] | None = None,
             **arm_changes: Any) -> Iterator[DioLine]:
    """A dry-run cell with ``line.dio`` (and ``line.opcua`` if given) against the RTDE controller peer,
    its digital I/O link connected (the trigger's level read then is its baseline): the served line, the
    peer and the cell file's arm section (``arm_changes`` wire more I/O)."""
    base = yaml.safe_load(DRY_RUN.read_text())
    peer = ControllerPeer(q=base["arm"]["home_joints_rad"])
    try:
        arm = base["arm"] | {"host": peer.host} | arm_changes
        line_config = {"dio": dio, "max_time_s": max_time_s} | ({} if opcua is None else {"opcua": opcua})
        config = _cell_file(tmp_path, DRY_RUN, line_config, arm=arm)
        with caplog.at_level(logging.INFO, logger="cell.line"), served_line(tmp_path, config) as line:
            deadline = time.monotonic() + WAIT_S
            while not any("digital I/O connected" in m for m in caplog.messages):
                assert time.monotonic() < deadline, "the digital I/O link never connected"
                time.sleep(0.05)
            yield line, peer, arm
    finally:
        peer.stop()


def drive(dio: DioLine, name: str, level: bool) -> None:
    """The PLC sets input ``name`` to ``level`` and holds it until the handshake counted it."""
    line, peer, arm = dio
    peer.set_digital_input(arm[name], level)
    line.counted(name, level)


def pulse(dio: DioLine, name: str) -> None:
    """A PLC's pulse on input ``name``: high, then low, each held until the handshake counted it."""
    drive(dio, name, True)
    drive(dio, name, False)


def sampled_after(line: Line, controller_s: float) -> dict[str, Any]:
    """Wait until the handshake shows levels counted from a sample the controller took after
    ``controller_s`` [s, its RTDE clock]; what it shows then."""
    deadline = time.monotonic() + WAIT_S
    while (seen := line.dio())["sampled_s"] is None or seen["sampled_s"] < controller_s:
        assert time.monotonic() < deadline, seen
        time.sleep(0.02)
    return seen


def outputs(peer: ControllerPeer, value: int, what: str) -> dict[str, Any]:
    """Wait until the controller's digital outputs are ``value`` (a bit per output)."""
    return peer.wait_for(lambda s: s["digital_out"] == value, timeout_s=WAIT_S, what=what)


def test_the_digital_io_handshake_against_the_rtde_peer(tmp_path: Path, caplog: pytest.LogCaptureFixture):
    debounce_s = 0.3
    with dio_line(tmp_path, caplog, {"part_id": "horizontal_box", "debounce_s": debounce_s}) as dio:
        line, peer, arm = dio
        trigger, busy, done = arm["trigger_input"], 1 << arm["busy_output"], 1 << arm["done_output"]
        line.command("reset")
        line.wait({"Idle"})
        # a 50 ms pulse, on the controller's clock, is a bounce to a 300 ms filter: nothing starts, however
        # late the handshake reads the samples (the filter counts their RTDE timestamps)
        falls_s = peer.pulse_digital_input(trigger, 0.05)
        seen = sampled_after(line, falls_s + debounce_s)
        assert seen["inputs"][0] == {"name": "trigger_input", "pin": trigger, "level": False}, seen
        assert line.state()["state_name"] == "Idle" and peer.state()["digital_out"] == 0
        # the link stalls during a bounce (the controller's packages stop for a second, as a loaded PC's RTDE
        # child can fall behind): the last sample, high, is read again and again, but it is one sample at
        # one controller time, no level held for 300 ms (a filter on the service's clock took it for one)
        falls_s = peer.pulse_digital_input(trigger, 0.1)
        time.sleep(0.05)  # the high samples reach the service
        with peer.frozen():
            time.sleep(1.0)
        seen = sampled_after(line, falls_s + debounce_s)
        assert seen["inputs"][0]["level"] is False, seen
        assert line.state()["state_name"] == "Idle" and peer.state()["digital_out"] == 0
        drive(dio, "trigger_input", True)
        outputs(peer, busy, "busy high in Execute")
        assert line.state()["state_name"] == "Execute"
        outputs(peer, done, "done high in Complete")
        complete = line.state()
        assert complete["state_name"] == "Complete" and complete["result"]["part_id"] == "horizontal_box"
        assert complete["message"] == "Start from digital input DI0 rising"
        drive(dio, "trigger_input", False)  # the trigger falls: Reset
        outputs(peer, 0, "done low after the trigger fell")
        line.wait({"Idle"})
        history = line.client.get("/api/v1/line/history", headers=line.auth("viewer")).json()
        assert [h["to_name"] for h in history].count("Starting") == 1  # the bounces started nothing
        # a real UR5e's inputs are the PLC's wires: REST does not set them
        refused = line.client.put("/api/v1/line/dio/inputs/trigger_input", json={"level": True},
                                  headers=line.auth("line"))
        assert refused.status_code == 409 and "only a sim cell's" in refused.json()["detail"], refused.text


def test_a_pulsed_trigger_acknowledges_each_part_with_the_next_ones_rising_edge(
        tmp_path: Path, caplog: pytest.LogCaptureFixture):
    """The PLC pulses the trigger (shorter than a scan) and waits for done: the pulse's fall during Execute
    does nothing, done stays high in Complete, and the next pulse's rise is Reset, then Start. A held
    trigger still works after it: its fall in Complete is Reset."""
    with dio_line(tmp_path, caplog, {"part_id": "horizontal_box", "debounce_s": 0.05}, max_time_s=3.0) as dio:
        line, peer, arm = dio
        busy, done = 1 << arm["busy_output"], 1 << arm["done_output"]
        line.command("reset")
        line.wait({"Idle"})
        for n in (1, 2, 3):
            pulse(dio, "trigger_input")
            outputs(peer, busy, f"busy high for part {n}")
            outputs(peer, done, f"done high for part {n}")
            complete = line.state()  # done holds after the pulse fell
            assert (complete["state_name"], complete["processed"]) == ("Complete", n), complete
            assert peer.state()["digital_out"] == done
        history = line.client.get("/api/v1/line/history?limit=1000", headers=line.auth("viewer")).json()
        causes = [h["cause"] for h in reversed(history) if h["to_name"] in ("Resetting", "Starting")]
        rise = "from digital input DI0 rising"
        assert causes == ["Reset from REST (key line)"] + [f"Start {rise}", f"Reset {rise}"] * 2 + [
            f"Start {rise}"], causes
        # a held trigger: its rise acknowledges part 3 and starts part 4, its fall after done is Reset
        drive(dio, "trigger_input", True)
        outputs(peer, busy, "busy high for part 4")
        outputs(peer, done, "done high for part 4")
        drive(dio, "trigger_input", False)
        outputs(peer, 0, "done low after the held trigger fell")
        assert line.wait({"Idle"})["processed"] == 4


def test_a_trigger_scans_the_part_id_the_plc_set_over_opc_ua(tmp_path: Path,
                                                             caplog: pytest.LogCaptureFixture):
    """Without line.dio.part_id, a trigger scans the part id the PLC set over OPC UA for this part, and
    part-<n> when none was set since the last Start (the feeder knows none of these: each is a defective
    part at once, no scan)."""
    url = f"opc.tcp://127.0.0.1:{free_port()}/cell"
    with dio_line(tmp_path, caplog, {"debounce_s": 0.05}, opcua={"endpoint": url, "security": "none"}) as dio:
        line = dio[0]

        def part(n: int) -> str:
            """Pulse the trigger; the part id of the n-th part processed."""
            pulse(dio, "trigger_input")
            deadline = time.monotonic() + WAIT_S
            while (state := line.state())["processed"] < n:
                assert time.monotonic() < deadline, state
                time.sleep(0.05)
            return str(state["result"]["part_id"])

        async def set_part_id(part_id: str) -> None:
            client = Client(url, timeout=30)
            client.set_user("line")
            client.set_password(line.keys["line"])
            async with client:
                ns = (await client.get_namespace_array()).index("urn:cell:packml")
                node = client.get_node(ua.NodeId("PackTags.Command.Parameter.PartId", ns))
                await node.write_value(ua.Variant(part_id, ua.VariantType.String))

        line.command("reset")
        line.wait({"Idle"})
        assert part(1) == "part-1"
        asyncio.run(set_part_id("widget-7"))
        assert part(2) == "widget-7"
        assert part(3) == "part-3"  # the PLC set none for this part: widget-7 was the last one's


def test_the_line_pins_are_named_once_and_the_docs_name_no_other():
    """The arm section's pin fields are the code's one list of them (the config's checks, the handshake's
    outputs read it), and the docs and templates that name pins name those."""
    fields = {name for name in UR5eArmConfig.model_fields if name.endswith(("_input", "_output"))}
    assert set(LINE_INPUTS) | set(LINE_OUTPUTS) == fields and set(LINE_NEEDS) <= fields
    executing = LineSnapshot(State.EXECUTE, UnitMode.PRODUCTION, "", "job-1", 0, 0, StopReason.NONE, "", None,
                             "")
    assert output_levels(executing) == {name: name == "busy_output" for name in LINE_OUTPUTS}
    templates = (REPO / "cell" / "templates").glob("*.yaml")
    for doc in (REPO / "README.md", *(REPO / "docs").glob("*.md"), *templates):
        named = set(re.findall(r"\b[a-z_]+_(?:input|output)\b", doc.read_text()))
        assert named <= fields, f"{doc.name} names pins the arm section has not: {named - fields}"
    handshake = (REPO / "docs" / "packml-opcua.md").read_text()
    assert all(f"`{name}`" in handshake for name in (*LINE_INPUTS, *LINE_OUTPUTS))


def test_two_digital_io_signals_of_the_line_may_not_share_a_pin():
    base = yaml.safe_load(DRY_RUN.read_text()) | {"line": {"dio": {}}}
    assert CellConfig.model_validate(base | {"arm": base["arm"] | {"reset_input": 1, "fault_output": 3}})
    for pins, why in (({"reset_input": 0}, "trigger_input and reset_input are the same digital input"),
                      ({"ready_output": 2, "fault_output": 2}, "ready_output and fault_output are the same "
                       "digital output"),
                      ({"fault_output": 1}, "done_output and fault_output are the same digital output")):
        with pytest.raises(ValidationError, match=why):
            CellConfig.model_validate(base | {"arm": base["arm"] | pins})


def test_the_reset_input_and_the_ready_and_fault_outputs(tmp_path: Path, caplog: pytest.LogCaptureFixture):
    """A line wired only to digital I/O: the reset input brings the cell from Stopped (after the start) and
    Aborted (Clear, then Reset) to Idle; ready shows Idle in Production, fault a stop the line did not
    command (an operator's STOP, until Reset) and Held; a reset the state refuses is said and changes
    nothing."""
    pins = {"reset_input": 1, "ready_output": 2, "fault_output": 3}
    dio = {"part_id": "horizontal_box", "debounce_s": 0.05}
    with dio_line(tmp_path, caplog, dio, max_time_s=30.0, **pins) as wired:
        line, peer, arm = wired
        busy, ready, fault = (1 << arm[name] for name in ("busy_output", "ready_output", "fault_output"))
        assert line.state()["state_name"] == "Stopped" and peer.state()["digital_out"] == 0
        pulse(wired, "reset_input")
        outputs(peer, ready, "ready high in Idle")
        assert line.state()["message"] == "Reset from digital input DI1 rising"
        # an operator's STOP: a fault until an operator resumes the queue and the line resets
        line.client.post("/api/v1/stop", json={"reason": "hands in the cell"}, headers=line.auth("viewer"))
        outputs(peer, fault, "fault high after an operator's STOP")
        pulse(wired, "reset_input")
        message = line.message("refused Reset from digital input DI1 rising")
        assert "POST /api/v1/queue/resume" in message, message
        assert line.state()["state_name"] == "Stopped" and peer.state()["digital_out"] == fault
        resumed = line.client.post("/api/v1/queue/resume", headers=line.auth("operator"))
        assert resumed.status_code == 200, resumed.text
        pulse(wired, "reset_input")
        outputs(peer, ready, "ready high, fault low after Reset")
        # the line's own Abort is no fault; the reset input clears it, then resets it
        assert line.command("abort").status_code == 200
        line.wait({"Aborted"})
        outputs(peer, 0, "no fault in Aborted after the line's Abort")
        pulse(wired, "reset_input")
        assert line.wait({"Stopped"})["message"] == "Clear from digital input DI1 rising"
        pulse(wired, "reset_input")
        outputs(peer, ready, "ready high in Idle after Clear and Reset")
        # Held is a fault; a reset in Held is refused
        pulse(wired, "trigger_input")
        outputs(peer, busy, "busy high in Execute")
        assert line.command("hold").status_code == 200
        outputs(peer, fault, "fault high in Held")
        pulse(wired, "reset_input")
        message = line.message("refused Reset from digital input DI1")
        assert "not valid in Held" in message and line.state()["state_name"] == "Held"
        assert line.command("stop").status_code == 200  # the line's own Stop: no fault
        outputs(peer, 0, "every output low in Stopped after the line's Stop")
        # in Manual mode a trigger starts nothing: not ready
        pulse(wired, "reset_input")
        outputs(peer, ready, "ready high in Idle")
        line.client.post("/api/v1/line/mode", json={"mode": "manual"}, headers=line.auth("line"))
        outputs(peer, 0, "ready low in Manual mode")
