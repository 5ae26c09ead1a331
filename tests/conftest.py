"""Shared fixtures: paths of the repository and its cell files."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
import yaml

from cell.planning.registry import PLANNERS, PlannerEntry
from drivers.scheduling import ordinary_scheduling

if TYPE_CHECKING:
    from fastapi.testclient import TestClient

REPO = Path(__file__).resolve().parent.parent
CONFIG_DIR = REPO / "config"
FRANKA = CONFIG_DIR / "sim-franka-rgbd.yaml"
UR5E = CONFIG_DIR / "sim-ur5e-tof.yaml"
# The test files that take longest, longest first: the suite hands out whole files to its processes in
# collection order (make test: --dist loadfile --no-loadscope-reorder), and one of these started last
# would run alone at the end (longest processing time first). Seconds of a process's time, summed from
# --durations=0 in a two-process run: 324, 204, 126, 115, 103, 85, 74, 69, 60, 57, 48, 46; every other
# file takes under 40 s and follows in name order.
LONGEST_FIRST = ("test_evaluation.py", "test_service_process.py", "test_line_opcua.py", "test_line.py",
                 "test_web_page.py", "test_calibration.py", "test_wheel.py", "test_bad_input.py",
                 "test_ur5e_driver.py", "test_safety_scenarios.py", "test_decimation.py",
                 "test_arm_conformance.py")
# Panda joints [rad] stretched to its reach: the flange at x = 0.65 m, smallest singular value of J 4e-4
PANDA_AT_REACH = (-0.1, 1.33, 0.08, -0.47, 0.0, 0.62, 0.33)


@pytest.fixture
def repo() -> Path:
    return REPO


@pytest.fixture
def franka_cfg_data() -> dict:
    return yaml.safe_load((CONFIG_DIR / "sim-franka-rgbd.yaml").read_text())


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Order the test files as :data:`LONGEST_FIRST` says (a stable sort: each file's tests keep their
    order)."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def register_planner(monkeypatch: pytest.MonkeyPatch, planner: Any) -> None:
    """Register the test's planner class ``planner`` (a ``Planner`` with a ``name``) for the test, as
    the shipped planners are: by where it lives."""
    entry = PlannerEntry(f"test planner {planner.__name__}", f"{planner.__module__}:{planner.__qualname__}")
    monkeypatch.setitem(PLANNERS, planner.name, entry)


def raster_scan(out: Path, config: Path, obj: str, seed: int, max_time_s: float) -> str:
    """``cell scan`` of ``obj`` on the cell file ``config`` with the raster planner (a fixed path: the same
    views whatever the map shows) into ``out``, asserted to complete; its output."""
    from typer.testing import CliRunner  # the command line only for the tests that scan

    from cell.cli.main import app

    res = CliRunner().invoke(app, ["scan", "--config", str(config), "--object", obj, "--seed", str(seed),
                                   "--planner", "raster", "--out", str(out), "--max-time", f"{max_time_s:g}"])
    assert res.exit_code == 0, res.output
    return res.output


def ended_without_a_frame(result: dict[str, Any], termination: str) -> bool:
    """Whether a job whose test planner ended with ``termination`` before capturing any frame ended as
    such a scan does: failed, its planner's termination kept (cell.jobs.runner)."""
    return bool(result["status"] == "failed" and result["termination"]
                == f"nothing captured: the scan ended before its first view ({termination})")


def wait_for(predicate: Callable[[], bool], timeout_s: float = 30.0) -> bool:
    """Poll ``predicate`` every 10 ms until it holds (True) or ``timeout_s`` [s] of wall time pass (False):
    for what another thread does."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return False


def wait_started(client: TestClient, headers: dict[str, str], job_id: str) -> None:
    """Poll the job ``job_id`` through the API (with ``headers``) every 50 ms until its worker has started
    it (its first progress); a job not started within 90 s of wall time fails the test."""
    deadline = time.monotonic() + 90.0
    while client.get(f"/api/v1/jobs/{job_id}", headers=headers).json()["progress"] is None:
        assert time.monotonic() < deadline, f"job {job_id} did not start"
        time.sleep(0.05)


@pytest.fixture
def built_worlds(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The collision worlds (``cell.safety.collision.CollisionWorld``) built from now on, however each is
    made (``CollisionWorld.for_cell`` or its constructor)."""
    from cell.safety.collision import CollisionWorld  # FCL, for the tests that count worlds only

    built: list[Any] = []
    build = CollisionWorld.__init__

    def counted(self: CollisionWorld, *args: Any, **kwargs: Any) -> None:
        built.append(self)
        build(self, *args, **kwargs)

    monkeypatch.setattr(CollisionWorld, "__init__", counted)
    return built


@pytest.fixture(autouse=True)
def _no_realtime_leak() -> Iterator[None]:
    """franky (libfranka) leaves the test's thread at a realtime priority (see ``drivers.scheduling``);
    later tests' peers and clients, started from it, would inherit it and starve each other."""
    yield
    ordinary_scheduling()
