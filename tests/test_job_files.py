"""A job folder's files against what happens to files: a write cut short (a full disk, a kill) leaves no
truncated file under its final name; a damaged frame or result.json that is there anyway is named and
skipped, or kept aside and rebuilt, by ``cell reprocess`` and ``cell sensor replay`` and refused by
``cell scan --replay`` before its folder is made; a read-only job folder is refused before any work, and
``--out`` writes elsewhere."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cell.cli.main import app
from cell.jobs.live_cloud import LIVE_CLOUD_FILE
from cell.perception.cloud import read_ply
from cell.service.recovery import finish_folder
from cell.service.store import JobRecord

from .conftest import UR5E, raster_scan

NOBODY = 65534


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A short ToF scan's folder (read it, do not change it: copy it with ``job``)."""
    out = tmp_path_factory.mktemp("jobs") / "job"
    raster_scan(out, UR5E, "cube", 1, 10)
    assert len(list((out / "frames").glob("*.npz"))) >= 3
    return out


@pytest.fixture
def job(recorded, tmp_path):
    copy = tmp_path / "job"
    shutil.copytree(recorded, copy)
    return copy


def _truncate(path: Path) -> bytes:
    """Cut ``path`` to half its length, as a write cut short leaves it; returns what is left."""
    data = path.read_bytes()[: path.stat().st_size // 2]
    path.write_bytes(data)
    return data


def test_a_write_cut_short_by_a_full_disk_leaves_no_truncated_file(tmp_path):
    # a file size limit makes every write past 4 KiB fail (EFBIG), as a full disk fails it (ENOSPC)
    script = textwrap.dedent(f"""
        import resource, signal
        import numpy as np
        from pathlib import Path
        from drivers.depth.base import DepthFrame
        from cell.jobs.recorder import JobRecorder
        recorder = JobRecorder(Path({str(tmp_path / "job")!r}))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))
        points = np.random.default_rng(0).random((2000, 3))
        for attempt in (lambda: recorder.frame(DepthFrame(seq=0, timestamp=0.1, points=points), np.eye(4),
                                               np.eye(4), {{}}),
                        lambda: recorder.result({{"status": "completed", "points": points.tolist()}})):
            try:
                attempt()
            except OSError as exc:
                print(exc.errno)
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["27", "27"]  # both writes failed: EFBIG
    job = tmp_path / "job"
    assert not (job / "frames" / "000000.npz").exists()
    assert not (job / "result.json").exists()
    assert sorted(p.name for p in job.rglob(".*")) == []  # no temporary file left either


def test_a_process_killed_right_after_its_result_leaves_every_trajectory_and_joint_row(tmp_path):
    """``trajectory.csv`` and ``joints.csv`` buffer their rows (one per control tick): a worker killed
    between ``result.json`` and closing them left a folder whose result said the job was whole while its
    trajectory lacked its last rows."""
    script = textwrap.dedent(f"""
        import os, signal
        import numpy as np
        from pathlib import Path
        from cell.jobs.recorder import JobRecorder
        recorder = JobRecorder(Path({str(tmp_path / "job")!r}))
        for k in range(50):  # a short job's ticks: far less than the files' buffers
            recorder.pose(k * 0.01, np.eye(4))
            recorder.joints(k * 0.01, np.zeros(7))
        recorder.result({{"status": "completed"}})
        os.kill(os.getpid(), signal.SIGKILL)  # before close(), as a kill of the worker there
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert res.returncode == -9, res.stderr
    job = tmp_path / "job"
    assert json.loads((job / "result.json").read_text())["status"] == "completed"
    for name in ("trajectory.csv", "joints.csv"):
        assert len((job / name).read_text().splitlines()) == 51, name  # the header and every row


def test_reprocess_skips_a_damaged_frame_naming_it(job):
    n = len(list((job / "frames").glob("*.npz")))
    _truncate(job / "frames" / "000001.npz")
    res = CliRunner().invoke(app, ["reprocess", str(job)])
    assert res.exit_code == 0, res.output
    assert f"warning: skipped {job / 'frames' / '000001.npz'}: not a readable frame (BadZipFile" in res.stderr
    assert f"{n - 1} frames (1 unreadable frames skipped)" in res.stdout
    hires = json.loads((job / "result_hires.json").read_text())
    assert hires["n_frames"] == n - 1
    assert [s["file"] for s in hires["skipped_frames"]] == ["frames/000001.npz"]
    assert read_ply(job / "cloud_hires.ply").shape[0] == hires["n_cloud_points"] > 0


def test_sensor_replay_skips_a_damaged_frame_naming_it(job):
    n = len(list((job / "frames").glob("*.npz")))
    _truncate(job / "frames" / "000002.npz")
    res = CliRunner().invoke(app, ["sensor", "replay", str(job)])
    assert res.exit_code == 0, res.output
    assert f"warning: skipped {job / 'frames' / '000002.npz'}: not a readable frame (BadZipFile" in res.stderr
    assert f"{n - 1} frames replayed (1 unreadable frames skipped)" in res.stdout
    assert (job / "cloud_replay.ply").is_file()


def test_scan_replay_refuses_a_damaged_frame_before_making_its_folder(job, tmp_path):
    _truncate(job / "frames" / "000001.npz")
    out = tmp_path / "replayed"
    res = CliRunner().invoke(app, ["scan", "--replay", str(job), "--out", str(out)])
    assert res.exit_code == 1, res.output
    assert res.stderr.startswith(f"error: {job / 'frames' / '000001.npz'}: not a readable frame (BadZipFile")
    assert "job folder" not in res.stderr
    assert not out.exists()


def test_a_trajectory_cut_short_mid_line_replays_and_a_damaged_row_is_named(job, tmp_path):
    trajectory = job / "trajectory.csv"
    with trajectory.open("a") as f:
        f.write("9.87,0.4")  # the job killed while it wrote a row: no line end
    res = CliRunner().invoke(app, ["sensor", "replay", str(job)])
    assert res.exit_code == 0, res.output
    assert "identical to the recorded cloud.ply" in res.stdout
    n_lines = len(trajectory.read_text().splitlines())
    with trajectory.open("a") as f:
        f.write("\n1.0,2.0\n")  # now a whole line that is no pose row
    out = tmp_path / "replayed"
    res = CliRunner().invoke(app, ["scan", "--replay", str(job), "--out", str(out)])
    assert res.exit_code == 1, res.output
    assert res.stderr == (f"error: replay {job}: {trajectory} line {n_lines}: not a pose row (2 fields, "
                          "expected 8)\n")
    assert not out.exists()


def test_an_unreadable_result_is_kept_aside_and_rebuilt(job, recorded):
    online = json.loads((recorded / "result.json").read_text())
    damaged = _truncate(job / "result.json")
    # the replays read the job's identity from job.json and write nothing to the folder
    replay = CliRunner().invoke(app, ["sensor", "replay", str(job)])
    assert replay.exit_code == 0, replay.output
    assert f"warning: {job / 'result.json'} is unreadable (" in replay.stderr
    assert (job / "result.json").read_bytes() == damaged
    res = CliRunner().invoke(app, ["reprocess", str(job)])
    assert res.exit_code == 0, res.output
    assert f"{job / 'result.json'} was unreadable (" in res.stdout
    assert f"the unreadable file is kept as {job / 'result.json.unreadable'}" in res.stdout
    assert (job / "result.json.unreadable").read_bytes() == damaged
    rebuilt = json.loads((job / "result.json").read_text())
    assert rebuilt["status"] == "interrupted" and rebuilt["n_captures"] == online["n_captures"]
    assert {k: rebuilt[k] for k in ("planner", "object", "seed", "config", "object_pose")} == {
        k: online[k] for k in ("planner", "object", "seed", "config", "object_pose")}
    assert json.loads((job / "result_hires.json").read_text())["metrics"]["coverage_pct"] > 0


def test_reprocess_reads_an_unreadable_result_once(job, monkeypatch):
    """cell reprocess read a damaged result.json, then read it again to rebuild it."""
    _truncate(job / "result.json")
    reads = []
    read_text = Path.read_text

    def counted(path: Path, *args, **kwargs) -> str:
        reads.append(path)
        return read_text(path, *args, **kwargs)

    monkeypatch.setattr(Path, "read_text", counted)
    res = CliRunner().invoke(app, ["reprocess", str(job)])
    assert res.exit_code == 0, res.output
    assert reads.count(job / "result.json") == 1


def test_reprocess_tries_once_whether_it_can_write_to_the_job_folder(job, monkeypatch):
    """cell reprocess of a job folder with a damaged result.json made a probe file in it to see that it
    could write its outputs there, then another to see that it could rebuild result.json there."""
    _truncate(job / "result.json")
    probes = []
    open_path = Path.open

    def counted(path: Path, *args, **kwargs):
        if path.parent == job and ".write-check." in path.name:
            probes.append(path)
        return open_path(path, *args, **kwargs)

    monkeypatch.setattr(Path, "open", counted)
    res = CliRunner().invoke(app, ["reprocess", str(job)])
    assert res.exit_code == 0, res.output
    assert "was unreadable" in res.stdout and len(probes) == 1


def test_the_service_keeps_an_unreadable_result_aside_when_it_settles_a_dead_workers_job(job):
    """A worker killed while it wrote result.json (before this release wrote it whole): the service's
    restart gave the job its own result.json over the damaged one."""
    damaged = _truncate(job / "result.json")
    np.save(job / LIVE_CLOUD_FILE, np.zeros((4, 3), dtype=np.float32))
    record = JobRecord(id="a" * 16, cell="c", status="running", planner="raster", object="cube",
                       object_pose=(0.0, 0.0, 0.0), seed=1, max_time_s=None, part_id=None, folder=str(job),
                       submitted_by="op", created_at=datetime.now(UTC))
    result = finish_folder(job, record, "interrupted", "the service stopped while the job ran")
    assert (job / "result.json.unreadable").read_bytes() == damaged
    assert json.loads((job / "result.json").read_text()) == result
    assert result["status"] == "interrupted" and "result.json.unreadable" in result["files"]
    assert not (job / LIVE_CLOUD_FILE).exists()


def test_reprocess_of_a_folder_that_does_not_exist_says_so(tmp_path):
    res = CliRunner().invoke(app, ["reprocess", str(tmp_path / "nowhere")])
    assert res.exit_code == 1
    assert res.stderr == f"error: {tmp_path / 'nowhere'} does not exist\n"
    assert not (tmp_path / "nowhere").exists()


def test_reprocess_removes_the_live_cloud_a_killed_job_left(job):
    (job / "result.json").unlink()  # killed (kill -9) while watched: no result, the snapshot left behind
    np.save(job / LIVE_CLOUD_FILE, np.zeros((4, 3), dtype=np.float32))
    res = CliRunner().invoke(app, ["reprocess", str(job)])
    assert res.exit_code == 0, res.output
    assert "removed the live cloud snapshot cloud_live.npy the job left behind" in res.stdout
    assert not (job / LIVE_CLOUD_FILE).exists()


# -- read-only job folders: root writes anywhere, so the command runs as nobody then ----------------------
def _unprivileged(args: list[str], home: Path) -> subprocess.CompletedProcess[str]:
    """``cell args`` in a process that cannot write to a folder whose mode says so (as nobody when the
    tests run as root, with ``home`` as its home folder for the libraries' caches)."""
    prefix = ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups"] if os.geteuid() == 0 \
        else []
    command = [*prefix, sys.executable, "-m", "cell.cli.main", *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=300,
                          cwd=Path(__file__).parent.parent,
                          env={**os.environ, "HOME": str(home), "MPLCONFIGDIR": str(home / "matplotlib")})


@pytest.fixture
def read_only_job(recorded):
    """A copy of the job that the command's process may read but not write, and a folder beside it that
    it may write, in a folder all may enter (pytest's own is private to its user)."""
    if os.geteuid() == 0 and shutil.which("setpriv") is None:
        pytest.skip("running as root without setpriv: no way to run a command that a folder's mode stops")
    base = Path(tempfile.mkdtemp(prefix="cell-read-only-"))
    base.chmod(0o755)
    job = base / "job"
    shutil.copytree(recorded, job)
    writable = base / "elsewhere"
    writable.mkdir()
    writable.chmod(0o777)
    if os.geteuid() == 0 and _unprivileged(["--help"], writable).returncode != 0:
        shutil.rmtree(base)
        pytest.skip("nobody cannot run this checkout's Python")
    for path in (job, *job.rglob("*")):
        path.chmod(0o555 if path.is_dir() else 0o444)
    yield job, writable
    for path in (job, *job.rglob("*")):
        path.chmod(0o755 if path.is_dir() else 0o644)
    shutil.rmtree(base)


def test_reprocess_refuses_a_read_only_folder_before_any_work_and_writes_to_out(read_only_job):
    job, elsewhere = read_only_job
    res = _unprivileged(["reprocess", str(job)], elsewhere)
    assert res.returncode == 1, res.stderr
    assert res.stderr == (f"error: cannot write cloud_hires.ply and result_hires.json to {job}: Permission "
                          "denied; give --out DIR to write them elsewhere\n")  # no progress line: no work
    res = _unprivileged(["reprocess", str(job), "--out", str(elsewhere / "hires")], elsewhere)
    assert res.returncode == 0, res.stderr
    hires = elsewhere / "hires"
    assert f"wrote {hires / 'cloud_hires.ply'} and {hires / 'result_hires.json'}" in res.stdout
    assert read_ply(elsewhere / "hires" / "cloud_hires.ply").shape[0] > 0
    assert not (job / "cloud_hires.ply").exists()


def test_sensor_replay_refuses_a_read_only_folder_before_any_work_and_writes_to_out(read_only_job):
    job, elsewhere = read_only_job
    res = _unprivileged(["sensor", "replay", str(job)], elsewhere)
    assert res.returncode == 1, res.stderr
    assert res.stderr == (f"error: cannot write cloud_replay.ply to {job}: Permission denied; give --out DIR "
                          "to write it elsewhere\n")
    res = _unprivileged(["sensor", "replay", str(job), "--out", str(elsewhere)], elsewhere)
    assert res.returncode == 0, res.stderr
    assert read_ply(elsewhere / "cloud_replay.ply").tobytes() == read_ply(job / "cloud.ply").tobytes()


def test_scan_into_a_folder_it_cannot_make_names_no_job_folder(tmp_path):
    (tmp_path / "file").write_text("")
    out = tmp_path / "file" / "sub"
    res = CliRunner().invoke(app, ["scan", "--config", str(UR5E), "--object", "cube", "--out", str(out)])
    assert res.exit_code == 1
    assert res.stderr == (f"error: cannot create job folder {out}: {tmp_path / 'file'} is a file; choose "
                          "another --out\n")
