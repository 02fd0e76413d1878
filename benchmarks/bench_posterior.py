"""Wall time, draws/s and ESS/s of :func:`rbo_jax.fitting._posterior.posterior` (NUTS through the
fit's residuals): forward-mode gradients (``fast_simulate``, -Jᵀr in a custom VJP) against
reverse mode through diffrax (``simulate``), chains split over the devices (``shard_map``)
against a plain ``vmap``.

The problem: the rig of docs/topics/fitting.md — a transversely isotropic body (A1 = 1, A3 = 0.6) on
QuadraticFoundation(c=1, d=2) with Friction(b=0.05); two experiments of ``--seconds`` s each made
by ``synthetic_sensor_data``: quaternions at 100 Hz (jittered, 5 % missing, 0.01 rad noise) and
a gyroscope at 200 Hz with a bias (0.02 rad/s noise, a gap); c, d, b, the bias and both
initial states sampled (18 coordinates). Target: 2 chains x 1000 draws (500 warmup) in
<= 3 min on 2 cores, R-hat < 1.01, bulk ESS > 200, the truth inside the 90 % interval.

Usage: ``python benchmarks/bench_posterior.py [--seconds 10] [--warmup 500] [--samples 1000]
[--integrators fast_simulate,simulate] [--chain-methods pmap,vmap]``. A standalone table (not
part of ``benchmarks/run.py``).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from rbo_jax.fitting import fit, synthetic_sensor_data  # noqa: E402
from rbo_jax.fitting._fit import setup  # noqa: E402
from rbo_jax.fitting._posterior import (  # noqa: E402
    _dense_budget,
    _laplace,
    _log_density,
    posterior,
)
from rbo_jax.foundations import QuadraticFoundation  # noqa: E402
from rbo_jax.inertia import transversely_isotropic_inertia  # noqa: E402
from rbo_jax.loads import Friction  # noqa: E402
from rbo_jax.model import RigidBodyOscillator  # noqa: E402

K = jnp.array([0.0, 0.0, 1.0])
A = transversely_isotropic_inertia(1.0, 0.6, K)
TRUTH = {"foundation.c": 1.0, "foundation.d": 2.0, "loads[0].b": 0.05}
BIAS = np.array([0.02, -0.015, 0.01])


def model(c, d, b):
    return RigidBodyOscillator(A, QuadraticFoundation(c, d, K), loads=(Friction(b),))


def params(m):
    return (m.foundation.c, m.foundation.d, m.loads[0].b)


def experiment(theta0, Omega0, T, seed):
    """The rig's records (``synthetic_sensor_data``): quaternions at 100 Hz with jitter, 5 %
    lost; a gyroscope at 200 Hz with the bias and a gap over 40-50 % of the run."""
    return synthetic_sensor_data(
        model(1.0, 2.0, 0.05), theta0, Omega0, T, quaternion_rate=100.0, gyro_rate=200.0,
        bias=BIAS, dropped=0.05, gaps=((0.4 * T, 0.5 * T),), seed=seed,
    )  # fmt: skip


def gradient_ms(start, data, integrator, batch, dense=True):
    """Milliseconds per value-and-gradient of the log density (``batch`` chains vmapped), and
    its compilation in seconds. ``dense``: ``simulate`` samples from its dense output with the
    posterior's step budget (as the sampler runs it), else saves inside the solve."""
    datas, spec, _ = setup(start, data, params, fit_initial_state=True, solve_rtol=1e-8,
                           solve_atol=1e-8)  # fmt: skip
    res = fit(start, data, params, fit_initial_state=True, solve_rtol=1e-8, solve_atol=1e-8)
    _, L = _laplace(start, datas, spec, res.unconstrained)
    dense = dense and integrator == "simulate"
    budget = _dense_budget(start, datas, spec, res.unconstrained) if dense else 0
    sampled = dataclasses.replace(spec, integrator=integrator, forward=False, dense_steps=budget)
    density = _log_density(start, datas, sampled, {}, res.unconstrained, L)
    f = jax.jit(jax.vmap(jax.value_and_grad(density)))
    z = jnp.zeros((batch, L.shape[0]))
    tic = time.perf_counter()
    jax.block_until_ready(f(z))
    compile_s = time.perf_counter() - tic
    tic = time.perf_counter()
    for i in range(10):
        jax.block_until_ready(f(z + 0.01 * i))
    return (time.perf_counter() - tic) / 10 * 1e3, compile_s


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--warmup", type=int, default=500)
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--integrators", default="fast_simulate,simulate")
    parser.add_argument("--chain-methods", default="pmap,vmap")
    args = parser.parse_args()
    data = [
        experiment([0.5, -0.2, 0.3], [0.1, 0.8, -0.5], args.seconds, 1),
        experiment([0.1, 0.4, -0.2], [-0.4, 0.2, 0.7], args.seconds, 2),
    ]
    start = model(1.3, 1.5, 0.08)
    print(f"devices: {jax.devices()}; {args.seconds:g} s x 2 experiments, "
          f"{args.warmup} warmup + {args.samples} draws x 2 chains")  # fmt: skip
    rows = []
    for integrator in args.integrators.split(","):
        one, compile_s = gradient_ms(start, data, integrator, 1)
        two, _ = gradient_ms(start, data, integrator, 2)
        print(f"{integrator}: gradient {one:.1f} ms (1 chain), {two:.1f} ms (2 chains vmapped), "
              f"compiled in {compile_s:.0f} s")  # fmt: skip
        if integrator == "simulate":
            saved, saved_compile = gradient_ms(start, data, integrator, 1, dense=False)
            print(f"simulate saving at ts inside the solve: gradient {saved:.1f} ms (1 chain), "
                  f"compiled in {saved_compile:.0f} s")  # fmt: skip
        for method in args.chain_methods.split(","):
            tic = time.perf_counter()
            idata = posterior(start, data, params, num_warmup=args.warmup,
                              num_samples=args.samples, integrator=integrator,
                              chain_method=method)  # fmt: skip
            wall = time.perf_counter() - tic
            a = idata.posterior.attrs
            post = idata.posterior
            covered = all(
                np.quantile(post[k].values, 0.05) < v < np.quantile(post[k].values, 0.95)
                for k, v in TRUTH.items()
            )
            steps = (args.warmup + args.samples) * a["mean_n_steps"]  # gradients per chain
            rows.append(
                (integrator, a["chain_method"], wall, a["fit_time"], a["compile_time"],
                 a["sampling_time"], a["draws_per_second"], 1e3 * a["sampling_time"] / steps,
                 a["mean_n_steps"], a["min_ess_bulk"], a["min_ess_bulk"] / a["sampling_time"],
                 a["max_r_hat"], a["divergences"], covered)
            )  # fmt: skip
    header = ("integrator", "chains", "wall s", "fit s", "compile s", "sample s", "draws/s",
              "ms/grad", "leapfrog", "min ESS", "ESS/s", "max R-hat", "diverg.",
              "truth in 90%")  # fmt: skip
    print(" | ".join(header))
    for r in rows:
        print(f"{r[0]} | {r[1]} | {r[2]:.0f} | {r[3]:.0f} | {r[4]:.0f} | {r[5]:.0f} | "
              f"{r[6]:.1f} | {r[7]:.1f} | {r[8]:.1f} | {r[9]:.0f} | {r[10]:.1f} | "
              f"{r[11]:.3f} | {r[12]} | {r[13]}")  # fmt: skip


if __name__ == "__main__":
    main()
