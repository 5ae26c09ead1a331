"""The RTDE controller peer's own watchdog: what the tests that run against the peer rely on."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.rtde_peer import ControllerPeer
from tests.rtde_peer.controller import TICK_S, Controller

COMMAND_REGISTER = "input_int_register_0"
# the lines of ur-rtde's control script the peer reads: where its registers start
SCRIPT = "def rtde_control():\n  global reg_offset_int = 0\n  global reg_offset_float = 0\nend"


def running_controller(watchdog_hz: float) -> Controller:
    """A controller running ur-rtde's script, its watchdog armed, the command register just written."""
    ctl = Controller()
    ctl.start_program(SCRIPT)
    assert ctl.program_running
    ctl.watchdog_hz = watchdog_hz
    ctl.write_inputs([COMMAND_REGISTER], [0])
    return ctl


def test_a_stall_of_the_peer_is_not_the_clients_silence_but_its_cycles_are() -> None:
    ctl = running_controller(watchdog_hz=2.0)
    ctl.tick(0.6)  # the peer's process descheduled for longer than the watchdog's 0.5 s
    assert ctl.program_running
    for _ in range(round(0.45 / TICK_S)):
        ctl.tick(TICK_S)
    assert ctl.program_running
    for _ in range(round(0.05 / TICK_S)):
        ctl.tick(TICK_S)
    assert not ctl.program_running
    assert "program ended: RTDE watchdog expired: no command for 0.50" in ctl.events[-1]


def test_a_write_of_the_command_register_renews_the_watchdog() -> None:
    ctl = running_controller(watchdog_hz=2.0)
    for _ in range(4):
        for _ in range(round(0.4 / TICK_S)):
            ctl.tick(TICK_S)
        ctl.write_inputs([COMMAND_REGISTER], [0])
    assert ctl.program_running


def test_the_peer_and_its_threads_run_in_the_real_time_class_where_the_machine_allows_it() -> None:
    may = subprocess.run([sys.executable, "-c", "import os; os.sched_setscheduler(0, os.SCHED_RR, "
                          "os.sched_param(1))"], capture_output=True).returncode == 0
    peer = ControllerPeer()
    try:
        peer.state()  # the control connection's thread runs too
        tasks = [int(t.name) for t in Path(f"/proc/{peer.pid}/task").iterdir()]
        policies = {os.sched_getscheduler(tid) for tid in tasks}
    finally:
        peer.stop()
    assert len(tasks) > 2
    assert policies == {os.SCHED_RR if may else os.SCHED_OTHER}
