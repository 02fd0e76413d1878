"""Regular precession (4.110)-(4.113) and its stability (4.115)-(4.118), section 4.7.

Expected values: the rate formulas (4.106), (4.113) evaluated here in numpy, the printed
variational system after (4.118) coded here in numpy, and trajectories of the full nonlinear
equations (rbo_jax.simulate) compared with the linear prediction exp(Jt)·z0.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from helpers import spectrum_match_error

import rbo_jax as rbo

K = jnp.array([0.0, 0.0, 1.0])
KN = np.array([0.0, 0.0, 1.0])


_match_error = spectrum_match_error


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


class _TransverseF(eqx.Module):
    """F(x, t) = a t + b t² + q x² + r x of (4.24), x = k·θ, t = θ²:
    C = 2∂F/∂t = 2a + 4bt, D = ∂F/∂x = 2qx + r (4.48). (a, b, q, r) = (c/2, 0, (d − c)/2, 0)
    is the quadratic foundation (4.50)."""

    a: jax.Array
    b: jax.Array
    q: jax.Array
    r: jax.Array

    def __call__(self, x, t):
        return self.a * t + self.b * t**2 + self.q * x**2 + self.r * x


class _IsotropicF(eqx.Module):
    """F(s) = ½c s + e s², s = θ²: C = c(θ²) = c + 4e θ² (4.83)."""

    c: jax.Array
    e: jax.Array

    def __call__(self, s):
        return 0.5 * self.c * s + self.e * s**2


def _transverse_model(A1, A3, a, b, q, r=0.0, inertia=None):
    F = _TransverseF(*(jnp.asarray(v, dtype=float) for v in (a, b, q, r)))
    A = rbo.transversely_isotropic_inertia(A1, A3, K) if inertia is None else inertia
    return rbo.RigidBodyOscillator(A, rbo.TransverselyIsotropicFoundation(F, K))


def _isotropic_model(A, c, e=0.0):
    F = _IsotropicF(jnp.asarray(c, dtype=float), jnp.asarray(e, dtype=float))
    return rbo.RigidBodyOscillator(A * jnp.eye(3), rbo.IsotropicFoundation(F))


E_UNSTABLE = -0.3
CASES = {
    # F = ½t + ¼e t² + ½x², e = −0.3, A1 = 1, A3 = 1.2, ϑ = 1.8: max Re p ≈ 1.35
    "unstable": dict(A1=1.0, A3=1.2, a=0.5, b=0.25 * E_UNSTABLE, q=0.5, vartheta=1.8),
    # QuadraticFoundation(c = 1.2, d = 2.0) (4.50), A1 = 1, A3 = 0.6, ϑ = 0.7
    "stable": dict(A1=1.0, A3=0.6, a=0.6, b=0.0, q=0.4, vartheta=0.7),
}


def _case_model(name):
    kw = dict(CASES[name])
    del kw["vartheta"]
    return _transverse_model(**kw)


def _rate_4_113(C, vartheta, A1, A3):
    """ψ̇ of (4.113): ψ̇² = C(ϑ², 0)ϑ / (sinϑ [A3(1 − cosϑ) + A1 cosϑ])."""
    return np.sqrt(
        C * vartheta / (np.sin(vartheta) * (A3 * (1 - np.cos(vartheta)) + A1 * np.cos(vartheta)))
    )


@eqx.filter_jit
def _precession(model, vartheta, k=None):
    """Precession, variational matrix, spectrum, residual, and the residual at a 1% wrong
    rate (one compilation per model structure)."""
    pr = rbo.regular_precession(model, vartheta, k=k)
    wrong = eqx.tree_at(lambda x: x.rate, pr, 1.01 * pr.rate)
    return dict(
        pr=pr,
        J=rbo.precession_variational_matrix(model, pr),
        p=rbo.precession_spectrum(model, pr),
        residual=rbo.precession_residual(model, pr),
        wrong_residual=rbo.precession_residual(model, wrong),
    )


# ---------------------------------------------------------------------------------------------
# The rate (4.106), (4.113)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("vartheta", [0.3, 1.8, 2.4])
@pytest.mark.parametrize("A1, A3", [(1.0, 1.2), (1.0, 0.6), (0.8, 0.8)])
def test_rate_4_113_transversely_isotropic(A1, A3, vartheta):
    """ψ̇ = (4.113) with C(ϑ², 0) = 2a + 4bϑ² (4.48); the precession is a fixed point of the
    precessing-frame equations (residual at rounding level, not at a 1% wrong rate)."""
    a, b, q = 0.5, 0.02, 0.5
    out = _precession(_transverse_model(A1, A3, a, b, q), jnp.asarray(vartheta))
    pr = out["pr"]
    expected = _rate_4_113(2 * a + 4 * b * vartheta**2, vartheta, A1, A3)
    np.testing.assert_allclose(float(pr.rate), expected, rtol=1e-14)
    np.testing.assert_allclose(float(pr.p @ K), 0.0, atol=1e-16)
    assert float(out["residual"]) <= 1e-14
    assert float(out["wrong_residual"]) > 1e-3 * float(pr.rate)


@pytest.mark.parametrize(
    "A, c, e, vartheta", [(1.3, 0.8, 0.0, 1.1), (0.7, 1.5, 0.1, 2.5), (1.0, 2.0, -0.05, 0.4)]
)
def test_rate_4_106_isotropic(A, c, e, vartheta):
    """(4.106), A1 = A3 = A: ψ̇² = c(ϑ²)ϑ/(A sinϑ), c(θ²) = 2F'(θ²) (4.83)."""
    out = _precession(_isotropic_model(A, c, e), jnp.asarray(vartheta), k=K)
    c_theta = c + 4 * e * vartheta**2
    np.testing.assert_allclose(
        float(out["pr"].rate), np.sqrt(c_theta * vartheta / (A * np.sin(vartheta))), rtol=1e-14
    )
    assert float(out["residual"]) <= 1e-14
    assert float(out["wrong_residual"]) > 1e-3


