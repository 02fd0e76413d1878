r"""What a stability map computes at one point: the equilibrium (4.61), its spectrum
(4.63)–(4.69) and the classification, in one function (:func:`equilibrium_stability`), and the
critical value of a load parameter along one line (:func:`critical_value`).

The grids themselves are run by the batch engine: :func:`rbo_jax.stability_map` and
:func:`rbo_jax.critical_load` are presets of :func:`rbo_jax.sweep` built on these functions.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Complex, Float

from . import _enumeration as enum
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

__all__ = [
    "EquilibriumStability",
    "equilibrium_stability",
    "critical_value",
    "STABILITY_KIND_NAMES",
]

STABILITY_KIND_NAMES = enum.names(StabilityKind)


class EquilibriumStability(eqx.Module):
    r"""Result of :func:`equilibrium_stability`: the equilibrium ``theta`` (4.61), its six
    ``eigenvalues`` (NaN where the equilibrium could not be computed), the spectral
    ``abscissa`` max Re p, the classification ``kind`` (:class:`StabilityKind`) and the
    equilibrium ``status`` (:class:`EquilibriumStatus`)."""

    theta: Float[Array, "3"]
    eigenvalues: Complex[Array, "6"]
    abscissa: Float[Array, ""]
    kind: StabilityKind
    status: EquilibriumStatus

    @property
    def ok(self):
        return self.status == EquilibriumStatus.successful


def equilibrium_stability(
    model: RigidBodyOscillator,
    theta_guess=None,
    *,
    theta_eq=None,
    rtol: float = 1e-9,
    fast: bool = True,
    t=0.0,
    **equilibrium_kwargs,
) -> EquilibriumStability:
    r"""The stability of an equilibrium of ``model``: Lyapunov's first method in one call.

    1. The equilibrium: ``theta_eq`` if given (a closed form such as (4.62), checked finite), else
       :func:`solve_equilibrium` (Newton for the moment balance (4.61)) from ``theta_guess``
       (default 0) with ``equilibrium_kwargs``.
    2. Its spectrum (4.63)–(4.69): :func:`fast_spectrum` (block structure) or, with
       ``fast=False``, :func:`spectrum`; NaN when the equilibrium failed.
    3. :func:`classify` with tolerance ``rtol``.

    Never raises for a failed equilibrium: ``status`` says why. This is what
    :func:`rbo_jax.stability_map`, the ``spectral_abscissa`` quantity of ``rbo-jax sweep`` and
    ``rbo-jax stability-map`` compute at every point; jit- and vmap-compatible.
    """
    if theta_eq is not None:
        theta = _as_vector(theta_eq, "theta_eq")
        status = EquilibriumStatus.where(
            jnp.all(jnp.isfinite(theta)), EquilibriumStatus.successful, EquilibriumStatus.nonfinite
        )
    else:
        guess = jnp.zeros(3) if theta_guess is None else theta_guess
        sol = solve_equilibrium(model, guess, t=t, **equilibrium_kwargs)
        theta, status = sol.theta, sol.status
    p = (fast_spectrum if fast else spectrum)(model, theta, t=t)
    p = jnp.where(status == EquilibriumStatus.successful, p, jnp.nan + 0j)
    kind, a = classify(p, rtol=rtol)
    return EquilibriumStability(theta=theta, eigenvalues=p, abscissa=a, kind=kind, status=status)


def is_unstable(result: EquilibriumStability):
    """Whether the classification is divergence or flutter (a traced boolean)."""
    code = enum.code(result.kind)
    return (code == enum.code(StabilityKind.flutter)) | (
        code == enum.code(StabilityKind.divergence)
    )


def critical_value(unstable: Callable, lo, hi, *, n_scan: int = 64, n_bisect: int = 48):
    r"""The smallest value $x \in (lo, hi]$ at which ``unstable(x)`` (a traced boolean) becomes
    true: a scan at ``n_scan`` points, then ``n_bisect`` bisection steps on the first change (if
    the first scan point is already unstable, the interval from ``lo`` to it is bisected).
    ``inf`` if ``unstable`` is false on the whole scan. jit- and vmap-compatible."""
    scan = jnp.linspace(lo, hi, n_scan + 1)[1:]
    flags = jax.vmap(unstable)(scan)
    i = jnp.argmax(flags)
    upper = scan[i]
    lower = jnp.where(i > 0, scan[jnp.maximum(i - 1, 0)], lo)

    def body(_, bounds):
        lower, upper = bounds
        mid = 0.5 * (lower + upper)
        u = unstable(mid)
        return jnp.where(u, lower, mid), jnp.where(u, mid, upper)

    lower, upper = jax.lax.fori_loop(0, n_bisect, body, (lower, upper))
    return jnp.where(jnp.any(flags), upper, jnp.inf)
