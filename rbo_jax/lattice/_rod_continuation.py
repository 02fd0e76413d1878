r"""The rods' name of the continuation of equilibria: :func:`continue_equilibrium` follows a rod's
equilibria in a load with the continuation every model shares
(:func:`rbo_jax.continue_equilibria`, Keller's pseudo-arclength method with the rod's
block-tridiagonal solves), and returns the branch as a :class:`RodBranch`."""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..models.rod import Rod, RodState
from ..stability import unstable_roots

__all__ = ["RodBranch", "continue_equilibrium"]


class RodBranch(eqx.Module):
    r"""A branch of rod equilibria from :func:`continue_equilibrium`, over its points in the
    order of the arclength: ``loads`` (P,), ``states`` (a :class:`RodState` at rest with a
    leading axis of P), ``eigenvalues`` (P, 12N: :func:`rbo_jax.lattice.spectrum` at every point;
    empty with ``spectra=False``), ``special`` (tuples ``(kind, load, index)``: ``"fold"`` (a
    limit point of the load, located by the parabola through three points), ``"branch_point"``
    or ``"hopf"``, ``index`` the point before it) and ``stop_reason``."""

    loads: np.ndarray
    states: RodState
    eigenvalues: np.ndarray
    special: tuple = eqx.field(static=True)
    stop_reason: str = eqx.field(static=True)

    @property
    def tip(self):
        """The tip positions, ``(P, 3)``."""
        return self.states.r[:, -1, :]

    @property
    def spectral_abscissa(self):
        """``max Re p`` at every point, ``(P,)`` (NaN without spectra)."""
        if self.eigenvalues.shape[-1] == 0:
            return np.full(self.loads.shape, np.nan)
        return np.max(self.eigenvalues.real, axis=1)

    @property
    def stable(self):
        r"""Every root stable by :func:`rbo_jax.classify`'s test ($\mathrm{Re}\,p < 0$ beyond
        $10^{-9}$ of its own modulus: Lyapunov's first method; a conservative rod without
        damping sits on the border: see ``neutral``), ``(P,)``."""
        return np.array([bool(np.all(np.asarray(unstable_roots(-p)))) for p in self.eigenvalues])

    @property
    def neutral(self):
        r"""No root unstable by :func:`rbo_jax.classify`'s test: stable in the linear sense of
        an undamped conservative rod (its spectrum lies on the imaginary axis), ``(P,)``."""
        return np.array([not np.any(np.asarray(unstable_roots(p))) for p in self.eigenvalues])

    @property
    def folds(self):
        """The loads of the folds (limit points), in the order met."""
        return np.array([s[1] for s in self.special if s[0] == "fold"], dtype=float)


def continue_equilibrium(
    rod_fn: Callable[..., Rod],
    start: float,
    stop: float,
    *,
    guess: RodState | None = None,
    ds: float = 0.05,
    ds_max: float = 0.2,
    load_scale: float | None = None,
    **options,
) -> RodBranch:
    r"""Follow the equilibria of ``rod_fn(λ)`` (a :class:`Rod` for every load value λ, traced:
    build load vectors with ``jnp.stack``) from λ = ``start`` towards ``stop`` by
    pseudo-arclength continuation through limit points of λ: :func:`rbo_jax.continue_equilibria`
    with the rod's steps (``ds``, ``ds_max``, ``ds_min`` (default 1e-6), in the norm of turns,
    displacements over the rod's size and loads over ``load_scale``, default
    ``max(|start|, |stop|)``). ``guess``: the first equilibrium's (``steps`` load steps,
    default 1: :func:`rbo_jax.solve_equilibrium`). The other ``options`` are
    :func:`rbo_jax.continue_equilibria`'s (``steps``, ``ds_min``, ``max_points`` (500),
    ``tol`` (1e-10), ``spectra``: the eigenvalues at every point, needed for the stability and
    the Hopf test).

    Returns a :class:`RodBranch`. Not differentiable (a loop in Python around compiled steps).
    """
    from ..bifurcation import continue_equilibria

    if not callable(rod_fn):
        raise TypeError(f"continue_equilibrium: rod_fn must be callable, got {type(rod_fn)}.")
    if not (np.isfinite(start) and np.isfinite(stop)) or start == stop:
        raise ValueError(
            f"continue_equilibrium: start and stop must be finite and differ, got {start}, {stop}."
        )
    scale = max(abs(start), abs(stop)) if load_scale is None else float(load_scale)
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"continue_equilibrium: load_scale must be > 0, got {load_scale}.")
    if not isinstance(rod_fn(jnp.asarray(float(start))), Rod):
        raise TypeError(f"continue_equilibrium: rod_fn must return a Rod at {start}.")
    ds_ = continue_equilibria(
        lambda load: rod_fn(load), {}, "load", float(start), float(stop), theta_guess=guess,
        ds=ds, ds_max=ds_max, parameter_scale=scale, locate_hopf=False, **options,
    )  # fmt: skip
    special = tuple(
        (str(k), float(v), int(i))
        for k, v, i in zip(
            ds_["special_type"].values, ds_["special_value"].values, ds_["special_index"].values
        )  # fmt: skip
    )
    return RodBranch(
        loads=np.asarray(ds_["load"].values),
        states=RodState.at_rest(np.asarray(ds_["theta"].values), np.asarray(ds_["r"].values)),
        eigenvalues=np.asarray(ds_["eigenvalues"].values),
        special=special,
        stop_reason=str(ds_.attrs["stop_reason"]),
    )
