"""``cell eval <command> --help``: each option's help names the default of that command, not one text for
every command ("default: the shipped sim-ur5e-tof cell for packing, sim-franka-rgbd for the others" read,
under ``cell eval grid``, as if its packing planners got the ToF cell; they get the Franka cell)."""

from __future__ import annotations

import typer

from cell.cli.eval import eval_app


def _helps(command: str) -> dict[str, str]:
    """Option name -> its help, of ``cell eval <command>``."""
    group = typer.main.get_command(eval_app)
    cmd = group.commands[command]  # type: ignore[attr-defined]
    return {param.opts[0]: param.help or "" for param in cmd.params if param.opts}


def test_each_grid_command_names_its_own_defaults():
    packing = _helps("packing")
    assert packing["--config"] == "cell file (default: the shipped sim-ur5e-tof cell)"
    assert packing["--planners"].endswith("(default: lr-nbv nbv heu)")
    assert packing["--seeds"].endswith("(default: 0 1 2 3 4)")
    assert "horizontal_box" in packing["--objects"]
    table = _helps("vs-table")
    assert table["--config"] == "cell file (default: the shipped sim-franka-rgbd cell)"
    assert table["--planners"].endswith("(default: vs-local vs-global vs-hybrid)")
    assert table["--seeds"].endswith("(default: 0 1 2)")
    assert _helps("heldout")["--planners"].endswith("(default: vs-local)")
    grid = _helps("grid")
    assert grid["--config"].startswith("cell file (default: the shipped sim-franka-rgbd cell, whatever the "
                                       "planners")
    assert "sim-ur5e-tof" not in grid["--config"].split("whatever")[0]
    assert grid["--planners"].endswith("(needed)") and grid["--objects"].endswith("(needed)")
    assert grid["--seeds"].endswith("(default: 0)")
    assert _helps("limit")["--config"] == "cell file (default: the shipped sim-franka-rgbd cell)"
