"""``cell scan``: a scan on a cell file (the shipped simulated cell by default), or the replay of a recorded
job, writing its job folder."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from cell.cli.entry import EXIT_INTERRUPTED
from cell.cli.errors import fail, print_error, print_warning
from cell.cli.jobs import EXIT_NOT_COMPLETED, coverage_line, packing_lines, time_label
from cell.cli.object_scale import scale_of
from cell.cli.progress import BAR_CONSOLE, scan_progress
from cell.cli.signals import interrupting
from cell.cli.values import parse_pose
from cell.config import load_config
from cell.config.placeholders import require_measured
from cell.jobs.replay import recorded_job, replay_config
from cell.jobs.runner import INTERRUPTED, PreparedScan, ScanRequest, prepare_scan, run_prepared
from cell.templates import DEFAULT_TEMPLATE, template_path
from drivers.errors import ARM_FAULT, CellError, JobError, SafetyStop
from drivers.sim.objects import DEFAULT_OBJECT, EMPTY_TABLE

DEFAULT_CONFIG = template_path(DEFAULT_TEMPLATE)

console = Console(soft_wrap=True)
err_console = BAR_CONSOLE  # a line printed while the bar shows goes above it


def _replay_request(job_dir: Path, config: Path | None, planner: str | None, seed: int | None,
                    out: Path | None, max_time: float | None) -> ScanRequest:
    """A replay of ``job_dir`` (``cell scan --replay``): the job's cell file (or ``config``) with the replay
    backends, and by default the job's own planner, seed and time budget (a budget the cell file changed
    since would end the replay at another time than the job)."""
    cfg, job_result, config_path = recorded_job(job_dir, config)
    if job_result.problem is not None:
        print_warning(f"{job_dir / 'result.json'} is {job_result.problem}: replaying with the job's identity "
                      "from job.json")
    recorded = job_result.result
    return ScanRequest(config=replay_config(cfg, job_dir), config_path=str(config_path),
                       object=str(recorded.get("object") or "unknown"),
                       planner=planner or recorded.get("planner"),
                       seed=seed if seed is not None else int(recorded.get("seed", 0)), out=out,
                       max_time_s=max_time if max_time is not None else job_result.budget_s)


def _arm_fault_hint(request: ScanRequest) -> str:
    """What becomes of the fault that stopped ``request``'s arm: a hardware arm stays faulted until an
    operator recovers it (``cell arm recover``, a commissioning command of hardware arms only); the
    simulated arm is made anew for every job, so the next one starts without the fault."""
    if request.config.arm.type == "sim":
        return "the simulated arm starts fresh with the next job: nothing to recover"
    return (f"the arm stays faulted until recovered: clear the cause, then cell arm recover --config "
            f"{request.config_path}")


def _print_folder(folder: Path) -> None:
    """``job folder: <folder>`` to standard error: at the start, for a ``cell stop`` from another terminal
    while the scan runs (standard output keeps only the outcome), and again after a stop or a failure."""
    err_console.print(f"job folder: {folder}", markup=False, highlight=False, soft_wrap=True)


def _stopped(job: PreparedScan, exc: Exception, received: list[int]) -> typer.Exit:
    """A scan that stopped or failed after its folder was made: ``stopped: <reason>`` for a stop (an
    operator's, a safety check's), else the error; then where the folder is, when it was made (its
    log.txt holds the traceback of an internal error). The exit code of a signal that stopped it is the
    shell's, 128 + its number."""
    if isinstance(exc, SafetyStop):
        err_console.print(f"stopped: {exc.reason}", markup=False, highlight=False, soft_wrap=True)
        if exc.reason.startswith(ARM_FAULT):  # what the guard names a fault the arm latched
            err_console.print(_arm_fault_hint(job.request), markup=False, highlight=False, soft_wrap=True)
    else:
        print_error(exc if isinstance(exc, CellError) else f"internal error: {type(exc).__name__}: {exc}")
    if job.folder.is_dir():  # not when the folder could not be made
        _print_folder(job.folder)
    if received:
        return typer.Exit(code=128 + received[0])
    interrupted = isinstance(exc, SafetyStop) and exc.reason == INTERRUPTED
    return typer.Exit(code=EXIT_INTERRUPTED if interrupted else 1)


