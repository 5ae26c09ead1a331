"""Where a grid's tasks run: a local pool of worker processes, or Ray (a local instance or a cluster).

Both run one task per item, each at most twice: a worker process that dies while it runs a task (killed,
out of memory, a crash in native code) has that task run once more on a fresh worker, and a task whose
second attempt dies too is reported as a :class:`TaskFailure`, never dropped. An exception raised by the
task itself is not retried (it would raise again) and is reported the same way.

Results arrive through ``on_done(index, result)`` in the order tasks finish, on the caller's thread.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from types import FrameType
from typing import Any, ClassVar, Protocol

from drivers.errors import CellError

ATTEMPTS = 2
"""Runs of a task at most: the first and one retry after its worker died."""


@dataclass(frozen=True)
class TaskFailure:
    """A task that produced no result: why, and how many times it was started."""

    reason: str
    attempts: int


OnDone = Callable[[int, Any], None]


class Executor(Protocol):
    """Runs ``fn(item)`` for every item; calls ``on_done(index, result or TaskFailure)`` as each ends.
    Given no items, it starts nothing. ``name``: what the grid records as having run a scan."""

    @property
    def name(self) -> str: ...

    def run(self, fn: Callable[[Any], Any], items: Sequence[Any], on_done: OnDone) -> None: ...


def _stop_task(signum: int, _frame: FrameType | None) -> None:
    """SIGTERM in a pool worker: the driver stops the pool. The task under way is interrupted as Ctrl-C
    would (a scan stops through its guard and finishes its folder); a later one is ignored, so as not to
    interrupt that stop."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise KeyboardInterrupt(f"received {signal.Signals(signum).name}")


def _serve(conn: Connection, fn: Callable[[Any], Any]) -> None:
    """A pool worker's loop: (index, item) in, (index, ok, result or reason) out, until None. The worker
    starts with SIGINT ignored (``LocalPool``): a Ctrl-C is the driver's, which stops its workers with
    SIGTERM (``_stop_task``); then the worker ends quietly (the driver says what happened)."""
    signal.signal(signal.SIGTERM, _stop_task)
    try:
        while (message := conn.recv()) is not None:
            index, item = message
            try:
                conn.send((index, True, fn(item)))
            except Exception as exc:
                conn.send((index, False, f"{type(exc).__name__}: {exc}"))
    except (KeyboardInterrupt, EOFError, OSError):
        return


@dataclass
class _Worker:
    process: BaseProcess
    conn: Connection
    index: int | None = None


THREADS_VAR = "OMP_NUM_THREADS"
"""Threads of OpenMP and of OpenBLAS (which falls back to it) in a worker process."""


