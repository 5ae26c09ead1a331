"""The ``cell`` program loads the command it runs and nothing else (``cell.cli.commands``): an operator's
``cell stop``, the service's clients (``cell jobs``, ``cell keys``) and ``cell planners`` answer without
loading Open3D, SciPy or the planners, which only a scan needs; the service lists planners by name and
leaves them to its job's worker; ``cell --help`` lists every command, with the help each has, and loads
none of them."""

from __future__ import annotations

import importlib
import inspect
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import typer

from cell.cli.commands import COMMANDS, command_help
from cell.planning.base import Planner
from cell.planning.registry import PLANNERS, get_planner
from tests.service_process import REPO

# Runs the installed program's entry point with the given arguments, then prints which of the heavy
# libraries it loaded; the command's own exit is not the point here.
_LOADED_AFTER = """
import json, sys
sys.argv = ["cell", *sys.argv[1:]]
from cell.cli.entry import main
try:
    main()
except SystemExit:
    pass
heavy = ("open3d", "scipy", "cell.planning.base", "cell.jobs.runner", "fastapi")
loaded = {name: name in sys.modules for name in heavy}
print(json.dumps({**loaded, "commands": sorted(m for m in sys.modules if m.startswith("cell.cli.")
                                               and m not in ("cell.cli.entry", "cell.cli.commands"))}))
"""


def _loaded(*args: str) -> dict[str, bool]:
    """Which of the heavy libraries ``cell *args`` loaded (the command modules it loaded left out)."""
    return {name: loaded for name, loaded in _run(*args).items() if name != "commands"}


def _run(*args: str) -> dict:
    proc = subprocess.run([sys.executable, "-c", _LOADED_AFTER, *args], cwd=REPO, capture_output=True,
                          text=True, timeout=120, check=False)
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("args", [("stop", "nowhere"), ("jobs", "--help"), ("keys", "--help"), ("planners",)])
def test_stop_the_service_clients_and_the_planner_list_load_no_heavy_library(args):
    assert not any(_loaded(*args).values())


@pytest.mark.parametrize("args", [("--help",), (), ("nosuch",)])
def test_the_command_list_loads_no_command(args):
    loaded = _run(*args)
    assert loaded.pop("commands") == [] and not any(loaded.values())


def test_the_list_gives_each_command_the_help_the_command_has():
    """The list reads each command's help from its module's source; loaded, the command has the same."""
    for location in COMMANDS.values():
        module, attribute = location.split(":")
        target = getattr(importlib.import_module(module), attribute)
        if isinstance(target, typer.Typer):
            assert command_help(location) == (target.info.help, True)
        else:
            assert command_help(location) == (inspect.getdoc(target), False)


def _commands(command: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], Any]]:
    """Every command of the ``cell`` command line with its path of names, groups' commands included."""
    for name, sub in getattr(command, "commands", {}).items():
        yield (*path, name), sub
        yield from _commands(sub, (*path, name))


def test_every_argument_has_a_help_and_an_upper_case_name():
    """As the docs name them (``cell reprocess JOB_DIR``, ``cell deploy files FOLDER``): usage lines said
    ``{job_dir}`` and ``{folder}``, and three arguments had no help at all."""
    from typer.core import TyperArgument

    from cell.cli.main import app

    arguments = [(" ".join(path), param) for path, command in _commands(typer.main.get_command(app))
                 for param in command.params if isinstance(param, TyperArgument)]
    assert len(arguments) >= 14
    for path, param in arguments:
        assert param.help, f"cell {path} {param.name}: no help"
        assert param.metavar and param.metavar == param.metavar.upper(), f"cell {path} {param.name}"


def test_no_help_gives_a_flag_a_type():
    """``--help <bool>``, ``--wait <bool>``: Typer's type column made every flag read as an option that takes
    a value; the command list, read from the sources, is checked as well."""
    from typer.testing import CliRunner

    from cell.cli.main import app

    paths = [path for path, _ in _commands(typer.main.get_command(app))]
    for path in [(), *paths]:
        shown = CliRunner().invoke(app, [*path, "--help"], env=_wide())
        assert shown.exit_code == 0 and "--help" in shown.stdout, path
        assert "<bool>" not in shown.stdout, path
    listing = subprocess.run([sys.executable, "-m", "cell.cli.entry", "--help"], cwd=REPO,
                             capture_output=True, text=True, timeout=120, check=True, env=_wide()).stdout
    assert "--install-completion" in listing and "<bool>" not in listing


