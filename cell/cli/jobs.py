"""``cell jobs``: submit, list, show, stop, wait for, keep and prune the jobs of a running ``cell serve``,
and resume its queue after a STOP, from scripts.

Every command talks to the service at ``--server`` (default: ``$CELL_SERVER``, else
``http://127.0.0.1:8080``) with the API key ``--key`` (default: ``$CELL_KEY``; ``cell keys create`` makes
one on the service's machine). The key is never printed. Any error is one line ``error: ...`` on stderr and
exit code 1: an HTTP error reads ``error: <status> <detail>`` (a 422 names each field), a server that does
not answer says so with its URL.

``submit`` prints the new job's id alone on its last line (``id=$(cell jobs submit ... | tail -1)``).
``wait`` (and ``submit --wait``) follows the job's events and exits 0 when it ends ``completed``, 2 when it
ends otherwise (no_object, failed, stopped, cancelled, interrupted) and 1 on an error or when ``--timeout``
passes.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from typing import Annotated, Any

import typer
from rich.console import Console

from cell.cli.client import FINISHED, JOB_STATUSES, ApiClient, ServerEvent
from cell.cli.commands import command_group
from cell.cli.errors import fail
from cell.cli.values import parse_pose
from cell.perception.entropy_form import h_roi_name
from drivers.errors import COMMAND_LINE_REASON, CellError

DEFAULT_SERVER = "http://127.0.0.1:8080"
PROGRESS_EVERY_S = 1.0
"""``wait`` prints at most one progress line this often [s]."""
TERMINATION_WIDTH = 48
"""``list`` shortens a termination to this many characters."""
EXIT_NOT_COMPLETED = 2

jobs_app = command_group(help="Jobs of a running `cell serve`: submit, list, show, stop, resume, keep, "
                              "prune, wait (for scripts).",
                         no_args_is_help=True)
console = Console(soft_wrap=True)

ServerOption = Annotated[str, typer.Option(
    "--server", envvar="CELL_SERVER", metavar="URL",
    help=f"the service's URL (default: $CELL_SERVER, else {DEFAULT_SERVER})")]
KeyOption = Annotated[str | None, typer.Option(
    "--key", envvar="CELL_KEY", metavar="KEY", show_default=False,
    help="API key (default: $CELL_KEY); `cell keys create` makes one on the service's machine")]
JsonOption = Annotated[bool, typer.Option("--json", help="print the server's JSON answer as it is")]


def _print(text: str) -> None:
    console.print(text, markup=False, highlight=False)


@contextlib.contextmanager
def _client(server: str, key: str | None) -> Iterator[ApiClient]:
    """A client of ``server`` with ``key``; every ``CellError`` inside becomes one line and exit code 1."""
    if key is None or not key.strip():
        raise fail("no API key: pass --key KEY or set CELL_KEY (on the service's machine, "
                    "`cell keys create --role operator` makes one)")
    try:
        with ApiClient(server or DEFAULT_SERVER, key) as client:
            yield client
    except CellError as exc:
        raise fail(exc) from None


def _utc(text: str | None) -> str:
    """An ISO 8601 time from the API in UTC to the second (``-`` for none)."""
    if not text:
        return "-"
    try:
        moment = datetime.fromisoformat(text)
    except ValueError:
        return text
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    return moment.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def _shorten(text: str | None, width: int) -> str:
    if not text:
        return "-"
    text = " ".join(text.split())
    return text if len(text) <= width else text[:width - 3] + "..."


def _number(value: object, fmt: str, unit: str = "") -> str | None:
    """``value`` formatted with ``fmt`` and ``unit``, None when it is not a finite number."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return None
    return f"{value:{fmt}}{unit}"


def _print_json(data: object) -> None:
    _print(json.dumps(data, indent=2))


# --- wait -----------------------------------------------------------------------------------------------

def _progress_line(data: dict[str, Any]) -> str:
    parts = [f"t {_number(data.get('t_s'), '.1f', ' s') or '-'}", f"{data.get('n_captures', 0)} captures"]
    coverage = _number(data.get("coverage_pct"), ".1f", " %")
    if coverage is not None:
        parts.append(f"cloud coverage {coverage}")
    # a service from before the form was sent sent eq. 8's H_ROI
    parts.append(f"{h_roi_name(data.get('h_roi_entropy', 'paper'))} "
                 f"{_number(data.get('h_roi'), '.3f', ' nats') or '-'}")
    return "  ".join(parts)


