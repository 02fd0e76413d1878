"""Trajectories per second: ``jax.vmap(simulate)`` vs ``scipy.integrate.solve_ivp`` (DOP853).

The Nikolai problem (4.57)–(4.62): transversely isotropic body (A1 = 1, A3 = 0.5), quadratic
foundation (4.50), follower moment M; each parameter point (c, d, M) starts 1e-3 rad off its
equilibrium θ = (M/d)k; t ∈ [0, 20], rtol = atol = 1e-8, final state only.

Both sides use an 8th-order Dormand–Prince method at the same tolerances: diffrax ``Dopri8`` on
the JAX side, ``solve_ivp(method="DOP853")`` with a plain NumPy right-hand side on the scipy side
(run on a sample of the points: it is ~1000x slower). The final states of the sample are compared
(an independent check of the vector field), and the per-trajectory time ratio is printed.

Usage: ``python benchmarks/bench_simulate.py [--n 10000] [--scipy-sample 20] [--chunk 2500]``
"""

from __future__ import annotations

import argparse
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
from _numpy_reference import numpy_rhs
from scipy.integrate import solve_ivp

import rbo_jax
from rbo_jax import (
    FollowerMoment,
    QuadraticFoundation,
    RigidBodyOscillator,
    simulate,
    transversely_isotropic_inertia,
)

A1, A3 = 1.0, 0.5
K = np.array([0.0, 0.0, 1.0])
T1, RTOL = 20.0, 1e-8
PERTURBATION = np.array([1e-3, -5e-4, 2e-4])


def parameter_points(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    c = rng.uniform(0.5, 2.0, n)
    d = rng.uniform(0.5, 2.0, n)
    M = rng.uniform(0.05, 0.6, n)
    return np.stack([c, d, M], axis=1)


# ---------------------------------------------------------------------------------------------
# JAX side.
# ---------------------------------------------------------------------------------------------


def jax_final_state(p):
    c, d, M = p[0], p[1], p[2]
    k = jnp.asarray(K)
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, k),
        QuadraticFoundation(c, d, k),
        FollowerMoment(M, k),
    )
    theta0 = (M / d) * k + jnp.asarray(PERTURBATION)
    traj = simulate(
        model, theta0, jnp.zeros(3), jnp.array([0.0, T1]), rtol=RTOL, atol=RTOL, throw=False
    )
    return jnp.concatenate([traj.theta[-1], traj.Omega[-1]]), traj.num_steps


def run_jax(points: np.ndarray, chunk: int):
    fn = jax.jit(jax.vmap(jax_final_state))
    n = points.shape[0]
    pad = (-n) % chunk
    padded = np.concatenate([points, np.repeat(points[-1:], pad, axis=0)])
    t_compile = time.perf_counter()
    jax.block_until_ready(fn(jnp.asarray(padded[:chunk])))
    t_compile = time.perf_counter() - t_compile
    outs, steps = [], []
    start = time.perf_counter()
    for i in range(0, padded.shape[0], chunk):
        y, s = fn(jnp.asarray(padded[i : i + chunk]))
        outs.append(np.asarray(y))
        steps.append(np.asarray(s))
    elapsed = time.perf_counter() - start
    return np.concatenate(outs)[:n], np.concatenate(steps)[:n], elapsed, t_compile


# ---------------------------------------------------------------------------------------------
# NumPy / scipy side: an independent plain-NumPy right-hand side of (4.55)-(4.56).
# ---------------------------------------------------------------------------------------------


def run_scipy(points: np.ndarray):
    A = A1 * (np.eye(3) - np.outer(K, K)) + A3 * np.outer(K, K)
    A_inv = np.linalg.inv(A)
    outs, nfev = [], []
    start = time.perf_counter()
    for c, d, M in points:
        y0 = np.concatenate([(M / d) * K + PERTURBATION, np.zeros(3)])
        sol = solve_ivp(
            numpy_rhs, (0.0, T1), y0, method="DOP853", rtol=RTOL, atol=RTOL,
            args=(c, d, M, A, A_inv, K),
        )
        assert sol.success, sol.message
        outs.append(sol.y[:, -1])
        nfev.append(sol.nfev)
    elapsed = time.perf_counter() - start
    return np.array(outs), np.array(nfev), elapsed


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=10_000, help="parameter points for JAX")
    parser.add_argument("--scipy-sample", type=int, default=20, help="points run with scipy")
    parser.add_argument("--chunk", type=int, default=500, help="vmap chunk size")
    args = parser.parse_args(argv)

    points = parameter_points(args.n)
    y_jax, steps, t_jax, t_compile = run_jax(points, min(args.chunk, args.n))
    sample = points[: args.scipy_sample]
    y_sp, nfev, t_sp = run_scipy(sample)
    err = np.max(np.abs(y_jax[: args.scipy_sample] - y_sp))
    per_jax = t_jax / args.n
    per_sp = t_sp / args.scipy_sample
    print(f"rbo_jax {rbo_jax.__version__}, jax {jax.__version__}, {platform.processor() or platform.machine()}, "
          f"{jax.device_count()} {jax.default_backend()} device(s)")
    print(f"Nikolai problem, t in [0, {T1}], rtol = atol = {RTOL:g}, {args.n} points "
          f"(scipy: {args.scipy_sample})")
    header = f"{'method':<38}{'s / trajectory':>16}{'traj / s':>12}{'steps (mean)':>14}"
    print(header)
    print("-" * len(header))
    print(f"{'jax.vmap(simulate), Dopri8, chunks':<38}{per_jax:>16.3e}{1 / per_jax:>12.1f}"
          f"{steps.mean():>14.1f}")
    print(f"{'scipy solve_ivp DOP853, NumPy RHS':<38}{per_sp:>16.3e}{1 / per_sp:>12.1f}"
          f"{nfev.mean() / 12:>14.1f}")
    print(f"speed-up per trajectory: {per_sp / per_jax:.0f}x   (compile once: {t_compile:.1f} s, "
          f"not included)")
    print(f"max |final state difference| jax vs scipy on the sample: {err:.2e}")
    return {"per_jax": per_jax, "per_scipy": per_sp, "ratio": per_sp / per_jax, "max_diff": err}


if __name__ == "__main__":
    main()
