"""An operator stop of a job run by ``cell scan``: the ``STOP`` file in its folder, which the job reads at
its next control tick (``cell.jobs.session``) and removes. Kept apart from the recorder so that ``cell stop``
loads nothing else: a stop must not wait for the libraries a scan needs."""

from __future__ import annotations

from pathlib import Path

from drivers.errors import JobError

STOP_FILE = "STOP"


def request_stop(folder: Path, reason: str) -> None:
    """Ask the job running in ``folder`` to stop (operator stop): writes its ``STOP`` file, which the job
    reads at its next control tick. Raises ``JobError`` when no job is running there."""
    if not (folder / "log.txt").is_file():
        raise JobError(f"{folder} is not a job folder (no log.txt)")
    if (folder / "result.json").exists():
        raise JobError(f"the job in {folder} is not running: it has finished (result.json exists)")
    (folder / STOP_FILE).write_text(reason.strip() + "\n")
