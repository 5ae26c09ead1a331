"""Cost of a UR5e control tick through the process that holds the ur-rtde clients: ``state()`` then
``command_twist()`` (two round trips to the child: the state read, then ``speedL``; ``command_twist``
checks faults on the state read less than one RTDE period before, and only the first tick also reads the
state again and arms the watchdog), against the RTDE controller peer on loopback (tests/rtde_peer), paced
at 500 Hz (a UR e-series controller's cycle) for ``--ticks`` ticks. Also ``state()`` alone. Wall time
per call from ``time.perf_counter`` (median, p99, maximum); CPU per tick of the driver's process
(``time.process_time``) and of the child (its utime + stime from /proc, which includes its connection
monitor). No reference runs beside it (docs/ur5e-driver.md, "Cost"). Prints readable lines, then one
line of JSON.

    .venv/bin/python benchmarks/ur_rtde_tick.py [--ticks 1000]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from options import BenchmarkParser, count

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for tests.*

from drivers.arm.ur5e import UR5eArm
from drivers.robots import get_robot_model
from tests.arm_backends import ur5e_config
from tests.rtde_peer import ControllerPeer

PERIOD_S = 0.002  # 500 Hz
RTDE_HZ = 125.0  # the peer is a Python process: the rate the tests use


def child_cpu_s(pid: int) -> float:
    """User + system CPU time [s] of process ``pid``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def percentiles_ms(times: list[float]) -> dict[str, float]:
    t = np.asarray(times) * 1e3
    return {"median_ms": round(float(np.median(t)), 4), "p99_ms": round(float(np.percentile(t, 99)), 4),
            "max_ms": round(float(t.max()), 4)}


def main() -> None:
    parser = BenchmarkParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ticks", type=count, default=1000, help="ticks timed (and state() calls alone)")
    ticks = parser.parse_args().ticks
    peer = ControllerPeer()
    arm = UR5eArm(ur5e_config(peer.host, rtde_frequency_hz=RTDE_HZ), get_robot_model("ur5e"))
    arm.connect()
    try:
        token = arm.claim_motion()
        pid = arm.client_pid
        assert pid is not None
        state_times = []
        for _ in range(ticks):
            t0 = time.perf_counter()
            arm.state()
            state_times.append(time.perf_counter() - t0)
        tick_times = []
        cpu0, child0 = time.process_time(), child_cpu_s(pid)
        next_t = time.perf_counter()
        for k in range(ticks):
            # 1 mm/s up and down: the flange stays where it is
            v = np.array([0.0, 0.0, 0.001 if (k // 250) % 2 == 0 else -0.001, 0.0, 0.0, 0.0])
            t0 = time.perf_counter()
            arm.state()
            arm.command_twist(v, token)
            tick_times.append(time.perf_counter() - t0)
            next_t += PERIOD_S
            time.sleep(max(0.0, next_t - time.perf_counter()))
        cpu_ms = (time.process_time() - cpu0) / ticks * 1e3
        child_ms = (child_cpu_s(pid) - child0) / ticks * 1e3
        arm.stop()
    finally:
        arm.disconnect()
        peer.stop()
    state = percentiles_ms(state_times)
    tick = percentiles_ms(tick_times)
    over = int(np.sum(np.asarray(tick_times) > PERIOD_S))
    figures = {
        "state": state,
        "tick": {**tick, "cpu_driver_ms": round(cpu_ms, 4), "cpu_child_ms": round(child_ms, 4),
                 "over_period": over},
        "ticks": ticks, "period_ms": PERIOD_S * 1e3, "rtde_hz": RTDE_HZ,
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    print(f"state():                 median {state['median_ms']:.3f} ms, p99 {state['p99_ms']:.3f} ms, "
          f"max {state['max_ms']:.3f} ms")
    print(f"state() + command_twist: median {tick['median_ms']:.3f} ms, p99 {tick['p99_ms']:.3f} ms, "
          f"max {tick['max_ms']:.3f} ms, "
          f"CPU {cpu_ms:.3f} ms driver + {child_ms:.3f} ms child, {over} of {ticks} ticks over the 2 ms "
          "period")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
