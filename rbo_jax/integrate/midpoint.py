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
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from ..solvers import (
    RUNNING,
    FactoredTridiagonal,
    iterate,
    newton_update,
    tridiagonal_factor,
    tridiagonal_jacobian,
)

__all__ = ["midpoint"]


def _once_if(pred, fn, x):
    """``fn(x)`` where ``pred``, else ``x``: a ``while`` loop of at most one iteration, which
    under ``jax.vmap`` runs ``fn`` only when a member needs it (a ``cond`` would run both)."""

    def body(c):
        return False, fn(c[1])

    return lax.while_loop(lambda c: c[0], body, (pred, x))[1]


def midpoint(field, x0, counts, steps, *, rtol, atol, max_newton: int = 8, project=None):
    r"""Samples of $\dot x = f(x)$ from ``x0`` ``(N, m)``: ``counts[k]`` steps of ``steps[k]``
    between samples $k$ and $k+1$ (module docstring). ``field`` maps ``(N, m)`` to ``(N, m)``
    and couples neighbouring blocks only; ``project(x)``, if given, is applied after each step
    (a change of chart that leaves the state the same, e.g. a turn-vector recentred).

    Returns ``(xs, ok, refreshes)``: the samples ``(K+1, N, m)`` (``x0`` first; ``inf`` from a
    failed step on), whether every step converged, and how many times the Jacobian was
    computed. Differentiable in forward mode (``jax.jvp``); the loops stop on convergence, so
    reverse mode does not transpose them."""
    eye = jnp.eye(x0.shape[1], dtype=x0.dtype)

    def factor(J, h):
        L, D, U = J
        return tridiagonal_factor(-0.5 * h * L, eye[None] - 0.5 * h * D, -0.5 * h * U)

    linear = FactoredTridiagonal()

    def newton(x, y0, fac, h):
        """The chord iterations of one step from ``y0``: the project's one loop
        (:func:`rbo_jax.solvers.iterate`) of Newton's update with the step's factors."""

        def chord(y, state):
            r = y - x - h * field(0.5 * (x + y))
            y, _, done, finite = newton_update(r, fac, linear, y, rtol=rtol, atol=atol)
            code = jnp.where(finite, jnp.where(done, 0, RUNNING), 1)
            return y, state, code

        y, _, code, _ = iterate(chord, y0, None, max_steps=max_newton, exhausted=1)
        return y, code == 0

    def step(c):
        x, rate, J, fac, h, i, ok, refreshes = c
        y0 = x + h * rate  # the last step's rate, extrapolated
        y, conv = newton(x, y0, fac, h)

        def refresh(c):
            J, fac, refreshes, _, _ = c
            J = tridiagonal_jacobian(field, x)
            fac = factor(J, h)
            y, conv = newton(x, x, fac, h)
            return J, fac, refreshes + 1, y, conv

        J, fac, refreshes, y, conv = _once_if(~conv, refresh, (J, fac, refreshes, y, conv))
        rate = (y - x) / h
        if project is not None:
            y = project(y)
        ok = conv & jnp.all(jnp.isfinite(y))
        return jnp.where(ok, y, x), rate, J, fac, h, i + 1, ok, refreshes

    def interval(c, inputs):
        x, rate, J, fac, h_prev, ok, refreshes = c
        n, h = inputs
        fac = _once_if(h != h_prev, lambda f: factor(J, h), fac)
        x, rate, J, fac, _, _, ok, refreshes = lax.while_loop(
            lambda s: (s[5] < n) & s[6], step, (x, rate, J, fac, h, 0, ok, refreshes)
        )
        return (x, rate, J, fac, h, ok, refreshes), jnp.where(ok, x, jnp.inf)

    J0 = tridiagonal_jacobian(field, x0)
    h0 = steps[0]
    rate0 = jnp.zeros_like(x0)
    carry = (x0, rate0, J0, factor(J0, h0), h0, jnp.asarray(True), jnp.asarray(1))
    (_, _, _, _, _, ok, refreshes), xs = lax.scan(interval, carry, (counts, steps))
    return jnp.concatenate([x0[None], xs]), ok, refreshes
