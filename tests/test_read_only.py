"""A folder on a read-only file system is named as such, with a remount or another folder as its fix, not
as a permission problem that no chmod can fix: for the store, doctor and a job's folder (``cell scan``'s
--out, the service's data dir)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from cell.doctor import machine
from cell.doctor.findings import Status
from cell.jobs.inputs import check_job_folder
from cell.service.store import open_data_store, sqlite_url
from cell.service.worker import CHOOSE_DATA_DIR
from drivers.errors import JobError, StoreError
from drivers.file_access import access_problem, mount_point

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture
def read_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """``tmp_path/ro``, which ``statvfs`` says is on a file system mounted read-only."""
    folder = tmp_path / "ro"
    folder.mkdir()
    real = os.statvfs

    def statvfs(path: object) -> os.statvfs_result:
        result = real(path)  # type: ignore[arg-type]
        if Path(str(path)).resolve().is_relative_to(folder):
            fields = list(result)
            fields[8] |= os.ST_RDONLY  # f_flag
            return os.statvfs_result(fields)
        return result

    monkeypatch.setattr(os, "statvfs", statvfs)
    return folder


def test_a_read_only_file_system_is_named_with_a_remount_not_a_chmod(read_only: Path):
    problem = access_problem(read_only, folder=True, instead="choose another --data-dir")
    assert problem is not None and problem.read_only
    assert f"folder {read_only} is on a read-only file system" in problem.found
    assert "mount -o remount,rw" in problem.fix and problem.fix.endswith("or choose another --data-dir")
    assert "chmod" not in str(problem) and "belongs to" not in str(problem)
    assert access_problem(read_only.parent, folder=True) is None


def test_serve_and_doctor_on_a_read_only_data_dir_say_so(read_only: Path):
    with pytest.raises(StoreError, match=r"is on a read-only file system.*remount,rw.*--data-dir") as err:
        open_data_store(read_only, sqlite_url(read_only))
    assert "chmod" not in str(err.value)
    found = machine.disk(read_only)
    assert found.status is Status.FAIL and "read-only file system" in found.detail
    assert found.fix is not None and "remount,rw" in found.fix and "another --data-dir" in found.fix


def test_a_job_folder_on_a_read_only_file_system_asks_for_what_its_caller_chooses(read_only: Path):
    with pytest.raises(JobError, match=r"read-only file system.*or choose another --out$"):
        check_job_folder(read_only / "jobs" / "scan-1")
    with pytest.raises(JobError) as err:  # the service has no --out: its data dir is what is chosen
        check_job_folder(read_only / "0123456789abcdef", CHOOSE_DATA_DIR)
    assert "--out" not in str(err.value) and "cell serve --data-dir" in str(err.value)
    assert "remount,rw" in str(err.value)


@pytest.mark.skipif(os.geteuid() != 0 or sys.platform != "linux", reason="mounts need root on Linux")
def test_a_real_read_only_bind_mount_is_found_with_its_mount_point(tmp_path: Path):
    """``mount --bind R R; mount -o remount,ro,bind R`` in a mount namespace of its own (nothing leaks)."""
    folder = tmp_path / "R"
    (folder / "sub").mkdir(parents=True)
    script = (f"mount --bind {folder} {folder} && mount -o remount,ro,bind {folder} && "
              f"{sys.executable} -c 'import sys; from pathlib import Path; "
              "from drivers.file_access import access_problem; "
              "print(access_problem(Path(sys.argv[1]), folder=True))' " + str(folder / "sub"))
    done = subprocess.run(["unshare", "-m", "--propagation", "private", "sh", "-c", script], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    if done.returncode != 0 and "unshare" in done.stderr:
        pytest.skip(f"no mount namespace here: {done.stderr.strip()}")
    assert done.returncode == 0, done.stderr
    found = f"folder {folder / 'sub'} is on a read-only file system (mounted read-only at {folder})"
    assert found in done.stdout
    assert re.search(rf"sudo mount -o remount,rw,bind {re.escape(str(folder))}\)", done.stdout)
    assert mount_point(folder / "sub") != folder  # outside the namespace nothing was mounted