def follow_job(client: ApiClient, job_id: str, timeout_s: float | None) -> int:
    """Print the job's progress until it ends, then its status; its exit code (0 completed, 2 ended
    otherwise). A progress line is printed at most every ``PROGRESS_EVERY_S``; the newest one held back
    meanwhile is printed before the status, so that the last progress line shown is the job's last (a
    burst of events, such as the history a stream replays, showed its first one only)."""
    last_print = -math.inf
    held: str | None = None
    shown_state: str | None = None
    status, termination = "unknown", None
    event: ServerEvent
    for event in client.follow(job_id, timeout_s):
        data = event.data if isinstance(event.data, dict) else {}
        if event.event == "state":
            status, termination = str(data.get("status")), data.get("termination")
            if status not in FINISHED and status != shown_state:
                _print(status)
                shown_state = status
        elif event.event == "progress":
            held = _progress_line(data)
            now = time.monotonic()
            if now - last_print >= PROGRESS_EVERY_S:
                _print(held)
                held, last_print = None, now
        elif event.event == "result":
            status = str(data.get("status", status))
            result = data.get("result")
            if isinstance(result, dict) and termination is None:
                termination = result.get("termination")
    if held is not None:
        _print(held)
    return _print_end(status, termination)


def _print_end(status: str, termination: str | None) -> int:
    """Print how a job ended (its status and termination); its exit code (0 completed, 2 otherwise)."""
    _print(f"{status}: {termination}" if termination else status)
    return 0 if status == "completed" else EXIT_NOT_COMPLETED


def _check_seconds(option: str, seconds: float | None) -> None:
    if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
        raise fail(f"{option} must be a positive number of seconds, got {seconds:g}")


def _wait_exit(client: ApiClient, job_id: str, timeout_s: float | None) -> typer.Exit:
    code = follow_job(client, job_id, timeout_s)
    return typer.Exit(code=code)


# --- commands -------------------------------------------------------------------------------------------

@jobs_app.command("submit")
def submit(
    planner: Annotated[str | None, typer.Option(help="planner name (default: the cell's)")] = None,
    object: Annotated[str | None, typer.Option(
        "--object", help="object name (sim and dry-run cells; on a real cell, a label)")] = None,
    object_pose: Annotated[str | None, typer.Option(help="x,y,yaw_deg on the table from the station "
                                                         "(m, m, degrees)")] = None,
    seed: Annotated[int | None, typer.Option(help="random seed of the job (default 0)")] = None,
    max_time: Annotated[float | None, typer.Option(help="time budget, s (default: the cell's)")] = None,
    part_id: Annotated[str | None, typer.Option(help="the line's identifier of the part")] = None,
    wait: Annotated[bool, typer.Option("--wait", help="then follow the job until it ends, as `wait` "
                                                      "does")] = False,
    timeout: Annotated[float | None, typer.Option(help="with --wait: give up after this, s")] = None,
    server: ServerOption = DEFAULT_SERVER,
    key: KeyOption = None,
) -> None:
    """Queue a scan; prints the job's id alone on the last line (with --wait: first, then its progress)."""
    if timeout is not None and not wait:
        raise fail("--timeout is for --wait")
    _check_seconds("--timeout", timeout)
    _check_seconds("--max-time", max_time)
    body: dict[str, Any] = {"planner": planner, "object": object,
                            "object_pose": None if object_pose is None
                            else list(parse_pose("--object-pose", object_pose)),
                            "seed": seed, "max_time_s": max_time, "part_id": part_id}
    with _client(server, key) as client:
        job = client.submit({k: v for k, v in body.items() if v is not None})
        _print(str(job["id"]))
        if wait:
            raise _wait_exit(client, str(job["id"]), timeout)


@jobs_app.command("list")
def list_jobs(
    status: Annotated[list[str] | None, typer.Option(
        "--status", help="only these statuses (repeat or separate with commas): "
                         + ", ".join(JOB_STATUSES))] = None,
    planner: Annotated[str | None, typer.Option(help="only this planner")] = None,
    part_id: Annotated[str | None, typer.Option(help="only this part id")] = None,
    limit: Annotated[int, typer.Option(help="at most this many (1-500)")] = 50,
    offset: Annotated[int, typer.Option(help="skip this many of the newest first")] = 0,
    json_out: JsonOption = False,
    server: ServerOption = DEFAULT_SERVER,
    key: KeyOption = None,
) -> None:
    """The cell's jobs, newest first: id, status, planner, object, part id, created (UTC), termination."""
    statuses = [s.strip() for item in status or () for s in item.split(",") if s.strip()]
    params: dict[str, Any] = {"limit": limit, "offset": offset}
    if statuses:
        params["status"] = statuses
    if planner is not None:
        params["planner"] = planner
    if part_id is not None:
        params["part_id"] = part_id
    with _client(server, key) as client:
        page = client.jobs(params)
    if json_out:
        _print_json(page)
        return
    items: list[dict[str, Any]] = page["items"]
    header = ("ID", "STATUS", "PLANNER", "OBJECT", "PART ID", "CREATED (UTC)", "TERMINATION")
    rows = [(str(j["id"]), str(j["status"]), str(j["planner"]), j.get("object") or "-",
             j.get("part_id") or "-", _utc(j.get("created_at")),
             _shorten(j.get("termination"), TERMINATION_WIDTH)) for j in items]
    if rows:
        widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header) - 1)]
        for row in [header, *rows]:
            _print("  ".join([*(cell.ljust(w) for cell, w in zip(row[:-1], widths, strict=True)), row[-1]]))
    more = f" (from offset {page['offset']})" if page.get("offset") else ""
    _print(f"{len(items)} of {page['total']}{more}")