@contextmanager
def _worker_threads(jobs: int) -> Iterator[None]:
    """Processes spawned inside get ``THREADS_VAR`` = this machine's CPUs / ``jobs`` (at least 1) unless
    the user set it: ``jobs`` workers share the cores rather than each taking all of them, as Ray's
    workers do (Ray sets it to a task's CPUs). The variable must be in the environment a worker starts
    with: the libraries read it when they load, before the worker's own code runs."""
    if THREADS_VAR in os.environ:
        yield
        return
    os.environ[THREADS_VAR] = str(max(1, (os.cpu_count() or 1) // jobs))
    try:
        yield
    finally:
        del os.environ[THREADS_VAR]


STOP_WAIT_S = 10.0
"""How long a stopped worker may take to end its task (a scan stops and writes its folder) before it is
killed."""


@contextmanager
def _sigint_ignored() -> Iterator[None]:
    """Processes started inside ignore SIGINT from their start (an ignored signal stays ignored across
    ``exec``, and Python keeps it so): Ctrl-C in a terminal reaches the whole process group, and only the
    driver should answer it, before a worker has even imported its task's modules."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@dataclass
class LocalPool:
    """``jobs`` worker processes on this machine (started fresh, ``spawn``: no state inherited from the
    driver; their threads limited, see ``_worker_threads``), each running one task at a time."""

    jobs: int
    name: ClassVar[str] = "local"

    def __post_init__(self) -> None:
        if self.jobs < 1:
            raise CellError(f"--jobs must be at least 1, got {self.jobs}")

    def run(self, fn: Callable[[Any], Any], items: Sequence[Any], on_done: OnDone) -> None:
        ctx = mp.get_context("spawn")
        pending: deque[int] = deque(range(len(items)))
        attempts = dict.fromkeys(pending, 0)
        workers: list[_Worker] = []

        def start() -> _Worker:
            ours, theirs = ctx.Pipe()
            process = ctx.Process(target=_serve, args=(theirs, fn), daemon=True)
            with _worker_threads(self.jobs), _sigint_ignored():
                process.start()
            theirs.close()
            return _Worker(process, ours)

        def assign(worker: _Worker) -> None:
            worker.index = pending.popleft()
            attempts[worker.index] += 1
            worker.conn.send((worker.index, items[worker.index]))

        try:
            workers = [start() for _ in range(min(self.jobs, len(items)))]
            for worker in workers:
                assign(worker)
            while any(w.index is not None for w in workers):
                busy = [w for w in workers if w.index is not None]
                ready = wait([w.conn for w in busy] + [w.process.sentinel for w in busy])
                for worker in busy:
                    if worker.conn not in ready and worker.process.sentinel not in ready:
                        continue
                    index = worker.index
                    assert index is not None
                    try:
                        _, ok, value = worker.conn.recv()
                    except (EOFError, OSError):
                        # the worker died with the task: run it again on a fresh one, or give up
                        worker.process.join()
                        code = worker.process.exitcode
                        workers.remove(worker)
                        worker.conn.close()
                        if attempts[index] < ATTEMPTS:
                            pending.appendleft(index)
                        else:
                            on_done(index, TaskFailure(f"worker died twice (exit code {code})", ATTEMPTS))
                        if pending:
                            workers.append(replacement := start())
                            assign(replacement)
                        continue
                    worker.index = None
                    if pending:  # before on_done: the worker scans while the driver unpacks
                        assign(worker)
                    on_done(index, value if ok else TaskFailure(value, attempts[index]))
        finally:
            for worker in workers:  # busy ones only when the driver is interrupted: stop their tasks
                if worker.process.is_alive() and worker.index is None:
                    worker.conn.send(None)
                elif worker.process.is_alive():
                    worker.process.terminate()
                worker.conn.close()  # what a stopped task would still send goes nowhere
            for worker in workers:
                worker.process.join(timeout=STOP_WAIT_S)
                if worker.process.is_alive():
                    worker.process.kill()
                    worker.process.join()


@dataclass
class RayExecutor:
    """Tasks on Ray: the instance already initialised in this process, else one started here (a local
    instance of ``jobs`` CPUs, or the cluster at ``address``, e.g. ``auto`` or ``ray://head:10001``) and
    shut down at the end. Each task asks for one CPU; at most ``jobs`` are in flight (all when None).
    Ray reruns a task whose worker died (``max_retries=1``) and keeps its worker processes for the next
    tasks (``max_calls`` 0, the default), so each worker imports the scan's modules once. Given no
    items, it neither starts nor joins Ray (seconds for nothing to run)."""

    address: str | None = None
    jobs: int | None = None
    name: ClassVar[str] = "ray"

    def run(self, fn: Callable[[Any], Any], items: Sequence[Any], on_done: OnDone) -> None:
        if not items:
            return
        try:
            import ray
            from ray.exceptions import RayError, RayTaskError
        except ImportError:
            raise CellError("the Ray executor needs Ray: pip install 'cell[cluster]'") from None
        started = not ray.is_initialized()
        if started:
            ray.init(address=self.address, num_cpus=self.jobs if self.address is None else None,
                     include_dashboard=False, log_to_driver=False)
        try:
            remote = ray.remote(num_cpus=1, max_retries=ATTEMPTS - 1, retry_exceptions=False)(fn)
            limit = self.jobs or len(items)
            queue = deque(range(len(items)))
            in_flight: dict[Any, int] = {}
            while queue or in_flight:
                while queue and len(in_flight) < limit:
                    index = queue.popleft()
                    in_flight[remote.remote(items[index])] = index
                done, _ = ray.wait(list(in_flight), num_returns=1)
                index = in_flight.pop(done[0])
                try:
                    value = ray.get(done[0])
                except RayTaskError as exc:
                    value = TaskFailure(f"{type(exc.cause).__name__}: {exc.cause}", 1)
                except RayError as exc:
                    value = TaskFailure(f"worker died twice ({type(exc).__name__})", ATTEMPTS)
                on_done(index, value)
        finally:
            if started:
                ray.shutdown()


def make_executor(kind: str, jobs: int | None, address: str | None) -> Executor:
    """``local`` (a pool of ``jobs`` processes, default 2) or ``ray``."""
    if kind == "local":
        if address is not None:
            raise CellError("--ray-address needs --executor ray")
        return LocalPool(jobs if jobs is not None else 2)
    if kind == "ray":
        return RayExecutor(address, jobs)
    raise CellError(f"unknown executor {kind!r}; choose local or ray")