def scan(
    config: Annotated[Path | None, typer.Option(help=f"cell file (default: the shipped {DEFAULT_TEMPLATE} "
                                                     "cell; with --replay, the job's)")] = None,
    object: Annotated[str | None, typer.Option(
        "--object", help=f"shipped name or mesh file (default {DEFAULT_OBJECT}), {EMPTY_TABLE!r} for an "
                         "empty table; on a real cell, a label for the record; not with --replay, which "
                         "scans the recorded job's")] = None,
    object_pose: Annotated[str | None, typer.Option(help="x,y,yaw_deg from the station (default 0,0,0)")]
    = None,
    object_scale: Annotated[float | None, typer.Option(help="multiplies a mesh file's coordinates into "
                                                            "metres (0.001 for a mesh in millimetres; "
                                                            "default 1); not for a shipped object, which is "
                                                            "in metres")]
    = None,
    planner: Annotated[str | None, typer.Option(help="planner name (default: the cell file's; with "
                                                     "--replay, the job's)")] = None,
    seed: Annotated[int | None, typer.Option(help="random seed of the job (default 0; with --replay, the "
                                                  "job's)")] = None,
    out: Annotated[Path | None, typer.Option(help="job folder to create, new or empty (default: "
                                                  "jobs/{stamp}-...)")] = None,
    max_time: Annotated[float | None, typer.Option(help="time budget [s] (default: the cell file's; with "
                                                        "--replay, the job's)")] = None,
    replay: Annotated[Path | None, typer.Option(help="re-run a recorded job folder's frames and poses "
                                                     "through perception and the planner (nothing moves)")]
    = None,
) -> None:
    """Run a scan and write its job folder.

    Exit code 0 when it completed (also when its time budget ended it before an object was found: the
    termination says so), 2 when it found no object on the table, 1 when it failed or was stopped
    and on an error in its input, a usage error of its command line included (nothing is made then), 130
    after Ctrl-C, 143 after SIGTERM and 129 after SIGHUP (they stop the scan as Ctrl-C does). The job
    folder is printed to standard error as soon as it exists (``job folder: DIR``, for ``cell stop DIR``
    from another terminal), and again at the end in every case: with the outcome on standard output, or
    after the error or stop on standard error.
    Progress: a bar on a terminal, else a line to standard error every few seconds of job time."""
    try:
        if replay is not None:
            given = [name for name, value in (("--object", object), ("--object-pose", object_pose),
                                              ("--object-scale", object_scale)) if value is not None]
            if given:
                raise JobError(f"{', '.join(given)} cannot be given with --replay: a replay scans the "
                               "recorded job's object, where the recording has it")
            request = _replay_request(replay, config, planner, seed, out, max_time)
        else:
            path = config if config is not None else DEFAULT_CONFIG
            cfg = load_config(path)
            require_measured(path, cfg.mode)
            label = object or (DEFAULT_OBJECT if cfg.mode != "real" else "unknown")
            scale = scale_of(label, object_scale)
            request = ScanRequest(config=cfg, config_path=str(path), object=label,
                                  object_pose=parse_pose("--object-pose", object_pose or "0,0,0"),
                                  planner=planner,
                                  seed=seed if seed is not None else 0, out=out, max_time_s=max_time,
                                  object_scale=scale)
        job = prepare_scan(request)
    except CellError as exc:
        raise fail(exc) from None
    with interrupting() as received:
        try:
            with scan_progress(job.max_time_s) as show:
                outcome = run_prepared(job, on_progress=show, on_folder=_print_folder)
        except Exception as exc:  # the job's folder holds its result whatever the error: say where it is
            raise _stopped(job, exc, received) from None
    r = outcome.result
    cov = r["metrics"]["coverage_pct"]
    console.print(f"{r['status']}: {r['termination']}", markup=False, highlight=False)
    scan = f" (scan {r['scan_time_s']:.1f} s from the first frame)" if r["scan_time_s"] is not None else ""
    console.print(f"{r['n_captures']} captures, {time_label(r)} {r['sim_time_s']:.1f} s{scan}, path "
                  f"{r['path_length_m']:.2f} m", highlight=False)
    console.print(coverage_line(cov), highlight=False)
    packing = r.get("packing") or {}
    if packing.get("dims_m"):  # an object was measured: its box, upper bound and container
        for label, value in packing_lines(packing):
            console.print(f"{label}: {value}", markup=False, highlight=False)
    console.print(f"job folder: {outcome.folder}", markup=False, highlight=False)
    if r["status"] == "no_object":
        raise typer.Exit(code=EXIT_NOT_COMPLETED)
    if r["status"] != "completed":  # failed: e.g. nothing captured, no view being reachable
        raise typer.Exit(code=1)
