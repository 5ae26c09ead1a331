"""``cell jobs``: the command-line client of the service's API, run as a user runs it against a real
``cell serve`` (tests/service_process.py), plus its event-stream parsing and reconnection against a
scripted transport."""

from __future__ import annotations

import json
import os
import re
import subprocess
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from typer.testing import CliRunner, Result

from cell.cli import client as client_module
from cell.cli.client import ApiClient, ServerEvent, ServerUnreachable, parse_events
from cell.cli.jobs import _progress_line, follow_job, packing_lines, time_label
from cell.cli.main import app
from cell.service.store import FINISHED_STATUSES, JOB_STATUSES
from tests.service_process import CELL, REPO, ServedCell, free_port

CONFIG = REPO / "config" / "sim-franka-rgbd.yaml"
JOB_ID = re.compile(r"[0-9a-f]{16}")
UTC_SECONDS = re.compile(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ")
PROGRESS_LINE = re.compile(r"t \d+\.\d s  \d+ captures  (cloud coverage \d+\.\d %  )?"
                           r"H_ROI \(observation-aware\) (\d+\.\d{3} nats|-)")  # the sim cell's form
Completed = tuple[str, subprocess.CompletedProcess[str]]
FINISHED = ("completed", "no_object", "failed", "stopped", "cancelled", "interrupted")


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServedCell]:
    cell = ServedCell(CONFIG, tmp_path_factory.mktemp("jobs-cli"))
    yield cell
    cell.close()


def run_cell(served: ServedCell, *args: str, role: str | None = "operator", server: str | None = None,
             timeout_s: float = 120.0) -> subprocess.CompletedProcess[str]:
    """``cell jobs ARGS`` in a subprocess, with CELL_SERVER and CELL_KEY set as a script would."""
    env = {k: v for k, v in os.environ.items() if k not in ("CELL_SERVER", "CELL_KEY")}
    env["CELL_SERVER"] = server or served.url
    if role is not None:
        env["CELL_KEY"] = served.keys[role]
    return subprocess.run([*CELL, "jobs", *args], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=timeout_s)


def invoke(served: ServedCell, *args: str, role: str = "operator") -> Result:
    """``cell jobs ARGS`` in this process (typer's runner), CELL_SERVER and CELL_KEY in its environment."""
    return CliRunner().invoke(app, ["jobs", *args], env={"CELL_SERVER": served.url,
                                                         "CELL_KEY": served.keys[role]})


