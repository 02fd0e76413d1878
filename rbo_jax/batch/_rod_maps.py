r"""Stability maps and critical loads of rods: what :func:`rbo_jax.stability_map` and
:func:`rbo_jax.critical_load` do when ``model_fn`` returns a :class:`rbo_jax.lattice.Rod`.

At every point the equilibrium is :func:`rbo_jax.lattice.solve_equilibrium` (Newton from the
straight rod, with the given keywords such as ``steps``), its spectrum the eigenvalues of
:func:`rbo_jax.lattice.linearize` ($2\cdot 6N$ of them for a clamped rod of $N$ bodies past the
base, where a rigid body has 6), classified by :func:`rbo_jax.classify` as a rigid body's
are (Lyapunov's first method, real parts within ``rtol`` × max|p| of zero count as zero).
A point whose equilibrium fails has NaN eigenvalues, the kind ``undefined`` and its
:class:`rbo_jax.lattice.RodEquilibriumStatus` in ``equilibrium_status``; for a critical load
it counts as unstable, as in :func:`rbo_jax.lattice.critical_load`, and a point whose rod has
invalid parameters (``invalid_parameters``; at the ends of the load's range for a critical
load) gets NaN. Both are quantities of the
sweep engine: chunks over every local device (the spectra of a critical load's scan are batched
inside one point; the engine runs such LAPACK calls in blocks, :mod:`rbo_jax._sharding`).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from ..bifurcation._interface import abstract_model
from ..lattice._rod import Rod
from ..maps import critical_value
from ..stability import StabilityKind, classify
from ._engine import sweep
from ._output import sort_eigenvalues

__all__ = ["returns_rod", "rod_critical_load", "rod_stability_map"]


def returns_rod(model_fn, point) -> bool:
    """Whether ``model_fn(**point)`` builds a :class:`rbo_jax.lattice.Rod` (traced abstractly
    once; a function that cannot be traced so is left to the rigid body's path)."""
    return isinstance(abstract_model(model_fn, {str(k): () for k in point}), Rod)


def _stability(model_fn, rtol, eq_items, point):
    # imported here: the rods' solvers pull in diffrax, which a rigid body's map does not need
    # (0.17 s of every first stability_map)
    from ..lattice._rod_dynamics import linearize
    from ..lattice._rod_statics import solve_equilibrium

    rod = model_fn(**point)
    if not isinstance(rod, Rod):
        raise TypeError(f"model_fn must return a Rod at every point, got {type(rod).__name__}.")
    sol = solve_equilibrium(rod, **dict(eq_items))
    p = jnp.linalg.eigvals(linearize(rod, sol.state))
    p = jnp.where(sol.ok, p, jnp.full_like(p, jnp.nan))
    kind, a = classify(p, rtol=rtol)
    return p, a, kind, sol


def rod_stability_map(model_fn, axes, *, rtol, eq_items, **sweep_options):
    """The map of :func:`rbo_jax.stability_map` for a rod (module docstring): variables
    ``eigenvalues`` (axes × mode, sorted by real then imaginary part), ``spectral_abscissa``,
    ``kind``, ``tip`` (the equilibrium's tip position, × component) and
    ``equilibrium_status`` (codes of :class:`rbo_jax.lattice.RodEquilibriumStatus`)."""

    def stability(**point):
        p, a, kind, sol = _stability(model_fn, rtol, eq_items, point)
        values = {"eigenvalues": p, "spectral_abscissa": a, "kind": kind, "tip": sol.state.tip}
        return values, sol.status

    ds = sweep(
        stability,
        axes,
        dims={"eigenvalues": ("mode",), "tip": ("component",)},
        attrs={"classify_rtol": rtol, "model": "rod"},
        desc="stability map (rod)",
        postprocess=sort_eigenvalues,
        **sweep_options,
    )
    ds = ds.rename({"status": "equilibrium_status"})
    ds = ds.assign_coords(mode=np.arange(ds.sizes["mode"]), component=["x", "y", "z"])
    ds["kind"].attrs["long_name"] = "stability classification (Lyapunov's first method)"
    ds["spectral_abscissa"].attrs["long_name"] = "max Re p"
    return ds


def _critical(model_fn, load, point, lo, hi, rtol, eq_items, n_scan, n_bisect):
    unstable_codes = [enum.code(StabilityKind.flutter), enum.code(StabilityKind.divergence)]

    def unstable(value):
        _, _, kind, sol = _stability(model_fn, rtol, eq_items, {**point, load: value})
        code = enum.code(kind)
        return (code == unstable_codes[0]) | (code == unstable_codes[1]) | ~sol.ok

    from ..lattice._rod_dynamics import valid_between

    value = critical_value(unstable, lo, hi, n_scan=n_scan, n_bisect=n_bisect)
    valid = valid_between(lambda v: model_fn(**{**point, load: v}), lo, hi)
    return jnp.where(valid, value, jnp.nan)


def rod_critical_load(model_fn, axes, load, load_min, load_max, *, rtol, eq_items, **options):
    """The critical load of :func:`rbo_jax.critical_load` for a rod (module docstring): the
    search of :func:`rbo_jax.lattice.critical_load` at every point of the grid, a quantity of
    the sweep engine (chunks over every local device, as the rigid body's)."""
    n_scan, n_bisect = int(options.pop("n_scan")), int(options.pop("n_bisect"))

    def critical(**point):
        lo, hi = jnp.asarray(load_min), jnp.asarray(load_max)
        return {"critical": _critical(model_fn, load, point, lo, hi, rtol, eq_items,
                                      n_scan, n_bisect)}  # fmt: skip

    ds = sweep(critical, axes, desc=f"critical {load} (rod)", **options)
    return ds["critical"].drop_attrs().rename(f"critical_{load}")
