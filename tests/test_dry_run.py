"""The dry run: ``cell scan`` with the UR5e hardware backend against the RTDE controller peer and a simulated
ToF sensor that renders the virtual object from the pose the arm reports, on the wall clock, through the
guard (config/dryrun-ur5e-peer.yaml, its host replaced by the test's peer)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from cell.config import load_config
from cell.config.load import parse_config
from cell.jobs.runner import ScanRequest, run_scan
from drivers.errors import ConfigError
from tests.conftest import CONFIG_DIR
from tests.loopback import FIRST_HOST
from tests.rtde_peer import ControllerPeer

DRY_RUN = CONFIG_DIR / "dryrun-ur5e-peer.yaml"
MAX_TIME_S = 15.0  # wall-clock budget of the test's scan [s]


def test_a_dry_run_scans_the_virtual_object_through_the_guard(tmp_path: Path) -> None:
    cfg = load_config(DRY_RUN)
    assert cfg.arm.home_joints_rad is not None
    peer = ControllerPeer(q=cfg.arm.home_joints_rad)
    try:
        cfg = cfg.model_copy(update={"arm": cfg.arm.model_copy(update={"host": peer.host})})
        out = run_scan(ScanRequest(config=cfg, config_path=str(DRY_RUN), object="horizontal_box",
                                   planner="raster", out=tmp_path / "job", max_time_s=MAX_TIME_S))
        peer_state = peer.state()
        servoj = peer.records("servoJ")
    finally:
        peer.stop()
    result = out.result
    assert result["status"] == "completed", result["termination"]
    assert result["safety"]["stops"] == [], result["safety"]
    assert result["n_captures"] >= 1 and result["n_capture_failures"] == 0
    frames = sorted((out.folder / "frames").glob("*.npz"))
    assert len(frames) == result["n_captures"]
    # the moves went to the controller as servoJ streams, and the arm moved there
    assert servoj and result["path_length_m"] > 0.05
    assert peer_state["safety_mode"] == "NORMAL"
    # the sensor saw the virtual box from where the arm reported it was: points on the box or the table
    assert result["n_cloud_points"] > 0 and result["metrics"]["coverage_pct"] > 0.0
    assert json.loads((out.folder / "result.json").read_text())["status"] == "completed"


def test_the_shipped_dry_run_host_is_one_no_test_peer_takes() -> None:
    arm = load_config(DRY_RUN).arm
    assert arm.type == "ur5e"
    assert arm.host.startswith("127.0.0.") and int(arm.host.rsplit(".", 1)[1]) < FIRST_HOST


@pytest.mark.parametrize(("arm_type", "sensor_type", "match"), [
    ("sim", "sim-tof", "mode 'dry-run' needs a hardware arm"),
    ("ur5e", "vl53l8cx", "mode 'dry-run' needs a hardware arm"),
])
def test_dry_run_mode_needs_a_hardware_arm_and_a_simulated_sensor(arm_type: str, sensor_type: str,
                                                                  match: str) -> None:
    data = yaml.safe_load(DRY_RUN.read_text())
    if arm_type == "sim":
        data["arm"] = {"type": "sim", "model": "ur5e"}
    if sensor_type == "vl53l8cx":
        data["sensor"] = {"type": "vl53l8cx", "port": "loop://"}
    with pytest.raises(ConfigError, match=match):
        parse_config(data, file="cell.yaml")


def test_real_mode_with_a_simulated_sensor_points_to_the_dry_run() -> None:
    data = yaml.safe_load(DRY_RUN.read_text())
    data["mode"] = "real"
    with pytest.raises(ConfigError, match="is mode 'dry-run'"):
        parse_config(data, file="cell.yaml")
