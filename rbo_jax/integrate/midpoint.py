r"""The implicit midpoint rule for a chain of bodies, with block-tridiagonal Newton solves.

A rod or an open chain of $N$ bodies couples each body to its neighbours only: with the
unknowns ordered body by body ($m$ a body), the Jacobian $J = \partial f/\partial x$ of its
equations of motion $\dot x = f(x)$ is block-tridiagonal. One step of the implicit midpoint
rule,

$$x_{n+1} = x_n + h\,f\!\left(\tfrac12 (x_n + x_{n+1})\right),$$

is second order, symmetric and A-stable, and it keeps every quadratic invariant exactly: on a
linear elastic system its energy is kept to the Newton tolerance at any step. A mode of
frequency $\omega$ keeps its amplitude at every $h$ and turns by
$2\arctan(\omega h/2)$ a step instead of $\omega h$ (a relative phase error
$(\omega h)^2/12$ where $\omega h \ll 1$). So the stiff stretch and shear waves of a slender
rod, which hold every explicit step below $2/\omega_{max}$, neither limit the step nor lose
their energy (an L-stable method damps them, a loss the size of their share of the energy);
the step is chosen for the slow motion that is wanted.

**Newton.** Each step solves $G(y) = y - x_n - h f((x_n + y)/2) = 0$ by the chord method from
$y = x_n + h\,(x_n - x_{n-1})/h_{n-1}$ (the last step extrapolated; $x_0$ at the first), with
the matrix $I - \tfrac h2 J$: its blocks from $3m$ Jacobian-vector products
(:func:`rbo_jax.solvers.tridiagonal_jacobian`), factored by block elimination
(:func:`rbo_jax.solvers.tridiagonal_factor`), each iteration two scans
(:class:`~rbo_jax.solvers.FactoredTridiagonal`, in the project's one loop of Newton updates:
:func:`~rbo_jax.solvers.iterate`, :func:`~rbo_jax.solvers.newton_update`): O(N m³) to factor,
O(N m²) an iteration. The Jacobian is kept from step to step (a small motion barely changes it)
and computed anew at the current state only when the iterations do not converge within
``max_newton``; the factors are made anew when the step changes. The iterations stop when the
update is within ``atol + rtol |y|`` in every component. A step that does not converge with a
fresh Jacobian ends the solve: ``ok`` is false and the samples from there on are ``inf``.

**Derivatives.** Each step's solution $y(x_n, p)$ is differentiated by the project's one
implicit-derivative rule (:func:`rbo_jax.solvers.implicit`): $dy = (I - \tfrac h2 J)^{-1}
[(I + \tfrac h2 J)\,dx_n + h\,\partial_p f\,dp]$ with $J$ at the midpoint, its block-tridiagonal
matrix from $3m$ products and one block elimination; the chord iterations are never
differentiated. With the steps' counts known before tracing (``max_count``) every loop has a
fixed length, so ``jax.grad`` (reverse mode) runs through the solve: it transposes one
block-tridiagonal solve per step, each step recomputed on the way back (``jax.checkpoint``:
memory of one state per step); forward mode (``jax.jvp``) works with traced counts too.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from ..solvers import (
    RUNNING,
    FactoredTridiagonal,
    Implicit,
    Tridiagonal,
    implicit,
    iterate,
    newton_update,
    tridiagonal_factor,
    tridiagonal_jacobian,
)

__all__ = ["midpoint"]

# after a step whose kept Jacobian failed, the next steps begin with a new one (at the
# predicted midpoint) instead of chord iterations that would fail first
EAGER_STEPS = 8
# the new Jacobians a step may take when its chord iterations do not converge
MAX_REFRESH = 2


def _once_if(pred, fn, x):
    """``fn(x)`` where ``pred``, else ``x``: a ``while`` loop of at most one iteration, which
    under ``jax.vmap`` runs ``fn`` only when a member needs it (a ``cond`` would run both)."""

    def body(c):
        return False, fn(c[1])

    return lax.while_loop(lambda c: c[0], body, (pred, x))[1]


def _frozen(tree):
    """``tree`` with its float leaves cut from differentiation (the chord iterations)."""
    dynamic, static = eqx.partition(tree, eqx.is_inexact_array)
    return eqx.combine(lax.stop_gradient(dynamic), static)


class _Residual(eqx.Module):
    r"""$G(y \oplus d) = y + d - x - h\,f(t + h/2, (x + y + d)/2)$ of one step, at the
    parameters ``(args, x, t, h, root, converged)`` (:func:`rbo_jax.solvers.implicit`)."""

    field: Callable = eqx.field(static=True)

    def __call__(self, y, d, params):
        args, x, t, h, _, _ = params
        z = y + d
        return z - x - h * self.field(t + 0.5 * h, 0.5 * (x + z), args)


def _found(params):
    """The step's solution, found by the chord iterations before (``params[4]``)."""
    return Implicit(params[4], None, params[5], None)


