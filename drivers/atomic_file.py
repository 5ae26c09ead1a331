"""Files written whole or not at all: written to a temporary name beside their final one, then renamed over
it (``os.replace``, atomic within one file system). A process killed mid-write, or a disk that fills up,
leaves the previous file (or none) and a hidden temporary file, never a truncated file under the final
name: a reader finds the old file or the new one, whole.

``durable=True`` also flushes the file and then its folder to the disk (``fsync``) before returning, so
that the new file survives a power cut once the call has returned; that costs milliseconds on a real
disk, so it is for the files whose presence means something (a job's ``result.json``: the job ended),
not for every recorded frame.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import IO


def temporary_path(path: Path) -> Path:
    """A hidden temporary file beside ``path`` (same folder, so the rename is atomic), with ``path``'s
    suffix (a plot library picks the format from it) and this process's id (two writers never share it).
    Its name starts with a dot: no pattern of the final names (``[0-9]*.npz``, ``*.ply``) matches it."""
    return path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")


_TEMPORARY = re.compile(r"\..*\.[0-9]+\.tmp(\.[^.]+)?")
"""The names :func:`temporary_path` gives."""


def is_temporary(path: Path) -> bool:
    """Whether ``path`` is a temporary file of :func:`temporary_path`: a write under way, or left half
    written by a process killed mid-write (never a job's file of its own)."""
    return _TEMPORARY.fullmatch(path.name) is not None


def _sync_folder(folder: Path) -> None:
    """``fsync`` a folder, so that a rename in it is on the disk (where the platform allows it)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def atomic_path(path: Path, *, durable: bool = False) -> Iterator[Path]:
    """The temporary path to write ``path``'s content to, for a writer that wants a file name (a plot's
    ``savefig``); renamed over ``path`` when the block ends without an exception, removed when it raises."""
    path = Path(path)
    tmp = temporary_path(path)
    try:
        yield tmp
        if durable:
            with tmp.open("rb+") as f:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if durable:
        _sync_folder(path.parent)


@contextlib.contextmanager
def atomic_open(path: Path, *, durable: bool = False) -> Iterator[IO[bytes]]:
    """A binary file to write ``path``'s content to (see the module docstring); renamed over ``path``
    when the block ends without an exception, removed when it raises."""
    with atomic_path(path, durable=durable) as tmp, tmp.open("wb") as f:
        yield f


def write_bytes_atomic(path: Path, data: bytes, *, durable: bool = False) -> None:
    """Write ``data`` as ``path``, whole or not at all."""
    with atomic_open(path, durable=durable) as f:
        f.write(data)


def write_text_atomic(path: Path, text: str, *, durable: bool = False) -> None:
    """Write ``text`` (UTF-8) as ``path``, whole or not at all."""
    write_bytes_atomic(path, text.encode("utf-8"), durable=durable)


UNREADABLE_SUFFIX = ".unreadable"
"""What a file that cannot be read is renamed with when a new one takes its place (:func:`keep_aside`)."""


def keep_aside(path: Path) -> Path:
    """Rename the unreadable file ``path`` to a free name beside it, ``<name>.unreadable`` (then
    ``<name>.unreadable-2``, ...), so that a new file can take its place without the old one being lost;
    returns that name. Raises ``OSError``."""
    path = Path(path)
    candidate = path.with_name(path.name + UNREADABLE_SUFFIX)
    n = 1
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.name}{UNREADABLE_SUFFIX}-{n}")
    path.rename(candidate)
    return candidate


def check_writable(folder: Path) -> None:
    """Raise ``OSError`` naming ``folder`` (``PermissionError`` for a read-only folder, ``OSError`` with
    ``EROFS`` on a read-only file system) unless a file can be made in it: tried, not guessed from the
    mode bits (which say nothing of root or of access control lists)."""
    probe = temporary_path(Path(folder) / "write-check")
    try:
        with probe.open("xb"):
            pass
    except OSError as exc:
        raise type(exc)(exc.errno, exc.strerror, str(folder)) from None
    probe.unlink()


def writable_folder(folder: Path) -> Path:
    """``folder``, made (with its parents) when missing, once a file can be made in it
    (:func:`check_writable`); raises ``OSError`` otherwise."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    check_writable(folder)
    return folder