def test_no_regular_precession_gives_nan():
    """(4.113) has no real rate where its right side is negative: A3(1 − cosϑ) + A1cosϑ < 0
    (A3 = 0.2, ϑ = 2.5), or C(ϑ², 0) < 0 (b = −0.3 at ϑ = 1.8)."""
    out = _precession(_transverse_model(1.0, 0.2, 0.5, 0.0, 0.5), jnp.asarray(2.5))
    assert np.isnan(float(out["pr"].rate))
    out = _precession(_transverse_model(1.0, 1.2, 0.5, -0.3, 0.5), jnp.asarray(1.8))
    assert np.isnan(float(out["pr"].rate))


def test_regular_precession_refuses_what_4_113_excludes():
    """D ≠ 0 at k·θ = 0, an inertia not transversely isotropic about k (4.40), and an isotropic
    foundation without k are refused."""
    with pytest.raises(eqx.EquinoxRuntimeError, match="D"):
        jax.block_until_ready(
            _precession(_transverse_model(1.0, 0.6, 0.5, 0.0, 0.5, r=0.2), jnp.asarray(0.7))
        )
    A = rbo.principal_inertia(jnp.array([1.0, 1.3, 0.6]), jnp.eye(3))
    with pytest.raises(eqx.EquinoxRuntimeError, match="transversely isotropic"):
        jax.block_until_ready(
            _precession(_transverse_model(1.0, 0.6, 0.5, 0.0, 0.5, inertia=A), jnp.asarray(0.7))
        )
    with pytest.raises(TypeError, match="k="):
        rbo.regular_precession(_isotropic_model(1.0, 1.0), 0.7)


# ---------------------------------------------------------------------------------------------
# The variational system after (4.118)
# ---------------------------------------------------------------------------------------------


