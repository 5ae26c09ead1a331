"""``cell init`` on each template, ``cell config check``'s placeholders, and a real cell refused while any
value is still marked."""

from __future__ import annotations

import re

import pytest
from typer.testing import CliRunner

from cell.cli.main import app
from cell.config import load_config
from cell.config.placeholders import find_placeholders, require_measured
from cell.service.startup import ServiceSettings, build_service
from cell.templates import TEMPLATES, template_path
from drivers.errors import ConfigError

MEASURED = {"sim-franka-rgbd": [], "sim-ur5e-tof": [],
            "ur5e-vl53l8cx": ["arm.host", "sensor.port", "mount.xyz_m", "mount.rpy_deg", "station.xy_m",
                              "station.table_z_m"],
            "franka-realsense": ["arm.host", "sensor.serial", "mount.xyz_m", "mount.rpy_deg", "station.xy_m",
                                 "station.table_z_m", "calibration.board.square_m",
                                 "calibration.board.marker_m"]}


def _measure(text: str) -> str:
    """The integrator's edit: each marked value kept (as if measured equal) and its mark deleted."""
    return re.sub(r"\s*#\s*MEASURE:.*$", "", text, flags=re.MULTILINE)


@pytest.mark.parametrize("template", TEMPLATES)
def test_init_then_check_lists_the_placeholders_until_measured(tmp_path, template):
    runner = CliRunner()
    folder = tmp_path / "cell-a"
    res = runner.invoke(app, ["init", str(folder), "--template", template, "--name", "line-3"])
    assert res.exit_code == 0, res.output
    cell_file = folder / "cell.yaml"
    # the calibration commands keep their views in calibrations/ (calibration/README.md)
    assert {p.name for p in (folder / "data").iterdir()} == {"jobs", "objects", "logs", "calibrations"}
    assert "name: line-3\n" in cell_file.read_text()
    for field in MEASURED[template]:
        assert field in res.output

    check = runner.invoke(app, ["config", "check", str(cell_file)])
    # in the words of cell init's list and of "ready: nothing left to measure" (it said "placeholder:")
    listed = re.findall(r"^to measure: line \d+ (\S+):", check.output, re.MULTILINE)
    assert listed == MEASURED[template]
    assert check.exit_code == (1 if MEASURED[template] else 0), check.output
    if MEASURED[template]:
        assert f"not ready: {len(MEASURED[template])} values" in check.output

    cell_file.write_text(_measure(cell_file.read_text()))
    check = runner.invoke(app, ["config", "check", str(cell_file)])
    assert check.exit_code == 0 and "ready: nothing left to measure" in check.output


def test_init_never_overwrites_a_cell_file_and_names_bad_input(tmp_path):
    runner = CliRunner()
    assert runner.invoke(app, ["init", str(tmp_path), "--template", "sim-ur5e-tof"]).exit_code == 0
    before = (tmp_path / "cell.yaml").read_text()
    again = runner.invoke(app, ["init", str(tmp_path), "--template", "ur5e-vl53l8cx"])
    assert again.exit_code == 1 and "never overwrites" in again.output
    assert (tmp_path / "cell.yaml").read_text() == before
    unknown = runner.invoke(app, ["init", str(tmp_path / "b"), "--template", "kuka"])
    assert unknown.exit_code == 1 and "no template 'kuka'" in unknown.output
    assert "sim-ur5e-tof" in unknown.output
    elsewhere = runner.invoke(app, ["init", str(tmp_path / "etc"), "--template", "sim-ur5e-tof",
                                    "--data-dir", str(tmp_path / "var")])
    assert elsewhere.exit_code == 0 and (tmp_path / "var" / "jobs").is_dir()
    assert not (tmp_path / "etc" / "data").exists() and f"--data-dir {tmp_path / 'var'}" in elsewhere.output
    assert "\nname: etc\n" in (tmp_path / "etc" / "cell.yaml").read_text()  # the folder's name
    bad_name = runner.invoke(app, ["init", str(tmp_path / "c"), "--template", "sim-ur5e-tof",
                                   "--name", "../x"])
    assert bad_name.exit_code == 1 and "--name" in bad_name.output
    assert not (tmp_path / "c" / "cell.yaml").exists()


def test_a_mark_on_a_comment_line_marks_nothing():
    text = "# MEASURE: the header is not a field\narm:\n  host: 10.0.0.2  # MEASURE: the address\n  port: 1\n"
    found = find_placeholders(text)
    assert [(p.field, p.line, p.what) for p in found] == [("arm.host", 3, "the address")]


