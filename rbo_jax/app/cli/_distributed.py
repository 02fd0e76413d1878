"""``rbo-jax sweep --coordinator HOST:PORT --num-processes N --process-id I``: one process of a
multi-process sweep over :mod:`jax.distributed`, which ends in words when a process is lost.

**What JAX does on a loss.** Every process sends heartbeats to the coordination service that
process 0 runs. When one stops (killed, its host gone), the service tells every other process
after the heartbeat timeout (100 s by JAX's default), and each of them ends itself by a C++
``LOG(FATAL)``: SIGABRT, a "Check failure stack trace", no word of what happened. When process 0
is lost, the others abort at once. JAX offers no Python hook (its ``missed_heartbeat_callback``
cannot take a Python function: the status argument has no Python type).

**What this module does.**

- The options are checked before anything starts (exit 2 with one line): the three go together,
  ``HOST:PORT`` with a port in 1..65535, ``0 <= I < N``, a heartbeat timeout of at least 1 s
  (``--heartbeat-timeout``, default :data:`HEARTBEAT_S`).
- :func:`supervise`: the command runs again as a child process, which this process waits for.
  The child sends JAX's own log (C++ writes to file descriptor 2) to a file and keeps Python's
  ``sys.stderr`` (progress bar, messages) on the terminal. If the child is ended by a signal —
  JAX's abort — this process reads the log, names the lost process (with its pid and host,
  which the child logged there), releases the store's lock if the child held it, counts the
  chunks kept and missing and prints one line with the command that finishes the sweep
  (``--resume``), exit 1. The child ends itself (SIGKILL) when this process is gone — it watches
  a pipe whose other end this process holds — so that ``kill -9`` of the command a user started
  loses that process of the run, as losing its host does (before, the child went on computing
  unseen: the others never heard of a loss).
- :func:`initialize` (in the child): ``jax.distributed.initialize`` with the heartbeat timeout and
  JAX's recoverable mode (``jax_enable_recoverability``), in which the service survives the loss of
  a process other than 0: then process 0 says in one line which process was lost and which
  chunks it takes over, finishes them itself (:mod:`rbo_jax.batch._hosts`) and the sweep ends
  with exit 0.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

from ._common import Failure

HEARTBEAT_S = 10
#: Set in the child's environment: the file that receives JAX's log.
CHILD_ENV = "RBO_JAX_SWEEP_JAX_LOG"
#: Set in the child's environment: the read end of a pipe that the supervisor holds open.
PARENT_ENV = "RBO_JAX_SWEEP_SUPERVISOR_FD"


def check_options(args: argparse.Namespace) -> bool:
    """Whether the sweep is one process of a multi-process run; invalid options exit 2."""
    given = (args.coordinator, args.num_processes, args.process_id)
    if all(x is None for x in given):
        if args.heartbeat_timeout is not None:
            raise Failure(
                "--heartbeat-timeout belongs to a multi-process run (--coordinator, "
                "--num-processes, --process-id)."
            )
        return False
    if any(x is None for x in given):
        raise Failure("--coordinator, --num-processes and --process-id go together.")
    host, sep, port = args.coordinator.strip().rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host  # [IPv6]
    if (
        not sep
        or not host
        or not re.fullmatch(r"[A-Za-z0-9._:-]+", host)
        or not port.isdigit()
        or not 1 <= int(port) <= 65535
    ):
        raise Failure(
            f"--coordinator {args.coordinator!r}: expected HOST:PORT, the address of "
            "process 0, e.g. localhost:12345 or node01:12345."
        )
    if args.num_processes < 1:
        raise Failure(f"--num-processes must be at least 1, got {args.num_processes}.")
    if not 0 <= args.process_id < args.num_processes:
        raise Failure(
            f"--process-id must lie in 0..{args.num_processes - 1} (--num-processes "
            f"{args.num_processes}), got {args.process_id}."
        )
    if args.heartbeat_timeout is not None and args.heartbeat_timeout < 1:
        raise Failure(f"--heartbeat-timeout must be at least 1 s, got {args.heartbeat_timeout}.")
    return True


def supervised() -> bool:
    """Whether this process is the supervised child."""
    return CHILD_ENV in os.environ


def _who(log: str, index: int) -> str:
    """`` (pid N on host H)`` of process ``index``, as :mod:`rbo_jax.batch._hosts` logged it
    in the child's log; empty if it did not."""
    found = re.findall(rf"process {index} of \d+ is (pid \d+ on host \S+)", log)
    return f" ({found[-1]})" if found else ""


def _lost_process(log: str, count: int) -> str:
    """Which process was lost, from JAX's log of the child."""
    found = re.search(r"stopped sending heartbeats\):\s*([\d,\s]+)", log)
    if found:
        ids = [int(x) for x in re.findall(r"\d+", found.group(1))]
        return (
            f"process {', '.join(map(str, ids))} of {count} was lost (no heartbeat); process 0 "
            "could not go on without it"
        )
    if re.search(
        r"Failed to send RPC to coordination service|Socket closed|"
        r"failed to connect to all addresses|leader task",
        log,
    ):
        return f"process 0 of {count}{_who(log, 0)}, which coordinates the run, was lost"
    tail = [line for line in log.splitlines() if re.match(r"[EF]\d{4} ", line)]
    return "JAX's distributed runtime ended this process" + (
        f" ({tail[-1].split('] ', 1)[-1][:200]})" if tail else ""
    )