def midpoint(
    field,
    x0,
    ts,
    counts,
    steps,
    *,
    args=None,
    rtol,
    atol,
    max_newton: int = 8,
    project=None,
    max_count: int | None = None,
    uniform: bool = False,
):
    r"""Samples of $\dot x = f(t, x)$ at ``ts`` ``(K+1,)`` from ``x0`` ``(N, m)``:
    ``counts[k]`` steps of ``steps[k]`` between samples $k$ and $k+1$ (module docstring).
    ``field(t, x, args)`` maps ``(N, m)`` to ``(N, m)`` and couples neighbouring blocks only;
    ``args`` (a pytree: the model) is differentiated through each step's implicit derivative;
    ``project(x)``, if given, is applied after each step (a change of chart that leaves the
    state the same, e.g. a turn-vector recentred). ``max_count``: a Python int, at least every
    count, known before tracing: each interval is then a loop of that length (reverse-mode
    derivatives); ``None``: each runs its own count (forward mode only). ``uniform``: every
    count equals ``max_count`` (no step is masked: a plain loop).

    Returns ``(xs, ok, refreshes)``: the samples ``(K+1, N, m)`` (``x0`` first; ``inf`` from a
    failed step on), whether every step converged, and how many times the Jacobian was
    computed."""
    eye = jnp.eye(x0.shape[1], dtype=x0.dtype)
    residual = _Residual(field)

    def factor(J, h):
        L, D, U = J
        return tridiagonal_factor(-0.5 * h * L, eye[None] - 0.5 * h * D, -0.5 * h * U)

    linear = FactoredTridiagonal()

    def newton(a, x, y0, fac, h, t):
        """The chord iterations of one step from ``y0``: the project's one loop
        (:func:`rbo_jax.solvers.iterate`) of Newton's update with the step's factors."""

        def chord(y, state):
            r = residual(y, 0.0, (a, x, t, h, None, None))
            y, _, done, finite = newton_update(r, fac, linear, y, rtol=rtol, atol=atol)
            code = jnp.where(finite, jnp.where(done, 0, RUNNING), 1)
            return y, state, code

        y, _, code, _ = iterate(chord, y0, None, max_steps=max_newton, exhausted=1)
        return y, code == 0

    def step(c):
        x, rate, J, fac, h, t, ok, refreshes, eager_left = c
        eager = eager_left > 0
        a, xs, hs, ts_ = _frozen(args), lax.stop_gradient(x), lax.stop_gradient(h), t
        y0 = xs + hs * lax.stop_gradient(rate)  # the last step's rate, extrapolated

        def jacobian(c):
            J, fac, refreshes, y = c
            y = jnp.where(jnp.all(jnp.isfinite(y)), y, xs)
            J = tridiagonal_jacobian(lambda z: field(ts_ + 0.5 * hs, z, a), 0.5 * (xs + y))
            return J, factor(J, hs), refreshes + 1, y

        def attempt(c):
            """Chord iterations, with a new Jacobian first where ``need``."""
            J, fac, refreshes, y, _, rounds, need = c
            J, fac, refreshes, y = _once_if(need, jacobian, (J, fac, refreshes, y))
            y, conv = newton(a, xs, y, fac, hs, ts_)
            return J, fac, refreshes, y, conv, rounds + 1, True

        # the kept Jacobian first (a new one first after a step that needed one), then up to
        # MAX_REFRESH new ones at the midpoint of the chord's last iterate
        J, fac, refreshes, y, conv, rounds, _ = lax.while_loop(
            lambda c: ~c[4] & (c[5] <= MAX_REFRESH),
            attempt,
            (J, fac, refreshes, y0, jnp.asarray(False), 0, eager),
        )
        # the kept Jacobian failed this step: a new one first for the next EAGER_STEPS steps
        stale = rounds > 1
        eager_left = jnp.where(stale, EAGER_STEPS, jnp.maximum(eager_left - 1, 0))
        y = implicit(_found, residual, (args, x, t, h, y, conv), linear=Tridiagonal()).y
        rate = (y - x) / h  # the next step's start
        if project is not None:
            y = project(y)
        good = ok & conv & jnp.all(jnp.isfinite(y))
        return jnp.where(good, y, x), rate, J, fac, h, t + h, good, refreshes, eager_left

    checkpointed = jax.checkpoint(step)

    def interval(c, inputs):
        x, rate, J, fac, h_prev, ok, refreshes, eager = c
        n, h, t = inputs
        fac = _once_if(h != h_prev, lambda f: factor(J, lax.stop_gradient(h)), fac)
        inner = (x, rate, J, fac, h, t, ok, refreshes, eager)
        if max_count is None:  # each interval its own count
            inner = lax.while_loop(
                lambda s: (s[0] < n) & s[1][6],
                lambda s: (s[0] + 1, step(s[1])),
                (0, inner),
            )[1]
        else:  # a loop of fixed length, the steps past the count skipped

            def fixed(s, i):
                if uniform:  # after a failure the steps go on from the last good state, flagged
                    return checkpointed(s), None
                return lax.cond((i < n) & s[6], checkpointed, lambda s: s, s), None

            inner = lax.scan(fixed, inner, jnp.arange(max_count, dtype=counts.dtype))[0]
        x, rate, J, fac, _, _, ok, refreshes, eager = inner
        return (x, rate, J, fac, h, ok, refreshes, eager), jnp.where(ok, x, jnp.inf)

    J0 = tridiagonal_jacobian(lambda z: field(ts[0], z, _frozen(args)), lax.stop_gradient(x0))
    h0 = lax.stop_gradient(steps[0])
    carry = (x0, jnp.zeros_like(x0), J0, factor(J0, h0), h0, True, 1, 0)
    carry = jax.tree_util.tree_map(jnp.asarray, carry)
    (_, _, _, _, _, ok, refreshes, _), xs = lax.scan(interval, carry, (counts, steps, ts[:-1]))
    return jnp.concatenate([x0[None], xs]), ok, refreshes
