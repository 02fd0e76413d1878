"""Fitting: the bending and torsional stiffness recovered from noisy attitudes, within three
standard errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ...fitting import TrajectoryData, fit
from ...foundations import QuadraticFoundation
from ...inertia import transversely_isotropic_inertia
from ...kinematics import turn_tensor
from ...models.rigid_body import RigidBodyOscillator
from ...simulate import simulate
from ._common import TIGHT, Check, K


def fitting() -> list[Check]:
    sigma = 1e-3
    A = transversely_isotropic_inertia(1.0, 0.6, K)
    true = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    th0, Om0 = jnp.array([0.8, -0.3, 0.5]), jnp.array([0.2, 1.1, -0.7])
    ts = jnp.linspace(0.0, 6.0, 60)
    Q = simulate(true, th0, Om0, ts, **TIGHT).turn_tensor
    eta = sigma * jax.random.normal(jax.random.PRNGKey(7), (ts.shape[0], 3))
    Q_obs = jax.vmap(lambda e, q: turn_tensor(e) @ q)(eta, Q)
    res = fit(
        RigidBodyOscillator(A, QuadraticFoundation(1.3, 1.4, K)),
        TrajectoryData(ts, Q=Q_obs, theta0=th0, Omega0=Om0, sigma_theta=sigma),
        lambda m: (m.foundation.c, m.foundation.d),
    )
    checks = []
    for name, truth, val, se in zip(("c", "d"), (1.0, 2.0), res.params, res.stderr):
        z = abs(float(val) - truth) / float(se)
        checks.append(
            Check(
                "fitting",
                f"{name} from noisy attitudes (σ = 1e-3 rad), start 30 % off",
                f"{truth}",
                f"{float(val):.5f} ± {float(se):.1e}",
                z,
                3.0,
            )
        )
    return checks
