"""Retention (``service.retention``) on a synthetic data dir with running, queued and kept jobs, then
through a real ``cell serve``: ``cell jobs keep`` and ``cell jobs prune [--dry-run]``."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from datetime import UTC, datetime, timedelta

import pytest
import yaml
from typer.testing import CliRunner

from cell.cli.main import app
from cell.config.models import RetentionConfig
from cell.service import retention
from cell.service.retention import plan_prune, prune
from cell.service.store import FINISHED_STATUSES, open_store, sqlite_url
from tests.conftest import UR5E
from tests.service_process import ServedCell
from tests.test_store import make_job

NOW = datetime(2026, 11, 24, 12, 0, tzinfo=UTC)
MB = 1_000_000


@pytest.fixture
def data(tmp_path):
    """A store and ``jobs/`` folder: job n ended n days ago with an n MB folder, besides a running, a
    queued and a kept job (all old, all large)."""
    jobs_dir = tmp_path / "jobs"
    store = open_store(sqlite_url(tmp_path))

    def add(n: int, status: str, age_days: float, size_mb: int, **fields: object) -> None:
        folder = jobs_dir / f"{n:016x}"
        folder.mkdir(parents=True)
        (folder / "frames.npz").write_bytes(b"\0" * (size_mb * MB))
        ended = NOW - timedelta(days=age_days)
        store.add_job(make_job(n, status=status, folder=str(folder), created_at=ended - timedelta(minutes=5),
                               finished_at=None if status in ("running", "queued") else ended, **fields))

    for n, status in ((1, "completed"), (2, "failed"), (3, "stopped"), (4, "interrupted")):
        add(n, status, age_days=n, size_mb=n)
    add(10, "running", age_days=30, size_mb=5)
    add(11, "queued", age_days=30, size_mb=5)
    add(12, "completed", age_days=30, size_mb=5, keep=True)
    yield store, jobs_dir
    store.close()


def _ids(plan) -> list[int]:
    return [int(j.job_id, 16) for j in plan.jobs]


def test_age_and_size_limits_never_touch_running_queued_or_kept_jobs(data):
    store, jobs_dir = data
    assert _ids(plan_prune(store, "a", jobs_dir, RetentionConfig(), NOW)) == []
    by_age = plan_prune(store, "a", jobs_dir, RetentionConfig(days=2.5), NOW)
    assert _ids(by_age) == [4, 3]  # oldest first
    assert by_age.total_bytes == 25 * MB and by_age.freed_bytes == 7 * MB and by_age.unmet is None
    # 25 MB on disk, 20 allowed: the oldest ended jobs go until it fits (4 MB, then 3 MB)
    by_size = plan_prune(store, "a", jobs_dir, RetentionConfig(max_gb=0.020), NOW)
    assert _ids(by_size) == [4, 3] and "over 0.02 GB" in by_size.jobs[0].reason
    # 15 MB of running, queued and kept jobs stay: the limit cannot be met, and the plan says why
    tight = plan_prune(store, "a", jobs_dir, RetentionConfig(max_gb=0.001), NOW)
    assert _ids(tight) == [4, 3, 2, 1] and tight.unmet and "running, queued or kept" in tight.unmet
    assert plan_prune(store, "other-cell", jobs_dir, RetentionConfig(days=0.1), NOW).jobs == ()


def test_pruning_deletes_folders_and_rows_and_spares_a_job_kept_meanwhile(data):
    store, jobs_dir = data
    plan = plan_prune(store, "a", jobs_dir, RetentionConfig(days=1.5), NOW)
    assert _ids(plan) == [4, 3, 2]
    store.update_job(f"{3:016x}", keep=True)  # an operator keeps job 3 after the plan was made
    done = prune(store, plan, jobs_dir)
    assert [int(j.job_id, 16) for j in done] == [4, 2]
    for n in (4, 2):
        assert store.get_job(f"{n:016x}") is None and not (jobs_dir / f"{n:016x}").exists()
    for n in (1, 3, 10, 11, 12):
        assert store.get_job(f"{n:016x}") is not None and (jobs_dir / f"{n:016x}").is_dir()
    assert _ids(plan_prune(store, "a", jobs_dir, RetentionConfig(days=1.5), NOW)) == []


def test_keep_and_prune_through_the_service_and_the_cli(tmp_path):
    config = yaml.safe_load(UR5E.read_text())
    config.setdefault("service", {})["retention"] = {"days": 1e-5, "interval_h": 100}  # 0.9 s
    cell_file = tmp_path / "cell.yaml"
    cell_file.write_text(yaml.safe_dump(config))
    runner = CliRunner()
    with ServedCell(cell_file, tmp_path / "data") as cell:
        env = {"CELL_SERVER": cell.url}
        with cell.client() as client:
            ids = [client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 0.5}).json()["id"]
                   for _ in range(2)]
        for job_id in ids:
            cell.wait_job(job_id, tuple(FINISHED_STATUSES))
        kept, old = ids
        res = runner.invoke(app, ["jobs", "keep", kept, "--key", cell.keys["operator"]], env=env)
        assert res.exit_code == 0 and f"{kept}: kept" in res.output, res.output
        time.sleep(1.0)  # both are now older than the retention's 0.9 s
        dry = runner.invoke(app, ["jobs", "prune", "--dry-run", "--key", cell.keys["viewer"]], env=env)
        assert dry.exit_code == 0, dry.output
        assert old in dry.output and kept not in dry.output and "1 jobs, would free" in dry.output
        assert (cell.data_dir / "jobs" / old).is_dir()  # a dry run deletes nothing
        refused = runner.invoke(app, ["jobs", "prune", "--key", cell.keys["operator"]], env=env)
        assert refused.exit_code == 1 and "403" in refused.output
        done = runner.invoke(app, ["jobs", "prune", "--key", cell.keys["admin"]], env=env)
        assert done.exit_code == 0 and old in done.output and "1 jobs, freed" in done.output
        with cell.client("viewer") as client:
            assert client.get(f"/api/v1/jobs/{old}").status_code == 404
            assert client.get(f"/api/v1/jobs/{kept}").json()["keep"] is True
        assert not (cell.data_dir / "jobs" / old).exists() and (cell.data_dir / "jobs" / kept).is_dir()


def test_folders_the_store_does_not_know_are_reported_apart_never_counted_against_the_limit(data):
    """A 200 MB folder the store does not know made the size limit delete the cell's own jobs, more at
    every start: the limit governs the cell's job folders alone, and the rest is reported."""
    store, jobs_dir = data
    unknown = jobs_dir / "aaaa000000000000"
    unknown.mkdir()
    (unknown / "x").write_bytes(b"\0" * (50 * MB))
    (jobs_dir / "notes.txt").write_bytes(b"\0" * MB)
    plan = plan_prune(store, "a", jobs_dir, RetentionConfig(max_gb=0.030), NOW)
    assert plan.jobs == () and plan.total_bytes == 25 * MB and plan.unmet is None
    assert plan.unknown == ("aaaa000000000000", "notes.txt") and plan.unknown_bytes == 51 * MB
    # another cell's jobs in the same folder are not this cell's to count either
    other = plan_prune(store, "other-cell", jobs_dir, RetentionConfig(max_gb=0.001), NOW)
    assert other.total_bytes == 0 and other.jobs == () and len(other.unknown) == 9


