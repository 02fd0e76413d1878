r"""Classic problems of the paper as ready-made models.

:func:`nikolai_model` is the Nikolai problem of section 4.4: a transversely isotropic body (4.40)
on the quadratic foundation (4.50) under a follower moment (4.57), optionally with viscous
friction (4.84). Its equilibrium is :func:`rbo_jax.nikolai_equilibrium` (4.62), its spectrum
(4.69) :func:`rbo_jax.nikolai_spectrum`.
"""

from __future__ import annotations

import jax.numpy as jnp

from ._custom_types import ScalarLike
from .foundations import QuadraticFoundation
from .inertia import transversely_isotropic_inertia
from .loads import FollowerMoment, Friction
from .models.rigid_body import RigidBodyOscillator

__all__ = ["nikolai_model"]


def nikolai_model(
    M: ScalarLike,
    c: ScalarLike = 1.0,
    d: ScalarLike = 1.0,
    *,
    A1: ScalarLike = 1.0,
    A3: ScalarLike = 1.0,
    k=(0.0, 0.0, 1.0),
    friction: ScalarLike | None = None,
) -> RigidBodyOscillator:
    r"""The Nikolai problem (4.57)–(4.62): inertia $A = A_1(E - k\otimes k) + A_3\,k\otimes k$
    (4.40), foundation $U = \tfrac12 c(\theta^2 - (k\cdot\theta)^2) + \tfrac12 d(k\cdot\theta)^2$
    (4.50), follower moment $M\,P\cdot k$ (4.57) and, if ``friction`` is given, $-b\,\omega$
    (4.84). Every parameter may be traced (build it inside ``jax.vmap``)."""
    k = jnp.asarray(k, dtype=jnp.result_type(float))
    loads = [FollowerMoment(M, k)]
    if friction is not None:
        loads.append(Friction(friction))
    return RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, k), QuadraticFoundation(c, d, k), loads
    )
