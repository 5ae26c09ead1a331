"""``cell sensor check``: commissioning figures against the bridge emulator (the exact CRC error and gap
counts of injected faults) and against a replayed job; ``cell sensor emulate`` refuses bad input."""

from __future__ import annotations

import re

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from cell.cli.main import app
from drivers.depth.base import DepthFrame, ToFZones
from drivers.depth.check import SensorCheck
from drivers.depth.vl53l8cx.emulator import EmulatorFaults, SimToFSource, VL53L8CXEmulator

from .conftest import CONFIG_DIR, UR5E


def _cell_file(tmp_path, sensor: dict, **changes: object) -> str:
    data = yaml.safe_load((CONFIG_DIR / "ur5e-vl53l8cx.yaml").read_text())
    data["sensor"] = sensor
    data.update(changes)
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_check_counts_injected_corrupted_and_dropped_frames(tmp_path):
    corrupted, dropped = {4, 10, 15}, {7}
    faults = EmulatorFaults(garbage_bytes=200, corrupt_frames=frozenset(corrupted),
                            drop_frames=frozenset(dropped))
    emulator = VL53L8CXEmulator.on_pty(SimToFSource.fixed("cube", seed=5), faults, seed=6)
    cell = _cell_file(tmp_path, {"type": "vl53l8cx", "port": "/dev/null-replaced-by---port", "resolution": 4,
                                 "frequency_hz": 60, "timeout_s": 2.0})
    with emulator:
        res = CliRunner().invoke(app, ["sensor", "check", "--config", cell, "--port", emulator.url,
                                       "--frames", "25"])
    assert res.exit_code == 0, res.output
    assert "CRC errors: 3\n" in res.output
    assert emulator.counters.overflowed == 0  # the reader kept up: every gap is an injected one
    assert "sequence gaps: 4 (4 frames lost)" in res.output
    assert re.search(r"frames: 25 in [\d.]+ s, [\d.]+ Hz \(device clock [\d.]+ Hz\)", res.output)
    assert re.search(r"valid zones \(statuses 5, 9\): [\d.]+ %", res.output)
    noise_rows = res.output.split("per-zone noise [mm]")[1].strip().splitlines()[1:5]
    assert len(noise_rows) == 4 and all(len(row.split()) == 4 for row in noise_rows)
    assert "median zone noise:" in res.output


def test_check_reports_a_vanishing_device(tmp_path):
    emulator = VL53L8CXEmulator.on_pty(SimToFSource.fixed("cube"), EmulatorFaults(disconnect_after=5))
    cell = _cell_file(tmp_path, {"type": "vl53l8cx", "port": emulator.url, "resolution": 4,
                                 "frequency_hz": 60})
    with emulator:
        res = CliRunner().invoke(app, ["sensor", "check", "--config", cell, "--frames", "50"])
    assert res.exit_code == 1
    assert "vanished" in res.output and "CRC errors: 0" in res.output


def test_check_a_replayed_job(tmp_path):
    job = tmp_path / "job"
    res = CliRunner().invoke(app, ["scan", "--config", str(UR5E), "--object", "cube", "--out", str(job),
                                   "--planner", "raster", "--max-time", "8"])
    assert res.exit_code == 0, res.output
    cell = _cell_file(tmp_path, {"type": "replay", "job_dir": str(job)}, mode="replay",
                      arm={"type": "replay", "model": "ur5e", "job_dir": str(job)})
    res = CliRunner().invoke(app, ["sensor", "check", "--config", cell, "--frames", "2"])
    assert res.exit_code == 0, res.output
    assert "frames: 2" in res.output and "valid zones (statuses 5, 9)" in res.output
    assert "CRC errors" not in res.output  # a replay has no link


def test_check_refuses_a_simulated_sensor_and_a_port_for_another_sensor(tmp_path):
    res = CliRunner().invoke(app, ["sensor", "check", "--config", str(UR5E)])
    assert res.exit_code == 1 and "renders a simulated scene" in res.output
    res = CliRunner().invoke(app, ["sensor", "check", "--config", str(CONFIG_DIR / "franka-realsense.yaml"),
                                   "--port", "loop://"])
    assert res.exit_code != 0 and "--port is for a vl53l8cx sensor" in res.output


