"""Ctrl-C (SIGINT) and SIGTERM for the ``rbo-jax`` console command: the process stops within a
moment, even inside a long compiled XLA call, says in one line what was kept and how to go on,
and exits with 128 + the signal's number (130 for Ctrl-C, 143 for SIGTERM).

Why not Python's own handling: CPython runs a signal handler (and raises KeyboardInterrupt) only
in the main thread, between two bytecodes; while that thread waits in XLA's compiled solve it
runs no bytecode, so Ctrl-C did nothing for as long as the solve ran (minutes). What works
instead: CPython's C-level handler, which the kernel runs in whichever thread it interrupts,
writes the signal's number to the *wakeup file descriptor* (:func:`signal.set_wakeup_fd`) before
anything else. :func:`install` points that at a pipe and starts a daemon thread blocked on
reading it (blocked in ``read``, it holds no GIL; JAX releases the GIL while XLA computes, so the
thread gets it at once). On a signal that thread runs the cleanups (:func:`_stop`): the
temporaries of unfinished outputs are removed (outputs are written whole:
:mod:`rbo_jax.app._outputs`), the lock files of sweep stores are released
(:func:`rbo_jax.batch.progress.release_locks`), the one line is printed, and the process ends with
``os._exit``, whatever the main thread is doing. A watchdog ends it anyway after
:data:`DEADLINE_S`, should a cleanup hang (a stalled network file system).

This design blocks no signal, so child processes (``subprocess``, the processes of a local Dask
cluster) start with the usual signal mask and default handlers (``exec`` resets handled signals);
a child made by ``fork`` without ``exec`` gets the default handlers back too (:func:`_in_child`),
since the thread that would read the pipe does not exist there.

Only the console command installs this (:func:`rbo_jax.app.cli.run`); :func:`rbo_jax.app.cli.main`
called as a function leaves the process's signal handling alone and turns a
``KeyboardInterrupt`` into the same message and status (:func:`message`).
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from collections.abc import Callable

from ...batch.progress import release_locks

__all__ = ["DEADLINE_S", "install", "message", "set_command", "set_describer"]

DEADLINE_S = 1.5
_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_state: dict = {"command": None, "describe": None, "installed": False}


def set_command(name: str | None) -> None:
    """The command running (``simulate``, ``sweep``, ...), for the message."""
    _state["command"] = name


def set_describer(describe: Callable[[], str] | None) -> None:
    """A function that says what was kept and how to go on, replacing the default (the outputs
    written so far, or "nothing was written"); e.g. a sweep's chunks in its store. It runs in
    the interrupt thread and must be quick."""
    _state["describe"] = describe


def _default_description() -> str:
    from .._outputs import WRITTEN

    if WRITTEN:
        return (
            f"kept {', '.join(WRITTEN)} (complete); the rest was not written; run the command again"
        )
    return "nothing was written (outputs are written whole, at the end); run the command again"


def message(signum: int = signal.SIGINT) -> str:
    """The one line printed when the command is interrupted by ``signum``."""
    describe = _state["describe"] or _default_description
    try:
        what = describe()
    except Exception as e:  # the message must come out whatever went wrong
        what = f"could not tell what was kept ({type(e).__name__}: {e})"
    name = signal.Signals(signum).name
    command = _state["command"]
    # no full stop at the end: the line may end with a command to copy
    return f"rbo-jax{' ' + command if command else ''}: interrupted ({name}); {what}"


def cleanup() -> None:
    """Remove the temporaries of unfinished outputs and release the sweep stores' locks (also
    used by :func:`rbo_jax.app.cli.main` on a ``KeyboardInterrupt``)."""
    from .._outputs import remove_pending

    remove_pending()
    release_locks()


def _stop(signum: int) -> None:
    code = 128 + signum
    watchdog = threading.Timer(DEADLINE_S, os._exit, (code,))
    watchdog.daemon = True
    watchdog.start()
    logging.disable(logging.CRITICAL)  # one line from now on (e.g. no log of a local Dask
    # scheduler in this process about the workers that Ctrl-C took down with it)
    text = message(signum)
    try:
        cleanup()
    finally:
        try:
            if sys.stderr.isatty():
                sys.stderr.write("\n")  # past a progress bar's line
            sys.stderr.write(text + "\n")
            sys.stderr.flush()
            sys.stdout.flush()
        except (OSError, ValueError):
            pass
        os._exit(code)


def _watch(fd: int) -> None:
    while True:
        try:
            data = os.read(fd, 1)
        except InterruptedError:
            continue
        if not data:
            return
        if data[0] in _SIGNALS:
            _stop(data[0])


def _ignore(signum, frame) -> None:
    """The Python-level handler: nothing to do (the watcher thread acts); having a Python
    handler is what makes CPython write to the wakeup descriptor."""


def _in_child() -> None:
    """After ``fork`` in a child: default handling again (no thread reads the pipe there)."""
    try:
        signal.set_wakeup_fd(-1)
        for s in _SIGNALS:
            signal.signal(s, signal.SIG_DFL)
    except ValueError:  # not the main thread of the child
        pass


def install() -> None:
    """Take over SIGINT and SIGTERM for the rest of the process (from the main thread, before
    the command starts)."""
    if _state["installed"]:
        return
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    for s in _SIGNALS:
        signal.signal(s, _ignore)
    threading.Thread(target=_watch, args=(read_fd,), name="rbo-jax-interrupt", daemon=True).start()
    os.register_at_fork(after_in_child=_in_child)
    _state["installed"] = True
