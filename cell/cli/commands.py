"""The ``cell`` command line, built with the commands it is asked for.

Each command lives in a module of its own (:data:`COMMANDS`) and is imported only when it runs: a scan
needs Open3D, SciPy and the planners, seconds of imports, which ``cell stop``, ``cell jobs`` (a client of
the service) or ``cell keys`` must not wait for. ``cell.cli.entry`` builds the command line with the one
command named on it, or with all of them (``cell --help``, a mistyped name).
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable

import typer

# Each command's name and where it lives (module:attribute), a function or a group of commands, in the
# order ``cell --help`` lists them.
COMMANDS: dict[str, str] = {
    "scan": "cell.cli.scan:scan",
    "stop": "cell.cli.stop:stop",
    "reprocess": "cell.cli.reprocess:reprocess",
    "planners": "cell.cli.catalog:planners",
    "objects": "cell.cli.catalog:objects",
    "config": "cell.cli.config_check:config_app",
    "sensor": "cell.cli.sensor:sensor_app",
    "arm": "cell.cli.arm:arm_app",
    "calibrate": "cell.cli.calibrate:calibrate_app",
    "serve": "cell.cli.serve:serve",
    "jobs": "cell.cli.jobs:jobs_app",
    "keys": "cell.cli.keys:keys_app",
    "init": "cell.cli.init_cell:init",
    "backup": "cell.cli.backup:backup",
    "doctor": "cell.cli.doctor:doctor",
    "eval": "cell.cli.eval:eval_app",
}


def cell_app(names: Iterable[str]) -> typer.Typer:
    """The ``cell`` command line with the commands ``names`` (keys of :data:`COMMANDS`), their modules
    imported."""
    app = typer.Typer(help="Autonomous active-vision scanning cell.", no_args_is_help=True,
                      pretty_exceptions_enable=False)

    @app.callback()
    def cell() -> None:
        """Autonomous active-vision scanning cell."""

    for name in names:
        module, attribute = COMMANDS[name].split(":")
        target = getattr(importlib.import_module(module), attribute)
        if isinstance(target, typer.Typer):
            app.add_typer(target, name=name)
        else:
            app.command(name)(target)
    return app
