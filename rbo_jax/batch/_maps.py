r"""Eigenvalue stability maps and critical loads: presets of the batch engine, for every model.

:func:`stability_map` evaluates :func:`rbo_jax.equilibrium_stability` (equilibrium (4.61) →
spectrum (4.63)–(4.69) → classification) on the Cartesian product of named parameter axes with
:func:`rbo_jax.sweep`, so chunking, padding, device sharding, stores, progress and per-point
statuses are the sweep's. :func:`critical_load` finds, along one axis, where the stable interval
of a load ends (:mod:`rbo_jax.stability._critical`), e.g. the critical follower load against the
damping ``b``. A rigid body, a lattice and a rod are mapped by the same code: ``model_fn`` may
return any of them.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..mechanics import AbstractMechanics
from ..stability import (
    critical_between,
    equilibrium_stability,
    stability_code,
)
from ._engine import sweep
from ._output import sort_eigenvalues
from ._space import _as_1d, _check_name

__all__ = ["stability_map", "critical_load"]


def _items(kwargs: dict) -> tuple:
    try:
        items = tuple(sorted(kwargs.items()))
        hash(items)
    except TypeError:
        raise TypeError(
            "equilibrium keyword arguments must be hashable (numbers, not arrays)."
        ) from None
    return items


def _check_axes(axes: Mapping[str, object]) -> dict[str, np.ndarray]:
    if not isinstance(axes, Mapping) or not axes:
        raise ValueError("axes must be a non-empty mapping {name: 1-D array of values}.")
    out = {}
    for name, values in axes.items():
        v = _as_1d(values, f"axis {name!r}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"axis {name!r} contains non-finite values.")
        out[_check_name(name, "axes")] = v
    return out


def _guess(theta_guess):
    """The equilibrium guess as a hashable ``(shape, values)`` (``None``: the model's rest)."""
    if theta_guess is None:
        return None
    g = np.asarray(theta_guess, dtype=np.float64)
    return tuple(g.shape), tuple(float(x) for x in g.ravel())


def _bodies(model_fn, axes) -> int | None:
    """The number of bodies of the model at the grid's first point (traced abstractly), or
    ``None`` for one rigid body."""
    point = {name: np.asarray(v[0]) for name, v in axes.items()}
    model = eqx.filter_eval_shape(lambda p: model_fn(**p), point)
    shape = (
        jax.eval_shape(lambda m: m.rest(), model) if isinstance(model, AbstractMechanics) else None
    )
    theta = getattr(shape, "theta", shape)
    return None if theta is None or len(theta.shape) == 1 else int(theta.shape[0])


def _has_tip(model_fn, axes) -> bool:
    point = {name: np.asarray(v[0]) for name, v in axes.items()}
    model = eqx.filter_eval_shape(lambda p: model_fn(**p), point)
    # on the type: the property itself would index the abstract shapes
    return hasattr(type(jax.eval_shape(lambda m: m.rest(), model)), "tip")


def _point_stability(model_fn, theta_eq_fn, guess, rtol, fast, eq_items, point):
    """:func:`rbo_jax.equilibrium_stability` of ``model_fn(**point)``."""
    model = model_fn(**point)
    if not isinstance(model, AbstractMechanics):
        raise TypeError(
            "model_fn must return a RigidBodyOscillator, a Lattice or a Rod, got "
            f"{type(model).__name__}."
        )
    state = None if theta_eq_fn is None else theta_eq_fn(**point)
    start = None if guess is None else jnp.reshape(jnp.asarray(guess[1]), guess[0])
    return equilibrium_stability(model, start, state=state, rtol=rtol, fast=fast, **dict(eq_items))


def _map_quantity(model_fn, theta_eq_fn, guess, rtol, fast, eq_items):
    """The per-point quantity of a map. The engine caches its program on what it computes
    (``_program.py``), so a map repeated with the same settings and equal functions (the same
    cell run again, with new lambdas) is one compiled program."""

    def stability(**point):
        r = _point_stability(model_fn, theta_eq_fn, guess, rtol, fast, eq_items, point)
        values = {
            "eigenvalues": r.eigenvalues,
            "spectral_abscissa": r.abscissa,
            "kind": r.kind,
            "theta_eq": r.theta,
        }
        if hasattr(r.state, "tip"):  # a rod: its tip too
            values["tip"] = r.state.tip
        return values, r.status

    # no small_program: with XLA's element-wise emitters a map's eigenvalues on several CPU
    # devices differed from one device's by rounding (tests/test_devices.py)
    return stability


def stability_map(
    model_fn: Callable[..., AbstractMechanics],
    axes: Mapping[str, object],
    *,
    theta_eq_fn: Callable[..., object] | None = None,
    theta_guess=None,
    chunk_size: int = 16_384,
    rtol: float = 1e-9,
    fast: bool = True,
    progress: bool = False,
    store=None,
    resume: bool = False,
    overwrite: bool = False,
    devices=None,
    **equilibrium_kwargs,
):
    r"""Spectra of equilibria on a grid of parameters, as an :class:`xarray.Dataset`.

    **Arguments:**

    - `model_fn`: ``model_fn(**point)`` for one grid point, returning a
      :class:`rbo_jax.RigidBodyOscillator`, a :class:`rbo_jax.lattice.Lattice` or a
      :class:`rbo_jax.lattice.Rod`, e.g. ``lambda M, c, A3: RigidBodyOscillator(
      transversely_isotropic_inertia(1.0, A3, k), QuadraticFoundation(c, 1.0, k),
      FollowerMoment(M, k))``. Traced (vmapped) values are passed, so build the model from them
      directly.
    - `axes`: ``{name: 1-D values}``; the grid is their Cartesian product in this order.
    - `theta_eq_fn`: optional ``theta_eq_fn(**point)``, the equilibrium in closed form (e.g.
      :func:`rbo_jax.nikolai_equilibrium`, (4.62)); otherwise the equilibrium is solved by
      Newton (:func:`rbo_jax.solve_equilibrium`) from ``theta_guess`` (an array of the model's
      turn-vectors; default: the configuration at rest) with ``equilibrium_kwargs`` (such as a
      rod's ``steps=``), and points where it fails are flagged in ``equilibrium_status`` with
      NaN spectra (the rest of the map completes).
    - `chunk_size`: points per compiled call; memory is O(chunk_size).
    - `rtol`: tolerance of :func:`rbo_jax.classify` (each root against its own modulus).
    - `fast`: :func:`rbo_jax.fast_spectrum` (block structure, where no force depends on the
      velocities) instead of the whole eigenproblem of :func:`rbo_jax.spectrum`; the same
      eigenvalues.
    - `progress`: tqdm progress bar over points.
    - `store`, `resume`, `overwrite`, `devices`: as for :func:`rbo_jax.sweep` (the map is a
      sweep); without a store the map stays in memory.

    **Returns:** a Dataset with coordinates the axes (plus ``mode``, ``component``, and
    ``body`` for a lattice or a rod) and variables ``eigenvalues`` (complex, axes × mode,
    sorted by real then imaginary part: 6 for a rigid body, $6N$ for a lattice of $N$ bodies,
    $12N$ for a clamped rod of $N$ bodies past the base), ``spectral_abscissa`` (max Re p),
    ``kind`` (int8 codes of :class:`rbo_jax.StabilityKind`, names in its ``flag_meanings``),
    ``equilibrium_status`` (int8 codes of :class:`rbo_jax.EquilibriumStatus`, the sweep's
    per-point status), ``theta_eq`` (the equilibrium's turn-vectors) and, for a rod, ``tip``
    (the equilibrium's tip position).
    """
    axes = _check_axes(axes)
    quantity = _map_quantity(
        model_fn,
        theta_eq_fn,
        _guess(theta_guess),
        float(rtol),
        bool(fast),
        _items(equilibrium_kwargs),
    )
    bodies = _bodies(model_fn, axes)
    turn = ("component",) if bodies is None else ("body", "component")
    dims = {"eigenvalues": ("mode",), "theta_eq": turn}
    if bodies is not None and _has_tip(model_fn, axes):
        dims["tip"] = ("component",)
    ds = sweep(
        quantity,
        axes,
        chunk_size=chunk_size,
        store=store,
        resume=resume,
        overwrite=overwrite,
        progress=progress,
        devices=devices,
        dims=dims,
        attrs={"classify_rtol": rtol},
        desc="stability map",
        postprocess=sort_eigenvalues,
    )
    ds = ds.rename({"status": "equilibrium_status"})
    ds = ds.assign_coords(mode=np.arange(ds.sizes["mode"]), component=["x", "y", "z"])
    if bodies is not None:
        ds = ds.assign_coords(body=np.arange(bodies))
    ds["kind"].attrs["long_name"] = "stability classification (Lyapunov's first method)"
    ds["spectral_abscissa"].attrs["long_name"] = "max Re p"
    return ds


def _critical_quantity(
    model_fn, theta_eq_fn, guess, rtol, eq_items, load, load_min, load_max, n_scan, n_bisect
):
    def critical(**point):
        def code_at(value):
            result = _point_stability(
                model_fn, theta_eq_fn, guess, rtol, True, eq_items, {**point, load: value}
            )
            return stability_code(result)

        def model_at(value):
            return model_fn(**{**point, load: value})

        lo, hi = jnp.asarray(load_min), jnp.asarray(load_max)
        return {"critical": critical_between(model_at, code_at, lo, hi, n_scan=n_scan,
                                             n_bisect=n_bisect, like=point)}  # fmt: skip

    critical.small_program = True  # Newton and eigenproblems: XLA's small-program options
    return critical


def critical_load(
    model_fn: Callable[..., AbstractMechanics],
    axes: Mapping[str, object],
    load: str,
    load_max: float,
    *,
    load_min: float = 0.0,
    theta_eq_fn: Callable[..., object] | None = None,
    theta_guess=None,
    n_scan: int = 64,
    n_bisect: int = 48,
    rtol: float = 1e-9,
    chunk_size: int = 4096,
    progress: bool = False,
    **equilibrium_kwargs,
):
    r"""The smallest value of the parameter ``load`` in ``(load_min, load_max]`` at which the
    equilibrium loses stability (:func:`rbo_jax.classify`: an unstable root, each against its
    own modulus), for every point of the grid ``axes`` of the other parameters; any model.

    The interval is scanned at ``n_scan`` points up to the first that is not stable, then the
    end of the stable interval is refined by ``n_bisect`` bisection steps (one loop, the grid's
    points vmapped: :func:`rbo_jax.maps.critical_value`; if the first scan point is already
    unstable, the interval from ``load_min`` to it is bisected). Returns an
    :class:`xarray.DataArray` over ``axes`` (0-d for ``axes={}``: one model): ``inf`` where the
    equilibrium is stable on the whole interval; NaN where the stable interval ends at a load
    whose equilibrium cannot be computed (undefined, not unstable: a limit point of the
    branch, a singular point, Newton failing; check such points with :func:`stability_map`),
    and where the model's parameters are invalid at ``load_min`` or ``load_max``. Example: the
    critical follower load of the Nikolai problem against the damping ``b`` (with damping the
    paradox disappears below a critical load that tends to 0 with ``b``).
    """
    axes = _check_axes(axes)
    if load in axes:
        raise ValueError(f"{load!r} is the searched parameter; it cannot also be an axis.")
    if not load_max > load_min:
        raise ValueError(f"load_max ({load_max}) must exceed load_min ({load_min}).")
    quantity = _critical_quantity(
        model_fn,
        theta_eq_fn,
        _guess(theta_guess),
        float(rtol),
        _items(equilibrium_kwargs),
        load,
        float(load_min),
        float(load_max),
        int(n_scan),
        int(n_bisect),
    )
    ds = sweep(quantity, axes, chunk_size=chunk_size, progress=progress, desc=f"critical {load}")
    return ds["critical"].drop_attrs().rename(f"critical_{load}")
