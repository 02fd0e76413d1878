"""Accuracy and time of a lattice solve in float32 against float64 (issue 22).

    python benchmarks/lattice_float32.py [--n 1000,100000] [--t1 20]
    python benchmarks/lattice_float32.py --big 10000000 [--big-t1 2] [--devices D]

The chain of ``bench_lattice.py``; a reference at rtol = 1e-12, atol = 1e-13 (float64); then
float64 at rtol = 1e-8, atol = 1e-10 and float32 at two tolerances: accepted steps, the largest
error of theta over the samples, and microseconds per body and step (second call, after
compilation). Pin the process (``taskset -c 0``) for per-core figures.

``--big N``: one chain of N bodies (10⁷: 60 million state components) in float32 at rtol 1e-5,
atol 1e-6, final state only, on the default devices (one CPU device per core, asked for before
JAX starts; ``--devices`` chooses): the time of the first call and of a second one, the accepted
steps, and the process's peak resident memory (``ru_maxrss``).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
import warnings

import jax


def _devices(argv) -> int:
    """``--devices D`` of the command line, else the cores this process may use."""
    for i, a in enumerate(argv):
        if a.startswith("--devices="):
            return int(a.split("=", 1)[1])
        if a == "--devices" and i + 1 < len(argv):
            return int(argv[i + 1])
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


if __name__ == "__main__":  # one CPU device per core, before JAX starts
    jax.config.update("jax_num_cpu_devices", _devices(sys.argv[1:]))

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rbo_jax  # noqa: F401, E402  (float64 on)
from rbo_jax import lattice as L  # noqa: E402

try:
    from bench_lattice import build_lattice, initial_state
except ImportError:  # run from the repository root
    from benchmarks.bench_lattice import build_lattice, initial_state

SETTINGS = ((jnp.float64, 1e-8, 1e-10), (jnp.float32, 1e-5, 1e-6), (jnp.float32, 1e-6, 1e-6))


def big(n: int, t1: float):
    lat, _ = build_lattice(n)
    th0, Om0 = initial_state(n)
    ts = np.array([0.0, t1])
    run = lambda: L.simulate(lat, th0, Om0, ts, rtol=1e-5, atol=1e-6, dtype=jnp.float32)  # noqa: E731
    start = time.perf_counter()
    traj = run()
    jax.block_until_ready(traj.theta)
    first = time.perf_counter() - start
    start = time.perf_counter()
    traj = run()
    jax.block_until_ready(traj.theta)
    seconds = time.perf_counter() - start
    steps = int(traj.num_steps)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB -> GiB
    print(
        f"N = {n}, float32, rtol 1e-5, atol 1e-6, t in [0, {t1:g}]: {traj.message}; "
        f"{steps} steps; {len(traj.theta.sharding.device_set)} shard(s) on "
        f"{jax.local_device_count()} CPU device(s); first call {first:.1f} s, second "
        f"{seconds:.1f} s = {seconds / n / steps * 1e6:.3f} us/body-step; peak resident "
        f"memory {rss:.1f} GiB; finite: {bool(np.all(np.isfinite(np.asarray(traj.theta))))}"
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", default="1000,100000", help="chain sizes")
    parser.add_argument("--t1", type=float, default=20.0)
    parser.add_argument("--big", type=int, default=0, help="one float32 chain of this size")
    parser.add_argument("--big-t1", type=float, default=2.0)
    parser.add_argument("--devices", type=int, default=None, help="CPU devices (default: cores)")
    args = parser.parse_args()
    if args.big:
        return big(args.big, args.big_t1)
    print(
        f"{'N':>8}  {'precision':>9}  {'rtol':>6}  {'atol':>6}  {'steps':>5}  "
        f"{'max|theta-ref|':>14}  {'us/body-step':>12}"
    )
    for n in (int(x) for x in args.n.split(",")):
        lat, _ = build_lattice(n)
        th0, Om0 = initial_state(n)
        ts = np.linspace(0.0, args.t1, 5)
        ref = L.simulate(lat, th0, Om0, ts, rtol=1e-12, atol=1e-13)
        for dtype, rtol, atol in SETTINGS:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # float32 at tolerances near its resolution
                run = lambda: L.simulate(lat, th0, Om0, ts, rtol=rtol, atol=atol, dtype=dtype)  # noqa: E731
                jax.block_until_ready(run().theta)
                start = time.perf_counter()
                traj = run()
                jax.block_until_ready(traj.theta)
                seconds = time.perf_counter() - start
            err = np.abs(np.asarray(traj.theta, np.float64) - np.asarray(ref.theta)).max()
            steps = int(traj.num_steps)
            print(
                f"{n:8d}  {jnp.dtype(dtype).name:>9}  {rtol:6.0e}  {atol:6.0e}  {steps:5d}  "
                f"{err:14.1e}  {seconds / n / steps * 1e6:12.3f}"
            )


if __name__ == "__main__":
    main()
