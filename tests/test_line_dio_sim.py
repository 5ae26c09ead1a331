"""The digital-I/O handshake on a sim cell: its simulated UR5e's inputs set and its outputs read with
``cell line dio`` against a real ``cell serve``, through a whole cycle (Reset input, trigger, busy, done,
the trigger's fall as the acknowledgement), as an integrator tries the handshake before the robot
arrives."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from pydantic import ValidationError
from typer.testing import CliRunner, Result

from cell.cli.main import app
from cell.config.models import CellConfig
from tests.service_process import ServedCell

from .conftest import CONFIG_DIR

TOF = CONFIG_DIR / "sim-ur5e-tof.yaml"
PINS = {"trigger_input": 0, "reset_input": 1, "busy_output": 0, "done_output": 1, "ready_output": 2,
        "fault_output": 3}
WAIT_S = 120.0
"""A bound on waiting for the line (a scan on a loaded machine), not a timed check."""


def _sim_dio_cell(folder: Path) -> Path:
    data = yaml.safe_load(TOF.read_text())
    data["arm"] |= PINS
    data["line"] = {"dio": {"part_id": "horizontal_box", "debounce_s": 0.02}, "max_time_s": 3.0}
    path = folder / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServedCell]:
    folder = tmp_path_factory.mktemp("line-dio-sim")
    with ServedCell(_sim_dio_cell(folder), folder / "data") as cell:
        yield cell


def _dio(cell: ServedCell, *args: str, role: str = "line") -> Result:
    return CliRunner().invoke(app, ["line", "dio", *args], env={"CELL_SERVER": cell.url,
                                                                "CELL_KEY": cell.keys[role]})


def _levels(cell: ServedCell) -> dict[str, bool | None]:
    shown = _dio(cell, "show", "--json", role="viewer")
    assert shown.exit_code == 0, shown.output
    dio = json.loads(shown.stdout)
    return {signal["name"]: signal["level"] for signal in dio["inputs"] + dio["outputs"]}


def _wait(cell: ServedCell, what: str, **levels: bool) -> dict[str, bool | None]:
    """Poll ``cell line dio show`` until the signals have ``levels``."""
    deadline = time.monotonic() + WAIT_S
    while True:
        now = _levels(cell)
        if all(now[name] == level for name, level in levels.items()):
            return now
        assert time.monotonic() < deadline, f"never {what}: {now}\n{cell.log()}"
        time.sleep(0.05)


def _set(cell: ServedCell, name: str, level: str) -> None:
    """Set a simulated input and wait until the handshake has counted it (past its debounce filter): a
    PLC holds a level that long, however slowly this machine runs."""
    done = _dio(cell, "set", name, level)
    assert done.exit_code == 0, done.output
    assert done.stdout.startswith(f"{name} (DI{PINS[name]}) set {level}"), done.stdout
    _wait(cell, f"{name} counted {level}", **{name: level == "high"})


def _line(cell: ServedCell) -> dict[str, Any]:
    with cell.client("viewer") as client:
        state: dict[str, Any] = client.get("/api/v1/line").json()
    return state


def test_a_whole_handshake_on_the_sim_cell_with_cell_line_dio(served: ServedCell) -> None:
    """A sim cell refused line.dio (a sim arm had no digital I/O): an integrator had nothing to try the
    handshake against before the robot came. The simulated UR5e's inputs now drive it."""
    shown = _dio(served, "show", role="viewer")
    assert shown.exit_code == 0, shown.output
    assert shown.stdout.splitlines() == [
        "digital I/O: simulated UR5e (sim cell), connected",
        "  DI0  trigger_input   low", "  DI1  reset_input     low", "  DO0  busy_output     low",
        "  DO1  done_output     low", "  DO2  ready_output    low", "  DO3  fault_output    low"]
    assert _line(served)["state_name"] == "Stopped"
    # the reset input's pulse: Reset, ready high in Idle
    _set(served, "reset_input", "high")
    _set(served, "reset_input", "low")
    _wait(served, "ready in Idle", ready_output=True, busy_output=False, fault_output=False)
    assert _line(served)["message"] == "Reset from digital input DI1 rising"
    # a held trigger: Start, busy in Execute, done in Complete with the feeder's part; its fall is Reset
    _set(served, "trigger_input", "high")
    _wait(served, "busy or done after the trigger rose", ready_output=False)
    complete = _wait(served, "done in Complete", done_output=True)
    assert complete["busy_output"] is False
    line = _line(served)
    assert (line["state_name"], line["result"]["part_id"]) == ("Complete", "horizontal_box"), line
    assert line["message"] == "Start from digital input DI0 rising"
    _set(served, "trigger_input", "low")
    _wait(served, "ready after the trigger fell", done_output=False, ready_output=True)
    assert _line(served)["processed"] == 1
    assert "simulated digital input trigger_input (DI0) set low by REST (key test-line)" in served.log()


def test_only_wired_inputs_with_a_line_key_and_a_level_word(served: ServedCell) -> None:
    unwired = _dio(served, "set", "busy_output", "high")
    assert unwired.exit_code == 1
    assert "no wired input 'busy_output'; this cell's: trigger_input, reset_input" in unwired.output
    assert _dio(served, "set", "trigger_input", "maybe").exit_code == 1
    refused = _dio(served, "set", "trigger_input", "high", role="viewer")
    assert refused.exit_code == 1 and "403" in refused.output, refused.output
    assert _levels(served)["trigger_input"] is False


def test_line_dio_needs_a_real_or_simulated_ur5e() -> None:
    data = yaml.safe_load(TOF.read_text())
    data["arm"] |= PINS
    data["line"] = {"dio": {}}
    assert CellConfig.model_validate(data).line is not None
    data["arm"]["model"] = "panda"
    with pytest.raises(ValidationError, match=r"line\.dio is the UR5e's digital-I/O handshake .* a simulated "
                                              r"panda has none"):
        CellConfig.model_validate(data)
