"""Accuracy and time of a lattice solve in float32 against float64 (issue 22).

    python benchmarks/lattice_float32.py [--n 1000,100000] [--t1 20]

The chain of ``bench_lattice.py``; a reference at rtol = 1e-12, atol = 1e-13 (float64); then
float64 at rtol = 1e-8, atol = 1e-10 and float32 at two tolerances: accepted steps, the largest
error of theta over the samples, and microseconds per body and step (second call, after
compilation). Pin the process (``taskset -c 0``) for per-core figures.
"""

from __future__ import annotations

import argparse
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

import rbo_jax  # noqa: F401  (float64 on)
from rbo_jax import lattice as L

try:
    from bench_lattice import build_lattice, initial_state
except ImportError:  # run from the repository root
    from benchmarks.bench_lattice import build_lattice, initial_state

SETTINGS = ((jnp.float64, 1e-8, 1e-10), (jnp.float32, 1e-5, 1e-6), (jnp.float32, 1e-6, 1e-6))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", default="1000,100000", help="chain sizes")
    parser.add_argument("--t1", type=float, default=20.0)
    args = parser.parse_args()
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
