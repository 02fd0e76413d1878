"""One writer per sweep store.

The process that writes a store (process 0 of a multi-process run, for all of them) holds the
file ``PATH.lock`` beside the store (so that creating or overwriting the store happens under the
lock), created atomically (``O_CREAT | O_EXCL``) with its host, process
id, process start time and a heartbeat: a background thread touches the file every
``HEARTBEAT_S`` seconds while the sweep runs. A second writer (same host or another) gets an
error that names the store and the owner. A lock left by a process that died is taken over,
with a message: on the same host when that process no longer exists (or its id was reused by
another process), on another host when the heartbeat is older than ``STALE_S``. The lock is
removed when the sweep ends, so a finished store holds no trace of it.

The locks this process holds are listed (:func:`release_held`), so that the interrupt handler of
``rbo-jax`` (which ends the process with ``os._exit``, skipping every ``finally``) can remove
their files: an interrupted sweep leaves no lock behind, and ``--resume`` starts without taking
one over.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import threading
import time
from pathlib import Path

from ._errors import SweepError

HEARTBEAT_S = 30.0
STALE_S = 300.0
_HELD: set[StoreLock] = set()


def _process_start(pid: int) -> str | None:
    """The start time of process ``pid`` (Linux /proc), or None where unknown."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _alive(owner: dict) -> bool | None:
    """Whether the owner process runs: True/False on this host, None on another host."""
    if owner.get("host") != socket.gethostname():
        return None
    pid = int(owner.get("pid", -1))
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    start = owner.get("start")
    return start is None or _process_start(pid) in (None, start)


def _describe(owner: dict) -> str:
    return (
        f"process {owner.get('pid')} on host {owner.get('host')} (since {owner.get('since', '?')})"
    )


class StoreLock:
    """The lock of one store; use as a context manager (``with StoreLock(path): ...``)."""

    def __init__(self, path: Path):
        path = Path(path)
        self.file = path.with_name(path.name + ".lock")
        self.store = path
        self._stop = threading.Event()
        self._thread = None

    def _create(self) -> bool:
        self.file.parent.mkdir(parents=True, exist_ok=True)
        owner = {
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "start": _process_start(os.getpid()),
            "since": time.strftime("%Y-%m-%d %H:%M:%S"),
        }
        try:
            fd = os.open(self.file, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            return False
        with os.fdopen(fd, "w") as f:
            json.dump(owner, f)
        return True

    def _owner(self) -> dict:
        try:
            return json.loads(self.file.read_text())
        except (OSError, ValueError):
            return {}

    def acquire(self):
        store = self.store
        while not self._create():
            owner = self._owner()
            alive = _alive(owner)
            try:
                age = time.time() - self.file.stat().st_mtime
            except FileNotFoundError:
                continue  # released meanwhile: try again
            if alive or (alive is None and age < STALE_S):
                raise SweepError(
                    f"the store {store} is being written by {_describe(owner)}; one writer per "
                    "store (wait for it to finish, or write to another store)."
                )
            why = "no longer runs" if alive is False else f"sent no heartbeat for {age:.0f} s"
            print(
                f"rbo_jax.sweep: taking over the lock of {store}: its owner, "
                f"{_describe(owner)}, {why}.",
                file=sys.stderr,
            )
            self.file.unlink(missing_ok=True)
        self._thread = threading.Thread(target=self._beat, daemon=True)
        self._thread.start()
        _HELD.add(self)
        return self

    def _beat(self):
        while not self._stop.wait(HEARTBEAT_S):
            try:
                os.utime(self.file)
            except OSError:
                return

    def release(self):
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.file.unlink(missing_ok=True)
        _HELD.discard(self)

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()


def release_held() -> None:
    """Remove the lock files of every store this process holds, at once (from any thread: the
    heartbeat threads are told to stop, not waited for). For a process about to end abruptly."""
    for lock in list(_HELD):
        lock._stop.set()
        try:
            lock.file.unlink(missing_ok=True)
        except OSError:
            pass
        _HELD.discard(lock)
