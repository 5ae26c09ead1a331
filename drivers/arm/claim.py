"""One program of this machine drives an arm at a time.

A UR controller takes any number of connections, and the control script a second program uploads ends
the first one's: a ``cell scan`` started beside the service's job took the arm in the middle of the job's
motion, and the job ended on "control script not running". So a driver claims its arm while connected: an
``flock`` on a file named after the arm in the system's temporary folder, which the kernel releases when
the holder exits however it ends. The file says who holds it, for the refusal. It does not reach other
machines: one arm, one cell PC.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import sys
import tempfile
from pathlib import Path

from drivers.errors import DriverError


def claim_path(arm: str) -> Path:
    """The claim file of ``arm`` (its type and address, e.g. ``ur5e 192.168.0.2``)."""
    digest = hashlib.sha256(arm.encode()).hexdigest()[:16]
    return Path(tempfile.gettempdir()) / f"cell-arm-{digest}.lock"


class ArmClaim:
    """The claim on ``arm`` of this process; ``device`` names it in errors."""

    def __init__(self, arm: str, device: str) -> None:
        self.path = claim_path(arm)
        self._device = device
        self._fd: int | None = None

    def take(self) -> None:
        """Claim the arm; ``DriverError`` naming the holder when another process has it."""
        if self._fd is not None:
            return
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise DriverError(f"cannot open the arm's claim file {self.path}: {exc.strerror}",
                              device=self._device) from None
        with contextlib.suppress(OSError):  # another user's program reads and claims it too
            os.fchmod(fd, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 512, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise DriverError(f"the arm is driven by another program of this machine ({holder}): stop it "
                              f"or wait for its job to end", device=self._device) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}: {' '.join(sys.argv)[:400]}\n".encode(), 0)
        self._fd = fd

    def release(self) -> None:
        """Give the arm up (safe to call twice)."""
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor releases its flock
            self._fd = None
