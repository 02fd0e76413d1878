r"""The flat vector field $F(x)$, $x = [\theta, \Omega]$, of the right form (4.55)–(4.56), and its
multilinear derivatives at a point, extended to complex arguments: what Hopf points, Lyapunov
coefficients and shooting are written in."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp

from ..model import RigidBodyOscillator

__all__ = ["flat_field", "multilinear", "complex_form"]


def flat_field(model: RigidBodyOscillator, t=0.0):
    r"""$x \mapsto F(x) = [\dot\theta, \dot\Omega]$ of the right form (4.55)–(4.56) at time ``t``
    (autonomous models: any ``t``)."""
    rhs = model.right_form()

    def F(x):
        theta_dot, Omega_dot = rhs(t, (x[:3], x[3:]))
        return jnp.concatenate([theta_dot, Omega_dot])

    return F


def multilinear(F, x0):
    r"""The real multilinear forms $D^kF(x_0)[u_1, \dots, u_k]$ by nested forward-mode
    derivatives: ``form(u1, u2)`` is Kuznetsov's $B$, ``form(u1, u2, u3)`` his $C$. Each
    argument may carry a leading batch axis (the same for all): the directions are then
    evaluated in one vmapped pass, one compiled graph per order."""

    def single(*us):
        def nest(level):
            if level == 0:
                return F
            inner = nest(level - 1)
            return lambda x: jax.jvp(inner, (x,), (us[level - 1],))[1]

        return nest(len(us))(x0)

    def form(*us):
        if us[0].ndim == x0.ndim:
            return single(*us)
        return jax.vmap(single)(*us)

    return form


def complex_form(real_form, *vectors):
    r"""A real multilinear form extended to complex vectors by multilinearity,
    $B(a + ib, c + id) = B(a, c) - B(b, d) + i[B(a, d) + B(b, c)]$ and so on: the $2^k$ real
    evaluations in one batched call of ``real_form``."""
    parts = [(jnp.real(v), jnp.imag(v)) for v in vectors]
    choices = list(itertools.product((0, 1), repeat=len(vectors)))
    args = [jnp.stack([parts[j][c[j]] for c in choices]) for j in range(len(vectors))]
    values = real_form(*args)
    weights = jnp.asarray([1j ** sum(c) for c in choices])
    return weights @ values.astype(weights.dtype)
