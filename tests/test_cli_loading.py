"""The ``cell`` program loads the command it runs and nothing else (``cell.cli.commands``): an operator's
``cell stop`` and the service's clients (``cell jobs``, ``cell keys``) answer without loading Open3D, SciPy
or the planners, which only a scan needs; ``cell --help`` still lists every command."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from cell.cli.commands import COMMANDS
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
heavy = ("open3d", "scipy", "cell.planning.registry", "cell.jobs.runner", "fastapi")
print(json.dumps({name: name in sys.modules for name in heavy}))
"""


def _loaded(*args: str) -> dict[str, bool]:
    proc = subprocess.run([sys.executable, "-c", _LOADED_AFTER, *args], cwd=REPO, capture_output=True,
                          text=True, timeout=120, check=False)
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("args", [("stop", "nowhere"), ("jobs", "--help"), ("keys", "--help")])
def test_stop_and_the_service_clients_load_no_heavy_library(args):
    assert not any(_loaded(*args).values())


def test_a_scan_command_loads_what_it_needs():
    assert _loaded("planners") == {"open3d": True, "scipy": True, "cell.planning.registry": True,
                                   "cell.jobs.runner": False, "fastapi": False}


def test_the_help_lists_every_command_and_a_stop_of_no_job_says_why(tmp_path: Path):
    help_text = subprocess.run([sys.executable, "-m", "cell.cli.entry", "--help"], cwd=REPO,
                               capture_output=True, text=True, timeout=120, check=True).stdout
    assert all(f" {name} " in help_text for name in COMMANDS)
    stop = subprocess.run([sys.executable, "-m", "cell.cli.entry", "stop", str(tmp_path)], cwd=REPO,
                          capture_output=True, text=True, timeout=120, check=False)
    assert stop.returncode == 1
    assert stop.stderr.strip() == f"error: {tmp_path} is not a job folder (no log.txt)"
