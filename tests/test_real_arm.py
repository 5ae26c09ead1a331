"""Commissioning checks on a real robot (marker ``real_robot``): they run only when the robot's address is
in the environment, and otherwise are skipped.

- ``CELL_UR_HOST``: a UR5e controller in remote control; ``CELL_UR_CONFIG`` the cell file (default the
  hardware template config/ur5e-vl53l8cx.yaml, whose host is replaced).
- ``CELL_FRANKA_HOST``: a Franka arm with FCI enabled; ``CELL_FRANKA_CONFIG`` likewise (default
  config/franka-realsense.yaml).

Each reads the status, then jogs the flange 5 mm up and back down through the guard (the cell's limits,
workspace, planes and collision checks): keep the space above the flange clear and a hand on the stop.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from cell.cli.arm import arm_app
from tests.conftest import CONFIG_DIR
from tests.test_arm_cli import tcp_position

ROBOTS = {
    "ur5e": ("CELL_UR_HOST", "CELL_UR_CONFIG", CONFIG_DIR / "ur5e-vl53l8cx.yaml"),
    "franka": ("CELL_FRANKA_HOST", "CELL_FRANKA_CONFIG", CONFIG_DIR / "franka-realsense.yaml"),
}
JOG_M = 0.005  # the jog's height [m]


def robot_param(name: str) -> object:
    host_var = ROBOTS[name][0]
    return pytest.param(name, id=name, marks=[
        pytest.mark.real_robot,
        pytest.mark.skipif(not os.environ.get(host_var), reason=f"needs a real {name}: set {host_var}"),
    ])


@pytest.fixture(params=[robot_param("ur5e"), robot_param("franka")])
def cell_file(request: pytest.FixtureRequest, tmp_path: Path) -> Path:
    host_var, config_var, template = ROBOTS[request.param]
    data = yaml.safe_load(Path(os.environ.get(config_var, template)).read_text())
    data["arm"]["host"] = os.environ[host_var]
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def run(*args: str) -> str:
    result = CliRunner().invoke(arm_app, list(args))
    assert result.exit_code == 0, result.output
    return result.output


def test_status_reads_the_robot(cell_file: Path) -> None:
    output = run("status", "--config", str(cell_file))
    assert "connected" in output and "faults: none" in output, output
    assert np.all(np.isfinite(tcp_position(output)))


def test_a_tiny_guarded_jog_up_and_back(cell_file: Path) -> None:
    start = tcp_position(run("status", "--config", str(cell_file)))
    up = tcp_position(run("jog", "--config", str(cell_file), "--axis", "z", "--distance", str(JOG_M)))
    back = tcp_position(run("jog", "--config", str(cell_file), "--axis", "z", "--distance", str(-JOG_M)))
    assert up - start == pytest.approx([0.0, 0.0, JOG_M], abs=1e-3)
    assert back == pytest.approx(start, abs=1e-3)
