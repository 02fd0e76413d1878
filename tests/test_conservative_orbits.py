"""Periodic orbits of conservative models (issue 23, part D): shooting unfolded by a signed
friction -eps omega with the energy condition (Munoz-Almaraz et al., Physica D 181 (2003)),
against regular precessions (4.110)-(4.113), the planar pendulum of the cosine foundation
(elliptic integral) and the families of axisymmetric and isotropic models (4.78), (4.94)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special

import rbo_jax as rbo
from rbo_jax.bifurcation._orbit import is_conservative

K = (0.0, 0.0, 1.0)
A1, A3, C, D = 1.0, 0.6, 1.0, 2.0


def axisymmetric(a3=A3, d=D):
    """A transversely isotropic body on the quadratic foundation (4.50): no loads."""
    k = jnp.asarray(K)
    return rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(A1, a3, k), rbo.QuadraticFoundation(C, d, k)
    )


@pytest.fixture(scope="module")
def model():
    return axisymmetric()


@pytest.fixture(scope="module")
def precession(model):
    pr = rbo.regular_precession(model, 0.5)
    return pr, 2 * np.pi / float(pr.rate), float(model.energy(pr.theta0, pr.Omega0))


def energy_of(model, orbit):
    return float(model.energy(orbit.theta0, orbit.Omega0))


def near_one(orbit, tol):
    return int(np.sum(np.abs(np.asarray(orbit.multipliers) - 1) < tol))


def assert_symplectic(orbit, tol):
    """Conservative (reversible) spectra: the moduli come in reciprocal pairs mu, 1/mu."""
    m = np.sort(np.abs(np.asarray(orbit.multipliers)))
    np.testing.assert_allclose(m * m[::-1], 1.0, atol=tol)


def test_conservative_models_are_told_by_their_loads(model):
    """Potential loads (4.52) keep the energy; friction (4.84), follower (4.57), dead (4.75) and
    callable moments do not, and plain shooting refuses an energy condition for them."""
    k = jnp.asarray(K)
    assert is_conservative(model)
    assert is_conservative(
        rbo.RigidBodyOscillator(model.inertia, model.foundation, rbo.PotentialLoad(lambda t: t @ t))
    )
    for load in (
        rbo.Friction(0.1),
        rbo.FollowerMoment(0.1, k),
        rbo.DeadMoment(0.1, k),
        rbo.SemiTangentialMoment(0.1, k),
        lambda t, theta, omega: -omega,
    ):
        assert not is_conservative(rbo.RigidBodyOscillator(model.inertia, model.foundation, load))
    nikolai = rbo.nikolai_model(0.1, C, D, A1=A1, A3=A3, k=K, friction=0.1)
    with pytest.raises(ValueError, match="energy"):
        rbo.periodic_orbit(nikolai, (0.1, 0.0, 0.0), (0.0, 0.0, 0.0), 6.0, energy=0.1)


def test_shooting_returns_to_a_regular_precession(model, precession):
    """From a perturbed state and period, with the precession's energy: the precession itself
    (4.110)-(4.113), period 2 pi / psi_dot, eps = 0, two multipliers 1 (a Jordan block: they
    split by ~sqrt(solver tolerance) ~ 1e-6) and the others on the unit circle."""
    pr, T, E = precession
    rng = np.random.default_rng(0)
    d = 0.01 * rng.normal(size=6)
    orbit = rbo.periodic_orbit(model, pr.theta0 + d[:3], pr.Omega0 + d[3:], 1.01 * T, energy=E)
    assert bool(orbit.ok), orbit.status
    assert float(orbit.residual) < 1e-9
    assert abs(float(orbit.unfolding)) < 1e-9
    assert energy_of(model, orbit) == pytest.approx(E, abs=1e-10)
    assert float(orbit.period) == pytest.approx(T, rel=1e-9)
    theta0 = np.asarray(orbit.theta0)
    assert np.linalg.norm(theta0) == pytest.approx(0.5, abs=1e-8)  # vartheta, another phase
    assert abs(theta0[2]) < 1e-8  # k . theta = 0
    assert near_one(orbit, 1e-5) >= 2
    np.testing.assert_allclose(np.abs(np.asarray(orbit.multipliers)), 1.0, atol=1e-5)
    assert_symplectic(orbit, 1e-8)


@pytest.mark.slow  # cost: ~13-18 s, the periodic orbit's program compiled under vmap
def test_neighbouring_precessions_at_other_energies(model, precession):
    """Requesting other energies from a perturbed precession (vmapped over the energy) gives the
    orbits of those energies around it: the regular precessions whose nutation angles have
    those energies, with their rates (4.113)."""
    pr, T, E = precession
    d = 1e-3 * np.array([1.0, -2.0, 0.5, 0.3, 1.0, -1.0])
    factors = np.array([0.9, 1.05])
    orbits = jax.vmap(
        lambda e: rbo.periodic_orbit(model, pr.theta0 + d[:3], pr.Omega0 + d[3:], T, energy=e)
    )(jnp.asarray(factors * E))
    for i, factor in enumerate(factors):
        orbit = jax.tree_util.tree_map(lambda x: x[i], orbits)
        assert bool(orbit.ok), orbit.status
        assert abs(float(orbit.unfolding)) < 1e-9
        assert energy_of(model, orbit) == pytest.approx(factor * E, abs=1e-10)
        vartheta = float(jnp.linalg.norm(orbit.theta0))
        assert abs(vartheta - 0.5) > 1e-3  # another orbit
        other = rbo.regular_precession(model, vartheta)
        assert float(orbit.period) == pytest.approx(2 * np.pi / float(other.rate), rel=1e-9)
        assert abs(float(orbit.theta0[2])) < 1e-8
        assert near_one(orbit, 1e-5) >= 2
        assert_symplectic(orbit, 1e-8)


@pytest.mark.parametrize("amplitude", [0.5, 1.0])
def test_the_pendulum_without_symmetry(amplitude):
    """A body of three distinct principal moments on the cosine foundation: the plane swing
    about a principal axis is the pendulum A phi'' + c sin phi = 0, period
    4 sqrt(A/c) K(sin^2(phi0/2)), energy c (1 - cos phi0). No continuous symmetry: the energy is
    the only integral. At phi0 = 1 the swing is unstable (a real pair mu, 1/mu)."""
    model = rbo.RigidBodyOscillator(
        rbo.principal_inertia((1.0, 1.5, 0.7), np.eye(3)), rbo.CosineFoundation(1.0)
    )
    T = 4 * scipy.special.ellipk(np.sin(amplitude / 2) ** 2)
    E = 1 - np.cos(amplitude)
    d = 1e-2 * np.array([0.3, -0.5, 0.2, 1.0, 0.4, -0.3])
    orbit = rbo.periodic_orbit(model, (amplitude + d[0], d[1], d[2]), d[3:], 1.01 * T, energy=E)
    assert bool(orbit.ok), orbit.status
    assert abs(float(orbit.unfolding)) < 1e-9
    assert float(orbit.period) == pytest.approx(T, rel=1e-9)
    assert energy_of(model, orbit) == pytest.approx(E, abs=1e-10)
    assert near_one(orbit, 1e-5) == 2
    assert_symplectic(orbit, 1e-6)


@pytest.mark.parametrize("a3, d", [(A3, D), (A1, C)], ids=["axisymmetric", "isotropic"])
def test_families_of_one_energy_by_minimum_norm_steps(a3, d):
    """Axisymmetric models (integral (4.78)) and the isotropic oscillator (4.83) (integrals
    (4.94)) have families of orbits at one energy (turns of the plane swing): more multipliers
    equal 1 and the 8x8 system keeps a kernel. Least squares still converge, to an orbit of the
    guess's energy (energy=None); the plane bending swing is isochronous, T = 2 pi sqrt(A1/c)."""
    model = axisymmetric(a3, d)
    theta0, Omega0 = np.array([0.3, 0.01, 0.005]), np.array([0.004, -0.002, 0.001])
    orbit = rbo.periodic_orbit(model, theta0, Omega0, 1.01 * 2 * np.pi)
    assert bool(orbit.ok), orbit.status
    assert float(orbit.residual) < 1e-9
    assert abs(float(orbit.unfolding)) < 1e-9
    assert energy_of(model, orbit) == pytest.approx(float(model.energy(theta0, Omega0)), abs=1e-10)
    assert float(orbit.period) == pytest.approx(2 * np.pi, rel=1e-9)
    assert near_one(orbit, 1e-5) >= 4
    # minimum-norm steps: an orbit of the family near the guess (the swing turned a little)
    assert np.linalg.norm(np.asarray(orbit.theta0) - theta0) < 0.1
    assert float(jnp.linalg.norm(orbit.theta0)) == pytest.approx(0.3, abs=0.01)
