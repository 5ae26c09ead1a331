"""The cell files ``cell init`` starts from, shipped as package data (``<name>.yaml`` beside this module).

Two simulated cells (the papers' cells, nothing to measure) and two hardware templates whose measured
values (the robot's address, the sensor's port, the mount, the station) carry a ``# MEASURE:`` mark
(:mod:`cell.config.placeholders`). The repository's ``config/`` links to these files.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from drivers.errors import ConfigError

TEMPLATES = ("sim-franka-rgbd", "sim-ur5e-tof", "ur5e-vl53l8cx", "franka-realsense")
DEFAULT_TEMPLATE = "sim-franka-rgbd"
"""The embedded default cell: what ``cell scan`` and ``cell serve`` run without ``--config``."""


def template_path(name: str) -> Path:
    """The shipped file of template ``name``; ``ConfigError`` naming the templates if there is none."""
    if name not in TEMPLATES:
        raise ConfigError(f"no template {name!r}", allowed=", ".join(TEMPLATES))
    return Path(str(files(__name__).joinpath(f"{name}.yaml")))