def test_a_deletion_cut_between_the_folders_rename_and_the_rows_delete_is_finished(tmp_path, monkeypatch):
    """Killed after its folder was renamed ``.deleting-<id>``, before its row went: the next start deletes
    the row and the folder; a folder that cannot be removed is said so, not said finished."""
    jobs_dir = tmp_path / "jobs"
    store = open_store(sqlite_url(tmp_path))
    for n in (1, 2):
        folder = jobs_dir / f"{n:016x}"
        (folder / "frames").mkdir(parents=True)
        (folder / "frames" / "000000.npz").write_bytes(b"\0" * 10)
        store.add_job(make_job(n, status="completed", folder=str(folder), finished_at=NOW))
        folder.rename(jobs_dir / f".deleting-{n:016x}")
    store.add_job(make_job(3, status="completed", folder=str(jobs_dir / f"{3:016x}"), finished_at=NOW))
    rmtree = retention.shutil.rmtree

    def refused_for_job_2(path, *args, **kwargs):
        if path.name.endswith("2"):
            raise PermissionError(13, "Permission denied", str(path / "frames" / "000000.npz"))
        rmtree(path, *args, **kwargs)

    monkeypatch.setattr(retention.shutil, "rmtree", refused_for_job_2)
    done = retention.finish_deletions(store, jobs_dir)
    assert done[0] == f"job {1:016x}: its deletion, cut short when the service stopped, is finished"
    assert done[1].startswith(f"job {2:016x}: deleted, but its folder {jobs_dir / f'.deleting-{2:016x}'} "
                              "could not be removed (Permission denied: ")
    assert store.get_job(f"{1:016x}") is None and store.get_job(f"{2:016x}") is None
    assert store.get_job(f"{3:016x}") is not None  # no folder being deleted: not touched
    assert sorted(p.name for p in jobs_dir.iterdir()) == [f".deleting-{2:016x}"]


def test_a_deletion_killed_midway_leaves_the_job_whole_or_gone_after_a_restart(tmp_path):
    """A prune killed while it deleted a job's folder left the job listed over a folder cut in half (its
    row is deleted after its folder)."""
    with ServedCell(UR5E, tmp_path / "data") as cell:
        with cell.client() as client:
            job_id = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 0.5}).json()["id"]
        cell.wait_job(job_id, tuple(FINISHED_STATUSES))
        cell.stop()
        # the service's own delete_job, killed (SIGKILL) right after the first file of the folder went
        script = textwrap.dedent(f"""
            import os, signal
            from pathlib import Path
            from cell.service.retention import delete_job
            from cell.service.store import open_data_store, sqlite_url
            data = Path({str(cell.data_dir)!r})
            store = open_data_store(data, sqlite_url(data))
            unlink = os.unlink
            def unlink_then_die(*args, **kwargs):
                unlink(*args, **kwargs)
                os.kill(os.getpid(), signal.SIGKILL)
            os.unlink = unlink_then_die
            delete_job(store, store.get_job({job_id!r}), data / "jobs")
        """)
        killed = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
        assert killed.returncode == -9, killed.stderr
        cell.start()
        with cell.client("viewer") as client:
            assert client.get(f"/api/v1/jobs/{job_id}").status_code == 404
        assert sorted(p.name for p in (cell.data_dir / "jobs").iterdir()) == []  # its folder's rest too
