"""Recovery gaps a chaos review found, against a real ``cell serve`` (``tests.service_process``) on the
Franka sim cell with its SQLite store: an arm fault's hold across a ``kill -9``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from tests.conftest import FRANKA
from tests.service_process import ServedCell, submit


def _faulty_cell(tmp_path: Path) -> Path:
    """The Franka sim cell whose arm reports a protective stop 3.5 s into each job (sim time)."""
    data = yaml.safe_load(FRANKA.read_text())
    data["sim"]["faults"] = [{"at_s": 3.5, "kind": "protective stop"}]
    path = tmp_path / "faulty.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _cell(cell: ServedCell) -> dict[str, Any]:
    with cell.client("viewer") as client:
        answer: dict[str, Any] = client.get("/api/v1/cell").json()
    return answer


def test_an_arm_faults_hold_outlives_a_kill_9_until_the_arm_is_recovered(tmp_path: Path) -> None:
    """The hold was read from the arm's live latch alone (``held_at`` null): after a ``kill -9`` and a
    restart the queue was free, ``/readyz`` ready and the next job would have run on a faulted arm."""
    with ServedCell(_faulty_cell(tmp_path), tmp_path / "data", key_prefix="faulty") as cell:
        job = submit(cell, object="bunny", max_time_s=8.0)
        ended = cell.wait_job(job["id"], ("stopped", "failed", "completed"))
        assert ended["termination"] == "safety stop: arm fault: protective stop", ended
        before = _cell(cell)["queue"]
        assert "recover the arm first" in before["held"] and before["held_at"] is not None, before
        cell.kill()
        cell.start()
        after = _cell(cell)
        assert after["queue"]["held"] == before["held"] and after["queue"]["held_at"] == before["held_at"]
        assert after["arm"]["faults"] == ["protective stop"], after["arm"]
        with cell.client("operator") as client:
            ready = client.get("/readyz")
            assert ready.status_code == 503 and "recover the arm first" in ready.json()["status"]
            assert client.post("/api/v1/queue/resume").status_code == 409  # the arm first
            recovered = client.post("/api/v1/arm/recover")
            assert recovered.status_code == 200 and recovered.json()["ok"], recovered.text
            assert client.get("/api/v1/cell").json()["queue"]["held"] is None
            assert client.get("/readyz").status_code == 200
        # the recovery released the hold in the store too
        cell.kill()
        cell.start()
        assert _cell(cell)["queue"]["held"] is None
