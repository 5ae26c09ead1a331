"""One program of this machine drives an arm at a time.

A UR controller takes any number of connections, and the control script a second program uploads ends
the first one's: a ``cell scan`` started beside the service's job took the arm in the middle of the job's
motion, and the job ended on "control script not running". So a driver claims its arm while connected: an
``flock`` on a file named after the arm (its type and address, the host name resolved), which the kernel
releases when the holder exits however it ends. The file says who holds it, for the refusal. It does not
reach other machines: one arm, one cell PC.

The files are in ``/run/lock``, the system's folder for locks every user shares (the systemd unit makes
it writable to the service: ``ReadWritePaths``), not in ``/tmp``, which the unit makes private to the
service (``PrivateTmp``), out of an operator's sight; in the temporary folder only where ``/run/lock``
is missing or not writable. An existing file is opened without ``O_CREAT`` (``drivers.file_lock``): on a
sticky folder the kernel refuses that flag for a file of another user (``fs.protected_regular``).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import socket
import sys
import tempfile
from pathlib import Path

from drivers.errors import DriverError
from drivers.file_lock import try_lock

LOCK_DIR = Path("/run/lock")


def claim_path(kind: str, host: str) -> Path:
    """The claim file of the arm of type ``kind`` (``ur5e``, ``franka``) at ``host``: by address, so that
    a name and the address it resolves to are one arm."""
    with contextlib.suppress(OSError):
        host = str(socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)[0][4][0])
    digest = hashlib.sha256(f"{kind} {host}".encode()).hexdigest()[:16]
    folder = LOCK_DIR if os.access(LOCK_DIR, os.W_OK) else Path(tempfile.gettempdir())
    return folder / f"cell-arm-{digest}.lock"


class ArmClaim:
    """The claim on the arm of type ``kind`` at ``host`` of this process."""

    def __init__(self, kind: str, host: str) -> None:
        self._where = (kind, host)
        self._device = f"arm {kind} at {host}"  # as the arm's driver names it
        self._fd: int | None = None

    def check(self) -> None:
        """``DriverError`` naming the holder when another program drives the arm now (taken and given
        back at once: a scan refuses before it makes its folder)."""
        if self._fd is None:
            self.take()
            self.release()

    def take(self) -> None:
        """Claim the arm; ``DriverError`` naming the holder when another process has it."""
        if self._fd is not None:
            return
        path = claim_path(*self._where)
        try:
            fd = try_lock(path, 0o666)  # every user's: an operator's cell commands beside the service
            holder = None if fd is not None else path.read_text(errors="replace").strip()[:512] or "unknown"
        except OSError as exc:
            raise DriverError(f"cannot open the arm's claim file {path}: {exc.strerror}",
                              device=self._device) from None
        if fd is None:
            raise DriverError(f"the arm is driven by another program of this machine ({holder}): stop it "
                              f"or wait for its job to end", device=self._device)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}: {' '.join(sys.argv)[:400]}\n".encode(), 0)
        self._fd = fd

    def release(self) -> None:
        """Give the arm up (safe to call twice)."""
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor releases its flock
            self._fd = None