def test_a_scan_loads_the_planners_and_the_service_does_not():
    assert _loaded("scan", "--help") == {"open3d": True, "scipy": True, "cell.planning.base": True,
                                         "cell.jobs.runner": True, "fastapi": False}
    # SciPy's special functions for the map's parameters; no planner, no Open3D
    assert _loaded("serve", "--help") == {"open3d": False, "scipy": True, "cell.planning.base": False,
                                          "cell.jobs.runner": False, "fastapi": True}


def test_the_help_lists_every_command_and_a_stop_of_no_job_says_why(tmp_path: Path):
    help_text = subprocess.run([sys.executable, "-m", "cell.cli.entry", "--help"], cwd=REPO,
                               capture_output=True, text=True, timeout=120, check=True).stdout
    assert all(f" {name} " in help_text for name in COMMANDS)
    stop = subprocess.run([sys.executable, "-m", "cell.cli.entry", "stop", str(tmp_path)], cwd=REPO,
                          capture_output=True, text=True, timeout=120, check=False)
    assert stop.returncode == 1
    assert stop.stderr.strip() == f"error: {tmp_path} is not a job folder (no log.txt)"


def test_a_commands_help_keeps_its_units_and_placeholders():
    """Help texts give units in brackets and placeholders in braces; a markup that took "[s]" for a style
    tag printed "time budget  (default: ...)"."""
    scan = subprocess.run([sys.executable, "-m", "cell.cli.entry", "scan", "--help"], cwd=REPO,
                          capture_output=True, text=True, timeout=120, check=True, env=_wide()).stdout
    assert "time budget [s]" in scan and "jobs/{stamp}-..." in scan
    jog = subprocess.run([sys.executable, "-m", "cell.cli.entry", "arm", "jog", "--help"], cwd=REPO,
                         capture_output=True, text=True, timeout=120, check=True, env=_wide()).stdout
    assert "signed distance [m] or angle [rad]" in jog


def _wide() -> dict[str, str]:
    """The environment with a terminal wide enough that no help line wraps inside a phrase tested."""
    return {**os.environ, "COLUMNS": "160"}


# Imports every command's module and then runs the named command line, with the client libraries of
# the optional extras (pyproject.toml) unimportable, as in a venv installed with none of them.
_WITHOUT_EXTRAS = """
import importlib, importlib.abc, json, sys
EXTRAS = {"franky", "rtde_control", "rtde_receive", "rtde_io", "serial", "psycopg", "cv2", "ray", "board",
          "busio", "adafruit_extended_bus", "vl53lxcx"}

class NoExtras(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in EXTRAS:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, NoExtras())
from cell.cli.commands import COMMANDS
failed = {}
for name, location in COMMANDS.items():
    try:
        importlib.import_module(location.split(":")[0])
    except ImportError as exc:
        failed[name] = str(exc)
print(json.dumps(failed))
"""


def test_every_command_loads_without_the_optional_extras():
    """A venv built from the wheel with the extras of one robot lacks the other robot's library; a module
    that imports a driver library at its top (``cell doctor`` imported franky) fails even ``--help``."""
    proc = subprocess.run([sys.executable, "-c", _WITHOUT_EXTRAS], cwd=REPO, capture_output=True, text=True,
                          timeout=120, check=True)
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == {}


def test_every_registered_planner_loads_as_a_planner():
    """The registry names each planner by where it lives, imported only when a job runs it: each entry
    must load a planner class."""
    assert all(issubclass(get_planner(name), Planner) for name in PLANNERS)
    assert len({entry.location for entry in PLANNERS.values()}) == len(PLANNERS)


@pytest.mark.parametrize("args", [
    ("scan", "--bogus"), ("scan", "--seed", "abc"), ("scan", "--max-time", "abc"),
    ("scan", "--object-scale", "abc"),
    ("scan", "--planner", "vs-local", "--planner", "vs-global"), ("nosuch",), ("config", "check"),
    ("config", "check", "--bogus"), ("jobs", "list", "--bogus"), ("stop", "--bogus"),
])
def test_a_usage_error_of_any_command_exits_1_with_clicks_message(args):
    """Click's usage errors exited 2, the code ``cell scan`` documents for a scan that found no object."""
    proc = subprocess.run([sys.executable, "-m", "cell.cli.entry", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=120, check=False, env={**os.environ, "COLUMNS": "200"})
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "Usage: cell" in proc.stderr and "Error" in proc.stderr


def test_an_option_of_one_value_given_twice_is_refused():
    proc = subprocess.run([sys.executable, "-m", "cell.cli.entry", "scan", "--planner", "vs-local",
                           "--planner", "vs-global"], cwd=REPO, capture_output=True, text=True, timeout=120,
                          check=False, env={**os.environ, "COLUMNS": "200"})
    assert proc.returncode == 1
    assert "option --planner was given 2 times; it takes one value: give it once" in proc.stderr
