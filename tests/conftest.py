"""Shared fixtures: paths of the repository and its cell files."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parent.parent
CONFIG_DIR = REPO / "config"
FRANKA = CONFIG_DIR / "sim-franka-rgbd.yaml"
UR5E = CONFIG_DIR / "sim-ur5e-tof.yaml"


@pytest.fixture
def repo() -> Path:
    return REPO


@pytest.fixture
def franka_cfg_data() -> dict:
    return yaml.safe_load((CONFIG_DIR / "sim-franka-rgbd.yaml").read_text())
