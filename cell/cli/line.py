"""``cell line dio``: the packing line's digital-I/O handshake (``line.dio``) of a running ``cell serve``.

``show`` prints each wired input as the handshake counts it (after its debounce filter) and each output as
the service last wrote it; ``set`` drives an input of a sim cell's simulated UR5e high or low, as a PLC's
wire would, so that an integrator can try the whole handshake (``docs/packml-opcua.md``) before the robot
arrives. A real UR5e's inputs are its wires: ``set`` is refused there. The service and the key are given as
to ``cell jobs`` (``--server``, ``--key``; ``set`` needs a ``line`` key).
"""

from __future__ import annotations

from typing import Annotated, Any

import typer

from cell.cli.commands import command_group
from cell.cli.errors import fail
from cell.cli.jobs import DEFAULT_SERVER, JsonOption, KeyOption, ServerOption, _client, _print, _print_json

line_app = command_group(help="The packing line of a running `cell serve`: its digital-I/O handshake "
                              "(`cell line dio`).", no_args_is_help=True)
dio_app = command_group(help="The line's digital-I/O handshake: show its signals; set a sim cell's inputs.",
                        no_args_is_help=True)
line_app.add_typer(dio_app, name="dio")

LEVELS = {"high": True, "1": True, "on": True, "true": True, "low": False, "0": False, "off": False,
          "false": False}
"""The words ``set`` takes for a level."""


def _level(level: bool | None) -> str:
    return "-" if level is None else ("high" if level else "low")


def _print_levels(dio: dict[str, Any]) -> None:
    link = "connected" if dio["connected"] else "not connected"
    _print(f"digital I/O: {'simulated UR5e (sim cell)' if dio['simulated'] else 'UR5e'}, {link}")
    for kind, prefix in (("inputs", "DI"), ("outputs", "DO")):
        for signal in dio[kind]:
            _print(f"  {prefix}{signal['pin']}  {signal['name']:14s}  {_level(signal['level'])}")


@dio_app.command("show")
def show(
    json_out: JsonOption = False,
    server: ServerOption = DEFAULT_SERVER,
    key: KeyOption = None,
) -> None:
    """Each wired input (as the handshake counts it, after its debounce filter) and output (as last
    written; `-` before the link first connected)."""
    with _client(server, key) as client:
        dio = client.line_dio()
    if json_out:
        _print_json(dio)
    else:
        _print_levels(dio)


@dio_app.command("set")
def set_input(
    name: Annotated[str, typer.Argument(metavar="INPUT", help="the input: trigger_input or reset_input")],
    level: Annotated[str, typer.Argument(metavar="LEVEL", help="high or low (also 1/0, on/off)")],
    server: ServerOption = DEFAULT_SERVER,
    key: KeyOption = None,
) -> None:
    """Drive an input of a sim cell's simulated UR5e high or low (a line key). The handshake counts the new
    level once it has held for line.dio.debounce_s; `show` says when it has."""
    wanted = LEVELS.get(level.strip().lower())
    if wanted is None:
        raise fail(f"level {level!r}: give high or low (1/0, on/off)")
    with _client(server, key) as client:
        dio = client.set_line_input(name, wanted)
    pin = next(signal["pin"] for signal in dio["inputs"] if signal["name"] == name)
    # the handshake has not counted it yet: the level shown by `show` follows after the debounce filter
    _print(f"{name} (DI{pin}) set {_level(wanted)}; the handshake counts it once it has held for "
           "line.dio.debounce_s (cell line dio show)")
