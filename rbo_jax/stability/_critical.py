r"""The critical value of a load: the smallest load at which an equilibrium loses stability.

Along a load $P \in (P_{min}, P_{max}]$ every point is **stable** (no unstable root:
:func:`rbo_jax.classify`), **unstable** (divergence or flutter) or **undefined** (its
equilibrium could not be computed). The critical load is where the stable interval that starts
at $P_{min}$ ends: a scan at ``n_scan`` loads finds the first point that is not stable, and
``n_bisect`` bisections locate the end between it and the last stable one. It is that load
where the end is a loss of stability, ``inf`` where every scanned load is stable, and NaN —
undefined, and reported as such — where the end is a failure of the equilibrium (the branch
ends at a limit point, a singular point of $Z$, a foundation's barrier, or Newton does not
converge): a failed equilibrium counts neither as stable nor as unstable, for every model.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from .. import _programs
from ._classify import is_unstable
from ._point import equilibrium_stability, first_change

__all__ = [
    "STABLE",
    "UNDEFINED",
    "UNSTABLE",
    "critical_between",
    "critical_load_along",
    "critical_search",
]

STABLE, UNSTABLE, UNDEFINED = 0, 1, 2


def stability_code(result) -> jax.Array:
    """:data:`STABLE`, :data:`UNSTABLE` or :data:`UNDEFINED` of an
    :class:`rbo_jax.EquilibriumStability`."""
    code = jnp.where(is_unstable(result.kind), UNSTABLE, STABLE)
    return jnp.where(result.ok, code, UNDEFINED)


def critical_search(code_at: Callable, lo, hi, *, n_scan: int, n_bisect: int, like=None):
    """The critical value (module docstring) of ``code_at(P)`` (a traced code) on
    ``(lo, hi]``; jit- and vmap-compatible (``like``: :func:`._point.first_change`'s)."""
    value, end = first_change(
        code_at, lo, hi, n_scan=n_scan, n_bisect=n_bisect, base=STABLE, like=like
    )
    return jnp.where(jnp.isfinite(value) & (end == UNDEFINED), jnp.nan, value)


def critical_between(
    model_at: Callable, code_at: Callable, lo, hi, *, n_scan: int, n_bisect: int, like=None
):
    """:func:`critical_search` of ``code_at`` on ``(lo, hi]``, NaN where the parameters of the
    model ``model_at(P)`` are invalid at either end (values traced at construction)."""
    value = critical_search(code_at, lo, hi, n_scan=n_scan, n_bisect=n_bisect, like=like)
    valid = model_at(lo).parameter_status()[0] & model_at(hi).parameter_status()[0]
    return jnp.where(valid, value, jnp.nan)


def critical_load_along(
    model_fn: Callable,
    load_max: float,
    *,
    load_min: float = 0.0,
    guess=None,
    n_scan: int = 32,
    n_bisect: int = 40,
    rtol: float = 1e-9,
    steps: int = 1,
):
    r"""The smallest load $P \in (P_{min}, P_{max}]$ at which the equilibrium of
    ``model_fn(P)`` (a model for every load value, traced) loses stability (module docstring):
    a scan at ``n_scan`` loads, then ``n_bisect`` bisections; ``inf`` if it stays stable, NaN
    where the stable interval ends at a failed equilibrium. Equilibria by Newton from ``guess``
    (the configuration at rest) in ``steps`` load steps; unstable as :func:`rbo_jax.classify`
    says with ``rtol`` (each root against its own modulus). NaN too where the model's
    parameters are invalid at ``load_min`` or ``load_max`` (values traced at construction, e.g.
    a negative stiffness in a ``jax.vmap``)."""
    if not load_max > load_min:
        raise ValueError(f"critical_load: load_max ({load_max}) must exceed load_min ({load_min}).")

    return _critical_load_program(
        model_fn,
        guess,
        rtol,
        int(steps),
        int(n_scan),
        int(n_bisect),
        jnp.asarray(float(load_min)),
        jnp.asarray(float(load_max)),
    )


def _critical_load(model_fn, guess, rtol, steps, n_scan, n_bisect, lo, hi):
    """:func:`critical_load_along`'s program: one per ``model_fn`` (a static argument, by
    identity) and settings, so a second call with the same function compiles nothing."""

    def code_at(P):
        result = equilibrium_stability(model_fn(P), guess, rtol=rtol, steps=steps)
        return stability_code(result)

    return critical_between(model_fn, code_at, lo, hi, n_scan=n_scan, n_bisect=n_bisect)


_critical_load_program = _programs.jit(_critical_load, fast_compile=True)
