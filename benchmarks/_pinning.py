"""Pin every thread of this process to a set of cores (Linux), for per-core figures.

``os.sched_setaffinity(0, ...)`` moves only the calling thread; XLA's and numba's worker threads
exist already, so every task of ``/proc/self/task`` is moved. On other systems nothing is pinned
and :func:`pinned` says so.
"""

from __future__ import annotations

import contextlib
import os
import sys


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


def restart_pinned(argv) -> None:
    """Run this script again on one core from its start, as ``taskset -c C`` would, when
    ``argv`` asks for a core (``--core C``; the first core of the process's affinity when it
    asks for none) and the process may run on others: a process started on every core and
    pinned later (:func:`pinned`) keeps XLA's thread pools and JAX's CPU devices sized for all
    of them, and their tasks then queue on one core (measured: the rod's midpoint rule 127 us a
    step pinned later against 87 us started on the core, benchmarks/README.md). Does nothing
    where the process runs on that core alone already, or where affinity cannot be set."""
    if not hasattr(os, "sched_setaffinity"):
        return
    core = None
    for i, arg in enumerate(argv):
        if arg == "--core" and i + 1 < len(argv):
            core = int(argv[i + 1])
        elif arg.startswith("--core="):
            core = int(arg.split("=", 1)[1])
    allowed = os.sched_getaffinity(0)
    core = min(allowed) if core is None else core
    if allowed == {core}:
        return
    os.sched_setaffinity(0, {core})
    os.execv(sys.executable, [sys.executable, *sys.argv])
