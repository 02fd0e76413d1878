r"""The flat vector field $F(x)$, $x = [\theta, \Omega]$, of the right form (4.55)–(4.56), and its
directional derivatives up to third order: what Hopf points, Lyapunov coefficients and shooting
are written in.

Derivatives are taken along given directions only (nested ``jax.jvp``), never as whole tensors:
one traced copy of :func:`jet` serves the Jacobian (unit directions), the Hessian-vector products
of Newton's method on the Hopf system and Kuznetsov's multilinear forms $B(u, v) = D^2F[u, v]$,
$C(u, v, w) = D^3F[u, v, w]$ (complex arguments by multilinearity, :mod:`._lyapunov`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..models.rigid_body import RigidBodyOscillator

__all__ = ["flat_field", "jet", "jets", "jets_by_row"]


def flat_field(model: RigidBodyOscillator, t=0.0, *, throw: bool = True):
    r"""$x \mapsto F(x) = [\dot\theta, \dot\Omega]$ of the right form (4.55)–(4.56) at time ``t``
    (autonomous models: any ``t``). ``throw=False``: a configuration where the equations are
    undefined gives NaN instead of a runtime error (no host callback in the program)."""
    rhs = model.right_form(throw)

    def F(x):
        theta_dot, Omega_dot = rhs(t, (x[:3], x[3:]))
        return jnp.concatenate([theta_dot, Omega_dot])

    return F


def jet(F, y, t1, t2, t3):
    r"""$F(y)$, $DF(y)[t_1]$, $D^2F(y)[t_1, t_2]$ and $D^3F(y)[t_1, t_2, t_3]$ by nested forward
    mode (one traced copy of ``F``'s third-order derivative, which holds every lower order).
    $t_3 = 0$ gives a zero third derivative, $t_2 = t_3 = 0$ the Jacobian-vector product only."""

    def first(z):
        return jax.jvp(F, (z,), (t1,))

    def second(z):
        return jax.jvp(first, (z,), (t2,))

    (lower, (_, d2)), (_, (_, d3)) = jax.jvp(second, (y,), (t3,))
    f0, d1 = lower
    return f0, d1, d2, d3


def jets(F, y, directions):
    r""":func:`jet` for every row $(t_1, t_2, t_3)$ of ``directions`` (shape ``(N, 3, m)``) in
    one vmapped pass. Returns ``(F(y), D1, D2, D3)`` with ``D1``, ``D2``, ``D3`` of shape
    ``(N, n)``."""
    f0, d1, d2, d3 = jax.vmap(lambda d: jet(F, y, d[0], d[1], d[2]))(directions)
    return f0[0], d1, d2, d3


def jets_by_row(F, y, directions, count=None, shifts=None, size=None):
    r""":func:`jets` one row per iteration of a loop: ``(D1, D2, D3)``, each of shape ``(N, n)``;
    only the first ``count`` rows (default all; may be traced) are computed, the others stay
    zero; row $i$ at ``y + shifts[i]`` where ``shifts`` (``(N, m)``) is given. The same
    numbers; XLA compiles the loop's single row of third derivatives faster than the rows
    vmapped (the Hopf program's $\ell_1$; benchmarks/README.md, History). ``size``: $n$, where
    the caller knows it (otherwise ``F`` is traced once more for it)."""
    n = jax.eval_shape(F, y).shape[0] if size is None else size
    zeros = jnp.zeros((directions.shape[0], n), y.dtype)

    def row(i, acc):
        at = y if shifts is None else y + shifts[i]
        _, d1, d2, d3 = jet(F, at, *directions[i])
        return acc[0].at[i].set(d1), acc[1].at[i].set(d2), acc[2].at[i].set(d3)

    count = directions.shape[0] if count is None else count
    return jax.lax.fori_loop(0, count, row, (zeros, zeros, zeros))