def one_error_line(stderr: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: "), stderr
    return lines[0]


def no_key_in(served: ServedCell, *texts: str) -> None:
    for key in served.keys.values():
        assert all(key not in text for text in texts)


def show_json(served: ServedCell, job_id: str) -> dict[str, Any]:
    result = invoke(served, "show", job_id, "--json", role="viewer")
    assert result.exit_code == 0, result.output
    job: dict[str, Any] = json.loads(result.stdout)
    return job


@pytest.fixture(scope="module")
def completed_job(served: ServedCell) -> Completed:
    """A short sim scan run with ``submit --wait``: its id and the finished command."""
    proc = run_cell(served, "submit", "--object", "bunny", "--max-time", "3", "--seed", "2", "--part-id",
                    "P-42", "--wait")
    lines = proc.stdout.strip().splitlines()
    assert lines and JOB_ID.fullmatch(lines[0]), proc.stdout + proc.stderr + served.log()
    return lines[0], proc


def test_submit_prints_the_id_alone_on_the_last_line(served: ServedCell):
    proc = run_cell(served, "submit", "--object", "bunny", "--object-pose", "0.01,-0.02,15", "--seed", "1",
                    "--max-time", "2", "--part-id", "P-7")
    assert proc.returncode == 0, proc.stderr
    last = proc.stdout.splitlines()[-1]
    assert JOB_ID.fullmatch(last), proc.stdout
    no_key_in(served, proc.stdout, proc.stderr)
    with served.client("viewer") as http:
        job = http.get(f"/api/v1/jobs/{last}").json()
    assert (job["object"], job["seed"], job["max_time_s"], job["part_id"]) == ("bunny", 1, 2.0, "P-7")
    assert job["object_pose"] == [0.01, -0.02, 15.0]
    assert job["submitted_by"] == "test-operator"
    served.wait_job(last, FINISHED)  # not to hold the queue for the next tests


def test_submit_wait_follows_the_job_to_completed(completed_job: Completed):
    job_id, proc = completed_job
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert lines[0] == job_id
    assert re.fullmatch(r"completed: time budget of 3 s used up", lines[-1]), proc.stdout
    progress = [line for line in lines if line.startswith("t ")]
    assert progress and all(PROGRESS_LINE.fullmatch(line) for line in progress), proc.stdout
    assert proc.stderr == ""


def test_wait_for_an_ended_job_prints_its_status_alone(served: ServedCell, completed_job: Completed):
    """Not the history its event stream replays (queued, running, its first progress line) as if live."""
    job_id, _ = completed_job
    waited = run_cell(served, "wait", job_id, role="viewer")
    assert waited.returncode == 0, waited.stdout + waited.stderr
    assert waited.stdout == "completed: time budget of 3 s used up\n"
    assert waited.stderr == ""


def test_a_job_logs_into_its_folder_and_leaves_no_empty_worker_log(served: ServedCell,
                                                                   completed_job: Completed):
    """Every job left an empty logs/worker-<id>.log beside the log it writes, jobs/<id>/log.txt."""
    job_id, _ = completed_job
    assert (served.data_dir / "jobs" / job_id / "log.txt").stat().st_size > 0
    assert not (served.data_dir / "logs" / f"worker-{job_id}.log").exists()


def test_show_and_list_find_the_job(served: ServedCell, completed_job: Completed):
    job_id, _ = completed_job
    shown = invoke(served, "show", job_id, role="viewer")
    assert shown.exit_code == 0, shown.output
    fields = dict(re.split(r"\s{2,}", line.strip(), maxsplit=1) for line in shown.stdout.splitlines())
    assert fields["id"] == job_id and fields["status"] == "completed"
    assert fields["object"] == "bunny" and fields["part id"] == "P-42" and fields["seed"] == "2"
    assert fields["termination"] == "time budget of 3 s used up"
    assert fields["result"] == "completed: time budget of 3 s used up"
    assert UTC_SECONDS.fullmatch(fields["created"]) and UTC_SECONDS.fullmatch(fields["finished"])
    record = show_json(served, job_id)
    result = record["result"]
    assert fields["captures"] == str(result["n_captures"]) and result["n_captures"] >= 1
    assert result["mode"] == "sim" and fields["sim time"].startswith(f"{result['sim_time_s']:.1f} s")
    assert fields["path length"] == f"{result['path_length_m']:.2f} m"
    assert fields["cloud coverage (eq. 13)"] == f"{result['metrics']['coverage_pct']:.1f} %"
    assert fields["chamfer"] == f"{result['metrics']['chamfer_mm']:.2f} mm"

    listed = invoke(served, "list", "--status", "completed", "--part-id", "P-42", role="viewer")
    assert listed.exit_code == 0, listed.output
    lines = listed.stdout.strip().splitlines()
    assert lines[0].split() == ["ID", "STATUS", "PLANNER", "OBJECT", "PART", "ID", "CREATED", "(UTC)",
                                "TERMINATION"]
    row = lines[1].split(None, 6)
    assert row[:5] == [job_id, "completed", record["planner"], "bunny", "P-42"]
    assert UTC_SECONDS.fullmatch(row[5]) and row[6] == "time budget of 3 s used up"
    assert lines[-1] == "1 of 1"

    everything = invoke(served, "list", "--status", "completed,stopped", "--json", role="viewer")
    page = json.loads(everything.stdout)
    assert job_id in [j["id"] for j in page["items"]]
    assert {j["status"] for j in page["items"]} <= {"completed", "stopped"}
    assert page["total"] == len(page["items"]) >= 2
    none = invoke(served, "list", "--status", "running", "--planner", "no-such-planner", role="viewer")
    assert none.exit_code == 0 and none.stdout.strip() == "0 of 0"


def test_invalid_input_names_the_field(served: ServedCell):
    proc = run_cell(served, "submit", "--planner", "nope", "--object", "bunny")
    assert proc.returncode == 1 and proc.stdout == ""
    line = one_error_line(proc.stderr)
    assert line.startswith("error: 422 planner: unknown planner 'nope'; registered: "), line
    assert "vs-local" in line

    bad_status = invoke(served, "list", "--status", "finished")
    assert bad_status.exit_code == 1
    assert one_error_line(bad_status.stderr).startswith("error: 422 status: unknown status 'finished'")
    bad_pose = invoke(served, "submit", "--object-pose", "1,2")
    assert bad_pose.exit_code == 1
    assert "--object-pose" in one_error_line(bad_pose.stderr)
    for option, value in (("--object-pose", "0,0,nan"), ("--max-time", "nan"), ("--max-time", "inf")):
        refused = invoke(served, "submit", "--object", "bunny", option, value)  # JSON has no NaN: a traceback
        assert refused.exit_code == 1 and one_error_line(refused.stderr).startswith(f"error: {option}")
    unknown = invoke(served, "show", "0000000000000000")
    assert unknown.exit_code == 1
    assert one_error_line(unknown.stderr).startswith("error: 404 no job '0000000000000000'")


def test_a_viewer_key_cannot_submit(served: ServedCell):
    proc = run_cell(served, "submit", "--object", "bunny", role="viewer")
    assert proc.returncode == 1 and proc.stdout == ""
    assert one_error_line(proc.stderr) == "error: 403 a viewer key may not submit"
    no_key_in(served, proc.stderr)


def test_stop_a_running_job_then_wait_exits_2(served: ServedCell):
    submitted = invoke(served, "submit", "--object", "bunny", "--max-time", "120", "--part-id", "to-stop")
    assert submitted.exit_code == 0, submitted.output
    job_id = submitted.stdout.strip().splitlines()[-1]
    deadline = time.monotonic() + 60.0
    # its worker has started it (its first progress): the stop goes through the worker, not a kill of a
    # worker still loading its libraries
    while (job := show_json(served, job_id))["progress"] is None:
        assert job["status"] in {"queued", "running"} and time.monotonic() < deadline, job
        time.sleep(0.1)
    stopped = invoke(served, "stop", job_id)
    assert stopped.exit_code == 0, stopped.output
    assert stopped.stdout.strip(), "stop prints the service's message"
    # the stop is answered once the worker has taken it: never `running` after, `stopping` until the
    # worker has written the job's end
    assert show_json(served, job_id)["status"] in {"stopping", "stopped"}

    waited = run_cell(served, "wait", job_id, "--timeout", "60", role="viewer")
    assert waited.returncode == 2, waited.stdout + waited.stderr
    said = waited.stdout.splitlines()
    # the job's events say so too, when the wait met the job before its end (else its status alone)
    assert len(said) == 1 or "stopping" in said, waited.stdout
    last = waited.stdout.strip().splitlines()[-1]
    # said once: the default reason was 'operator stop', after the guard's 'operator stop: '
    assert last == "stopped: operator stop: requested from the command line (key test-operator)", \
        waited.stdout
    assert show_json(served, job_id)["status"] == "stopped"

    again = invoke(served, "stop", job_id)
    assert again.exit_code == 1
    assert one_error_line(again.stderr) == f"error: 409 job {job_id} is stopped: nothing to stop"


def test_wait_gives_up_after_its_timeout(served: ServedCell):
    submitted = invoke(served, "submit", "--object", "bunny", "--max-time", "120")
    job_id = submitted.stdout.strip().splitlines()[-1]
    try:
        waited = invoke(served, "wait", job_id, "--timeout", "0.5", role="viewer")
        assert waited.exit_code == 1
        assert one_error_line(waited.stderr) == f"error: job {job_id} did not end within 0.5 s"
    finally:
        assert invoke(served, "stop", job_id).exit_code == 0
        served.wait_job(job_id, FINISHED)


def test_a_missing_key_is_one_line_that_says_where_to_get_one(served: ServedCell):
    proc = run_cell(served, "list", role=None)
    assert proc.returncode == 1 and proc.stdout == ""
    line = one_error_line(proc.stderr)
    assert "CELL_KEY" in line and "--key" in line and "cell keys create" in line
    wrong = CliRunner().invoke(app, ["jobs", "list", "--server", served.url, "--key", "cell_not-a-key"])
    assert wrong.exit_code == 1
    assert one_error_line(wrong.stderr).startswith("error: 401 a valid API key is needed")
    assert "cell_not-a-key" not in wrong.output


def test_a_server_that_is_not_there(served: ServedCell):
    url = f"http://127.0.0.1:{free_port()}"
    proc = run_cell(served, "list", server=url)
    assert proc.returncode == 1 and proc.stdout == ""
    assert one_error_line(proc.stderr).startswith(f"error: the server did not answer at {url} ")
    no_key_in(served, proc.stderr)
    waited = CliRunner().invoke(app, ["jobs", "wait", "0000000000000000", "--server", url, "--key", "k"])
    assert waited.exit_code == 1
    assert one_error_line(waited.stderr).startswith(f"error: the server did not answer at {url} ")


def test_stop_all_is_the_cells_stop_and_resume_lets_the_queue_go_on(served: ServedCell):
    """Last of the served tests: the STOP holds the queue, and `cell jobs resume` (an operator's) lets it go
    on; stop --all's output had sent the user to POST /api/v1/queue/resume, which no command did."""
    try:
        result = invoke(served, "stop", "--all", "--reason", "cli stop all", role="viewer")
        assert result.exit_code == 0, result.output
        lines = result.stdout.strip().splitlines()
        assert lines[0] and lines[-1] == "queued jobs are held until the queue is resumed (cell jobs resume)"
        with served.client("viewer") as http:
            held = http.get("/api/v1/cell").json()["queue"]["held"]
            assert held is not None and "cell jobs resume" in held
        refused = run_cell(served, "resume", role="viewer")
        assert refused.returncode == 1 and one_error_line(refused.stderr).startswith("error: 403 ")
        resumed = run_cell(served, "resume")
        assert resumed.returncode == 0, resumed.stderr
        assert resumed.stdout.startswith("queue resumed: ") and resumed.stdout.endswith(" jobs queued\n")
        no_key_in(served, resumed.stdout, resumed.stderr)
        with served.client("viewer") as http:
            assert http.get("/api/v1/cell").json()["queue"]["held"] is None
    finally:
        with served.client("operator") as http:
            assert http.post("/api/v1/queue/resume").status_code == 200
    neither = invoke(served, "stop")
    assert neither.exit_code == 1 and one_error_line(neither.stderr)


# --- the event stream, against a scripted server ----------------------------------------------------------

def sse(event_id: int, kind: str, data: dict[str, Any]) -> str:
    return f"id: {event_id}\nevent: {kind}\ndata: {json.dumps(data)}\n\n"


def progress(t_s: float) -> dict[str, Any]:
    return {"t_s": t_s, "n_captures": 1, "h_roi": 0.5, "coverage_pct": None}


def test_a_progress_line_names_the_form_of_h_roi():
    """H_ROI is in planners.vs.objective.entropy's form; a service that did not send it sent eq. 8's."""
    aware = {**progress(1.0), "h_roi_entropy": "observation_aware"}
    assert _progress_line(aware) == "t 1.0 s  1 captures  H_ROI (observation-aware) 0.500 nats"
    assert _progress_line(progress(1.0)) == "t 1.0 s  1 captures  H_ROI (eq. 8) 0.500 nats"
    # a newer service's form this release does not know is shown by its own name, not a crash
    newer = {**progress(1.0), "h_roi_entropy": "variance"}
    assert _progress_line(newer) == "t 1.0 s  1 captures  H_ROI (variance) 0.500 nats"


def test_parse_events():
    text = (": keep-alive\n\nid: 3\nevent: progress\ndata: {\"t_s\": 1.0,\ndata:  \"x\": 2}\n\n"
            "event: note\ndata: plain text\n\nid: 4\n\n")
    events = list(parse_events(iter(text.splitlines())))
    assert events == [ServerEvent(3, "progress", {"t_s": 1.0, "x": 2}), ServerEvent(3, "note", "plain text")]


def test_a_broken_stream_resumes_after_the_last_event(monkeypatch: pytest.MonkeyPatch,
                                                       capsys: pytest.CaptureFixture[str]):
    """The first connection breaks after two events; the client comes back with Last-Event-ID: 2 and gets
    the rest. Ten progress events inside a second print the first and, before the status, the newest."""
    monkeypatch.setattr(client_module, "RECONNECT_DELAY_S", 0.01)
    asked: list[str | None] = []

    def first() -> Iterator[bytes]:
        yield sse(1, "state", {"status": "running", "termination": None}).encode()
        yield sse(2, "progress", progress(0.5)).encode()
        raise httpx.ReadError("connection reset")

    def rest() -> Iterator[bytes]:
        for i in range(10):
            yield sse(3 + i, "progress", progress(1.0 + i / 10)).encode()
        yield sse(13, "state", {"status": "failed", "termination": "PlanningError: no view"}).encode()
        yield sse(14, "result", {"status": "failed", "result": {"status": "failed"}}).encode()

    def handler(request: httpx.Request) -> httpx.Response:
        assert request.url.path == "/api/v1/jobs/abc/events"
        assert request.headers["authorization"] == "Bearer k"
        asked.append(request.headers.get("last-event-id"))
        return httpx.Response(200, headers={"content-type": "text/event-stream"},
                              content=first() if len(asked) == 1 else rest())

    with ApiClient("http://cell.test", "k", transport=httpx.MockTransport(handler)) as api:
        ids = [e.id for e in api.follow("abc")]
        assert ids == list(range(1, 15))
        assert asked == [None, "2"]
        capsys.readouterr()
        asked.clear()
        assert follow_job(api, "abc", None) == 2
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0] == "running"
    shown = [line for line in lines if line.startswith("t ")]
    assert [line.split("  ")[0] for line in shown] == ["t 0.5 s", "t 1.9 s"]
    assert lines[-2:] == [shown[-1], "failed: PlanningError: no view"]


