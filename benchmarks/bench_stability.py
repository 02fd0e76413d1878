"""Time per point of a stability map of the Nikolai problem, three ways, side by side.

Grid: M × c/d × A3/A1 (d = A1 = 1), equilibrium θ = (M/d)k (4.62), spectrum of the 6×6
linearization (4.63)-(4.67).

1. ``rbo_jax.stability_map`` (fast path: the block structure at Ω = 0 reduces the spectrum to
   p = ±sqrt(eig(Zᵀ·∂Ω̇/∂θ)), a 3×3 eigenproblem; jit + vmap in chunks);
2. (a) the plain ``jax.vmap(jnp.linalg.eigvals(jax.jacfwd(vector_field)))`` on the same chunks;
3. (b) a NumPy/SciPy loop (hand-written RHS, finite-difference Jacobian, ``np.linalg.eigvals``)
   on a sample of the points.

Accuracy: every eigenvalue of 1. and 2. is compared with the closed form (4.69).

Usage: ``python benchmarks/bench_stability.py [--n-per-axis 100] [--numpy-sample 2000]``
(100 per axis = 10⁶ points).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
from _common import run_in_chunks, versions
from _numpy_reference import numpy_jacobian

from rbo_jax import (
    FollowerMoment,
    QuadraticFoundation,
    RigidBodyOscillator,
    nikolai_spectrum,
    stability_map,
    transversely_isotropic_inertia,
)

K = jnp.array([0.0, 0.0, 1.0])


def model_fn(M, c, A3):
    return RigidBodyOscillator(
        transversely_isotropic_inertia(1.0, A3, K),
        QuadraticFoundation(c, 1.0, K),
        FollowerMoment(M, K),
    )


def theta_eq_fn(M, c, A3):
    return M * K  # (4.62) with d = 1


def plain_point(x):
    M, c, A3 = x[0], x[1], x[2]
    model = model_fn(M, c, A3)

    def flat(y):
        th_dot, Om_dot = model.vector_field(0.0, (y[:3], y[3:]))
        return jnp.concatenate([th_dot, Om_dot])

    y0 = jnp.concatenate([theta_eq_fn(M, c, A3), jnp.zeros(3)])
    return jnp.sort(jnp.linalg.eigvals(jax.jacfwd(flat)(y0)))


def run_plain(flat_points, chunk):
    """(eigenvalues, seconds, compile seconds) of (a) over the points in chunks."""
    return run_in_chunks(jax.jit(jax.vmap(plain_point)), flat_points, chunk)


def run_numpy(flat_points):
    k = np.asarray(K)
    out = []
    t0 = time.perf_counter()
    for M, c, A3 in flat_points:
        A = (np.eye(3) - np.outer(k, k)) + A3 * np.outer(k, k)
        J = numpy_jacobian(c, 1.0, M, A, np.linalg.inv(A), k, M * k)
        out.append(np.sort_complex(np.linalg.eigvals(J)))
    return np.array(out), time.perf_counter() - t0


def max_error_vs_closed_form(points, eigs):
    spectrum = jax.vmap(lambda x: jnp.sort(nikolai_spectrum(1.0, x[2], x[1], 1.0, x[0])))
    ref = np.asarray(jax.jit(spectrum)(jnp.asarray(points)))
    return float(np.max(np.abs(np.sort_complex(eigs) - np.sort_complex(ref))))


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-per-axis", type=int, default=100)
    parser.add_argument("--numpy-sample", type=int, default=2000)
    parser.add_argument("--chunk", type=int, default=50_000)
    args = parser.parse_args(argv)
    n = args.n_per_axis
    axes = {
        "M": np.linspace(-0.9, 0.9, n),
        "c": np.linspace(0.2, 2.0, n),
        "A3": np.linspace(0.3, 2.0, n),
    }
    grids = np.meshgrid(*axes.values(), indexing="ij")
    flat_points = np.stack([g.ravel() for g in grids], axis=1)
    N = flat_points.shape[0]
    chunk = min(args.chunk, N)

    # First run compiles (once for all chunks); the second, timed run reuses the compiled program.
    t0 = time.perf_counter()
    stability_map(model_fn, axes, theta_eq_fn=theta_eq_fn, chunk_size=chunk)
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    ds = stability_map(model_fn, axes, theta_eq_fn=theta_eq_fn, chunk_size=chunk)
    t_map = time.perf_counter() - t0
    eig_map = ds["eigenvalues"].values.reshape(N, 6)

    eig_plain, t_plain, t_compile_plain = run_plain(flat_points, chunk)
    rng = np.random.default_rng(0)
    sample = flat_points[rng.choice(N, size=min(args.numpy_sample, N), replace=False)]
    eig_np, t_np = run_numpy(sample)

    err_map = max_error_vs_closed_form(flat_points, eig_map)
    err_plain = max_error_vs_closed_form(flat_points, eig_plain)
    err_np = max_error_vs_closed_form(sample, eig_np)
    per = {"map": t_map / N, "plain": t_plain / N, "numpy": t_np / sample.shape[0]}
    print(f"{versions()}; {N} map points (numpy: {sample.shape[0]}), chunk {chunk}")
    header = f"{'method':<44}{'us / point':>12}{'ratio':>9}{'max |p - (4.69)|':>18}"
    print(header)
    print("-" * len(header))
    for key, name, err in [
        ("map", "rbo_jax.stability_map (block fast path)", err_map),
        ("plain", "(a) vmap(eigvals(jacfwd(vector_field)))", err_plain),
        ("numpy", "(b) NumPy loop: FD Jacobian + eigvals", err_np),
    ]:
        print(f"{name:<44}{per[key] * 1e6:>12.3f}{per[key] / per['map']:>9.1f}{err:>18.2e}")
    print(
        f"first map run incl. compilation {t_first:.1f} s; plain compile {t_compile_plain:.1f} s "
        "(compilation not included above)"
    )
    print(f"unstable points (max Re p > 0): {int((ds['kind'] >= 2).sum())} of {N}")
    return {
        "per_point": per,
        "errors": {"map": err_map, "plain": err_plain, "numpy": err_np},
        "ratio": {"plain": per["plain"] / per["map"], "numpy": per["numpy"] / per["map"]},
        "first_run_s": t_first,
        "compile_map_estimate": t_first - t_map,
        "compile_plain": t_compile_plain,
        "n": N,
        "numpy_sample": int(sample.shape[0]),
    }


if __name__ == "__main__":
    main()
