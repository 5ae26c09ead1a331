"""A job's worker process: runs one scan (or one arm recovery) for the service, apart from the web side.

The control loop runs here, in a process of its own, so that no web client, however many or slow, holds
the interpreter lock it needs at every tick. The protocol is ``cell.service.protocol``. Three threads:

- the main thread runs the job (``cell.jobs.runner.run_prepared``); its progress callback only queues a
  line;
- the reader takes commands from the service; a stop commands the arm to stop from this thread at once
  (``JobControl``), before it answers; the end of its input (the service is gone) stops the job too;
- the writer sends the queued lines; when the service stops reading, progress lines are dropped (the
  queue is bounded) and the control loop never waits for it.

SIGTERM and SIGINT (a system shutdown, an operator's kill) stop the job the same way: the arm stops
through the guard and the folder is finished, with ``status: stopped``.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from types import FrameType
from typing import Any, BinaryIO

from cell.jobs.control import JobControl, StopEffect
from cell.service.protocol import WORKER_BEAT_S, WorkerSpec

PROGRESS_QUEUE = 256
"""Progress lines held for a slow reader before newer ones are dropped."""
CHOOSE_DATA_DIR = "serve the cell from another data dir (cell serve --data-dir)"
"""What a job folder the service cannot make asks of its administrator (``cell scan`` asks for --out)."""
SERVICE_GONE = "the service stopped while the job ran (no one could stop the arm any more)"


class Outbox:
    """Lines to the service, written by a thread of their own (see the module docstring)."""

    def __init__(self, out: BinaryIO) -> None:
        self._out = out
        self._queue: queue.Queue[dict[str, Any] | None] = queue.Queue(PROGRESS_QUEUE)
        self._closed = threading.Event()
        self.n_dropped = 0
        self._thread = threading.Thread(target=self._run, name="outbox", daemon=True)
        self._thread.start()

    def send(self, message: dict[str, Any]) -> None:
        """Queue a line; waits for room (not for the control loop: use ``offer``)."""
        if not self._closed.is_set():
            self._queue.put(message)

    def offer(self, message: dict[str, Any]) -> None:
        """Queue a line if there is room, else drop it (progress, from the control loop)."""
        try:
            self._queue.put_nowait(message)
        except queue.Full:
            self.n_dropped += 1

    def close(self) -> None:
        """Send what is queued, then stop."""
        self._queue.put(None)
        self._thread.join()

    def _run(self) -> None:
        while (message := self._queue.get()) is not None:
            if self._closed.is_set():
                continue
            try:
                self._out.write((json.dumps(message) + "\n").encode())
                self._out.flush()
            except OSError:  # the service has gone; its end of the pipe is closed
                self._closed.set()


def _lines(fd: int) -> Iterator[bytes]:
    """Lines read from a file descriptor with ``os.read``: no Python file object, whose lock a reader
    thread blocked at exit would hold while the interpreter shuts down."""
    pending = b""
    while chunk := os.read(fd, 4096):
        *lines, pending = (pending + chunk).split(b"\n")
        yield from lines


def _listen(source: Iterator[bytes], outbox: Outbox, stop: Callable[..., StopEffect]) -> None:
    """The reader thread: stop commands (``JobControl.request_stop``), then the end of the input."""
    for raw in source:
        try:
            command = json.loads(raw)
            reason = str(command["reason"]) if command.get("op") == "stop" else None
            operator = command.get("operator", True)
        except (ValueError, KeyError, TypeError, AttributeError):
            reason = None
        if reason is None or not isinstance(operator, bool):
            print(f"worker: ignored a malformed command: {raw[:200]!r}", file=sys.stderr)
            continue
        outbox.send({"type": "stop", "effect": stop(reason, operator=operator).value, "reason": reason})
    stop(SERVICE_GONE, operator=False)  # nobody asked: the safety layer's stop


def _beat(outbox: Outbox, done: threading.Event) -> None:
    """The beat thread: an ``alive`` line every ``WORKER_BEAT_S`` until ``done`` (never waits on the
    service: a beat the outbox has no room for is dropped, its progress lines say as much)."""
    while not done.wait(WORKER_BEAT_S):
        outbox.offer({"type": "alive"})


def _run_scan(spec: WorkerSpec, outbox: Outbox, control: JobControl) -> int:
    # imported once the protocol's output is set aside: the perception libraries may print as they load
    from cell.config.load import parse_config
    from cell.jobs.progress import JobProgress
    from cell.jobs.runner import ScanRequest, prepare_scan, run_prepared
    from drivers.errors import CellError

    def report(progress: JobProgress) -> None:
        outbox.offer({"type": "progress", "progress": progress.as_dict()})

    folder = Path(spec.folder)
    result: dict[str, Any] | None = None
    status, termination = "failed", "not started"
    try:
        # the kept cell file relative to the job folder: the result is served, the host's paths are not
        request = ScanRequest(config=parse_config(spec.config, file=spec.config_file),
                              config_path=os.path.relpath(spec.config_file, folder), object=spec.object,
                              object_pose=spec.object_pose, planner=spec.planner, seed=spec.seed, out=folder,
                              max_time_s=spec.max_time_s, choose_folder=CHOOSE_DATA_DIR, part_id=spec.part_id,
                              submitted_by=spec.submitted_by)
        # not run_scan: its heap trim (tens of ms) would delay the end the line waits for, in a process
        # that exits with its job
        outcome = run_prepared(prepare_scan(request), on_progress=report, control=control)
        result = outcome.result
    except CellError as exc:
        termination = f"{type(exc).__name__}: {exc}"
    except Exception as exc:
        termination = f"internal error: {type(exc).__name__}: {exc}"
    if result is None and (folder / "result.json").is_file():
        result = json.loads((folder / "result.json").read_text())
    if result is not None:
        status, termination = result["status"], result["termination"]
    ticks = ((result or {}).get("control") or {}).get("histogram")
    outbox.send({"type": "ended", "status": status, "termination": termination, "result": result,
                 "ticks": ticks})
    return 0 if status == "completed" else 1


def _recover(spec: WorkerSpec, outbox: Outbox) -> int:
    from cell.config.load import parse_config
    from drivers.errors import CellError
    from drivers.factory import make_arm
    from drivers.robots import get_robot_model

    try:
        cfg = parse_config(spec.config, file=spec.config_file)
        arm = make_arm(cfg.arm, get_robot_model(cfg.arm.model), None)
        with arm:
            arm.recover()
            state = arm.state()
        outbox.send({"type": "recovered", "ok": not state.faults, "message": "recovered" if not state.faults
                     else f"still faulted: {', '.join(state.faults)}",
                     "arm": {"faults": list(state.faults), "mode": state.mode.value,
                             "T_base_flange": state.T_base_flange.tolist()}})
        return 0
    except CellError as exc:
        outbox.send({"type": "recovered", "ok": False, "message": str(exc), "arm": None})
        return 1


def _preload() -> None:
    """Import what a scan needs before the task comes: a warm worker (``service.warm_worker``) then
    starts its job without the second the imports take."""
    import cell.jobs.runner  # noqa: F401
    import drivers.factory  # noqa: F401
    from cell.planning.registry import PLANNERS

    for entry in PLANNERS.values():  # the registry imports a planner only when asked for it
        entry.load()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m cell.service.worker", description=__doc__)
    parser.add_argument("--job", required=True, help="the job's id (for the process list)")
    parser.parse_args(argv)
    # The protocol keeps the original standard output; everything else printing there goes to stderr.
    protocol = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    outbox = Outbox(protocol)
    _preload()
    outbox.send({"type": "loaded"})
    source = _lines(sys.stdin.fileno())
    try:
        spec = WorkerSpec.parse(next(source).decode())
    except StopIteration:
        # a spare whose service went away (shut down, restarted or killed) before it had a job: nothing
        # happened (the service drops its log when it stays empty)
        outbox.close()  # os._exit follows: what is queued ("loaded") is written first
        return 0
    except (ValueError, TypeError, KeyError) as exc:
        print(f"worker: no valid task on standard input: {exc!r}", file=sys.stderr)
        outbox.close()
        return 2
    control = JobControl()

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        # JobControl takes a lock the interrupted main thread may hold: stop from another thread
        name = signal.Signals(signum).name
        threading.Thread(target=control.request_stop, args=(f"worker received {name}",), daemon=True).start()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_signal)
    outbox.send({"type": "started", "pid": os.getpid()})
    threading.Thread(target=_listen, args=(source, outbox, control.request_stop), name="commands",
                     daemon=True).start()
    done = threading.Event()
    threading.Thread(target=_beat, args=(outbox, done), name="beat", daemon=True).start()
    code = _run_scan(spec, outbox, control) if spec.op == "scan" else _recover(spec, outbox)
    done.set()
    outbox.close()
    return code


if __name__ == "__main__":
    exit_code = main()
    # Everything is closed by now (the arm, the sensor, the job's files, the protocol): the interpreter's
    # teardown (a few hundred milliseconds with the perception libraries) would only keep the arm from
    # the next job, which starts once this process has exited.
    sys.stderr.flush()
    os._exit(exit_code)
