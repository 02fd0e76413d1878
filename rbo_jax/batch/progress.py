"""The progress of a sweep store as a front end reads it without opening the store as a dataset:
``rbo-jax sweep`` says in one line what an interrupted run, or a run that lost a process, kept
and how to finish it.

:func:`chunks_done` and :func:`missing_chunks` read the done markers of the store's chunks
(:mod:`rbo_jax.batch._store`), :func:`chunk_ranges` writes chunk ids for people,
:func:`release_locks` removes the lock files this process holds (for an interrupt handler that
ends the process at once) and :func:`release_lock_of` the one a process that died left. Nothing
here imports more than the standard library's ``sys`` and ``pathlib`` before it is called, so
the command line imports it at its start and its interrupt handler may call it at any time.
"""

from __future__ import annotations

import sys
from pathlib import Path

__all__ = ["chunk_ranges", "chunks_done", "missing_chunks", "release_lock_of", "release_locks"]


def chunk_ranges(ids: list[int], most: int = 8) -> str:
    """``[1, 2, 3, 5, 8, 9]`` as ``"1-3, 5, 8-9"``; past ``most`` ranges the rest as "..."."""
    ranges: list[list[int]] = []
    for i in sorted(ids):
        if ranges and i == ranges[-1][1] + 1:
            ranges[-1][1] = i
        else:
            ranges.append([i, i])
    words = [str(a) if a == b else f"{a}-{b}" for a, b in ranges]
    return ", ".join(words[:most] + (["..."] if len(words) > most else []))


def _markers(path):
    """The done marker of every chunk (1: done), or None where there is no store at ``path``
    (yet), or not one of a sweep."""
    import numpy as np

    from . import _store

    if not (Path(path) / "zarr.json").exists():
        return None
    try:
        group = _store.open_group(path, "r")
        return np.asarray(group[f"{_store.META}/chunk_done"][...]).ravel()
    except Exception:  # a store being created, or not one of a sweep
        return None


def chunks_done(path) -> tuple[int, int] | None:
    """``(done, all)``: the chunks of the store at ``path`` that are written, and all of them;
    None where there is no store (yet)."""
    done = _markers(path)
    return None if done is None else (int((done == 1).sum()), int(done.size))


def missing_chunks(path) -> list[int] | None:
    """The ids of the chunks the store at ``path`` is missing; None where there is no store."""
    done = _markers(path)
    return None if done is None else [int(i) for i in (done == 0).nonzero()[0]]


def release_locks() -> None:
    """Remove the lock files of every store this process holds, at once, if a sweep ran in
    it (:func:`rbo_jax.batch._lock.release_held`)."""
    lock = sys.modules.get(f"{__package__}._lock")  # loaded only if a sweep ran
    if lock is not None:
        lock.release_held()


def release_lock_of(path, pid: int) -> None:
    """Remove the lock file of the store at ``path`` if process ``pid`` of this host (one that
    died) held it."""
    import json
    import socket

    lock = Path(str(path) + ".lock")
    try:
        owner = json.loads(lock.read_text())
    except (OSError, ValueError):
        return
    if owner.get("pid") == pid and owner.get("host") == socket.gethostname():
        lock.unlink(missing_ok=True)
