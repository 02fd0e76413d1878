"""Shared test helpers (cf. diffrax ``test/helpers.py`` and optimistix ``tests/helpers.py``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

try:
    import zarr
except ImportError:  # zarr >= 3 needs Python >= 3.11; there sweeps run in memory only
    zarr = None
needs_zarr = pytest.mark.skipif(
    zarr is None, reason="the sweep store needs zarr >= 3, which needs Python >= 3.11"
)


def tree_allclose(x, y, *, rtol=1e-12, atol=1e-12) -> bool:
    """Whether two pytrees have the same structure and all leaves are close."""
    xs, xd = jax.tree_util.tree_flatten(x)
    ys, yd = jax.tree_util.tree_flatten(y)
    if xd != yd:
        return False
    return all(
        np.allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=atol) for a, b in zip(xs, ys)
    )


def finite_difference_jacobian(f, x, *, scale=1.0, order=4):
    """Central finite-difference Jacobian of ``f`` at ``x`` (a 1-D array), ε = eps^(1/3)·scale for
    order 2 or eps^(1/5)·scale for order 4 (the optimal step of each stencil)."""
    x = jnp.asarray(x, dtype=jnp.float64)
    eps = np.finfo(np.float64).eps
    h = (eps ** (1 / 5) if order == 4 else eps ** (1 / 3)) * scale
    cols = []
    for i in range(x.size):
        e = jnp.zeros_like(x).at[i].set(h)
        if order == 4:
            d = (-f(x + 2 * e) + 8 * f(x + e) - 8 * f(x - e) + f(x - 2 * e)) / (12 * h)
        else:
            d = (f(x + e) - f(x - e)) / (2 * h)
        cols.append(jnp.asarray(d))
    return jnp.stack(cols, axis=-1)


def random_rotation_vectors(key, n, max_angle=jnp.pi):
    """n turn-vectors with uniformly random axes and angles in [0, max_angle)."""
    k1, k2 = jax.random.split(key)
    axes = jax.random.normal(k1, (n, 3))
    axes = axes / jnp.linalg.norm(axes, axis=1, keepdims=True)
    angles = jax.random.uniform(k2, (n, 1), maxval=max_angle)
    return axes * angles


def spectrum_match_error(p, q) -> float:
    """max |p_i − q_σ(i)| over the best one-to-one matching σ (spectra compared as multisets)."""
    from scipy.optimize import linear_sum_assignment

    p, q = np.asarray(p).ravel(), np.asarray(q).ravel()
    assert p.shape == q.shape
    cost = np.abs(p[:, None] - q[None, :])
    rows, cols = linear_sum_assignment(cost)
    return float(cost[rows, cols].max())


def damped_nikolai(M, b, c, A3):
    """The damped Nikolai problem (follower moment (4.57), friction (4.84)), d = 2, A1 = 1: one
    function, so one program of each kind for every test of the codimension-two analysis (and
    one entry of the compilation cache the test run shares)."""
    import rbo_jax as rbo

    return rbo.nikolai_model(M, c, 2.0, A1=1.0, A3=A3, friction=b)


def run_cli(capsys, argv):
    """``rbo-jax ARGV`` in-process: (exit status, stdout, stderr)."""
    from rbo_jax.app import cli

    try:
        code = cli.main(argv)
    except SystemExit as e:  # argparse: usage errors
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err


def open_output(path):
    """A command's netCDF or zarr output, loaded."""
    import xarray as xr

    path = str(path)
    if path.endswith(".zarr"):
        with xr.open_zarr(path) as ds:
            return ds.load()
    with xr.open_dataset(path) as ds:
        return ds.load()


def ziegler_pendulum(P, b=0.0):
    """Ziegler's double pendulum (rbo_jax.lattice.pendulum): masses 2m, m, links l, hinge
    springs c (m = l = c = 1), hinge dampers b, a follower force P at the tip."""
    from rbo_jax import lattice

    return lattice.pendulum(
        [2.0, 1.0],
        [1.0, 1.0],
        [1.0, 1.0],
        damping=b,
        loads=lattice.TipForce(jnp.stack([0.0, 0.0, -P]), follower=True),
    )
