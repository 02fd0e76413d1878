"""Wall time of the README's ``rbo-jax fit`` in a first process (empty compilation cache) and a
second one (the same cache). Not part of ``run.py``: every run spawns processes.

    python benchmarks/cli_fit_time.py --runs 3                 # this checkout
    python benchmarks/cli_fit_time.py --tree /path/to/checkout  # another one (before/after)
    python benchmarks/cli_fit_time.py --example follower        # the former README example

Each run makes a fresh cache directory (``RBO_JAX_COMPILATION_CACHE``), runs the fit twice and
prints both wall times (process start to exit) and CPU times (user + system) with the load
average; the data file is made once by ``rbo-jax simulate`` (not timed). Timings on a shared
machine vary with its load: compare runs made side by side.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time

from _common import README_FIT, README_OBSERVATIONS, README_SIMULATE

EXAMPLES = {
    # the README's example: a stable (conservative) motion, the fit starts 30 % / 25 % off
    "readme": (README_OBSERVATIONS, README_FIT),
    # the README's example before: flutter under a follower moment, fitted without it
    "follower": (README_SIMULATE, ["--params", "c,d"]),
}


def _cpu():
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _rbo_jax(tree, args, env):
    """(wall time, CPU time, completed process) of ``rbo-jax ARGS`` run from ``tree``."""
    code = "import sys; from rbo_jax.app.cli import main; sys.exit(main())"
    env = dict(env, PYTHONPATH=tree)
    start, cpu = time.perf_counter(), _cpu()
    # run from the tree: ``python -c`` puts the working directory first on sys.path, ahead of
    # PYTHONPATH, so a run started elsewhere would import that directory's rbo_jax
    proc = subprocess.run(
        [sys.executable, "-c", code, *args], env=env, capture_output=True, text=True, cwd=tree
    )
    return time.perf_counter() - start, _cpu() - cpu, proc


def main(argv=None):
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", default=here, help="checkout to time (default: this one)")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--example", choices=sorted(EXAMPLES), default="readme")
    parser.add_argument("--fit-args", default="", help="more options for rbo-jax fit")
    args = parser.parse_args(argv)
    sim_args, fit_args = EXAMPLES[args.example]
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, RBO_JAX_COMPILATION_CACHE="off")
        data = os.path.join(tmp, "run.nc")
        _, _, proc = _rbo_jax(args.tree, ["simulate", *sim_args, "--out", data], env)
        if proc.returncode:
            sys.exit(f"rbo-jax simulate failed:\n{proc.stdout}\n{proc.stderr}")
        fit = ["fit", "--data", data, *fit_args, *args.fit_args.split()]
        print(f"tree {args.tree}, example {args.example}: rbo-jax {' '.join(fit)}")
        for run in range(args.runs):
            env["RBO_JAX_COMPILATION_CACHE"] = tempfile.mkdtemp(dir=tmp)
            times = []
            for _ in range(2):
                wall, cpu, proc = _rbo_jax(args.tree, fit, env)
                if proc.returncode not in (0, 1):
                    sys.exit(f"rbo-jax fit failed:\n{proc.stdout}\n{proc.stderr}")
                times.append((wall, cpu))
            load = os.getloadavg()[0]
            last = proc.stdout.strip().splitlines()
            (w1, c1), (w2, c2) = times
            print(
                f"run {run + 1}: first {w1:.2f} s (CPU {c1:.2f} s), second {w2:.2f} s "
                f"(CPU {c2:.2f} s), load {load:.2f}; "
                f"{next((x.strip()[:60] for x in last if 'iterations' in x), '')}"
            )
        print(proc.stdout)


if __name__ == "__main__":
    main()
