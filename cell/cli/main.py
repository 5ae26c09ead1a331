"""``cell`` with all its commands (:mod:`cell.cli.commands`): what tests and ``python -m cell.cli.main``
run. The installed ``cell`` program (:mod:`cell.cli.entry`) loads only the command it runs."""

from __future__ import annotations

from cell.cli.commands import COMMANDS, cell_app

app = cell_app(COMMANDS)

if __name__ == "__main__":
    app(prog_name="cell")