def test_check_realsense_without_a_camera_says_so():
    res = CliRunner().invoke(app, ["sensor", "check", "--config", str(CONFIG_DIR / "franka-realsense.yaml")])
    assert res.exit_code == 1 and "no RealSense camera found" in res.output


def test_zone_noise_is_the_per_zone_standard_deviation():
    tally = SensorCheck((5, 9))
    rng = np.random.default_rng(0)
    sigma = np.linspace(0.001, 0.01, 16)
    for k in range(400):
        d = 0.5 + sigma * rng.standard_normal(16)
        status = np.full(16, 5, dtype=np.uint8)
        status[0] = 255 if k % 2 else 4  # zone 0 is never valid
        zones = ToFZones(distance_m=d, sigma_m=sigma, status=status, nb_targets=np.ones(16, np.uint8),
                         reflectance_pct=np.full(16, 30.0), directions=np.tile([0.0, 0.0, 1.0], (16, 1)))
        tally.add(DepthFrame(seq=k, timestamp=k / 15, points=np.zeros((0, 3)), zones=zones), k / 15.0,
                  (2**32 - 1000 + k * 66_667) % 2**32)  # device stamps wrap during the run
    report = tally.report()
    assert report.frames == 400 and report.rate_hz == pytest.approx(15.0)
    assert report.device_rate_hz == pytest.approx(15.0, rel=1e-3)
    assert report.valid_share == pytest.approx(15 / 16)
    assert np.isnan(report.zone_noise_m[0, 0])
    np.testing.assert_allclose(report.zone_noise_m.reshape(-1)[1:], sigma[1:], rtol=0.15)


@pytest.mark.parametrize("option, message", [
    (("--frames", "0"), "Invalid value for '--frames': Input should be greater than or equal to 1"),
    (("--seconds", "-1"), "Invalid value for '--seconds': -1.0 is not a time to read frames for"),
    (("--seconds", "0"), "Invalid value for '--seconds': 0.0 is not a time to read frames for"),
    (("--seconds", "inf"), "Invalid value for '--seconds': inf is not a time to read frames for"),
])
def test_check_refuses_a_count_or_time_that_reads_nothing(tmp_path, option, message):
    """'--frames 0' and '--seconds -1' read nothing and passed: "frames: 0 in 0.00 s, - Hz", exit 0."""
    cell = _cell_file(tmp_path, {"type": "vl53l8cx", "port": "/dev/null", "resolution": 4})
    res = CliRunner().invoke(app, ["sensor", "check", "--config", cell, *option], env={"COLUMNS": "200"})
    assert res.exit_code == 1 and message in res.output, res.output
    assert "frames:" not in res.output


def test_a_port_that_does_not_open_says_what_to_check(tmp_path):
    """The driver's error says what failed; the commissioning command adds what to do about it."""
    cell = _cell_file(tmp_path, {"type": "vl53l8cx", "port": str(tmp_path / "ttyACM9"), "resolution": 4})
    res = CliRunner().invoke(app, ["sensor", "check", "--config", cell])
    assert res.exit_code == 1 and res.stdout == "", res.output
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: depth vl53l8cx at {tmp_path / 'ttyACM9'}: cannot "
                                                   "open the port: ")
    assert lines[0].endswith("; is the bridge board plugged in, and is sensor.port its port? (the udev rule "
                             "of `cell deploy files` makes it /dev/vl53l8cx; --port tries another; `cell "
                             "doctor --config FILE` checks it)")
    # A pyserial URL is no board plugged in: the driver's error alone.
    url = CliRunner().invoke(app, ["sensor", "check", "--config", cell, "--port", "socket://127.0.0.1:9"])
    assert url.exit_code == 1 and "cannot open the port" in url.stderr, url.output
    assert "plugged in" not in url.stderr


def test_check_that_read_no_frame_fails(tmp_path):
    emulator = VL53L8CXEmulator.on_pty(SimToFSource.fixed("cube"), EmulatorFaults())
    cell = _cell_file(tmp_path, {"type": "vl53l8cx", "port": emulator.url, "resolution": 4,
                                 "frequency_hz": 60})
    with emulator:
        res = CliRunner().invoke(app, ["sensor", "check", "--config", cell, "--seconds", "1e-9"])
    assert res.exit_code == 1, res.output
    assert "frames: 0 in" in res.output
    assert "error: depth vl53l8cx: read no frame in 1e-09 s: nothing to check" in res.output
