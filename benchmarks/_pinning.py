"""Pin every thread of this process to a set of cores (Linux), for per-core figures.

``os.sched_setaffinity(0, ...)`` moves only the calling thread; XLA's and numba's worker threads
exist already, so every task of ``/proc/self/task`` is moved. On other systems nothing is pinned
and :func:`pinned` says so.
"""

from __future__ import annotations

import contextlib
import os


def _set(cpus) -> bool:
    if not hasattr(os, "sched_setaffinity") or not os.path.isdir("/proc/self/task"):
        return False
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), cpus)
        except OSError:  # the thread ended meanwhile
            pass
    return True


@contextlib.contextmanager
def pinned(cpus=(0,)):
    """Within the block every thread runs on ``cpus``; yields whether pinning was possible."""
    before = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    ok = _set(set(cpus))
    try:
        yield ok
    finally:
        if ok and before is not None:
            _set(before)
