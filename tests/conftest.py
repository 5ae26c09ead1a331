"""Shared fixtures: paths of the repository and its cell files."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from cell.planning.registry import PLANNERS, PlannerEntry
from drivers.scheduling import ordinary_scheduling

REPO = Path(__file__).resolve().parent.parent
CONFIG_DIR = REPO / "config"
FRANKA = CONFIG_DIR / "sim-franka-rgbd.yaml"
UR5E = CONFIG_DIR / "sim-ur5e-tof.yaml"
# Panda joints [rad] stretched to its reach: the flange at x = 0.65 m, smallest singular value of J 4e-4
PANDA_AT_REACH = (-0.1, 1.33, 0.08, -0.47, 0.0, 0.62, 0.33)


@pytest.fixture
def repo() -> Path:
    return REPO


@pytest.fixture
def franka_cfg_data() -> dict:
    return yaml.safe_load((CONFIG_DIR / "sim-franka-rgbd.yaml").read_text())


def register_planner(monkeypatch: pytest.MonkeyPatch, planner: Any) -> None:
    """Register the test's planner class ``planner`` (a ``Planner`` with a ``name``) for the test, as
    the shipped planners are: by where it lives."""
    entry = PlannerEntry(f"test planner {planner.__name__}", f"{planner.__module__}:{planner.__qualname__}")
    monkeypatch.setitem(PLANNERS, planner.name, entry)


def wait_for(predicate: Callable[[], bool], timeout_s: float = 30.0) -> bool:
    """Poll ``predicate`` every 10 ms until it holds (True) or ``timeout_s`` [s] of wall time pass (False):
    for what another thread does."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return False


@pytest.fixture(autouse=True)
def _no_realtime_leak() -> Iterator[None]:
    """franky (libfranka) leaves the test's thread at a realtime priority (see ``drivers.scheduling``);
    later tests' peers and clients, started from it, would inherit it and starve each other."""
    yield
    ordinary_scheduling()