def _printed_system_after_4_118(A, c, vartheta, rate, p, omega0):
    """The linear system printed after (4.118), A = A E, D = 0, C = c (4.114):
    A(η̇ + ψ̇k×η) + cφ = 0,
    φ̇ + ψ̇k×φ = gη − (ϑ − sinϑ)/(2(1 − cosϑ)) (p·φ)ω0 − ½φ×ω0 − ½ϑ p×η
               + [2(1 − cosϑ) − ϑ sinϑ]/(2ϑ(1 − cosϑ)) (φ·ω0 + ϑ p·η) p,
    g = ϑ sinϑ/(2(1 − cosϑ)); as a 6×6 matrix in (φ, η)."""
    th = vartheta
    one_minus_cos = 1 - np.cos(th)
    g = th * np.sin(th) / (2 * one_minus_cos)
    a = (th - np.sin(th)) / (2 * one_minus_cos)
    b = (2 * one_minus_cos - th * np.sin(th)) / (2 * th * one_minus_cos)
    kx, E = _skew(KN), np.eye(3)
    phi_phi = -rate * kx - a * np.outer(omega0, p) + 0.5 * _skew(omega0) + b * np.outer(p, omega0)
    phi_eta = g * E - 0.5 * th * _skew(p) + b * th * np.outer(p, p)
    eta_phi = -(c / A) * E
    eta_eta = -rate * kx
    return np.block([[phi_phi, phi_eta], [eta_phi, eta_eta]])


@pytest.mark.parametrize("A, c, vartheta", [(1.3, 0.8, 1.1), (1.0, 2.0, 0.4), (0.7, 1.5, 2.5)])
def test_variational_matrix_is_printed_system_after_4_118(A, c, vartheta):
    """For A = A E, D = 0, C = c (4.114) the autodiff matrix of the variational equations in the
    precessing frame (4.117) is the printed system after (4.118) (ERRATA 8 warns the print is
    partly garbled; as transcribed here it agrees entry by entry), so the eigenvalues agree too."""
    out = _precession(_isotropic_model(A, c), jnp.asarray(vartheta), k=K)
    pr = out["pr"]
    printed = _printed_system_after_4_118(
        A, c, vartheta, float(pr.rate), np.asarray(pr.p), np.asarray(pr.omega0)
    )
    J = np.asarray(out["J"])
    np.testing.assert_allclose(J, printed, rtol=0, atol=1e-14)
    assert np.abs(printed).max() > 0.5
    # the double root 0 (the family of precessions) splits by ~√eps: compare loosely there
    assert _match_error(out["p"], np.linalg.eigvals(printed)) <= 1e-6
    assert _match_error(out["p"], np.linalg.eigvals(J)) <= 1e-6


# ---------------------------------------------------------------------------------------------
# Stability checked on the nonlinear equations
# ---------------------------------------------------------------------------------------------


@eqx.filter_jit
def _simulate(model, theta0, Omega0, ts):
    return rbo.simulate(model, theta0, Omega0, ts, rtol=1e-12, atol=1e-12)


@jax.jit
def _to_precessing_frame(theta, omega, ts, rate):
    """x = Q(−ψ̇t k)·θ, w = Q(−ψ̇t k)·ω: the precessing frame of (4.117)."""
    Q = jax.vmap(lambda t: rbo.turn_tensor(-rate * t * K))(ts)
    return jnp.einsum("nij,nj->ni", Q, theta), jnp.einsum("nij,nj->ni", Q, omega)


