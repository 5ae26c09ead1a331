"""A real ``cell serve`` in a subprocess on loopback, started as a user starts it, for the tests.

:class:`ServedCell` makes a data dir, creates API keys (one per role; the first with ``cell keys create``,
the others through the store, which is quicker), starts
``cell serve --config ... --data-dir ... --port ...`` on a free port of 127.0.0.1 and waits for
``/healthz``. ``kill()`` sends SIGKILL to the service alone (its job's worker lives on, as after a crash);
``start()`` again runs a new service on the same data dir and port. ``nofile`` starts it under that soft
limit of file descriptors, as ``ulimit -n`` would. ``until`` and ``closed_by_server`` read raw HTTP from a
socket.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import uvicorn
import yaml

from cell.api.connections import ConnectionLimits, protocol_class
from cell.service.keys import create_key as add_key
from cell.service.store import open_store, sqlite_url

REPO = Path(__file__).resolve().parent.parent
CELL = [sys.executable, "-m", "cell.cli.entry"]  # the installed `cell` program's code
ROLES = ("viewer", "operator", "line", "admin")
WITH_NOFILE = [sys.executable, "-c", "import os, resource as r, sys; hard = r.getrlimit(r.RLIMIT_NOFILE)[1]; "
               "r.setrlimit(r.RLIMIT_NOFILE, (int(sys.argv[1]), hard)); os.execv(sys.argv[2], sys.argv[2:])"]
"""``[*WITH_NOFILE, N, *command]`` runs ``command`` under a soft descriptor limit of N."""
START_TIMEOUT_S = 60.0


def free_port(host: str = "127.0.0.1") -> int:
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])


def opcua_cell_file(folder: Path, base: Path) -> tuple[Path, int]:
    """The cell file ``base`` with a line whose OPC UA endpoint is a free loopback port, unencrypted
    (``security: none``, loopback only), written as ``folder``/cell.yaml; with that port."""
    port = free_port()
    data = yaml.safe_load(base.read_text())
    data["line"] = {"opcua": {"endpoint": f"opc.tcp://127.0.0.1:{port}/cell", "security": "none"}}
    cell_file = folder / "cell.yaml"
    cell_file.write_text(yaml.safe_dump(data))
    return cell_file, port


def until(sock: socket.socket, marker: bytes) -> bytes:
    """What the server sends until ``marker`` (or its end)."""
    data = b""
    while marker not in data and (chunk := sock.recv(65536)):
        data += chunk
    return data


def closed_by_server(sock: socket.socket) -> bool:
    """Whether the server closes the connection within the socket's timeout (what it sends is read)."""
    try:
        while sock.recv(65536):
            pass
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False
    return True


def create_key(data_dir: Path, role: str, name: str, db: str | None = None, tree: Path = REPO) -> str:
    """``cell keys create`` of the checkout ``tree`` (this one by default); returns the key (its output's
    last line)."""
    cmd = [*CELL, "keys", "create", "--data-dir", str(data_dir), "--role", role, "--name", name]
    out = subprocess.run([*cmd, *(["--db", db] if db else [])], cwd=tree, capture_output=True, text=True,
                         check=True)
    return out.stdout.strip().splitlines()[-1]


