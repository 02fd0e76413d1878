r"""The flat vector field $F(x)$, $x = [\theta, \Omega]$, of the right form (4.55)–(4.56), and its
directional derivatives up to third order: what Lyapunov coefficients and shooting are written in.

Derivatives are taken along given directions only (nested ``jax.jvp``), never as whole tensors,
and along one direction at a time: Kuznetsov's multilinear forms $B(u, v) = D^2F[u, v]$,
$C(u, v, w) = D^3F[u, v, w]$ (complex arguments by multilinearity, :mod:`._lyapunov`;
:mod:`._normal_form` up to fifth order) come from one traced :func:`jet` along $v$, $v$, $v$ by
the polarization identities of :func:`jets_by_row`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..models.rigid_body import RigidBodyOscillator

__all__ = ["flat_field", "jet", "jets_by_row"]


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


# the sign pairs (eps2, eps3) of the polarization in jets_by_row
_SIGNS = ((1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0))


def jets_by_row(F, y, directions, count=None, shifts=None, size=None):
    r"""$DF[t_1]$, $D^2F[t_1, t_2]$ and $D^3F[t_1, t_2, t_3]$ for every row $(t_1, t_2, t_3)$ of
    ``directions`` (``(N, 3, m)``), as ``(D1, D2, D3)`` of shape ``(N, n)`` each, from derivatives
    along single directions only: with $\hat t_k = t_k/|t_k|$ (or $t_k$ where it is zero) and
    $v = \hat t_1 + \epsilon_2\hat t_2 + \epsilon_3\hat t_3$ over the four signs
    $\epsilon_2, \epsilon_3 = \pm 1$, the polarization identities of symmetric forms

    $$DF[t_1] = \frac{|t_1|}{4}\sum DF[v],\quad
      D^2F[t_1, t_2] = \frac{|t_1||t_2|}{8}\sum\epsilon_2 D^2F[v, v],\quad
      D^3F[t_1, t_2, t_3] = \frac{|t_1||t_2||t_3|}{24}\sum\epsilon_2\epsilon_3 D^3F[v, v, v]$$

    (exact; in floating point a few roundings of the largest term: the unit directions keep the
    terms alike). One evaluation per iteration of a loop around one traced :func:`jet` with
    $t_1 = t_2 = t_3 = v$: XLA simplifies the nested derivative along one direction to a
    fraction of the mixed one, and compiles one row faster than the rows vmapped (figures:
    benchmarks/README.md, History). Only the
    first ``count`` rows (default all; may be traced) are computed, the others stay zero; row
    $i$ at ``y + shifts[i]`` where ``shifts`` (``(N, m)``) is given. ``size``: $n$, where the
    caller knows it (otherwise ``F`` is traced once more for it)."""
    n = jax.eval_shape(F, y).shape[0] if size is None else size
    zeros = jnp.zeros((directions.shape[0], n), y.dtype)
    signs = jnp.asarray(_SIGNS, y.dtype)

    def evaluation(k, acc):
        i, (e2, e3) = k // 4, signs[k % 4]
        t = directions[i]
        sq = jnp.sum(t * t, axis=1)
        norm = jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 1.0)  # finite derivatives
        v = t[0] / norm[0] + e2 * t[1] / norm[1] + e3 * t[2] / norm[2]
        _, d1, d2, d3 = jet(F, y if shifts is None else y + shifts[i], v, v, v)
        weights = (norm[0] / 4, e2 * norm[0] * norm[1] / 8, e2 * e3 * jnp.prod(norm) / 24)
        return tuple(a.at[i].add(w * d) for a, w, d in zip(acc, weights, (d1, d2, d3)))

    count = directions.shape[0] if count is None else count
    return jax.lax.fori_loop(0, 4 * count, evaluation, (zeros, zeros, zeros))
