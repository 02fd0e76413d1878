r"""Fitting a rod's constants to a measured tip trajectory (:func:`rbo_jax.lattice.fit_trajectory`).

The data are synthetic: a small cantilever ($N = 4$) with Kelvin–Voigt damping $\eta$, released
from its equilibrium under a dead tip force, its tip sampled over about one period of the first
bending mode ($2\pi/\omega_1$, $\omega_1 \approx 3.5\sqrt{EI/(\rho A L^4)}$). The fit starts
away from the true $EI$ and $\eta$ and must find them: to 1e-6 from noise-free data (the model
is the data's), within four Gauss–Newton standard errors from data with Gaussian noise, whose
standard errors must be comparable to the noise level over $\sqrt{3T}$ times the sensitivities.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from rbo_jax import lattice

TRUE = {"EI": 1.3, "eta": 0.02}
TS = np.linspace(0.0, 1.6, 33)


def make(EI, eta):
    return lattice.rod(
        4, 1.0, bending=EI, torsion=1.0, shear=50.0, stretch=50.0, mass=1.0, rotary=1e-2,
        damping=eta,
    )  # fmt: skip


def released():
    """The deflected start (measured, held fixed in the fit) and the tip's motion from it."""
    true = make(**TRUE)
    loaded = true.with_loads(lattice.TipForce(jnp.array([0.2, 0.0, 0.05])))
    state0 = lattice.equilibrium(loaded)
    traj = lattice.simulate(true, state0, TS, rtol=1e-10, atol=1e-12)
    return state0, np.asarray(traj.centreline[:, -1, :])


def test_bad_data_are_named():
    state0 = make(**TRUE).straight()
    with pytest.raises(ValueError, match="positions"):
        lattice.fit_trajectory(make, TRUE, TS, np.zeros((3, 3)), state0)
    with pytest.raises(ValueError, match="ts"):
        lattice.fit_trajectory(make, TRUE, TS[::-1], np.zeros((TS.size, 3)), state0)
    with pytest.raises(TypeError, match="state0"):
        lattice.fit_trajectory(make, TRUE, TS, np.zeros((TS.size, 3)), state0.r)
    with pytest.raises(ValueError, match="starting values"):
        lattice.fit_trajectory(make, {"EI": -1.0, "eta": 0.1}, TS, np.zeros((TS.size, 3)), state0)


@pytest.mark.slow  # a diffrax solve with its forward-mode derivative, compiled, then LM steps
def test_fit_recovers_bending_stiffness_and_damping_from_a_tip_trajectory():
    """Noise-free: EI and eta back to 1e-6 (relative) from a start 20 % and 50 % off, the
    residual at the 1e-8 level of the solver's tolerance. Noisy (sigma = 1e-3, 99 numbers):
    within 4 standard errors of the truth, the standard errors positive and below 5 % of the
    values, the rms residual the noise level to 30 %."""
    state0, tip = released()
    start = {"EI": 1.3 * 1.2, "eta": 0.02 * 1.5}
    fit = lattice.fit_trajectory(make, start, TS, tip, state0, rtol=1e-10, atol=1e-12)
    assert fit.converged
    for k, v in TRUE.items():
        assert fit.params[k] == pytest.approx(v, rel=1e-6), (k, fit.params)
    assert fit.rms < 1e-8
    rng = np.random.default_rng(7)
    sigma = 1e-3
    noisy = tip + sigma * rng.standard_normal(tip.shape)
    fit = lattice.fit_trajectory(make, start, TS, noisy, state0, rtol=1e-10, atol=1e-12)
    assert fit.converged
    for k, v in TRUE.items():
        assert 0 < fit.stderr[k] < 0.05 * v
        assert abs(fit.params[k] - v) < 4 * fit.stderr[k], (k, fit.params, fit.stderr)
    assert fit.rms == pytest.approx(sigma, rel=0.3)
