"""Quantities shared by tests/test_sweep.py and its subprocess worker (tests/_sweep_worker.py),
and a small sweep configuration shared by the CLI tests.

Module-level functions, so that the compiled sweep program is cached across tests (the runner
cache is keyed on the function) and identical in the test process and in its children.
"""

from __future__ import annotations

import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import rbo_jax as rbo

K = jnp.array([0.0, 0.0, 1.0])

#: A small TOML sweep of the damped Nikolai problem (the CLI tests change it with str.replace).
SMALL_CONFIG = """
[sweep]
quantity = "spectral_abscissa"
output = "small.zarr"
chunk_size = 4

[axes]
M = [0.0, 0.2, 0.4]
b = { start = 0.0, stop = 0.3, num = 4 }

[model]
inertia = { A1 = 1.0, A3 = 0.5 }
foundation = { type = "quadratic", c = 1.0, d = 2.0 }
loads = [{ type = "follower", M = "M" }, { type = "friction", b = "b" }]
"""

#: Host hook settings: seconds to sleep per call, and a file to which each call appends a line.
#: Read at call time, so the compiled program is the same whatever they are.
HOOK = {
    "sleep": float(os.environ.get("RBO_SWEEP_TEST_SLEEP", "0")),
    "log": os.environ.get("RBO_SWEEP_TEST_LOG"),
}


def _hook(x):
    if HOOK["sleep"]:
        time.sleep(HOOK["sleep"])
    if HOOK["log"]:
        with open(HOOK["log"], "a") as f:
            f.write(f"{jax.process_index()} {np.asarray(x).size}\n")
    return np.asarray(x)


def nikolai_model(c, M, A3=0.5, d=1.0):
    return rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(1.0, A3, K),
        rbo.QuadraticFoundation(c, d, K),
        rbo.FollowerMoment(M, K),
    )


def nikolai_abscissa(c, M):
    """Spectrum of the Nikolai problem at its closed-form equilibrium θ = (M/d)k (4.62), d = 1:
    cheap to compile, so the subprocess tests stay fast. A host callback (identity on ``c``)
    runs once per chunk and device: it sleeps and logs on demand (see ``HOOK``)."""
    c = jax.pure_callback(
        _hook, jax.ShapeDtypeStruct(jnp.shape(c), jnp.result_type(c)), c, vmap_method="expand_dims"
    )
    model = nikolai_model(c, M)
    p = rbo.fast_spectrum(model, M * K)
    kind, a = rbo.classify(p)
    return {"abscissa": a, "kind": kind, "p": p}


NIKOLAI_AXES = {"c": np.array([0.5, 1.0, 2.0]), "M": np.array([0.1, 0.2, np.nan, 0.4, 0.5])}
NIKOLAI_DIMS = {"p": ["mode"]}

#: The sweep killed midway and resumed: 4 x 6 grid in chunks of 2 points (12 chunks).
KILL_AXES = {"c": np.array([0.5, 1.0, 1.5, 2.0]), "M": np.array([0.05, 0.1, 0.2, 0.3, 0.4, 0.5])}
KILL_CHUNK = 2
#: The two-process sweep: 3 x 5 grid (with a NaN) in chunks of 2 points (9 chunks).
DIST_AXES = NIKOLAI_AXES
DIST_CHUNK = 2


# The sweeps on Dask (tests/test_dask_sweep.py); the workers import this module by name.


def nikolai_spectrum(c, M):
    """:func:`nikolai_abscissa` without its host callback: a program the program store keeps,
    which the Dask workers load instead of tracing it."""
    p = rbo.fast_spectrum(nikolai_model(c, M), M * K)
    kind, a = rbo.classify(p)
    return {"abscissa": a, "kind": kind, "p": p}


def slowed(seconds):
    """:func:`nikolai_spectrum` behind a host callback (identity on ``c``) that sleeps
    ``seconds`` per chunk: a closure, which cloudpickle sends by value, ``seconds`` included;
    every value of ``seconds`` compiles to the same program."""

    def sleep(x):
        time.sleep(seconds)
        return np.asarray(x)

    def slow(c, M):
        c = jax.pure_callback(
            sleep,
            jax.ShapeDtypeStruct(jnp.shape(c), jnp.result_type(c)),
            c,
            vmap_method="expand_dims",
        )
        return nikolai_spectrum(c, M)

    return slow


def raises_for_large_c(c, M):
    import equinox as eqx

    return {"x": eqx.error_if(c + M, c > 1.5, "c too large")}


#: 4 x 6 grid (a NaN among the M) in chunks of 2 points: 12 chunks.
DASK_AXES = {"c": np.array([0.5, 1.0, 1.5, 2.0]), "M": np.array([0.05, 0.1, np.nan, 0.3, 0.4, 0.5])}
DASK_CHUNK = 2


def _exit_if_large(x):
    if np.any(np.asarray(x) > 1.5):
        os._exit(3)  # the worker process dies, as by a crash in native code
    return np.asarray(x)


def kills_its_worker(c, M):
    """Ends the process that computes a chunk holding c = 2 (run on Dask workers only)."""
    c = jax.pure_callback(
        _exit_if_large,
        jax.ShapeDtypeStruct(jnp.shape(c), jnp.result_type(c)),
        c,
        vmap_method="expand_dims",
    )
    return {"x": c + M}