def test_a_stream_ended_early_is_completed_from_the_record(monkeypatch: pytest.MonkeyPatch):
    """A restarted service no longer has the job's events: the stream ends without a result, and the
    job's record tells how it ended."""
    monkeypatch.setattr(client_module, "RECONNECT_DELAY_S", 0.01)

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events"):
            return httpx.Response(200, content=b": keep-alive\n\n")
        return httpx.Response(200, json={"id": "abc", "status": "interrupted", "termination": "service died",
                                         "result": None})

    with ApiClient("http://cell.test", "k", transport=httpx.MockTransport(handler)) as api:
        events = list(api.follow("abc"))
    assert [(e.event, e.data["status"]) for e in events] == [("state", "interrupted"),
                                                             ("result", "interrupted")]
    assert events[0].data["termination"] == "service died"


@pytest.mark.parametrize("proxy", [None, 502, 503, 504])
def test_a_stream_broken_by_a_service_restart_is_waited_for_then_ends_from_the_record(
        monkeypatch: pytest.MonkeyPatch, proxy: int | None):
    """The service dies and systemd restarts it: the client reconnects for up to RECONNECT_WINDOW_S, and
    the restarted service's record of the job ends the wait (it had given up after five tries, 12 s, before
    a restart is back). A service that stays away past the window is said so. Behind a reverse proxy
    (``proxy``) the restart is its 502, 503 or 504 rather than a refused connection (the wait had ended
    with that error at once)."""
    monkeypatch.setattr(client_module, "RECONNECT_DELAY_S", 0.001)
    down = {"left": 8}  # refused connections while the service restarts: more than the five tried before

    def away() -> httpx.Response:
        if proxy is None:
            raise httpx.ConnectError("connection refused")
        return httpx.Response(proxy, text="<html>Bad Gateway</html>")

    def restarting(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events") and down["left"] == 8:
            down["left"] -= 1
            return httpx.Response(200, content=sse(1, "state", {"status": "running",
                                                                 "termination": None}).encode())
        if down["left"] > 0:
            down["left"] -= 1
            return away()
        if request.url.path.endswith("/events"):
            return httpx.Response(200, content=b": keep-alive\n\n")
        return httpx.Response(200, json={"id": "abc", "status": "interrupted",
                                         "termination": "the service restarted", "result": None})

    with ApiClient("http://cell.test", "k", transport=httpx.MockTransport(restarting)) as api:
        events = list(api.follow("abc"))
    assert [(e.event, e.data["status"]) for e in events][-1] == ("result", "interrupted")

    monkeypatch.setattr(client_module, "RECONNECT_WINDOW_S", 0.05)
    down["left"] = 8

    def gone(request: httpx.Request) -> httpx.Response:
        if down["left"] == 8:
            down["left"] -= 1
            return httpx.Response(200, content=sse(1, "state", {"status": "running",
                                                                 "termination": None}).encode())
        return away()

    with ApiClient("http://cell.test", "k", transport=httpx.MockTransport(gone)) as api, \
            pytest.raises(ServerUnreachable, match=r"failed for 0\.05 s"):
        list(api.follow("abc"))


def test_paths_are_one_segment():
    seen: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request.url.raw_path.decode())
        return httpx.Response(404, json={"detail": "no such job"})

    with ApiClient("http://cell.test/", "k", transport=httpx.MockTransport(handler)) as api, \
            pytest.raises(client_module.ApiError, match=r"^404 no such job$"):
        api.job("../stop")
    assert seen == ["/api/v1/jobs/..%2Fstop"]