@pytest.fixture(scope="module", params=list(CASES))
def perturbed_precession(request):
    """Simulate the precession ϑp (and a perturbation z0 of size 1e-6 of it) with the full
    equations; return the deviation z(t) = (x − ϑp, w − ω0) in the precessing frame and the
    linear prediction exp(Jt)·z0."""
    name = request.param
    model = _case_model(name)
    out = _precession(model, jnp.asarray(CASES[name]["vartheta"]))
    pr, J = out["pr"], np.asarray(out["J"])
    T = 6.0 if name == "unstable" else 30.0
    ts = jnp.linspace(0.0, T, 61)
    z0 = np.random.default_rng(118).standard_normal(6)
    z0 *= 1e-6 / np.linalg.norm(z0)
    res = {}
    for label, dz in (("exact", np.zeros(6)), ("perturbed", z0)):
        theta0 = pr.theta0 + dz[:3]
        Omega0 = rbo.turn_tensor(theta0).T @ (pr.omega0 + dz[3:])
        traj = _simulate(model, theta0, Omega0, ts)
        x, w = _to_precessing_frame(traj.theta, traj.omega, ts, pr.rate)
        res[label] = (
            np.asarray(traj.theta),
            np.concatenate(
                [np.asarray(x - pr.theta0[None, :]), np.asarray(w - pr.omega0[None, :])], axis=1
            ),
        )
    linear = np.stack([scipy.linalg.expm(J * t) @ z0 for t in np.asarray(ts)])
    return dict(
        name=name,
        pr=pr,
        J=J,
        p=np.asarray(out["p"]),
        ts=np.asarray(ts),
        z0=z0,
        res=res,
        linear=linear,
    )


def test_simulated_precession_follows_4_110(perturbed_precession):
    """Started on the precession, the full equations give θ(t) = ϑQ(ψ̇t k)·p (4.110) with the
    rate of (4.113) — an independent check of the rate."""
    d = perturbed_precession
    pr, ts = d["pr"], d["ts"]
    theta, dev = d["res"]["exact"]
    expected = np.stack([np.asarray(pr.theta(t)) for t in ts])
    np.testing.assert_allclose(
        theta, expected, rtol=0, atol=1e-8 if d["name"] == "unstable" else 1e-9
    )
    if d["name"] == "stable":
        assert np.abs(dev).max() <= 1e-9


def test_perturbed_precession_follows_the_variational_equations(perturbed_precession):
    """The deviation of a perturbed precession in the precessing frame is exp(Jt)·z0 with the
    variational matrix J, while it is small (relative error ≤ 1e-3): the linearization (4.117)
    describes the nonlinear dynamics."""
    d = perturbed_precession
    z = d["res"]["perturbed"][1]
    err = np.linalg.norm(z - d["linear"], axis=1) / np.linalg.norm(d["linear"], axis=1)
    assert err.max() <= 1e-3


def test_perturbation_grows_at_max_re_p_or_stays_bounded(perturbed_precession):
    """Unstable case: |z(t)| grows like exp(max Re p · t), max Re p of precession_spectrum
    (≈ 1.35; fitted slope of log|z| within 2%). Stable case: every Re p = 0 and |z(t)| stays
    within a few |z0| over 30 time units (~6 periods)."""
    d = perturbed_precession
    z = d["res"]["perturbed"][1]
    nz = np.linalg.norm(z, axis=1)
    a = np.max(d["p"].real)
    assert _match_error(d["p"], np.linalg.eigvals(d["J"])) <= 1e-6
    if d["name"] == "unstable":
        assert 1.3 < a < 1.4
        late = d["ts"] > 2.5
        slope = np.polyfit(d["ts"][late], np.log(nz[late]), 1)[0]
        np.testing.assert_allclose(slope, a, rtol=0.02)
        assert nz[-1] > 100 * nz[0]
    else:
        # the double root 0 (phase and neighbouring precessions: a Jordan block) splits by
        # ~√eps in floating point, in a direction set by rounding; the other roots are ±iω
        assert abs(a) <= 1e-6
        assert np.sum(np.abs(d["p"]) > 1e-6) == 4 and np.abs(d["p"].real).max() <= 1e-6
        assert nz.max() <= 5 * nz[0]
