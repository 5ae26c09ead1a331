"""What the digital-I/O handshake publishes (``GET /api/v1/line/dio``) while its link comes up: a connected
link always says when the levels it shows were sampled, even while its first write of the outputs is
still under way (a UR5e's first write connects RTDE IO, which takes seconds on a loaded PC)."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path
from types import SimpleNamespace

from cell.line.config import DigitalIOConfig, LineConfig
from cell.line.controller import LineController
from cell.line.dio import DigitalIOHandshake, DigitalLevels
from cell.service.store import open_store, sqlite_url
from drivers.arm.config import LinePinsConfig
from drivers.arm.sim_io import SimDigitalIO

WAIT_S = 10.0


class _SlowFirstWrite(SimDigitalIO):
    """A simulated UR5e's I/O whose first write of the outputs blocks until the test releases it."""

    def __init__(self) -> None:
        super().__init__()
        self.writing = threading.Event()
        self.release = threading.Event()

    def set_outputs(self, outputs: list[tuple[int, bool]]) -> None:
        self.writing.set()
        assert self.release.wait(WAIT_S), "the test never released the write"
        super().set_outputs(outputs)


def test_a_connected_link_says_when_its_levels_were_sampled_while_its_first_write_is_under_way(
        tmp_path: Path) -> None:
    io = _SlowFirstWrite()
    io.set_input(0, True)  # the trigger is high when the link connects: its baseline
    pins = LinePinsConfig(trigger_input=0, busy_output=0, done_output=1)

    async def scenario() -> DigitalLevels:
        line = LineController(SimpleNamespace(name="cell-a"), LineConfig(),  # type: ignore[arg-type]
                              open_store(sqlite_url(tmp_path)))
        await line.start()
        handshake = DigitalIOHandshake(line, pins, DigitalIOConfig(), io)
        handshake.start()
        try:
            assert await asyncio.to_thread(io.writing.wait, WAIT_S), "the outputs were never written"
            return handshake.levels()
        finally:
            io.release.set()
            await handshake.close()
            await line.close()

    during = asyncio.run(scenario())
    assert during.connected and during.sampled_s is not None, during
    assert [(s.name, s.level) for s in during.inputs] == [("trigger_input", True)], during
