"""Run the UR controller peer: ``python -m tests.rtde_peer --host 127.0.0.2``.

It prints ``ready <host>`` once its ports listen, then serves until killed or told ``{"op": "shutdown"}``
on its control port (30099). ``--q`` sets the start joints (e.g. a cell's ``home_joints_rad``). Example,
from another shell:
``echo '{"op": "protective_stop"}' | nc -q1 127.0.0.2 30099``.
"""

from __future__ import annotations

import argparse
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
    server = PeerServer(args.host, controller)
    if args.exit_on_stdin_eof:
        threading.Thread(target=_shutdown_on_eof, args=(server,), daemon=True).start()
    print(f"ready {args.host}", flush=True)
    server.run()


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
