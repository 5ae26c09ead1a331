"""Give the C heap's free memory back to the system after a job.

A job allocates and frees a few hundred MiB in numpy arrays, Open3D clouds and ray casts. glibc keeps
much of what is freed in its arenas for reuse, fragmented, so a process that runs job after job (an
embedding program, a worker of ``cell.evaluation``) sees its RSS creep up by the largest jobs' leftovers:
not a leak (``benchmarks/soak.py``: RSS stays flat once the free memory is returned), but what an
operator's monitoring sees. ``malloc_trim(0)`` returns it once the job's objects are gone (memory that
a still referenced object, or one in a reference cycle not yet collected, frees after the trim stays
retained: ``run_scan`` trims after its job has returned); where the C library has no ``malloc_trim``
(not glibc), only the garbage is collected.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
from functools import cache
from typing import Any


@cache
def _malloc_trim() -> Any:
    name = ctypes.util.find_library("c")
    libc = ctypes.CDLL(name) if name else None
    return getattr(libc, "malloc_trim", None)


def release_freed_heap() -> None:
    """Free the Python garbage in reference cycles, then return the C heap's free memory to the system
    (glibc; only the collection elsewhere). Takes tens of ms."""
    gc.collect()
    trim = _malloc_trim()
    if trim is not None:
        trim(0)