def supervise(args: argparse.Namespace, store: Path) -> int:
    """Run the command in a child process and turn its death by a signal into one line."""
    fd, log_path = tempfile.mkstemp(prefix="rbo-jax-sweep-", suffix=".log")
    os.close(fd)
    # the child ends itself when this process is gone (its end of the pipe closes): killing
    # this process, the one the user started, loses the process of the run, as losing its host
    # does; without it the child would go on unseen (the others never hear of a loss)
    watched, held = os.pipe()
    env = dict(os.environ, **{CHILD_ENV: log_path, PARENT_ENV: str(watched)})
    code = "import sys; sys.argv[0] = 'rbo-jax'; from rbo_jax.app.cli import run; run()"
    try:
        child = subprocess.Popen(
            [sys.executable, "-c", code, *args.argv], env=env, pass_fds=(watched,)
        )
    finally:
        os.close(watched)

    def forward(signum, frame):  # Ctrl-C reaches the child from the terminal too
        if child.poll() is None:
            child.send_signal(signum)

    signal.set_wakeup_fd(-1)  # the command's own Ctrl-C thread: the child says what was kept
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, forward)
    try:
        rc = child.wait()
        log = Path(log_path).read_text(errors="replace")
    finally:
        os.close(held)
        Path(log_path).unlink(missing_ok=True)
    if rc >= 0:
        return rc
    name = signal.Signals(-rc).name
    if -rc in (signal.SIGINT, signal.SIGTERM):
        return 128 - rc
    what = (
        _lost_process(log, args.num_processes)
        if -rc == signal.SIGABRT
        else f"process {args.process_id} was killed ({name})"
    )
    from ...batch.progress import chunk_ranges, chunks_done, missing_chunks, release_lock_of
    from ._sweep_store import resume_command

    release_lock_of(store, child.pid)
    counts = chunks_done(store)
    missing = missing_chunks(store) if counts is not None else None
    kept = (
        f"{counts[0]} of {counts[1]} chunks are kept in {store}"
        + (f" ({len(missing)} missing: {chunk_ranges(missing)})" if missing else "")
        if counts is not None
        else f"nothing was written to {store}"
    )
    one = argparse.Namespace(argv=single_process_argv(args.argv))
    print(
        f"rbo-jax sweep: error: {what}; {kept}; finish the sweep with: {resume_command(one)} "
        "(or all processes again with --resume)",
        file=sys.stderr,
    )
    return 1


_OPTIONS = ("--coordinator", "--num-processes", "--process-id", "--heartbeat-timeout")


def single_process_argv(argv: list[str]) -> list[str]:
    """``argv`` without the multi-process options (``--opt value`` and ``--opt=value``)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a in _OPTIONS:
            skip = True
        elif not a.startswith(tuple(o + "=" for o in _OPTIONS)):
            out.append(a)
    return out


def _end_with_supervisor():
    """In the child: a thread that kills this process (SIGKILL, as a lost host) as soon as the
    supervisor is gone, i.e. its end of the pipe of :data:`PARENT_ENV` closes."""
    import threading

    fd = os.environ.get(PARENT_ENV)
    if fd is None:
        return

    def watch():
        try:
            while os.read(int(fd), 1):  # the supervisor never writes: this waits for the end
                pass
        except OSError:  # not a pipe of ours
            return
        os.kill(os.getpid(), getattr(signal, "SIGKILL", signal.SIGTERM))

    threading.Thread(target=watch, name="rbo-jax supervisor watch", daemon=True).start()


def initialize(args: argparse.Namespace):
    """In the child: JAX's log to the file of :data:`CHILD_ENV`, Python's stderr kept on the
    terminal, and the processes' pids and hosts logged there too (``rbo_jax.sweep``, INFO),
    for :func:`supervise` to name a lost process 0; then ``jax.distributed.initialize`` with the
    heartbeat timeout, recoverable. The child ends when its supervisor does."""
    import io
    import logging

    import jax

    _end_with_supervisor()
    sys.stderr.flush()  # what Python wrote so far goes to the terminal
    terminal = os.dup(2)
    log = os.open(os.environ[CHILD_ENV], os.O_WRONLY | os.O_APPEND | os.O_CREAT)
    os.dup2(log, 2)
    os.close(log)
    sys.stderr = io.TextIOWrapper(
        io.FileIO(terminal, "w", closefd=True), write_through=True, line_buffering=True
    )
    to_log = logging.StreamHandler(open(2, "w", closefd=False, buffering=1))  # noqa: SIM115
    to_log.setFormatter(logging.Formatter("rbo_jax: %(message)s"))
    logger = logging.getLogger("rbo_jax.sweep")
    logger.addHandler(to_log)
    logger.setLevel(logging.INFO)
    logger.propagate = False  # not on the terminal
    jax.config.update("jax_enable_recoverability", True)
    heartbeat = HEARTBEAT_S if args.heartbeat_timeout is None else args.heartbeat_timeout
    try:
        jax.distributed.initialize(
            coordinator_address=args.coordinator.strip(),
            num_processes=args.num_processes,
            process_id=args.process_id,
            heartbeat_timeout_seconds=int(heartbeat),
        )
    except Exception as e:  # JAX's message names the address; say what to check
        raise Failure(
            f"could not join the run at --coordinator {args.coordinator} as process "
            f"{args.process_id} of {args.num_processes}: {str(e).splitlines()[0][:300]}",
            code=1,
        ) from None
