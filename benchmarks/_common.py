"""What the benchmark scripts share besides their problem (``_problem.py``): the README's
``rbo-jax`` example (``cli_fit_time.py``, ``latency.py``), a vmapped program timed over chunks of
points, the line naming the versions and the machine, and the ``--json`` output. Each script
still runs alone (``python benchmarks/X.py`` puts this folder first on ``sys.path``); nothing
here imports JAX at import (``bench_sweep.py`` sets JAX's device count before JAX starts).
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

# This checkout's rbo_jax, not the one an environment installed from elsewhere (an editable
# install of another checkout): ``python benchmarks/X.py`` puts only this folder on sys.path, so
# a before/after comparison run from two checkouts would otherwise time the same code twice.
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(1, ROOT)

# The README's example of `rbo-jax fit` (docs/topics/cli.md): observations of a stable
# (conservative) motion made by `rbo-jax simulate`, and the fit starting 30 % / 25 % off.
README_OBSERVATIONS = (
    "--c 1 --d 2 --theta0 0.8,-0.3,0.5 --Omega0 0.2,1.1,-0.7 --t1 6 --samples 61"
).split()
README_FIT = "--c 1.3 --d 1.5 --params c,d".split()
# The README's example of `rbo-jax simulate` (and, before, of the fit): flutter under a follower
# moment.
README_SIMULATE = "--c 1 --d 2 --follower 0.3 --theta0 0.1,0,0.15 --t1 50".split()


def run_in_chunks(fn, points: np.ndarray, chunk: int):
    """``fn`` (a jitted, vmapped function of a batch of points) over ``points`` in chunks of
    ``chunk`` rows, the last padded with copies of the last point. The first chunk is run once
    before, timed as the compilation. Returns (the outputs as NumPy arrays, the points' rows
    only; seconds of the chunks; seconds of the compilation)."""
    import jax
    import jax.numpy as jnp

    n = points.shape[0]
    pad = (-n) % chunk
    padded = np.concatenate([points, np.repeat(points[-1:], pad, axis=0)])
    t0 = time.perf_counter()
    jax.block_until_ready(fn(jnp.asarray(padded[:chunk])))
    t_compile = time.perf_counter() - t0
    outs = []
    t0 = time.perf_counter()
    for i in range(0, padded.shape[0], chunk):
        outs.append(jax.tree_util.tree_map(np.asarray, fn(jnp.asarray(padded[i : i + chunk]))))
    elapsed = time.perf_counter() - t0
    return jax.tree_util.tree_map(lambda *x: np.concatenate(x)[:n], *outs), elapsed, t_compile


def cpu_name() -> str:
    """The processor's model name (``/proc/cpuinfo``), else Python's guess."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if "model name" in line)
    except (OSError, StopIteration):
        pass
    return cpu


def versions() -> str:
    """``rbo_jax X, jax Y, MACHINE, N BACKEND device(s)``."""
    import jax

    import rbo_jax

    return (
        f"rbo_jax {rbo_jax.__version__}, jax {jax.__version__}, {platform.machine()}, "
        f"{jax.device_count()} {jax.default_backend()} device(s)"
    )


def write_json(path, result, **options) -> None:
    """``result`` as JSON to ``path`` (``--json``; nothing when it is not given); ``options``:
    ``json.dump``'s."""
    if path:
        with open(path, "w") as f:
            json.dump(result, f, **options)


# A benchmark's ``main(argv)`` in a fresh process: its stdout passed through, its returned dict
# back as JSON (NumPy values as lists and floats).
_CHILD = """
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
import importlib
result = importlib.import_module(sys.argv[2]).main(sys.argv[4:])
def plain(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return str(x)
with open(sys.argv[3], "w") as f:
    json.dump(result, f, default=plain)
"""


def run_child(module: str, argv, core: int | None = None) -> dict:
    """``module.main(argv)`` (a benchmark of this folder) in a fresh Python process, pinned to
    ``core`` from its start when given (``os.sched_setaffinity`` before the interpreter starts,
    as ``taskset -c core`` does: ``import rbo_jax`` then makes one CPU device, and XLA sizes its
    thread pools for one core). Per-core figures come from such processes: a process started on
    every core and pinned later keeps pools sized for all of them, whose tasks then queue on one
    core (measured: ``jax.vmap(fast_simulate)`` 42 us per trajectory pinned later against 22-27
    us in a process started on the one core). Returns what ``main`` returned."""
    here = os.path.dirname(os.path.abspath(__file__))
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_NUM_CPU_DEVICES",)}
    env["PYTHONUNBUFFERED"] = "1"  # its lines as they come

    def pin():
        if core is not None and hasattr(os, "sched_setaffinity"):
            os.sched_setaffinity(0, {core})

    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "result.json")
        cmd = [sys.executable, "-c", _CHILD, here, module, out, *argv]
        subprocess.run(cmd, check=True, env=env, preexec_fn=pin, cwd=here)
        with open(out) as f:
            return json.load(f)
