"""Another user's files, for the tests of what stops the service's user: a trial ``sudo cell serve`` leaves
root's files (mode 0600) in the data folder, which the service's user may then not open.

The tests run as root (the container, CI) or as an ordinary user. As root, the files are made root's and
the code under test runs in a child forked as ``nobody`` (:func:`run_unprivileged`); as an ordinary user
(who cannot give a file away), the files are left without permissions for their owner, which stops the
test's own user in the same way.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import pwd
import shutil
import tempfile
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")
AS_ROOT = os.geteuid() == 0
NOBODY = pwd.getpwnam("nobody")


@contextlib.contextmanager
def service_folder() -> Iterator[Path]:
    """A new folder of the user :func:`run_unprivileged` runs as, under the system's temporary folder
    (pytest's own is root's alone); removed at the end."""
    path = Path(tempfile.mkdtemp(prefix="cell-perm-"))
    path.chmod(0o755)
    if AS_ROOT:
        os.chown(path, NOBODY.pw_uid, NOBODY.pw_gid)
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


def foreign(path: Path) -> None:
    """Make ``path`` what a trial ``sudo cell serve`` leaves: root's, mode 0600 (a folder 0755); as an
    ordinary user, the test's own without read or write permission (a folder 0555)."""
    if AS_ROOT:
        os.chown(path, 0, 0)
        path.chmod(0o755 if path.is_dir() else 0o600)
    else:
        path.chmod(0o555 if path.is_dir() else 0o000)


def run_unprivileged(call: Callable[[], T]) -> T:
    """``call()`` as a user :func:`foreign` files stop: as root, in a child forked as ``nobody``, its
    result (or its exception, as an ``AssertionError`` with its traceback) sent back pickled; else here."""
    if not AS_ROOT:
        return call()
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: nothing of pytest's may run here, it ends with os._exit
        try:
            os.close(read)
            os.setgroups([])
            os.setgid(NOBODY.pw_gid)
            os.setuid(NOBODY.pw_uid)
            try:
                outcome: tuple[bool, object] = (True, call())
            except BaseException:  # reported to the parent, which fails the test with it
                outcome = (False, traceback.format_exc())
            with os.fdopen(write, "wb") as out:
                pickle.dump(outcome, out)
        finally:
            os._exit(0)
    os.close(write)
    with os.fdopen(read, "rb") as answer:
        data = answer.read()
    os.waitpid(pid, 0)
    ok, value = pickle.loads(data)
    if not ok:
        raise AssertionError(f"as nobody:\n{value}")
    return value
