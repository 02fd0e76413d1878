"""A lost process in a multi-process ``rbo-jax sweep`` (jax.distributed on localhost, real
processes, killed with SIGKILL): nothing is lost, nobody hangs (issue 26, item 2) and the
survivor says in one line which process was lost (index, pid, host) and what happens to its
chunks (issue 31, E).

- a worker (process 1) lost: process 0 notices within the heartbeat timeout, prints the line
  naming it and the chunks it takes over, computes them and ends with exit 0; the store equals
  the one-process sweep bit for bit;
- the coordinator (process 0) lost: process 1 ends within seconds with exit 1 and one line that
  names process 0, the chunks kept and missing, and gives the command that finishes the sweep —
  no C++ abort, no stack trace; that command (one process, ``--resume``) finishes the store,
  equal to the one-process sweep;
- either, killed as a user kills a command (``kill -9 PID`` of the ``rbo-jax`` process, not its
  process group): the same, and the process that computed for it ends with it (before, it went
  on unseen, and the survivor ended with exit 0 and no word of a loss);
- the options of a multi-process run are refused before anything starts (exit 2, one line).
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rbo_jax.app import cli

pytest.importorskip("zarr")

ROOT = Path(__file__).resolve().parent.parent

# The Nikolai growth map of examples/nikolai_growth.toml, made smaller: 9 chunks of 8 points
# whose solves take long enough (t1 = 600) that a process can be killed in the middle (with
# t1 = 200 the sweep once ended within one poll of the store, on a loaded machine).
CONFIG = """
[sweep]
quantity = "max_deviation"
output = "growth.zarr"
chunk_size = 8

[axes]
M = { start = 0.05, stop = 0.8, num = 12 }
A3 = { start = 0.2, stop = 2.0, num = 6, log = true }

[model]
inertia = { A1 = 1.0, A3 = "A3" }
foundation = { type = "quadratic", c = 1.0, d = 2.0 }
loads = [{ type = "follower", M = "M" }]

[initial]
about_equilibrium = true
theta0 = [1e-3, 0.0, 0.0]
Omega0 = [0.0, 0.0, 0.0]

