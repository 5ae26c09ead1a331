"""Run the UR controller peer: ``python -m tests.rtde_peer --host 127.0.0.2``.

It prints ``ready <host>`` once its ports listen, then serves until killed or told ``{"op": "shutdown"}``
on its control port (30099). ``--q`` sets the start joints (e.g. a cell's ``home_joints_rad``). Example,
from another shell:
``echo '{"op": "protective_stop"}' | nc -q1 127.0.0.2 30099``.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading

import numpy as np

from tests.rtde_peer.controller import Controller, PeerServer


def main() -> None:
    parser = argparse.ArgumentParser(description="Emulated UR e-series controller for ur-rtde clients.")
    parser.add_argument("--host", default="127.0.0.2", help="loopback address to listen on")
    parser.add_argument("--no-remote-control", action="store_true",
                        help="answer 'false' to the dashboard's 'is in remote control'")
    parser.add_argument("--q", type=_joints, default=None,
                        help="start joints [rad], six comma-separated values (default: the UR home pose)")
    parser.add_argument("--exit-on-stdin-eof", action="store_true",
                        help="shut down when standard input closes (the test process that started it ended)")
    args = parser.parse_args()
    controller = Controller(remote_control=not args.no_remote_control)
    if args.q is not None:
        controller.q = args.q
    _real_time()
    server = PeerServer(args.host, controller)
    if args.exit_on_stdin_eof:
        threading.Thread(target=_shutdown_on_eof, args=(server,), daemon=True).start()
    print(f"ready {args.host}", flush=True)
    server.run()


def _real_time() -> None:
    """Run this process's threads (the math libraries' pools, started at import, and the threads started
    later, which inherit it) in the round-robin real-time class, as a controller runs its cycle. In the
    normal class, a test run that loads both cores starved the peer for up to 0.25 s, and a driver rightly
    took that silence for a controller gone silent."""
    try:
        for task in os.listdir("/proc/self/task"):
            os.sched_setscheduler(int(task), os.SCHED_RR, os.sched_param(1))
    except PermissionError:
        print("the peer may not run in the real-time class here: under load it may fall silent, as a "
              "controller does not", file=sys.stderr, flush=True)


def _joints(text: str) -> np.ndarray:
    q = np.array([float(v) for v in text.split(",")])
    if q.shape != (6,):
        raise argparse.ArgumentTypeError(f"six joint values needed, got {q.size}")
    return q


def _shutdown_on_eof(server: PeerServer) -> None:
    sys.stdin.read()
    server.shutdown()


if __name__ == "__main__":
    main()
