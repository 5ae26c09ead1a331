"""A real PostgreSQL server for the tests, from Debian's ``postgresql`` package, on loopback.

``postgres_server()`` runs ``initdb`` (trust authentication, superuser ``cell``) in a fresh temporary
folder, starts ``postgres`` on 127.0.0.1 at a free port with fsync off, creates the database ``cell`` and
yields ``postgresql+psycopg://cell@127.0.0.1:PORT/cell``; at the end it stops the server (fast shutdown)
and removes the folder. PostgreSQL refuses to run as root: as root, initdb and the server run as the
``postgres`` system user. ``fresh_database(url)`` gives a test its own empty database on that server.
Import the ``postgres_url`` fixture into a test module to use it (it is session-scoped).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import pwd
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import psycopg
import pytest
from sqlalchemy import make_url

START_TIMEOUT_S = 20.0  # how long the server may take to accept connections [s]
STOP_TIMEOUT_S = 20.0  # how long a fast shutdown may take [s]
SERVER_USER = "postgres"  # the system user that runs the server when the tests run as root
_database_numbers = itertools.count()


def _bin_dir() -> Path:
    """The newest installed PostgreSQL's ``bin`` folder; fails the test if there is none."""
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"),
                   key=lambda p: int(p.parent.parent.name) if p.parent.parent.name.isdigit() else -1)
    if not found:
        pytest.fail("PostgreSQL's server is not installed (no /usr/lib/postgresql/*/bin/initdb): run "
                    "`bash deploy/system-deps.sh`")
    return found[-1].parent


def free_port() -> int:
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _connect(port: int, dbname: str) -> psycopg.Connection:
    return psycopg.connect(host="127.0.0.1", port=port, user="cell", dbname=dbname, connect_timeout=2,
                           autocommit=True)


@contextlib.contextmanager
def postgres_server() -> Iterator[str]:
    """A PostgreSQL server for the duration of the ``with``; yields the URL of its database ``cell``."""
    bin_dir = _bin_dir()
    as_root = os.geteuid() == 0
    prefix = ["runuser", "-u", SERVER_USER, "--"] if as_root else []
    base = Path(tempfile.mkdtemp(prefix="cell-pg-"))
    base.chmod(0o755)  # the server's user must reach the folders inside
    data, sockets = base / "data", base / "sockets"
    data.mkdir(mode=0o700)
    sockets.mkdir(mode=0o755)
    if as_root:
        user = pwd.getpwnam(SERVER_USER)
        for folder in (data, sockets):
            os.chown(folder, user.pw_uid, user.pw_gid)
    log_path = base / "server.log"
    server: subprocess.Popen[bytes] | None = None
    try:
        subprocess.run([*prefix, str(bin_dir / "initdb"), "-D", str(data), "-A", "trust", "-U", "cell",
                        "-E", "UTF8", "--locale=C", "--no-sync"],
                       cwd=base, check=True, capture_output=True)
        port = free_port()
        with log_path.open("wb") as log:
            server = subprocess.Popen([*prefix, str(bin_dir / "postgres"), "-D", str(data), "-h", "127.0.0.1",
                                       "-p", str(port), "-k", str(sockets), "-F"],
                                      cwd=base, stdout=log, stderr=subprocess.STDOUT)
        _wait_until_up(server, port, log_path)
        with _connect(port, "postgres") as connection:
            connection.execute("CREATE DATABASE cell")
        yield f"postgresql+psycopg://cell@127.0.0.1:{port}/cell"
    finally:
        if server is not None:
            _stop(server, prefix, bin_dir, data)
        shutil.rmtree(base, ignore_errors=True)


def _wait_until_up(server: subprocess.Popen[bytes], port: int, log_path: Path) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while True:
        if server.poll() is not None:
            pytest.fail(f"PostgreSQL exited with {server.returncode}: {log_path.read_text()}")
        try:
            _connect(port, "postgres").close()
            return
        except psycopg.OperationalError:
            if time.monotonic() > deadline:
                pytest.fail(f"PostgreSQL did not accept connections in {START_TIMEOUT_S:g} s: "
                            f"{log_path.read_text()}")
            time.sleep(0.05)


def _stop(server: subprocess.Popen[bytes], prefix: list[str], bin_dir: Path, data: Path) -> None:
    """Fast shutdown through ``pg_ctl`` (it signals the postmaster itself, not ``runuser``); kill what is
    left if that fails."""
    subprocess.run([*prefix, str(bin_dir / "pg_ctl"), "stop", "-D", str(data), "-m", "fast", "-w",
                    "-t", str(int(STOP_TIMEOUT_S))], cwd=data.parent, capture_output=True)
    try:
        server.wait(timeout=STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pid_file = data / "postmaster.pid"
        if pid_file.exists():
            os.kill(int(pid_file.read_text().split()[0]), signal.SIGKILL)
        server.kill()
        server.wait()


@contextlib.contextmanager
def fresh_database(server_url: str) -> Iterator[str]:
    """A new empty database on the server of ``server_url``, dropped (with its connections) at the end;
    yields its URL."""
    url = make_url(server_url)
    assert url.port is not None
    name = f"test_{os.getpid()}_{next(_database_numbers)}"
    with _connect(url.port, url.database or "cell") as connection:
        connection.execute(f"CREATE DATABASE {name}")
    try:
        yield url.set(database=name).render_as_string(hide_password=False)
    finally:
        with _connect(url.port, url.database or "cell") as connection:
            connection.execute(f"DROP DATABASE {name} WITH (FORCE)")


@pytest.fixture(scope="session")
def postgres_url() -> Iterator[str]:
    """The URL of a real PostgreSQL server's database ``cell``, shared by the whole test session."""
    with postgres_server() as url:
        yield url