def test_a_real_cell_with_placeholders_is_refused_and_runs_once_measured(tmp_path):
    cell_file = tmp_path / "cell.yaml"
    cell_file.write_text(template_path("ur5e-vl53l8cx").read_text())
    with pytest.raises(ConfigError, match=r"still to measure: arm\.host, sensor\.port, mount\.xyz_m"):
        require_measured(cell_file, "real")
    with pytest.raises(ConfigError, match="still to measure"):
        build_service(ServiceSettings(config_file=cell_file, data_dir=tmp_path / "data"))
    scan = CliRunner().invoke(app, ["scan", "--config", str(cell_file), "--out", str(tmp_path / "job")])
    assert scan.exit_code == 1 and "still to measure: arm.host" in scan.output
    assert not (tmp_path / "job").exists()
    # a dry run scans a virtual object, so its mount and station may wait, but it connects to the real arm
    with pytest.raises(ConfigError, match=r"before connecting to the arm, .*: arm\.host at line 10, "):
        require_measured(cell_file, "dry-run")
    cell_file.write_text(re.sub(r"(host: \S+)\s*# MEASURE:.*", r"\1", cell_file.read_text()))
    require_measured(cell_file, "dry-run")
    cell_file.write_text(_measure(cell_file.read_text()))
    require_measured(cell_file, "real")


@pytest.mark.parametrize("command", [("arm", "status"), ("arm", "recover"),
                                     ("arm", "jog", "--axis", "z", "--distance", "0.01"),
                                     ("calibrate", "mount", "--out", "mount.json")])
def test_a_command_that_connects_to_the_arm_refuses_the_templates_example_address(tmp_path, command):
    """``cell arm status`` on the template connected to its example arm.host and printed a long
    diagnosis of the dashboard handshake, never saying that the address was the template's example."""
    cell_file = tmp_path / "cell.yaml"
    cell_file.write_text(template_path("ur5e-vl53l8cx").read_text())
    res = CliRunner().invoke(app, [*command, "--config", str(cell_file)])
    assert res.exit_code == 1
    assert res.stderr == (f"error: {cell_file}: still to measure before connecting to the arm, its value "
                          "the template's example: arm.host at line 10, the controller's IP address "
                          "(PolyScope: Settings > System > Network); measure it, write it and delete its "
                          f"'# MEASURE:' mark (cell config check {cell_file} lists every mark left)\n")


@pytest.mark.parametrize("template", TEMPLATES)
def test_a_camera_cells_template_has_the_board_its_mount_calibration_needs(template):
    """The README's RGB-D path (cell calibrate mount --target charuco) failed on the franka-realsense
    template with "the cell file has no calibration.board" until the section was added by hand."""
    cfg = load_config(template_path(template))
    camera = cfg.sensor.type in ("realsense", "sim-rgbd")
    assert (cfg.calibration.board is not None) == camera


def test_a_folder_whose_name_is_no_cell_name_keeps_the_templates_and_says_so(tmp_path):
    res = CliRunner().invoke(app, ["init", str(tmp_path / "my cell"), "--template", "sim-ur5e-tof"])
    assert res.exit_code == 0, res.output
    assert "\nname: sim-ur5e-tof\n" in (tmp_path / "my cell" / "cell.yaml").read_text()
    assert "is not a cell name" in res.output and "--name" in res.output
    assert f"cell config check '{tmp_path / 'my cell' / 'cell.yaml'}'" in res.output  # a path to paste


def test_init_s_next_commands_run_cell_as_it_was_run(tmp_path, monkeypatch):
    """In a checkout whose venv is not activated, ``cell`` is not on the PATH: the next steps name the
    command that ran (``.venv/bin/cell``); where ``cell`` on the PATH is that command, plain ``cell``."""
    venv_cell = tmp_path / ".venv" / "bin" / "cell"
    venv_cell.parent.mkdir(parents=True)
    venv_cell.write_text("#!/bin/sh\n")
    venv_cell.chmod(0o755)
    monkeypatch.setattr("sys.argv", [str(venv_cell), "init"])
    monkeypatch.setenv("PATH", str(tmp_path / "elsewhere"))
    res = CliRunner().invoke(app, ["init", str(tmp_path / "a"), "--template", "sim-ur5e-tof"])
    assert res.exit_code == 0, res.output
    assert f"  {venv_cell} config check " in res.output and f"  {venv_cell} serve --config " in res.output
    monkeypatch.setenv("PATH", str(venv_cell.parent))
    res = CliRunner().invoke(app, ["init", str(tmp_path / "b"), "--template", "sim-ur5e-tof"])
    assert "\n  cell config check " in res.output and str(venv_cell) not in res.output