def _job_lines(job: dict[str, Any]) -> list[tuple[str, str]]:
    pose = job.get("object_pose")
    pose_text = (f"x {pose[0]:g} m, y {pose[1]:g} m, yaw {pose[2]:g} deg" if isinstance(pose, list)
                 and len(pose) == 3 else "-")
    lines = [("id", str(job["id"])), ("status", str(job["status"])), ("cell", str(job.get("cell", "-"))),
             ("planner", str(job.get("planner"))), ("object", job.get("object") or "-"),
             ("object pose", pose_text), ("seed", str(job.get("seed"))),
             ("time budget", _number(job.get("max_time_s"), "g", " s") or "the cell's"),
             ("part id", job.get("part_id") or "-"), ("submitted by", job.get("submitted_by") or "-"),
             ("created", _utc(job.get("created_at"))), ("started", _utc(job.get("started_at"))),
             ("finished", _utc(job.get("finished_at"))), ("termination", job.get("termination") or "-")]
    progress = job.get("progress")
    if job["status"] not in FINISHED and isinstance(progress, dict):
        lines.append(("progress", _progress_line(progress)))
    return lines


TIME_LABELS = {"sim": "sim time", "replay": "sim time", "dry-run": "time (wall clock)",
               "real": "time (wall clock)"}
"""What a result's ``sim_time_s`` is, by the cell's ``mode``: the job's clock, simulated in sim and replay,
the wall clock with a hardware arm."""


def time_label(result: dict[str, Any]) -> str:
    """The label of a result's ``sim_time_s`` by its ``mode`` (:data:`TIME_LABELS`; a result written before
    it held one: "job time")."""
    return TIME_LABELS.get(str(result.get("mode")), "job time")


def coverage_line(coverage_pct: float | None) -> str:
    """The summary line of a result's ``metrics.coverage_pct`` (eq. 13 on the cloud): not the packing
    section's share of the surface reconstructed, which :func:`packing_lines` gives."""
    return "cloud coverage (eq. 13): " + ("- (no ground truth)" if coverage_pct is None else
                                          f"{coverage_pct:.1f} %")


def packing_lines(packing: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, value) lines of a result.json's ``packing`` section: the box's estimate, its upper bound
    and the container chosen for that; none for a section without them."""
    lines = []
    for label, key in (("packing dims", "dims_m"), ("packing upper", "dims_upper_m")):
        value = packing.get(key)
        if isinstance(value, list) and value:
            # a face seen only at the field of view's edge has no upper bound (null)
            lines.append((label, " x ".join("unbounded" if v is None else f"{v:.3f}" for v in value) + " m"))
    surface = _number(packing.get("coverage_pct"), ".1f", " %")
    if surface is not None:
        lines.append(("surface reconstructed (voxels)", surface))
    container = packing.get("container")
    if isinstance(container, dict):
        name = container.get("name") or "none"
        reason = container.get("reason")
        lines.append(("container", f"{name} ({reason})" if reason else name))
    return lines


def _result_lines(result: dict[str, Any]) -> list[tuple[str, str]]:
    """The key figures of an ended job's result.json."""
    lines = [("result", f"{result.get('status')}: {result.get('termination')}")]
    duration = _number(result.get("sim_time_s"), ".1f", " s")
    if duration is not None:
        scan = _number(result.get("scan_time_s"), ".1f", " s")
        lines.append((time_label(result),
                      duration + (f" (scan {scan} from the first frame)" if scan else "")))
    if result.get("n_captures") is not None:
        lines.append(("captures", str(result["n_captures"])))
    path = _number(result.get("path_length_m"), ".2f", " m")
    if path is not None:
        lines.append(("path length", path))
    metrics = result.get("metrics") or {}
    for name, field, fmt, unit in (("cloud coverage (eq. 13)", "coverage_pct", ".1f", " %"),
                                   ("chamfer", "chamfer_mm", ".2f", " mm"),
                                   ("hausdorff", "hausdorff_mm", ".2f", " mm")):
        value = _number(metrics.get(field), fmt, unit)
        if value is not None:
            lines.append((name, value))
    lines += packing_lines(result.get("packing") or {})
    return lines