[solver]
t1 = 600.0
rtol = 1e-8
atol = 1e-8
samples = 51
"""
RBO_JAX = [
    sys.executable,
    "-c",
    "import sys; sys.argv[0] = 'rbo-jax'; from rbo_jax.app.cli import run; run()",
]
CRASH_MARKS = ("Check failure", "    @ 0x", "Traceback", "terminate called")


def _crashed(err: str) -> bool:
    """Whether stderr shows a C++ abort, JAX's log (glog lines: E1125 12:00:00...) or a
    Python traceback."""
    return any(mark in err for mark in CRASH_MARKS) or any(
        re.match(r"[IWEF]\d{4} \d\d:", line) for line in err.splitlines()
    )


def _env():
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    return env


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _arrays(store: Path) -> dict:
    import xarray as xr

    ds = xr.open_zarr(store)
    return {name: np.asarray(ds[name].values) for name in ds.data_vars}


def _chunks_done(store: Path) -> int:
    import zarr

    try:
        return int(
            (np.asarray(zarr.open_group(store, mode="r")["_sweep/chunk_done"][...]) == 1).sum()
        )
    except Exception:  # not created yet
        return 0


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The sweep on one process (the CLI, as the multi-process runs)."""
    folder = tmp_path_factory.mktemp("one")
    (folder / "growth.toml").write_text(CONFIG)
    done = subprocess.run(
        [*RBO_JAX, "sweep", "growth.toml", "--quiet", "--no-plot"],
        cwd=folder,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return _arrays(folder / "growth.zarr")


# The survivor's line (rbo_jax/batch/_hosts.py lost_line, rbo_jax/app/cli/_distributed.py).
WORKER_LOST = re.compile(
    r"^rbo_jax\.sweep: process 1 of 2 \(pid (\d+) on host (\S+)\) was lost \(no heartbeat\); "
    r"process 0 computes the (\d+) chunks? it left: ([\d, -]+)$"
)
COORDINATOR_LOST = re.compile(
    r"^rbo-jax sweep: error: process 0 of 2 \(pid (\d+) on host (\S+)\), which coordinates "
    r"the run, was lost; (\d+) of (\d+) chunks are kept in growth\.zarr \((\d+) missing: "
    r"([\d, -]+)\); finish the sweep with: rbo-jax (.+) \(or all processes again with --resume\)$"
)


def _ids(ranges: str) -> list[int]:
    """``"1, 3-5"`` as ``[1, 3, 4, 5]``."""
    out = []
    for word in ranges.split(", "):
        a, _, b = word.partition("-")
        out += range(int(a), int(b or a) + 1)
    return out


def _gone(pid: int) -> bool:
    """Whether process ``pid`` has ended (a zombie waiting to be reaped counts as ended)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] in "ZX"
    except FileNotFoundError:
        return True


def _two_processes(folder: Path, kill: int, heartbeat: int, group: bool = True):
    """Start processes 0 and 1 (each in its own session: killing one's group is losing its
    host), SIGKILL process ``kill`` once two chunks are in the store (its process group, or with
    ``group=False`` only the ``rbo-jax`` process, as ``kill -9 PID`` does); the survivor's
    (returncode, stderr, seconds from the kill to its end)."""
    (folder / "growth.toml").write_text(CONFIG)
    store, port = folder / "growth.zarr", _free_port()
    procs = [
        subprocess.Popen(
            [
                *RBO_JAX,
                "sweep",
                "growth.toml",
                "--no-plot",
                "--quiet",
                "--coordinator",
                f"localhost:{port}",
                "--num-processes",
                "2",
                "--process-id",
                str(i),
                "--heartbeat-timeout",
                str(heartbeat),
            ],
            cwd=folder,
            env=_env(),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        for i in range(2)
    ]
    survivor = procs[1 - kill]
    try:
        deadline = time.monotonic() + 300
        while _chunks_done(store) < 2:
            assert time.monotonic() < deadline and survivor.poll() is None, survivor.stderr.read()
            time.sleep(0.05)
        done_at_kill = _chunks_done(store)
        (os.killpg if group else os.kill)(procs[kill].pid, signal.SIGKILL)
        killed = time.monotonic()
        err = survivor.communicate(timeout=300)[1]
        seconds = time.monotonic() - killed
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)
            p.stderr.close()
    assert done_at_kill < 9, "the sweep ended before the kill: make its chunks slower"
    return survivor.returncode, err, seconds


def _same_as_reference(folder: Path, reference):
    got = _arrays(folder / "growth.zarr")
    assert got.keys() == reference.keys()
    for name in reference:
        np.testing.assert_array_equal(got[name], reference[name], err_msg=name)


@pytest.mark.slow  # fault test: SIGKILL to a jax.distributed process
@pytest.mark.parametrize("group", [True, False], ids=["host-lost", "kill-pid"])
def test_lost_worker_named_and_its_chunks_computed_by_process_0(tmp_path, reference, group):
    """Process 1 killed mid-sweep: process 0 sees it lost after the heartbeat timeout (3 s),
    says so in one line (its pid and host, the chunks it takes over), computes them, exits 0;
    the store equals the one-process sweep exactly. Killed by its pid only, process 1's child
    (the pid the line names) ends with it."""
    rc, err, seconds = _two_processes(tmp_path, kill=1, heartbeat=3, group=group)
    assert rc == 0, err[-3000:]
    lines = err.strip().splitlines()
    assert len(lines) == 1, err[-3000:]
    said = WORKER_LOST.match(lines[0])
    assert said, err[-3000:]
    pid, host, count, ids = int(said[1]), said[2], int(said[3]), _ids(said[4])
    assert host == socket.gethostname() and _gone(pid)
    assert 1 <= count == len(ids) <= 7 and all(0 <= i < 12 for i in ids), lines[0]
    assert not _crashed(err), err[-3000:]
    assert seconds < 120
    _same_as_reference(tmp_path, reference)
    assert not (tmp_path / "growth.zarr.lock").exists()


@pytest.mark.slow  # fault test: SIGKILL to a jax.distributed process
@pytest.mark.parametrize("group", [True, False], ids=["host-lost", "kill-pid"])
def test_lost_coordinator_ends_the_worker_in_one_line_and_resume_finishes(
    tmp_path, reference, group
):
    """Process 0 killed mid-sweep: process 1 ends within seconds (not JAX's abort: exit 1, one
    line naming process 0 with its pid and host, the chunks kept and missing and the command
    that finishes); that command on one process completes the store, equal to the one-process
    sweep bit for bit."""
    rc, err, seconds = _two_processes(tmp_path, kill=0, heartbeat=10, group=group)
    assert rc == 1, err[-3000:]
    lines = err.strip().splitlines()
    assert len(lines) == 1, err[-3000:]
    said = COORDINATOR_LOST.match(lines[0])
    assert said, err[-3000:]
    pid, host, kept, total, count, ids = (
        int(said[1]),
        said[2],
        int(said[3]),
        int(said[4]),
        int(said[5]),
        _ids(said[6]),
    )
    assert host == socket.gethostname() and _gone(pid)
    assert total == 12 and kept >= 2 and count == len(ids) == total - kept, lines[0]
    assert not _crashed(err), err[-3000:]
    assert seconds < 60
    command = said[7]
    assert "--coordinator" not in command and command.endswith("--resume")
    done = subprocess.run(
        [*RBO_JAX, *command.split()],
        cwd=tmp_path,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    _same_as_reference(tmp_path, reference)


@pytest.mark.parametrize(
    "lost, left, who, line",
    [
        (
            [1],
            [4, 7, 8],
            {1: "pid 5 on host h"},
            "rbo_jax.sweep: process 1 of 4 (pid 5 on host h) was lost (no heartbeat); "
            "process 0 computes the 3 chunks it left: 4, 7-8",
        ),
        (
            [1, 3],
            list(range(0, 40, 2)),
            {3: "pid 6 on host g"},
            "rbo_jax.sweep: processes 1, 3 (pid 6 on host g) of 4 were lost (no heartbeat); "
            "process 0 computes the 20 chunks they left: 0, 2, 4, 6, 8, 10, 12, 14, ...",
        ),
        (
            [2],
            [],
            {},
            "rbo_jax.sweep: process 2 of 4 was lost (no heartbeat); it left no chunk to compute",
        ),
    ],
)
def test_the_lost_line_names_processes_and_chunks(lost, left, who, line):
    from rbo_jax.batch._hosts import lost_line

    assert lost_line(lost, 4, left, who) == line


@pytest.mark.parametrize(
    "options, message",
    [
        (["--coordinator", "localhost:1234"], "go together"),
        (["--coordinator", "not a host", "--num-processes", "2", "--process-id", "0"], "HOST:PORT"),
        (
            ["--coordinator", "localhost:99999", "--num-processes", "2", "--process-id", "0"],
            "HOST:PORT",
        ),
        (
            ["--coordinator", "localhost:1234", "--num-processes", "2", "--process-id", "5"],
            "--process-id must lie in 0..1",
        ),
        (
            ["--coordinator", "localhost:1234", "--num-processes", "0", "--process-id", "0"],
            "--num-processes must be at least 1",
        ),
        (
            [
                "--coordinator",
                "localhost:1234",
                "--num-processes",
                "2",
                "--process-id",
                "0",
                "--heartbeat-timeout",
                "0",
            ],
            "--heartbeat-timeout must be at least 1",
        ),
        (["--heartbeat-timeout", "5"], "--heartbeat-timeout belongs to a multi-process run"),
    ],
)
def test_multi_process_options_refused_before_anything_starts(tmp_path, capsys, options, message):
    (tmp_path / "growth.toml").write_text(CONFIG)
    rc = cli.main(["sweep", str(tmp_path / "growth.toml"), "--no-plot", *options])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "growth.zarr").exists()
