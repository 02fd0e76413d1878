r"""Eigenvalue stability maps and critical loads: presets of the batch engine.

:func:`stability_map` evaluates :func:`rbo_jax.equilibrium_stability` (equilibrium (4.61) →
spectrum (4.63)–(4.69) → classification) on the Cartesian product of named parameter axes with
:func:`rbo_jax.sweep`, so chunking, padding, device sharding, stores, progress and per-point
statuses are the sweep's. :func:`critical_load` finds, along one axis, where the spectral abscissa
first becomes positive, e.g. the critical follower load against the damping ``b``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import jax.numpy as jnp
import numpy as np

from ..kinematics import _as_vector
from ..maps import STABILITY_KIND_NAMES, critical_value, equilibrium_stability, is_unstable
from ..model import RigidBodyOscillator
from ._engine import sweep
from ._output import sort_eigenvalues
from ._rod_maps import returns_rod, rod_critical_load, rod_stability_map

__all__ = ["stability_map", "critical_load", "STABILITY_KIND_NAMES"]


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


def _no_rigid_options(theta_eq_fn, theta_guess) -> None:
    for name, value in (("theta_eq_fn", theta_eq_fn), ("theta_guess", theta_guess)):
        if value is not None:
            raise ValueError(f"{name} does not apply to a rod (its equilibrium is solved from "
                             "the straight rod by rbo_jax.lattice.solve_equilibrium).")  # fmt: skip


def _guess(theta_guess) -> tuple[float, float, float]:
    g = np.zeros(3) if theta_guess is None else np.asarray(_as_vector(theta_guess, "theta_guess"))
    return tuple(float(x) for x in g)


def _point_stability(model_fn, theta_eq_fn, guess, rtol, fast, eq_items, point):
    """:func:`rbo_jax.equilibrium_stability` of ``model_fn(**point)``."""
    model = model_fn(**point)
    if not isinstance(model, RigidBodyOscillator):
        raise TypeError(f"model_fn must return a RigidBodyOscillator, got {type(model).__name__}.")
    theta_eq = None
    if theta_eq_fn is not None:
        theta_eq = _as_vector(theta_eq_fn(**point), "theta_eq_fn(...)")
    return equilibrium_stability(
        model, jnp.asarray(guess), theta_eq=theta_eq, rtol=rtol, fast=fast, **dict(eq_items)
    )


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
        return values, r.status

    return stability


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
    store=None,
    resume: bool = False,
    overwrite: bool = False,
    devices=None,
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
      (e.g. :func:`rbo_jax.nikolai_equilibrium`, (4.62)); otherwise the equilibrium is solved by
      Newton from ``theta_guess`` (default zero) with :func:`rbo_jax.solve_equilibrium`, and
      points where it fails are flagged in ``equilibrium_status`` with NaN spectra (the rest of
      the map completes).
    - `chunk_size`: points per compiled call; memory is O(chunk_size).
    - `rtol`: tolerance of :func:`rbo_jax.classify` (relative to max|p|).
    - `fast`: use :func:`rbo_jax.fast_spectrum` (block structure) instead of the plain 6×6
      eigenproblem of :func:`rbo_jax.spectrum`; same eigenvalues.
    - `progress`: tqdm progress bar over points.
    - `store`, `resume`, `overwrite`, `devices`: as for :func:`rbo_jax.sweep` (the map is a
      sweep); without a store the map stays in memory.

    **Returns:** a Dataset with coordinates the axes (plus ``mode`` 0..5 and ``component``)
    and variables ``eigenvalues`` (complex, axes × mode, sorted by real then imaginary part),
    ``spectral_abscissa`` (max Re p),
    ``kind`` (int8 codes of :class:`rbo_jax.StabilityKind`, names in its ``flag_meanings``),
    ``equilibrium_status`` (int8 codes of :class:`rbo_jax.EquilibriumStatus`, the sweep's
    per-point status) and ``theta_eq``.

    **Rods.** A ``model_fn`` returning a :class:`rbo_jax.lattice.Rod` is mapped the same way
    (:mod:`rbo_jax.batch._rod_maps`): the equilibrium by :func:`rbo_jax.lattice.solve_equilibrium`
    (``equilibrium_kwargs`` such as ``steps=``), all $12N$ eigenvalues of
    :func:`rbo_jax.lattice.linearize` over ``mode`` (a clamped rod of $N$ bodies past the base),
    ``tip`` (component) in place of ``theta_eq``, and ``equilibrium_status`` the codes of
    :class:`rbo_jax.lattice.RodEquilibriumStatus` (failed points: NaN spectra, kind
    ``undefined``). ``theta_eq_fn``, ``theta_guess`` and ``fast`` do not apply.
    """
    axes = _check_axes(axes)
    if returns_rod(model_fn, axes):
        _no_rigid_options(theta_eq_fn, theta_guess)
        options = dict(chunk_size=chunk_size, store=store, resume=resume, overwrite=overwrite)
        return rod_stability_map(
            model_fn, axes, rtol=float(rtol), eq_items=_items(equilibrium_kwargs),
            progress=progress, devices=devices, **options,
        )  # fmt: skip
    quantity = _map_quantity(
        model_fn,
        theta_eq_fn,
        _guess(theta_guess),
        float(rtol),
        bool(fast),
        _items(equilibrium_kwargs),
    )
    ds = sweep(
        quantity,
        axes,
        chunk_size=chunk_size,
        store=store,
        resume=resume,
        overwrite=overwrite,
        progress=progress,
        devices=devices,
        dims={"eigenvalues": ("mode",), "theta_eq": ("component",)},
        attrs={"classify_rtol": rtol},
        desc="stability map",
        postprocess=sort_eigenvalues,
    )
    ds = ds.rename({"status": "equilibrium_status"})
    ds = ds.assign_coords(mode=np.arange(6), component=["x", "y", "z"])
    ds["kind"].attrs["long_name"] = "stability classification (Lyapunov's first method)"
    ds["spectral_abscissa"].attrs["long_name"] = "max Re p"
    return ds


def _critical_quantity(
    model_fn, theta_eq_fn, guess, rtol, eq_items, load, load_min, load_max, n_scan, n_bisect
):
    def critical(**point):
        def unstable(value):
            return is_unstable(
                _point_stability(
                    model_fn, theta_eq_fn, guess, rtol, True, eq_items, {**point, load: value}
                )
            )

        return {
            "critical": critical_value(
                unstable, load_min, load_max, n_scan=n_scan, n_bisect=n_bisect
            )
        }

    return critical


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

    **Rods.** A ``model_fn`` returning a :class:`rbo_jax.lattice.Rod` is searched the same way
    with the rod's equilibrium and spectrum (:func:`stability_map`); as in
    :func:`rbo_jax.lattice.critical_load`, a load whose equilibrium fails counts as unstable.
    """
    axes = _check_axes(axes)
    if load in axes:
        raise ValueError(f"{load!r} is the searched parameter; it cannot also be an axis.")
    if not load_max > load_min:
        raise ValueError(f"load_max ({load_max}) must exceed load_min ({load_min}).")
    if returns_rod(model_fn, {**axes, load: load_max}):
        _no_rigid_options(theta_eq_fn, theta_guess)
        return rod_critical_load(
            model_fn, axes, load, float(load_min), float(load_max), rtol=float(rtol),
            eq_items=_items(equilibrium_kwargs), n_scan=int(n_scan), n_bisect=int(n_bisect),
            chunk_size=chunk_size, progress=progress,
        )  # fmt: skip
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
