"""An exclusive lock on a file that the kernel releases when its holder exits, however it ends (``flock``),
for "one process at a time" claims: an arm (``drivers.arm.claim``), a cell's lease on a SQLite store
(``cell.service.store.lease``)."""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path


def _open(path: Path, mode: int) -> int:
    """``path`` opened for reading and writing: an existing file without ``O_CREAT`` (on a sticky folder
    the kernel refuses that flag for a file of another user, ``fs.protected_regular``), a new one made
    with ``mode`` whatever the umask."""
    try:
        return os.open(path, os.O_RDWR)
    except FileNotFoundError:
        pass
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, mode)
    except FileExistsError:  # another process made it meanwhile
        return os.open(path, os.O_RDWR)
    with contextlib.suppress(OSError):
        os.fchmod(fd, mode)
    return fd


def try_lock(path: Path, mode: int) -> int | None:
    """An open descriptor of ``path`` holding its exclusive lock (closing it releases the lock), or None
    when another open file holds it; ``OSError`` when the file cannot be opened or made."""
    fd = _open(path, mode)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd
