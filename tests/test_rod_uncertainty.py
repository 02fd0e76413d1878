r"""A rod's fits under the API of the sensor fits (issue 51): ``rbo_jax.fit``,
``rbo_jax.profile_likelihood`` and ``rbo_jax.posterior`` of a rod function ``rod_fn(**constants)``
with :class:`rbo_jax.lattice.RodSpectrumData` (measured eigenvalues $p = -\zeta + i\omega$ of the
linearisation) or :class:`rbo_jax.lattice.RodTrajectoryData` (a body's measured positions).

The rods: Kelvin–Voigt cantilevers of circular section (each bending frequency twice, one per
plane), the constants EI and the damping time eta. With the noise level given, the likelihood is
Gaussian with that sigma: the Gauss–Newton standard errors, the profile's χ² interval and the
posterior's spread must agree where the likelihood is close to quadratic (issue 51's 30 %).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import rbo_jax
from rbo_jax import lattice


def spectrum_rod(EI, eta):
    return lattice.rod(
        8, 1.0, bending=EI, torsion=1.0, shear=1e4, stretch=1e4, mass=1.0, rotary=1e-4,
        damping=eta,
    )  # fmt: skip


def trajectory_rod(EI, eta):
    return lattice.rod(
        4, 1.0, bending=EI, torsion=1.0, shear=50.0, stretch=50.0, mass=1.0, rotary=1e-2,
        damping=eta,
    )  # fmt: skip


def test_rod_data_check_their_arguments():
    """Bad measurements raise a ValueError naming the argument, before anything compiles."""
    state0 = trajectory_rod(1.0, 0.01).straight()
    ts = np.linspace(0.0, 1.0, 5)
    with pytest.raises(ValueError, match="eigenvalues"):
        lattice.RodSpectrumData([1.0 - 2.0j])  # no positive frequency
    with pytest.raises(ValueError, match="sigma"):
        lattice.RodSpectrumData([-0.1 + 2.0j], sigma=0.0)
    with pytest.raises(ValueError, match="positions"):
        lattice.RodTrajectoryData(ts, np.full((5, 3), np.nan), state0)
    with pytest.raises(ValueError, match="ts"):
        lattice.RodTrajectoryData(ts[::-1], np.zeros((5, 3)), state0)
    with pytest.raises(TypeError, match="state0"):
        lattice.RodTrajectoryData(ts, np.zeros((5, 3)), state0.r)
    data = lattice.RodSpectrumData([-0.1 + 2.0j])
    with pytest.raises(ValueError, match="sigma"):  # the posterior's likelihood needs it
        rbo_jax.posterior(spectrum_rod, data, {"EI": 1.0, "eta": 1e-3})
    with pytest.raises(ValueError, match="name must be one of"):
        rbo_jax.profile_likelihood(spectrum_rod, data, {"EI": 1.0}, "eta", [1.0, 2.0])


def _measured_spectrum(sigma, seed=5):
    rod = spectrum_rod(1.3, 2e-3)
    p = np.asarray(lattice.spectrum(rod, rod.straight()))
    p = p[p.imag > 1e-6]
    p = p[np.argsort(p.imag)][:4]  # two planes x the two lowest bending modes
    rng = np.random.default_rng(seed)
    return p + sigma * (rng.standard_normal(4) + 1j * rng.standard_normal(4))


@pytest.mark.slow  # three programs: the fit's Jacobian, the profile's re-fits, NUTS
def test_spectrum_fit_profile_and_posterior_agree():
    """Measured eigenvalues with sigma = 1e-3 (4 complex numbers, 8 residuals):

    - ``rbo_jax.fit`` of the data is ``lattice.fit_spectrum``; the truth within 3 standard
      errors (s² = 1: sigma given);
    - the profile's 95 % interval of EI is ±1.96 standard errors within 30 % on each side;
    - the posterior (NUTS, 2 chains x (200 + 300)): R-hat < 1.01, bulk ESS > 200, no divergent
      transition (the model's eigenvalues are matched to the measured ones, so no mode enters
      or leaves the comparison in the typical set), its standard deviations within 25 % of the
      standard errors, its means within 3 standard errors of the truth."""
    sigma = 1e-3
    measured = _measured_spectrum(sigma)
    start = {"EI": 1.0, "eta": 1e-3}
    data = lattice.RodSpectrumData(measured, sigma=sigma)
    fit = rbo_jax.fit(spectrum_rod, data, start)
    assert fit.converged
    same = lattice.fit_spectrum(spectrum_rod, start, measured, sigma=sigma)
    for name, true in (("EI", 1.3), ("eta", 2e-3)):
        assert fit.params[name] == pytest.approx(same.params[name], rel=1e-7)
        assert abs(fit.params[name] - true) < 3 * fit.stderr[name]
    se = fit.stderr["EI"]
    values = fit.params["EI"] + se * np.linspace(-3.0, 3.0, 7)
    prof = rbo_jax.profile_likelihood(spectrum_rod, data, start, "EI", values, start=fit)
    assert bool(np.all(prof.converged))
    assert prof.attrs["lower"] < fit.params["EI"] < prof.attrs["upper"]
    for bound, side in ((prof.attrs["lower"], -1), (prof.attrs["upper"], 1)):
        half = side * (bound - fit.params["EI"])
        assert half == pytest.approx(1.96 * se, rel=0.3)
    assert float(prof.delta.min()) == pytest.approx(0.0, abs=1e-3)
    post = rbo_jax.posterior(spectrum_rod, data, start, num_warmup=200, num_samples=300)
    attrs = post.posterior.attrs
    assert attrs["max_r_hat"] < 1.01 and attrs["min_ess_bulk"] > 200
    assert attrs["divergences"] == 0
    for name, true in (("EI", 1.3), ("eta", 2e-3)):
        draws = np.asarray(post.posterior[name]).ravel()
        assert draws.std() == pytest.approx(fit.stderr[name], rel=0.25)
        assert abs(draws.mean() - true) < 3 * fit.stderr[name]


@pytest.mark.slow  # a diffrax solve with its forward-mode derivative, in two programs
def test_trajectory_fit_with_missing_samples_and_its_profile():
    """A tip recorded with sigma = 1e-3 and a fifth of its coordinates lost (NaN): the fit of
    ``RodTrajectoryData`` finds EI and eta within 4 standard errors (s² = 1, sigma given), and
    the profile's 95 % interval of eta is ±1.96 standard errors within 30 % on each side."""
    ts = np.linspace(0.0, 1.6, 33)
    true = trajectory_rod(1.3, 0.02)
    state0 = lattice.equilibrium(true.with_loads(lattice.TipForce(jnp.array([0.2, 0.0, 0.05]))))
    tip = np.asarray(lattice.simulate(true, state0, ts, rtol=1e-10, atol=1e-12).centreline[:, -1])
    rng = np.random.default_rng(3)
    sigma = 1e-3
    noisy = tip + sigma * rng.standard_normal(tip.shape)
    noisy[rng.random(tip.shape) < 0.2] = np.nan
    data = lattice.RodTrajectoryData(ts, noisy, state0, sigma=sigma)
    start = {"EI": 1.5, "eta": 0.03}
    options = dict(solve_rtol=1e-10, solve_atol=1e-12)
    fit = rbo_jax.fit(trajectory_rod, data, start, **options)
    assert fit.converged
    for name, value in (("EI", 1.3), ("eta", 0.02)):
        assert 0 < fit.stderr[name] and abs(fit.params[name] - value) < 4 * fit.stderr[name]
    se = fit.stderr["eta"]
    values = fit.params["eta"] + se * np.array([-3.0, -2.0, -1.0, 1.0, 2.0, 3.0])
    prof = rbo_jax.profile_likelihood(
        trajectory_rod, data, start, "eta", values, start=fit, **options
    )
    assert bool(np.all(prof.converged))
    for bound, side in ((prof.attrs["lower"], -1), (prof.attrs["upper"], 1)):
        assert side * (bound - fit.params["eta"]) == pytest.approx(1.96 * se, rel=0.3)
    assert set(prof.data_vars) >= {"EI", "neg_log_likelihood", "delta"}
