"""Which service answers on a port: each start of a cell's service draws a random id, writes it into its
data dir and answers it on ``/healthz``, so that ``cell doctor``, given the same data dir, tells the ports
this cell's running service holds from another program's (another cell's service included, one of the
same name too). The id says nothing of the cell; a stale file, left by a service that ended, matches no
answer. Beside the id the file holds the line's OPC UA endpoint the service listens on, once it does: the
port a cell file names is the running service's only when that service listens there, not when the cell
file was changed since it started (nothing of it is answered on a route without a key).

The file's lines: the id, then ``opcua HOST PORT`` when the service listens for the line's OPC UA
clients.

One service at a time serves a data dir (:class:`DataDirClaim`): a second one, even of another cell name
or on another store (whose cell's lease it would get), would overwrite the first one's instance file,
settle its running jobs and prune its folders. The claim is an ``flock`` on ``service.lock`` that the
kernel releases when its holder exits however it ends (a ``kill -9`` leaves no stale claim), and the file
names its holder for the service refused."""

from __future__ import annotations

import os
import secrets
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from urllib.parse import urlsplit

from cell.service.store import data_folder_not_made
from drivers.atomic_file import write_text_atomic
from drivers.errors import CellError
from drivers.file_access import access_problem
from drivers.file_lock import try_lock

INSTANCE_FILE = "service.instance"
"""The file in the data dir that holds the id of the service's latest start."""
LOCK_FILE = "service.lock"
"""The file in the data dir whose lock the service serving it holds (:class:`DataDirClaim`)."""


class DataDirClaim:
    """The claim of ``data_dir`` (made when missing) by this process, for as long as it serves it:
    ``CellError`` naming the holder (its pid, cell and start time, as it wrote them into
    :data:`LOCK_FILE`) when another process holds it, or naming the file when it cannot be made.
    :meth:`release` gives it up (so does the process's end)."""

    def __init__(self, data_dir: Path, cell: str) -> None:
        path = data_dir / LOCK_FILE
        try:
            data_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CellError(data_folder_not_made(data_dir, exc)) from None
        try:
            fd = try_lock(path, 0o644)
        except OSError as exc:
            # the service's whole data folder, as the store's files would be: whose it is and the fix
            problem = access_problem(data_dir, folder=True, recursive=True) or access_problem(path)
            raise CellError(f"cannot claim the data dir {data_dir}: "
                            f"{problem or f'{path}: {exc.strerror or exc}'}") from None
        if fd is None:
            try:
                holder = path.read_text().strip() or "a process that has not yet said which"
            except OSError:
                holder = "a process whose entry cannot be read"
            raise CellError(f"the data dir {data_dir} is served by another cell serve ({holder}; its lock "
                            f"{path}): a second service would take over its jobs and files; stop that one "
                            f"first, or give this one another --data-dir")
        # who holds it, for the service refused (read, never trusted: the lock decides)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}, cell {cell!r}, started "
                      f"{datetime.now(UTC).isoformat(timespec='seconds')}\n".encode(), 0)
        self._fd: int | None = fd

    def release(self) -> None:
        """Give the data dir up (once; later calls do nothing)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None



@dataclass(frozen=True)
class Instance:
    """What the latest start of a data dir's service wrote: its ``id`` (16 hex digits) and the host and
    port its line's OPC UA server listens on (``opcua``; None without one, or before it listens)."""

    id: str
    opcua: tuple[str, int] | None = None


def new_instance(data_dir: Path) -> str:
    """A new id (16 hex digits), written to ``data_dir``/:data:`INSTANCE_FILE`."""
    instance = secrets.token_hex(8)
    write_text_atomic(data_dir / INSTANCE_FILE, instance + "\n")
    return instance


def opcua_listening(data_dir: Path, instance: str, endpoint: str) -> None:
    """Write that the start ``instance`` listens on the OPC UA ``endpoint`` (``opc.tcp://HOST:PORT/...``)
    into ``data_dir``/:data:`INSTANCE_FILE`."""
    host, port = opcua_address(endpoint)
    write_text_atomic(data_dir / INSTANCE_FILE, f"{instance}\nopcua {host} {port}\n")


def opcua_address(endpoint: str) -> tuple[str, int]:
    """The host (lower case) and port of an OPC UA ``endpoint``, as :class:`Instance` holds them."""
    parts = urlsplit(endpoint)
    return (parts.hostname or "").lower(), parts.port or 0


def instance_of(data_dir: Path) -> Instance | None:
    """What the latest start of the service of ``data_dir`` wrote; None when there is nothing, or it
    cannot be read."""
    try:
        lines = (data_dir / INSTANCE_FILE).read_text().split("\n")
    except OSError:
        return None
    if not lines[0].strip():
        return None
    opcua = None
    for line in lines[1:]:
        words = line.split()
        if len(words) == 3 and words[0] == "opcua" and words[2].isdigit():
            opcua = (words[1], int(words[2]))
    return Instance(lines[0].strip(), opcua)
