"""A data dir's store restored from a backup (docs/deploy.md, section 9) and a data dir moved, through a
real ``cell serve``: what the job folders recorded after the backup is kept, folders the store does not
know are imported or counted apart, and the jobs' files follow the data dir."""

from __future__ import annotations

import json
import shutil
import sqlite3

import pytest
from typer.testing import CliRunner

from cell.cli.main import app
from cell.service.recovery import finish_folder, reconcile
from cell.service.store import FINISHED_STATUSES, open_store, sqlite_url
from tests.conftest import UR5E
from tests.service_process import ServedCell, submit
from tests.test_store import make_job

ENDED = tuple(FINISHED_STATUSES)


def _submit(cell: ServedCell, n: int, part_id: str | None = None) -> list[str]:
    return [submit(cell, object="cube", max_time_s=2.0, part_id=part_id)["id"] for _ in range(n)]


def test_a_restored_backup_keeps_the_jobs_folders_records_and_a_moved_data_dir_keeps_its_files(tmp_path):
    data = tmp_path / "data"
    backups = tmp_path / "backups"
    with ServedCell(UR5E, data) as cell:
        ran = _submit(cell, 2)  # one runs, one waits, as the backup is taken
        res = CliRunner().invoke(app, ["backup", f"{backups}/", "--data-dir", str(data)])
        assert res.exit_code == 0, res.output
        (backup,) = backups.glob("cell-*.db")
        with sqlite3.connect(backup) as db:
            assert db.execute("SELECT status FROM jobs WHERE id = ?", (ran[1],)).fetchone()[0] == "queued"
        before = {job_id: cell.wait_job(job_id, ENDED) for job_id in ran}
        (later,) = _submit(cell, 1, "crate-9")  # after the backup: the store restored does not know it
        before[later] = cell.wait_job(later, ENDED)
        junk = data / "jobs" / "aaaa000000000000"  # no job of any store: counted apart, never deleted
        junk.mkdir()
        (junk / "x").write_bytes(b"\0" * 1000)
        cell.stop()
        # the restore docs/deploy.md, section 9 describes
        shutil.copyfile(backup, data / "cell.db")
        for extra in ("cell.db-wal", "cell.db-shm"):
            (data / extra).unlink(missing_ok=True)
        cell.start()
        with cell.client("viewer") as client:
            for job_id, was in before.items():
                job = client.get(f"/api/v1/jobs/{job_id}").json()
                assert (job["status"], job["termination"]) == (was["status"], was["termination"]), job_id
                assert job["result"] == was["result"]
                # the part and who asked, also of the job imported from its folder's job.json
                assert (job["part_id"], job["submitted_by"]) == (was["part_id"], was["submitted_by"]), job_id
            assert before[later]["part_id"] == "crate-9" and before[later]["submitted_by"]
            files = client.get(f"/api/v1/jobs/{later}/files")
            assert files.status_code == 200 and "cloud.ply" in {f["name"] for f in files.json()}
            retention = client.get("/api/v1/retention").json()
            assert retention["unknown_folders"] == 1 and retention["unknown_gb"] == 1000 / 1e9
        assert f"job {later} was not in the store" in cell.log() and "aaaa000000000000" in cell.log()
        assert junk.is_dir()
        cell.stop()

        # the data dir moved: cp -a D D2; rm D2/store-url; serve D2; mv D Dold
        moved = tmp_path / "moved"
        shutil.copytree(data, moved, symlinks=True)
        (moved / "store-url").unlink()
        data.rename(tmp_path / "old")
        cell.data_dir = moved
        cell.start()
        with cell.client("viewer") as client:
            for job_id in before:
                names = {f["name"] for f in client.get(f"/api/v1/jobs/{job_id}/files").json()}
                assert {"log.txt", "result.json"} <= names, job_id
            assert client.get(f"/api/v1/jobs/{later}/files/log.txt").status_code == 200
            shutil.rmtree(moved / "jobs" / later)
            missing = client.get(f"/api/v1/jobs/{later}/files")
            assert missing.status_code == 410 and "missing" in missing.json()["detail"]
            assert str(tmp_path) not in missing.text
            assert client.get(f"/api/v1/jobs/{later}/files/log.txt").status_code == 410


def test_only_this_cells_job_folders_are_imported_and_a_stale_folder_is_never_made(tmp_path):
    """Unknown entries of jobs/ that are not this cell's jobs (another cell's job.json, a broken one, a
    folder not named as a job id, a file) are listed and left; finishing a job whose recorded folder is in
    no data dir any more does not make it again."""
    jobs_dir = tmp_path / "jobs"
    store = open_store(sqlite_url(tmp_path), jobs_dir=jobs_dir)
    try:
        mine, theirs, broken = (jobs_dir / f"{n:016x}" for n in (1, 2, 3))
        for folder, asked in ((mine, {"cell": "a", "planner": "vs-local", "object": "cube", "seed": 7,
                                      "object_placement": [0.01, 0.0, 15.0], "max_time_s": 5.0,
                                      "part_id": "crate-17", "submitted_by": "line"}),
                              (theirs, {"cell": "b", "planner": "vs-local", "object": "cube", "seed": 1}),
                              (broken, {"cell": "a", "planner": "vs-local", "seed": "seven"})):
            folder.mkdir(parents=True)
            (folder / "job.json").write_text(json.dumps(asked))
        (mine / "result.json").write_text(json.dumps({"status": "completed", "termination": "coverage"}))
        (jobs_dir / "scan-by-hand").mkdir()
        (jobs_dir / "notes.txt").write_text("x")
        done = reconcile(store, "a", worker_wait_s=0.0)
        job = store.get_job(mine.name)
        assert job is not None and (job.status, job.termination, job.seed) == ("completed", "coverage", 7)
        assert job.object_pose == (0.01, 0.0, 15.0) and job.folder == str(mine)
        assert (job.part_id, job.submitted_by) == ("crate-17", "line")
        assert store.get_job(theirs.name) is None and store.get_job(broken.name) is None
        assert any(f"4 entries of {jobs_dir} are no job of this cell's store" in line for line in done), done
        assert all(p.exists() for p in (theirs, broken, jobs_dir / "scan-by-hand", jobs_dir / "notes.txt"))
        again = reconcile(store, "a", worker_wait_s=0.0)  # imported once, the rest listed again
        assert again == done[-1:]

        stale = tmp_path / "old-data" / "jobs" / f"{9:016x}"
        with pytest.raises(OSError):
            finish_folder(stale, make_job(9), "interrupted", "the service stopped while the job ran")
        assert not (tmp_path / "old-data").exists()
    finally:
        store.close()