@jobs_app.command("show")
def show(
    job_id: Annotated[str, typer.Argument(metavar="ID", help="the job's id")],
    json_out: JsonOption = False,
    server: ServerOption = DEFAULT_SERVER,
    key: KeyOption = None,
) -> None:
    """A job's fields and, once it ended, its key result figures."""
    with _client(server, key) as client:
        job = client.job(job_id)
    if json_out:
        _print_json(job)
        return
    lines = _job_lines(job)
    if job["status"] in FINISHED and isinstance(job.get("result"), dict):
        lines += _result_lines(job["result"])
    width = max(len(name) for name, _ in lines)
    for name, value in lines:
        _print(f"{name:{width}s}  {value}")


@jobs_app.command("stop")
def stop(
    job_id: Annotated[str | None, typer.Argument(metavar="ID", help="the job to stop")] = None,
    all_: Annotated[bool, typer.Option("--all", help="the cell's STOP: whatever moves stops and queued "
                                                     "jobs are held")] = False,
    reason: Annotated[str, typer.Option(help="recorded in the job's termination, after 'operator stop: '")]
    = COMMAND_LINE_REASON,
    server: ServerOption = DEFAULT_SERVER,
    key: KeyOption = None,
) -> None:
    """Stop a job (a queued one is cancelled), or with --all the whole cell; prints what it did."""
    if (job_id is None) == (not all_):
        raise fail("give a job id or --all (not both)")
    with _client(server, key) as client:
        outcome = client.stop_all(reason) if all_ else client.stop(str(job_id), reason)
    _print(str(outcome.get("message")))
    if all_ and outcome.get("queue_held"):
        _print("queued jobs are held until the queue is resumed (cell jobs resume)")


@jobs_app.command("resume")
def resume(
    server: ServerOption = DEFAULT_SERVER,
    key: KeyOption = None,
) -> None:
    """Let queued jobs start again after `stop --all` (an operator's key; refused while the arm is faulted:
    `cell arm recover` first)."""
    with _client(server, key) as client:
        cell = client.resume()
    queue = cell.get("queue") or {}
    held = queue.get("held")
    _print(f"queue resumed: {queue.get('length', 0)} jobs queued" if held is None
           else f"queue resumed, but still held: {held}")


@jobs_app.command("keep")
def keep(
    job_id: Annotated[str, typer.Argument(metavar="ID", help="the job's id")],
    off: Annotated[bool, typer.Option("--off", help="release the job: retention may delete it again")]
    = False,
    server: ServerOption = DEFAULT_SERVER,
    key: KeyOption = None,
) -> None:
    """Keep a job: retention (service.retention) never deletes it."""
    with _client(server, key) as client:
        job = client.keep(job_id, not off)
    _print(f"{job['id']}: {'kept' if job['keep'] else 'not kept'}")


@jobs_app.command("prune")
def prune(
    dry_run: Annotated[bool, typer.Option("--dry-run", help="only show what would be deleted")] = False,
    server: ServerOption = DEFAULT_SERVER,
    key: KeyOption = None,
) -> None:
    """Delete the ended jobs that service.retention lets go.

    Their folders and records go (admin keys), as the service does by itself every
    retention.interval_h; --dry-run shows them (any key)."""
    with _client(server, key) as client:
        answer = client.retention(prune=not dry_run)
    limits = [f"{answer['days']:g} days" if answer["days"] is not None else None,
              f"{answer['max_gb']:g} GB" if answer["max_gb"] is not None else None]
    shown = " and ".join(limit for limit in limits if limit) or "no limit (service.retention): nothing goes"
    _print(f"retention: {shown}; job folders {answer['total_gb']:.3f} GB")
    for job in answer["jobs"]:
        _print(f"{job['id']}  ended {_utc(job['ended_at'])}  {job['size_mb']:8.1f} MB  {job['reason']}")
    verb = "would free" if dry_run else "freed"
    _print(f"{len(answer['jobs'])} jobs, {verb} {answer['freed_gb']:.3f} GB")
    if answer["unmet"]:
        _print(f"warning: {answer['unmet']}")


@jobs_app.command("wait")
def wait(
    job_id: Annotated[str, typer.Argument(metavar="ID", help="the job's id")],
    timeout: Annotated[float | None, typer.Option(help="give up after this, s (exit 1)")] = None,
    server: ServerOption = DEFAULT_SERVER,
    key: KeyOption = None,
) -> None:
    """Follow a job until it ends: a progress line at most every second, then its status.

    A job that has already ended: its status alone. Exit code 0 when it completed, 2 when it ended
    otherwise, 1 on an error or timeout."""
    _check_seconds("--timeout", timeout)
    with _client(server, key) as client:
        job = client.job(job_id)
        if job["status"] in FINISHED:  # its status alone, not the history its event stream would replay
            raise typer.Exit(code=_print_end(str(job["status"]), job.get("termination")))
        raise _wait_exit(client, job_id, timeout)

