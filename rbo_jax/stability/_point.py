r"""What a stability map computes at one point: the equilibrium (4.61), its spectrum
(4.63)–(4.69) and the classification, in one function (:func:`equilibrium_stability`), and the
critical value of a load parameter along one line (:func:`critical_value`). Any model.

The grids themselves are run by the batch engine: :func:`rbo_jax.stability_map` and
:func:`rbo_jax.critical_load` are presets of :func:`rbo_jax.sweep` built on these functions.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jaxtyping import Array, Complex, Float

from .. import _enumeration as enum
from .._validation import tree_finite
from ..mechanics import AbstractMechanics
from ..solvers import Outcome
from ._classify import StabilityKind, classify
from ._equilibrium import EquilibriumStatus, solve_equilibrium
from ._linearize import eigenvalues

__all__ = [
    "STABILITY_KIND_NAMES",
    "EquilibriumStability",
    "critical_value",
    "equilibrium_stability",
]

STABILITY_KIND_NAMES = enum.names(StabilityKind)


class EquilibriumStability(Outcome):
    r"""Result of :func:`equilibrium_stability`: the equilibrium ``state`` (the model's
    configuration; ``theta`` its turn-vectors), its ``eigenvalues`` (NaN where the equilibrium
    could not be computed), the spectral ``abscissa`` max Re p, the classification ``kind``
    (:class:`StabilityKind`) and the equilibrium ``status`` (:class:`EquilibriumStatus`)."""

    state: Any
    eigenvalues: Complex[Array, " n"]
    abscissa: Float[Array, ""]
    kind: StabilityKind
    status: EquilibriumStatus

    @property
    def theta(self):
        """The turn-vector(s) of the equilibrium."""
        return getattr(self.state, "theta", self.state)


def equilibrium_stability(
    model: AbstractMechanics,
    guess=None,
    *,
    state=None,
    theta_eq=None,
    rtol: float = 1e-9,
    fast: bool = True,
    t=0.0,
    **equilibrium_kwargs,
) -> EquilibriumStability:
    r"""The stability of an equilibrium of ``model``: Lyapunov's first method in one call.

    1. The equilibrium: ``state`` (or ``theta_eq``) if given (a closed form such as (4.62),
       checked finite), else :func:`rbo_jax.solve_equilibrium` from ``guess`` (default: the
       configuration at rest) with ``equilibrium_kwargs``.
    2. Its spectrum (4.63)–(4.69): :func:`rbo_jax.fast_spectrum` (block structure) or, with
       ``fast=False``, the whole linearisation's; NaN when the equilibrium failed.
    3. :func:`rbo_jax.classify` with tolerance ``rtol``, ``reversible`` where no force depends
       on the velocities.

    Never raises for a failed equilibrium: ``status`` says why. This is what
    :func:`rbo_jax.stability_map`, the ``spectral_abscissa`` quantity of ``rbo-jax sweep`` and
    ``rbo-jax stability-map`` compute at every point; jit- and vmap-compatible.
    """
    given = theta_eq if state is None else state
    if given is not None:
        config = model.configuration(given, "state")
        finite = tree_finite(config)
        S = EquilibriumStatus
        status = S.where(finite, S.successful, S.nonfinite)
    else:
        sol = solve_equilibrium(model, guess, t=t, **equilibrium_kwargs)
        config, status = sol.state, sol.status
    p = eigenvalues(model, config, t, fast=fast)
    p = jnp.where(status == EquilibriumStatus.successful, p, jnp.nan + 0j)
    kind, a = classify(p, rtol=rtol, reversible=not model.depends_on_velocity())
    return EquilibriumStability(state=config, eigenvalues=p, abscissa=a, kind=kind, status=status)


def first_change(
    code_at: Callable, lo, hi, *, n_scan: int = 64, n_bisect: int = 48, base=0, like=None
):
    r"""``(x, code)``: the smallest value $x \in (lo, hi]$ at which ``code_at(x)`` (a traced
    integer code) is no longer ``base``, and the code there: a scan of the ``n_scan`` points
    ``linspace(lo, hi, n_scan + 1)[1:]`` up to the first that has changed, then ``n_bisect``
    bisection steps between it and the point before (``lo`` before the first). ``x`` is ``inf``
    if the code is ``base`` on the whole scan. One loop evaluates ``code_at`` at one point an
    iteration (the scan's next point, then the bisection's midpoint): it is traced and compiled
    once, and the scan stops at the first change. jit- and vmap-compatible. ``like``: values
    that ``jax.vmap`` batches wherever it batches the search (a sweep's point): the loop's state
    starts batched like them, so that vmap's rule for the loop batches its body once instead of
    again after the first pass (the equilibria and spectra inside it, and their own loops)."""
    scan = jnp.linspace(lo, hi, n_scan + 1)[1:]

    def more(s):
        k, b, _, _, found, _ = s
        return jnp.where(found, b < n_bisect, k < n_scan)

    def evaluate(s):
        k, b, lower, upper, found, code = s
        x = jnp.where(found, 0.5 * (lower + upper), scan[jnp.minimum(k, n_scan - 1)])
        c = jnp.asarray(code_at(x)).astype(jnp.int32)
        changed = c != base
        lower, upper = jnp.where(changed, lower, x), jnp.where(changed, x, upper)
        code = jnp.where(changed, c, code)
        k, b = jnp.where(found, k, k + 1), jnp.where(found, b + 1, b)
        return k, b, lower, upper, found | changed, code

    # zeros batched like `like` (x != x is false but for NaN: times 0, zero for any value)
    leaves = jax.tree_util.tree_leaves(like)
    zf = sum(
        (jnp.sum(jnp.asarray(x) != x).astype(scan.dtype) * 0 for x in leaves),
        jnp.zeros((), scan.dtype),
    )
    zi = zf.astype(jnp.int32)
    lower = jnp.asarray(lo, scan.dtype) + zf
    s = (zi, zi, lower, scan[-1] + zf, zi != 0, jnp.asarray(base, jnp.int32) + zi)
    _, _, _, upper, found, code = jax.lax.while_loop(more, evaluate, s)
    return jnp.where(found, upper, jnp.inf), code


def critical_value(unstable: Callable, lo, hi, *, n_scan: int = 64, n_bisect: int = 48):
    r"""The smallest value $x \in (lo, hi]$ at which ``unstable(x)`` (a traced boolean) becomes
    true (:func:`first_change`); ``inf`` if it is false on the whole scan. jit- and
    vmap-compatible."""
    code_at = lambda x: jnp.asarray(unstable(x), jnp.int32)  # noqa: E731
    return first_change(code_at, lo, hi, n_scan=n_scan, n_bisect=n_bisect)[0]
