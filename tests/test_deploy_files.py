"""What a cell's PC has without a checkout: the deployment files as package data written out by ``cell
deploy files``, and packaged hints (the cell files' ``# MEASURE:`` marks, ``cell init``, ``cell sensor
emulate``) that name installed things, not the repository's folders."""

from __future__ import annotations

import re
import shlex
from importlib.resources import files

import pytest
from typer.testing import CliRunner

from calibration import GUIDE_COMMAND, guide_path
from cell.cli.main import app
from cell.cli.sensor import check_command
from cell.deploy import DEPLOY_FILES
from cell.templates import TEMPLATES, template_path
from tests.conftest import REPO

CHECKOUT_PATHS = re.compile(r"calibration/README\.md|deploy/udev|deploy/systemd|(?<![\w/])config/\S+\.yaml")
"""Paths of the repository a packaged hint pointed to (a PC with the wheel has none of them)."""


def test_the_deployment_files_are_package_data_and_the_repository_links_to_them():
    for name in DEPLOY_FILES:
        packaged = files("cell.deploy").joinpath(name)
        assert packaged.is_file(), name
        assert (REPO / "deploy" / name).resolve() == (REPO / "cell" / "deploy" / name).resolve()
    assert guide_path().is_file() and guide_path().read_text().startswith("# Calibration")


def test_cell_deploy_files_writes_them_and_how_to_install_them(tmp_path):
    runner = CliRunner()
    out = tmp_path / "deploy"
    res = runner.invoke(app, ["deploy", "files", str(out)])
    assert res.exit_code == 0, res.output
    for name in DEPLOY_FILES:
        assert (out / name).read_bytes() == files("cell.deploy").joinpath(name).read_bytes()
        assert f"wrote {out / name}" in res.output
    assert f"sudo cp {out}/systemd/cell.service /etc/systemd/system/" in res.output
    assert f"sudo cp {out}/udev/99-vl53l8cx.rules /etc/udev/rules.d/" in res.output
    assert "ExecStart=/opt/cell/venv/bin/cell serve" in (out / "systemd/cell.service").read_text()
    (out / "udev/99-vl53l8cx.rules").write_text("mine")
    again = runner.invoke(app, ["deploy", "files", str(out)])
    assert again.exit_code == 1 and "never overwrites" in again.output
    assert (out / "udev/99-vl53l8cx.rules").read_text() == "mine"


@pytest.mark.parametrize("template", TEMPLATES)
def test_packaged_hints_name_what_an_installed_cell_has(tmp_path, template):
    """The marks said '(calibration/README.md)', a file of the checkout; they name the command that
    prints the installed guide."""
    text = template_path(template).read_text()
    assert not CHECKOUT_PATHS.search(text)
    res = CliRunner().invoke(app, ["init", str(tmp_path / "c"), "--template", template, "--name", "c-1"])
    assert res.exit_code == 0 and not CHECKOUT_PATHS.search(res.output), res.output
    if "mount" in text and "MEASURE" in text:
        assert f"({GUIDE_COMMAND})" in res.output


def test_the_calibration_guide_is_printed_by_the_command_the_hints_name():
    res = CliRunner().invoke(app, GUIDE_COMMAND.split()[1:])
    assert res.exit_code == 0 and "## The sensor mount: `cell calibrate mount`" in res.output


def test_the_emulators_hint_names_a_cell_file_that_exists():
    command = check_command("socket://127.0.0.1:18790")
    assert not CHECKOUT_PATHS.search(command)
    words = shlex.split(command)
    config = words[words.index("--config") + 1]
    assert config == str(template_path("ur5e-vl53l8cx")) and template_path("ur5e-vl53l8cx").is_file()
