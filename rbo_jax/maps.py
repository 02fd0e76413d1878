r"""Eigenvalue stability maps over parameter grids, and critical loads.

:func:`stability_map` evaluates the spectrum of an equilibrium ((4.69) for the Nikolai problem)
on the Cartesian product of named parameter axes, with ``jit`` + ``vmap`` over memory-bounded
chunks (one compilation serves every chunk: the last one is padded, not recompiled), and returns
a labelled :class:`xarray.Dataset`. :func:`critical_load` finds, along one axis, where the spectral
abscissa first becomes positive, e.g. the critical follower load against the damping ``b``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .kinematics import _as_vector
from .model import RigidBodyOscillator
from .stability import (
    EquilibriumStatus,
    StabilityKind,
    classify,
    fast_spectrum,
    solve_equilibrium,
    spectrum,
)

__all__ = ["stability_map", "critical_load", "STABILITY_KIND_NAMES"]

STABILITY_KIND_NAMES = tuple(StabilityKind._name_to_item.keys())
_EQ_STATUS_NAMES = tuple(EquilibriumStatus._name_to_item.keys())


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
        v = np.asarray(values, dtype=np.float64)
        if v.ndim != 1 or v.size == 0:
            raise ValueError(f"axis {name!r} must be a non-empty 1-D array, got shape {v.shape}.")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"axis {name!r} contains non-finite values.")
        out[str(name)] = v
    return out


@functools.lru_cache(maxsize=32)
def _point_function(model_fn, names, theta_eq_fn, rtol, fast, eq_kwargs_items):
    """The per-point computation ``point(values, theta_guess)``; cached so that repeated maps with
    the same functions and settings reuse one compiled program."""
    spec = fast_spectrum if fast else spectrum
    eq_kwargs = dict(eq_kwargs_items)

    def point(values, theta_guess):
        params = {n: values[i] for i, n in enumerate(names)}
        model = model_fn(**params)
        if not isinstance(model, RigidBodyOscillator):
            raise TypeError(
                f"model_fn must return a RigidBodyOscillator, got {type(model).__name__}."
            )
        if theta_eq_fn is not None:
            theta_eq = _as_vector(theta_eq_fn(**params), "theta_eq_fn(...)")
            eq_status = EquilibriumStatus.where(
                jnp.all(jnp.isfinite(theta_eq)), EquilibriumStatus.successful,
                EquilibriumStatus.nonfinite,
            )
        else:
            sol = solve_equilibrium(model, theta_guess, **eq_kwargs)
            theta_eq, eq_status = sol.theta, sol.status
        ok = eq_status == EquilibriumStatus.successful
        p = spec(model, theta_eq)
        p = jnp.where(ok, p, jnp.nan + 0j)
        kind, a = classify(p, rtol=rtol)
        return p, a, kind._value, eq_status._value, theta_eq

    return point


@functools.lru_cache(maxsize=32)
def _jitted(fn):
    return jax.jit(jax.vmap(fn, in_axes=(0, None)))


def _run_chunks(fn, flat_params: np.ndarray, chunk_size: int, progress: bool, desc: str, arg):
    """Evaluate ``jit(vmap(fn))(points, arg)`` over chunks of ``chunk_size`` points (the last one
    padded, so one compilation serves all)."""
    n = flat_params.shape[0]
    chunk = int(min(chunk_size, n))
    jitted = _jitted(fn)
    outs = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, desc=desc, unit="pt", unit_scale=True)
    try:
        for start in range(0, n, chunk):
            block = flat_params[start : start + chunk]
            m = block.shape[0]
            if m < chunk:  # pad the last chunk: same shape, no recompilation
                block = np.concatenate([block, np.repeat(block[-1:], chunk - m, axis=0)])
            res = jax.device_get(jitted(jnp.asarray(block), arg))
            outs.append(jax.tree_util.tree_map(lambda x: np.asarray(x)[:m], res))
            if bar is not None:
                bar.update(m)
    finally:
        if bar is not None:
            bar.close()
    return jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *outs)


def stability_map(
    model_fn: Callable[..., RigidBodyOscillator],
    axes: Mapping[str, object],
    *,
    theta_eq_fn: Callable[..., object] | None = None,
    theta_guess=None,
    chunk_size: int = 16_384,
    rtol: float = 1e-9,
    fast: bool = True,
    progress: bool = False,
    **equilibrium_kwargs,
):
    r"""Spectra of equilibria on a grid of parameters, as an :class:`xarray.Dataset`.

    **Arguments:**

    - `model_fn`: ``model_fn(**point) -> RigidBodyOscillator`` for one grid point, e.g.
      ``lambda M, c, A3: RigidBodyOscillator(transversely_isotropic_inertia(1.0, A3, k),
      QuadraticFoundation(c, 1.0, k), FollowerMoment(M, k))``. Traced (vmapped) values are
      passed, so build the model from them directly.
    - `axes`: ``{name: 1-D values}``; the grid is their Cartesian product in this order.
    - `theta_eq_fn`: optional ``theta_eq_fn(**point) -> (3,)``, the equilibrium in closed form
      (e.g. ``(M/d)k`` of (4.62)); otherwise the equilibrium is solved by Newton from
      ``theta_guess`` (default zero) with :func:`rbo_jax.solve_equilibrium`, and points where it
      fails are flagged in ``equilibrium_status`` with NaN spectra (the rest of the map completes).
    - `chunk_size`: points per jit+vmap call; memory is O(chunk_size).
    - `rtol`: tolerance of :func:`rbo_jax.classify` (relative to max|p|).
    - `fast`: use :func:`rbo_jax.fast_spectrum` (block structure) instead of the plain 6×6
      eigenproblem of :func:`rbo_jax.spectrum`; same eigenvalues.
    - `progress`: tqdm progress bar over points.

    **Returns:** a Dataset with coordinates the axes (plus ``mode`` 0..5 and ``component``)
    and variables ``eigenvalues`` (complex, axes × mode, sorted by real then imaginary part),
    ``spectral_abscissa`` (max Re p),
    ``kind`` (int8 codes of :class:`rbo_jax.StabilityKind`, names in its ``flag_meanings``),
    ``equilibrium_status`` (int8 codes of :class:`rbo_jax.EquilibriumStatus`) and ``theta_eq``.
    """
    import xarray as xr

    axes = _check_axes(axes)
    names = tuple(axes)
    shape = tuple(v.size for v in axes.values())
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}.")
    grids = np.meshgrid(*axes.values(), indexing="ij")
    flat = np.stack([g.ravel() for g in grids], axis=1)
    guess = jnp.zeros(3) if theta_guess is None else _as_vector(theta_guess, "theta_guess")
    fn = _point_function(model_fn, names, theta_eq_fn, rtol, fast, _items(equilibrium_kwargs))
    p, a, kind, eq_status, theta_eq = _run_chunks(
        fn, flat, chunk_size, progress, "stability map", guess
    )
    p = np.sort_complex(p)  # lexicographic (Re, Im), like rbo_jax.spectrum; cheap on the host
    dims = list(names)
    ds = xr.Dataset(
        {
            "eigenvalues": (dims + ["mode"], p.reshape(shape + (6,))),
            "spectral_abscissa": (dims, a.reshape(shape)),
            "kind": (dims, kind.astype(np.int8).reshape(shape)),
            "equilibrium_status": (dims, eq_status.astype(np.int8).reshape(shape)),
            "theta_eq": (dims + ["component"], theta_eq.reshape(shape + (3,))),
        },
        coords={
            **{n: v for n, v in axes.items()},
            "mode": np.arange(6),
            "component": ["x", "y", "z"],
        },
    )
    ds["kind"].attrs.update(
        flag_values=list(range(len(STABILITY_KIND_NAMES))),
        flag_meanings=" ".join(STABILITY_KIND_NAMES),
        long_name="stability classification (Lyapunov's first method)",
    )
    ds["equilibrium_status"].attrs.update(
        flag_values=list(range(len(_EQ_STATUS_NAMES))), flag_meanings=" ".join(_EQ_STATUS_NAMES)
    )
    ds["spectral_abscissa"].attrs["long_name"] = "max Re p"
    ds.attrs["classify_rtol"] = rtol
    return ds


def critical_load(
    model_fn: Callable[..., RigidBodyOscillator],
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
    equilibrium loses stability (spectral abscissa > ``rtol``·max|p|), for every point of the
    grid ``axes`` of the other parameters.

    The interval is scanned at ``n_scan`` points, then the first sign change is refined by
    ``n_bisect`` bisection steps (everything vmapped; if the first scan point is already
    unstable, the interval from ``load_min`` to it is bisected). Returns an
    :class:`xarray.DataArray` over ``axes``; ``inf`` where the equilibrium is stable on the whole
    interval, ``load_min`` where it is unstable already at the first scan point past
    ``load_min``. Example: the critical follower load of the Nikolai problem against the damping
    ``b`` (with damping the paradox disappears below a critical load that tends to 0 with
    ``b``). Points whose equilibrium cannot be computed (classification ``undefined``) count as
    not unstable; check them with :func:`stability_map` when equilibria are solved by Newton.
    """
    import xarray as xr

    axes = _check_axes(axes)
    if load in axes:
        raise ValueError(f"{load!r} is the searched parameter; it cannot also be an axis.")
    if not load_max > load_min:
        raise ValueError(f"load_max ({load_max}) must exceed load_min ({load_min}).")
    names = tuple(axes) + (load,)
    guess = jnp.zeros(3) if theta_guess is None else _as_vector(theta_guess, "theta_guess")
    fn = _point_function(model_fn, names, theta_eq_fn, rtol, True, _items(equilibrium_kwargs))

    def unstable(values):
        p, a, kind, eq_status, _ = fn(values, guess)
        return (kind == StabilityKind.flutter._value) | (kind == StabilityKind.divergence._value)

    scan = jnp.linspace(load_min, load_max, n_scan + 1)[1:]

    def search(point):
        flags = jax.vmap(lambda L: unstable(jnp.append(point, L)))(scan)
        any_unstable = jnp.any(flags)
        i = jnp.argmax(flags)
        hi = scan[i]
        lo = jnp.where(i > 0, scan[jnp.maximum(i - 1, 0)], load_min)

        def body(_, bounds):
            lo, hi = bounds
            mid = 0.5 * (lo + hi)
            u = unstable(jnp.append(point, mid))
            return jnp.where(u, lo, mid), jnp.where(u, mid, hi)

        lo, hi = jax.lax.fori_loop(0, n_bisect, body, (lo, hi))
        return jnp.where(any_unstable, hi, jnp.inf)

    shape = tuple(v.size for v in axes.values())
    grids = np.meshgrid(*axes.values(), indexing="ij")
    flat = np.stack([g.ravel() for g in grids], axis=1)
    crit = _run_chunks(lambda x, _: search(x), flat, chunk_size, progress, f"critical {load}", None)
    return xr.DataArray(
        crit.reshape(shape), coords=dict(axes), dims=list(axes), name=f"critical_{load}"
    )
