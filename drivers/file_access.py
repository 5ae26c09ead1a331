"""Who this process runs as, and why it may not use a file or folder, with the command that fixes it: for
the messages of the store (its SQLite file, WAL, lease files), ``cell backup`` and ``cell doctor``, where
a file left by a trial ``sudo cell serve`` (root's, mode 0600) or a folder of another user stops the
service's user."""

from __future__ import annotations

import grp
import os
import pwd
import re
import shlex
import stat
from dataclasses import dataclass
from pathlib import Path

WRITABLE_ELSEWHERE = "choose a folder on a writable file system"
"""The other fix of a read-only file system, where the caller names no option that chooses the folder."""


def user_name(uid: int | None = None) -> str:
    """The name of user ``uid`` (default: this process's effective user), or its number where the
    machine has no name for it."""
    uid = os.geteuid() if uid is None else uid
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return str(uid)


def group_name(gid: int) -> str:
    """The name of group ``gid``, or its number where the machine has no name for it."""
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return str(gid)


@dataclass(frozen=True)
class AccessProblem:
    """What stops this user at a file or folder (``found``) and the command that fixes it (``fix``);
    ``read_only``: its file system is mounted read-only (no permission fixes it)."""

    found: str
    fix: str
    read_only: bool = False

    def __str__(self) -> str:
        return f"{self.found}; fix: {self.fix}"


def make_folder(path: Path) -> str:
    """The command that makes the folder ``path`` this process's user's (its parents stay whose they are:
    never a fix that gives the user a folder of the system's)."""
    return f"sudo install -d -o {user_name()} -m 0750 {shlex.quote(str(path))}"


def mount_point(path: Path) -> Path:
    """The mount point of the file system that holds ``path``: the longest mount point of
    ``/proc/self/mountinfo`` that contains it (a bind mount included, which shares its device with the
    folder above); ``/`` where that cannot be read."""
    resolved = path.resolve()
    best = Path("/")
    try:
        lines = Path("/proc/self/mountinfo").read_text().splitlines()
    except OSError:
        return best
    for line in lines:
        fields = line.split()
        if len(fields) < 5:
            continue
        # the mount point is field 5, with space, tab, newline and backslash written in octal
        point = Path(re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), fields[4]))
        if resolved.is_relative_to(point) and len(point.parts) > len(best.parts):
            best = point
    return best


def read_only_problem(path: Path, kind: str, instead: str) -> AccessProblem | None:
    """Why nothing can be written at ``path`` (a ``kind``: file or folder) whatever its permissions: it is
    on a file system mounted read-only (``statvfs`` flag ``ST_RDONLY``), with the remount that fixes it or
    ``instead``; None when it is not (or ``path`` is gone)."""
    try:
        if not os.statvfs(path).f_flag & os.ST_RDONLY:
            return None
    except OSError:
        return None
    point = shlex.quote(str(mount_point(path)))
    return AccessProblem(f"{kind} {path} is on a read-only file system (mounted read-only at {point}), where "
                         "no user may write",
                         f"remount it read-write (sudo mount -o remount,rw {point}; a bind mount: "
                         f"sudo mount -o remount,rw,bind {point}), or {instead}", read_only=True)


def access_problem(path: Path, *, folder: bool = False, recursive: bool = False,
                   instead: str = WRITABLE_ELSEWHERE) -> AccessProblem | None:
    """Why this process's user may not read and write the file ``path`` (with ``folder``: make and delete
    files in the folder ``path``): a read-only file system (:func:`read_only_problem`, the fix a remount
    or ``instead``), or its owner, group and mode, with the command that fixes it (for a folder with
    ``recursive``, all it holds too: a data folder whose files the same user left); None when it may, or
    when ``path`` does not exist."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    kind = "folder" if folder else "file"
    read_only = read_only_problem(path, kind, instead)
    if read_only is not None:
        return read_only
    wanted = os.R_OK | os.W_OK | (os.X_OK if folder else 0)
    if os.access(path, wanted):
        return None
    me = user_name()
    found = (f"{kind} {path} belongs to {user_name(st.st_uid)}:{group_name(st.st_gid)} with mode "
             f"{stat.S_IMODE(st.st_mode):04o}, and user {me} may not "
             f"{'write in' if folder else 'read and write'} it")
    quoted = shlex.quote(str(path))
    if st.st_uid == os.geteuid():
        return AccessProblem(found, f"chmod u+{'rwx' if folder else 'rw'} {quoted}")
    # a folder's files (the store's, the jobs') were left by the same user as the folder, mostly
    return AccessProblem(found, f"sudo chown {'-R ' if recursive else ''}{me}: {quoted}")


def files_problem(folder: Path, pattern: str, instead: str = WRITABLE_ELSEWHERE) -> AccessProblem | None:
    """What stops this user at ``folder`` (:func:`access_problem`, the folder and all it holds given back;
    on a read-only file system, the remount or ``instead``) or at the files in it that match ``pattern``
    (a glob: a database and the files it keeps beside it), all of them named in ``found`` and fixed by one
    command on the pattern; None when nothing does."""
    problem = access_problem(folder, folder=True, recursive=True, instead=instead)
    if problem is not None:
        return problem
    blocked = {path: each for path in sorted(folder.glob(pattern)) if (each := access_problem(path))}
    if not blocked:
        return None
    found = "; ".join(each.found for each in blocked.values())
    files = shlex.quote(str(folder)) + "/" + pattern
    if all(path.stat().st_uid == os.geteuid() for path in blocked):
        return AccessProblem(found, f"chmod u+rw {files}")
    return AccessProblem(found, f"sudo chown {user_name()}: {files}")