def test_the_key_option_is_not_shown_in_help():
    result = CliRunner().invoke(app, ["jobs", "list", "--help"], env={"CELL_KEY": "cell_secret-value"})
    assert result.exit_code == 0 and "CELL_KEY" in result.stdout
    assert "cell_secret-value" not in result.output


def test_the_command_line_knows_every_status_of_the_service():
    """``cell jobs`` keeps its own list (it does not load the store) and shows it in ``list --help``: the
    service's statuses, no_object included, which ``--status`` filters by."""
    assert client_module.JOB_STATUSES == JOB_STATUSES
    assert client_module.FINISHED == FINISHED_STATUSES
    result = CliRunner().invoke(app, ["jobs", "list", "--help"], env={"COLUMNS": "300"})
    listed = re.search(r"commas\): ([a-z_, ]+)", result.stdout)
    assert listed is not None and tuple(listed.group(1).strip().split(", ")) == JOB_STATUSES


def test_a_results_time_is_labelled_by_its_clock():
    """A real-mode job's time, on the wall clock, was labelled 'sim time'."""
    assert [time_label({"mode": mode}) for mode in ("sim", "replay", "dry-run", "real")] == \
        ["sim time", "sim time", "time (wall clock)", "time (wall clock)"]
    assert time_label({}) == "job time"  # a result.json from before it said its mode


def test_packing_lines_show_a_face_without_an_upper_bound():
    """A face seen only at the edge of the field of view has no upper bound (null in result.json)."""
    lines = dict(packing_lines({"dims_m": [0.035, 0.035, 0.26], "dims_upper_m": [None, None, 0.272],
                                "container": {"name": None, "reason": "none: a face has no upper bound"}}))
    assert lines == {"packing dims": "0.035 x 0.035 x 0.260 m",
                     "packing upper": "unbounded x unbounded x 0.272 m",
                     "container": "none (none: a face has no upper bound)"}
