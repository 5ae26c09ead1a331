"""Thread scheduling. libfranka raises the thread that talks to the robot to the highest realtime
(SCHED_FIFO) priority whenever it can, even with ``RealtimeConfig.Ignore`` (it only ignores a failure),
and Linux threads and child processes inherit that policy. Work that must never preempt the control loop,
such as perception, drops back to ordinary scheduling first."""

from __future__ import annotations

import os


def is_realtime() -> bool:
    """Whether the calling thread runs under a realtime policy (SCHED_FIFO or SCHED_RR)."""
    return os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR)


def ordinary_scheduling() -> None:
    """Put the calling thread (Linux: pid 0 is the calling thread) back under SCHED_OTHER when it
    inherited a realtime policy; nothing otherwise."""
    if is_realtime():
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
