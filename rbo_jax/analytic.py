r"""Closed forms of the paper: Nikolai roots (4.69), (4.72), torsion roots, precession rate (4.113).

These are independent of the numerical machinery (no autodiff, no ODE solver) and are what
:mod:`rbo_jax.stability` is checked against. All functions are jit/vmap-compatible.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Complex

from ._custom_types import Scalar, ScalarLike, Vector
from .kinematics import gcoef, sinc

__all__ = [
    "nikolai_equilibrium",
    "nikolai_bending_stiffness",
    "nikolai_bending_roots",
    "nikolai_bending_roots_small_load",
    "torsion_roots",
    "nikolai_spectrum",
    "precession_rate",
]


def nikolai_equilibrium(M: ScalarLike, d: ScalarLike, k=(0.0, 0.0, 1.0)) -> Vector:
    r"""The equilibrium $\theta_0 = (M/d)\,k$ of the Nikolai problem, eq. (4.62): the quadratic
    foundation (4.50) under a follower moment $M\,P\cdot k$ (4.57). ``k`` is normalised."""
    k = jnp.asarray(k, dtype=jnp.result_type(float))
    k = k / jnp.sqrt(k[0] * k[0] + k[1] * k[1] + k[2] * k[2])
    return (jnp.asarray(M) / jnp.asarray(d)) * k


def _g(theta0):
    """g = θ0 sinθ0 / (2(1 − cosθ0)) = 1 − θ0²·(1 − g)/θ0², safe at θ0 = 0 (4.11)."""
    t = theta0 * theta0
    return 1.0 - t * gcoef(t)


def nikolai_bending_stiffness(c: ScalarLike, d: ScalarLike, M: ScalarLike) -> Scalar:
    r"""The bending stiffness of (4.69) at the equilibrium $\theta_0 = M/d$ of (4.62):

    $K = c\,(g^2 + \frac{M^2}{4d^2}) - \frac{M^2}{4d} + (1 - g)\,g\,d$,
    $g = \frac{\theta_0\sin\theta_0}{2(1-\cos\theta_0)}$ (reading R4, docs/readings.md).
    """
    c, d, M = jnp.asarray(c), jnp.asarray(d), jnp.asarray(M)
    g = _g(M / d)
    return c * (g**2 + M**2 / (4 * d**2)) - M**2 / (4 * d) + (1 - g) * g * d


def _roots_of_biquadratic(A1, K, M):
    """Roots p of (A1 p² + K)² + M²/4 = 0: A1 p² = −K ± iM/2."""
    K, M, A1 = jnp.broadcast_arrays(
        *(jnp.asarray(x, dtype=jnp.result_type(float)) for x in (K, M, A1))
    )
    re = -K / A1
    im = 0.5 * M / A1
    p2 = jnp.stack([jax.lax.complex(re, im), jax.lax.complex(re, -im)])
    r = jnp.sqrt(p2)
    return jnp.concatenate([r, -r])


def nikolai_bending_roots(
    A1: ScalarLike, c: ScalarLike, d: ScalarLike, M: ScalarLike
) -> Complex[Array, "4"]:
    r"""The four bending roots of (4.69), $(A_1p^2 + K)^2 + M^2/4 = 0$, for the quadratic
    foundation (4.50) under a follower moment $M$ (4.57) at $\theta_0 = (M/d)k$.

    For $M \ne 0$ one root has $\mathrm{Re}\,p > 0$: the Nikolai paradox.
    """
    return _roots_of_biquadratic(A1, nikolai_bending_stiffness(c, d, M), M)


def nikolai_bending_roots_small_load(
    A1: ScalarLike, c: ScalarLike, d: ScalarLike, M: ScalarLike
) -> Complex[Array, "4"]:
    r"""Roots of (4.72), the small-$|M|/d$ form of (4.69) (reading R5):
    $(A_1p^2 + c + \frac{(c - 2d)M^2}{12 d^2})^2 + \frac{M^2}{4} = 0$."""
    c, d, M = jnp.asarray(c), jnp.asarray(d), jnp.asarray(M)
    return _roots_of_biquadratic(A1, c + (c - 2 * d) * M**2 / (12 * d**2), M)


def torsion_roots(A3: ScalarLike, d: ScalarLike) -> Complex[Array, "2"]:
    r"""Torsion roots of (4.69): $A_3p^2 + d = 0$, $p = \pm i\sqrt{d/A_3}$."""
    w = jnp.sqrt(jnp.asarray(d, dtype=jnp.result_type(float)) / jnp.asarray(A3))
    zero = jnp.zeros_like(w)
    return jnp.stack([jax.lax.complex(zero, w), jax.lax.complex(zero, -w)])


def nikolai_spectrum(A1, A3, c, d, M) -> Complex[Array, "6"]:
    """All six roots of (4.69): the four bending roots and the two torsion roots."""
    return jnp.concatenate([nikolai_bending_roots(A1, c, d, M), torsion_roots(A3, d)])


def precession_rate(C: ScalarLike, vartheta: ScalarLike, A1: ScalarLike, A3: ScalarLike) -> Scalar:
    r"""Rate $\dot\psi > 0$ of the regular precession (4.110)–(4.113):

    $\dot\psi^2 = \frac{C(\vartheta^2, 0)\,\vartheta}{\sin\vartheta\,[A_3(1-\cos\vartheta)
    + A_1\cos\vartheta]}$ (4.113), which is (4.106) for $A_1 = A_3$.

    $C$ is the coefficient (4.48) at $\theta = \vartheta p$ (see
    :func:`rbo_jax.transverse_coefficients`). NaN where the right side is negative (no regular
    precession with that $\vartheta$).
    """
    C, th = jnp.asarray(C), jnp.asarray(vartheta)
    # ϑ/sinϑ written as 1/sinc(ϑ²): finite (C/A1) as ϑ → 0.
    denom = sinc(th * th) * (A3 * (1 - jnp.cos(th)) + A1 * jnp.cos(th))
    return jnp.sqrt(C / denom)