class ServedCell:
    """One ``cell serve`` process (see the module docstring); ``keys[role]`` holds a key of each role."""

    def __init__(self, config: Path, data_dir: Path, *, db: str | None = None, host: str = "127.0.0.1",
                 key_prefix: str = "test", env: dict[str, str] | None = None,
                 nofile: int | None = None) -> None:
        """``key_prefix`` names the keys (``<prefix>-<role>``): cells sharing one store need their own;
        ``env`` is added to the service's environment; ``nofile`` is its soft descriptor limit."""
        self.config, self.data_dir, self.db, self.host = config, data_dir, db, host
        self.limit = [] if nofile is None else [*WITH_NOFILE, str(nofile)]
        self.env = {**os.environ, **(env or {})}
        self.port = free_port(host)
        self.url = f"http://{host}:{self.port}"
        # the first key as a user makes it (``cell keys create``); the others straight into the same store,
        # which saves a CLI start-up (~2 s) per key
        self.keys = {ROLES[0]: create_key(data_dir, ROLES[0], f"{key_prefix}-{ROLES[0]}", db)}
        store = open_store(db or sqlite_url(data_dir))
        try:
            self.keys |= {role: add_key(store, role, f"{key_prefix}-{role}")[1] for role in ROLES[1:]}
        finally:
            store.close()
        self.proc: subprocess.Popen[str] | None = None
        self._log = tempfile.NamedTemporaryFile("w+", suffix=".log", delete=False)  # noqa: SIM115
        self.start()

    def start(self) -> None:
        cmd = [*self.limit, *CELL, "serve", "--config", str(self.config), "--data-dir", str(self.data_dir),
               "--host", self.host, "--port", str(self.port), *(["--db", self.db] if self.db else [])]
        self.proc = subprocess.Popen(cmd, cwd=REPO, stdout=self._log, stderr=subprocess.STDOUT, text=True,
                                     env=self.env)
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"cell serve exited with {self.proc.returncode}:\n{self.log()}")
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{self.url}/healthz", timeout=1.0).status_code == 200:
                    return
            time.sleep(0.1)
        raise RuntimeError(f"cell serve did not answer within {START_TIMEOUT_S:g} s:\n{self.log()}")

    def client(self, role: str = "operator", timeout_s: float = 30.0) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers={"Authorization": f"Bearer {self.keys[role]}"},
                            timeout=timeout_s)

    def wait_job(self, job_id: str, statuses: tuple[str, ...], timeout_s: float = 120.0) -> dict[str, Any]:
        """Poll the job until its status is one of ``statuses`` (a bound on waiting, not a timed check)."""
        deadline = time.monotonic() + timeout_s
        with self.client("viewer") as client:
            while True:
                job: dict[str, Any] = client.get(f"/api/v1/jobs/{job_id}").json()
                if job["status"] in statuses:
                    return job
                if time.monotonic() > deadline:
                    raise AssertionError(f"job {job_id} never reached {statuses}: {job['status']}\n"
                                         f"{self.log()}")
                time.sleep(0.1)

    def kill(self) -> None:
        """SIGKILL the service process alone, as a crash would."""
        assert self.proc is not None
        os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait()

    def stop(self) -> int:
        """SIGTERM (a graceful shutdown); returns the exit code."""
        if self.proc is None or self.proc.poll() is not None:
            return self.proc.returncode if self.proc else 0
        self.proc.terminate()
        try:
            return self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait()

    def log(self) -> str:
        self._log.flush()
        return Path(self._log.name).read_text()

    def close(self) -> None:
        self.stop()
        self._log.close()
        Path(self._log.name).unlink(missing_ok=True)

    def __enter__(self) -> ServedCell:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def submit(cell: ServedCell, **body: Any) -> dict[str, Any]:
    """``POST /api/v1/jobs`` of ``body`` with the operator's key, asserted accepted (201); the job."""
    with cell.client("operator") as client:
        response = client.post("/api/v1/jobs", json=body)
    assert response.status_code == 201, response.text
    job: dict[str, Any] = response.json()
    return job


@contextlib.contextmanager
def serving_guarded(app: Any, limits: ConnectionLimits, wait_s: float, **config: Any) -> Iterator[int]:
    """``app`` under a uvicorn server on loopback with the connection guards of ``cell serve`` under
    ``limits``, in a thread (uvicorn ``config`` options besides); yields its port. ``wait_s`` bounds the
    wait for it to start and to end [s]."""
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_config=None,
                                           http=protocol_class(limits), backlog=limits.backlog,
                                           timeout_graceful_shutdown=1, **config))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + wait_s
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "the server did not start"
        time.sleep(0.01)
    try:
        yield port
    finally:
        server.should_exit = True
        thread.join(wait_s)
