"""Section 4.2: identities of the turn-tensor, the composition of turns and the integrating
tensor on random turn-vectors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ...kinematics import (
    composition_invariants,
    integrating_tensor,
    integrating_tensor_det,
    integrating_tensor_inv,
    skew,
    turn_tensor,
)
from ._common import Check, fmt


def kinematics(n: int) -> list[Check]:
    key = jax.random.PRNGKey(0)
    k1, k2, k3 = jax.random.split(key, 3)

    def sample(key):
        axes = jax.random.normal(key, (n, 3))
        axes = axes / jnp.linalg.norm(axes, axis=1, keepdims=True)
        return axes * jax.random.uniform(jax.random.fold_in(key, 1), (n, 1), maxval=3.0)

    th, ph, ps = sample(k1), sample(k2), sample(k3)
    eye = jnp.eye(3)

    def per_point(th, ph, ps):
        Q = turn_tensor(th)
        Z, Zi = integrating_tensor(th), integrating_tensor_inv(th)
        S = turn_tensor(ph)
        # Poisson (4.9)/(4.10) along θ(t) = th + t·ps: ω = Z⁻¹θ̇, dQ/dt = ω×Q
        Qdot = jax.jvp(turn_tensor, (th,), (ps,))[1]
        omega = Zi @ ps
        Qphps = turn_tensor(ph) @ turn_tensor(ps)
        cos_t, vec = composition_invariants(ph, ps)
        t2 = jnp.clip(0.5 * (jnp.trace(Qphps) - 1.0), -1.0, 1.0)
        vinv = 0.5 * jnp.stack(
            [Qphps[2, 1] - Qphps[1, 2], Qphps[0, 2] - Qphps[2, 0], Qphps[1, 0] - Qphps[0, 1]]
        )
        t = jnp.dot(th, th)
        return jnp.stack(
            [
                jnp.max(jnp.abs(Q @ Q.T - eye)),  # (4.27)
                jnp.max(jnp.abs(Q @ th - th)),  # (4.8)
                jnp.max(jnp.abs(Z @ Zi - eye)),  # (4.11)/(4.20)
                # det Z, rel.; 2(1 − cos θ) written as 4 sin²(θ/2), free of cancellation at small θ
                jnp.abs(integrating_tensor_det(th) * 4 * jnp.sin(0.5 * jnp.sqrt(t)) ** 2 / t - 1),
                jnp.max(jnp.abs(Z.T - Q @ Z)) + jnp.max(jnp.abs(Q @ Z - Z @ Q)),  # (4.13)
                jnp.max(jnp.abs(integrating_tensor(S @ th) - S @ Z @ S.T)),  # (4.12)
                jnp.max(jnp.abs(Qdot - skew(omega) @ Q)),  # (4.9)
                jnp.abs(cos_t - t2) + jnp.max(jnp.abs(vec - vinv)),  # (4.6)-(4.7)
            ]
        )

    errs = np.asarray(jax.jit(jax.vmap(per_point))(th, ph, ps)).max(axis=0)
    names = [
        ("(4.27)", "Q·Qᵀ = E", "0"),
        ("(4.8)", "Q(θ)·θ = θ", "0"),
        ("(4.11), (4.20)", "Z·Z⁻¹ = E", "0"),
        ("after (4.11)", "det Z = θ²/(2(1−cosθ)) (relative)", "closed form"),
        ("(4.13)", "Zᵀ = Q·Z = Z·Q", "0"),
        ("(4.12)", "Z(S·θ) = S·Z·Sᵀ", "0"),
        ("(4.9), (4.19)", "dQ/dt = ω×Q, ω = Z⁻¹·θ̇", "0"),
        ("(4.6), (4.7) readings R1-R2", "composition invariants vs Q(φ)·Q(ψ)", "matrix product"),
    ]
    return [
        Check(
            f"4.2 {eq}",
            f"{quantity} ({n} random points, max error)",
            paper,
            fmt(float(e)),
            float(e),
            1e-12,
        )
        for (eq, quantity, paper), e in zip(names, errs)
    ]
