"""Equilibria, linearization, spectra and classification (sections 4.4 and 4.5 of the paper).

Expected values come from the paper's closed forms evaluated here in numpy/scipy ((4.61) with
(4.49), (4.62), (4.66)-(4.67), (4.69), (4.73)-(4.74)), from ``rbo_jax.analytic`` (itself checked
against the printed polynomial (4.69) below), or from exact identities (Hessians, symmetries).

Compilation dominates the run time (seconds per model structure), so every JAX computation goes
through a few module-level ``jit`` functions taking the model as an argument, and most cases
share two "universal" model structures whose parameters select the case (a load of magnitude 0
contributes nothing; ``BarrierFoundation`` with ``alpha = beta = inf`` is exactly (4.50)).
"""

from __future__ import annotations

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import spectrum_match_error
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

import rbo_jax as rbo
from rbo_jax.stability import EquilibriumStatus, StabilityKind

K = jnp.array([0.0, 0.0, 1.0])
KN = np.array([0.0, 0.0, 1.0])
INF = float("inf")


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------


_match_error = spectrum_match_error


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _g(theta0):
    """g = θ0 sinθ0 / (2(1 − cosθ0)) of (4.59), (4.69) (its Taylor series near 0, ERRATA 3)."""
    if abs(theta0) < 1e-4:
        return 1.0 - theta0**2 / 12 - theta0**4 / 720
    return theta0 * np.sin(theta0) / (2.0 * (1.0 - np.cos(theta0)))


def _kind(p, **kwargs):
    kind, a = rbo.classify(jnp.asarray(p), **kwargs)
    return kind, float(a)


class _Potential(eqx.Module):
    """V(θ) = −m·θ − ½ e θ·θ, a potential external moment (4.52) with parameters."""

    m: jax.Array
    e: jax.Array

    def __call__(self, theta):
        return -(self.m @ theta) - 0.5 * self.e * (theta @ theta)


class _Gyroscopic(eqx.Module):
    """M_ex = γ k×ω: velocity dependent and workless (a gyroscopic torque)."""

    gamma: jax.Array

    def __call__(self, t, theta, omega):
        return self.gamma * jnp.cross(K, omega)


def _potential_model(
    A1=1.0,
    A3=0.6,
    c=1.0,
    d=2.0,
    alpha=INF,
    beta=INF,
    *,
    dead=0.0,
    follower=0.0,
    semi=0.0,
    l1=1.0,
    l2=1.0,
    m=(0.0, 0.0, 0.0),
    e=0.0,
):
    """One model structure for every velocity-independent case: the barrier foundation (4.49)
    (exactly (4.50) for alpha = beta = inf), a dead (4.75), a follower (4.57), a
    semi-tangential (4.75) moment and a potential load (4.52)."""
    return rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(A1, A3, K),
        rbo.BarrierFoundation(c, d, alpha, beta, K),
        (
            rbo.DeadMoment(dead, K),
            rbo.FollowerMoment(follower, K),
            rbo.SemiTangentialMoment(semi, K, l1, l2),
            rbo.PotentialLoad(_Potential(jnp.asarray(m, dtype=float), jnp.asarray(e, dtype=float))),
        ),
    )


def _velocity_model(M=0.0, b=0.0, gamma=0.0, A1=1.0, A3=0.6, c=1.0, d=2.0):
    """One model structure for the velocity-dependent cases: the Nikolai problem (4.50), (4.57)
    with friction (4.84) and a gyroscopic torque."""
    return rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(A1, A3, K),
        rbo.QuadraticFoundation(c, d, K),
        (
            rbo.FollowerMoment(M, K),
            rbo.Friction(b),
            rbo.CallableLoad(_Gyroscopic(jnp.asarray(gamma))),
        ),
    )


def _nikolai_model(A1, A3, c, d, M):
    """The Nikolai problem as printed: quadratic foundation (4.50), follower moment (4.57)."""
    return rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(A1, A3, K),
        rbo.QuadraticFoundation(c, d, K),
        rbo.FollowerMoment(M, K),
    )


@jax.jit
def _analyse(model, theta_eq):
    """Everything about one equilibrium, in one compilation per model structure: spectra,
    second-order form, |total moment at rest| (zero at an equilibrium (4.61)) and the Hessian
    of U + V."""
    return dict(
        p=rbo.spectrum(model, theta_eq),
        fast=rbo.fast_spectrum(model, theta_eq),
        form=rbo.second_order_form(model, theta_eq),
        moment=jnp.linalg.norm(model.world_moment(0.0, theta_eq, jnp.zeros(3))),
        hessian=jax.hessian(model.potential_energy)(theta_eq),
    )


_solve = eqx.filter_jit(rbo.solve_equilibrium)
_equilibrium = eqx.filter_jit(rbo.equilibrium)


_nikolai_spectra = jax.jit(jax.vmap(rbo.nikolai_spectrum))


# ---------------------------------------------------------------------------------------------
# Equilibria (4.60)-(4.62)
# ---------------------------------------------------------------------------------------------


BARRIER = dict(c=1.0, d=2.0, alpha=1.8, beta=1.5)


def _barrier_axial_moment(x, c, d, alpha, beta):
    """C x + D of (4.61) at θ = xk for the barrier energy (4.49): U(xk) = ½cx² +
    ½(d − c)β²x²/(β² − x²), so C x + D = dU/dx = cx + (d − c)β⁴x/(β² − x²)²."""
    del alpha  # the bending barrier does not act on the axis
    return c * x + (d - c) * beta**4 * x / (beta**2 - x**2) ** 2


def _barrier_root(M, lo, hi):
    return brentq(lambda x: _barrier_axial_moment(x, **BARRIER) - M, lo, hi, xtol=1e-15, rtol=1e-15)


@pytest.mark.parametrize("M", [0.4, 0.9, -1.3])
def test_equilibrium_barrier_follower_solves_4_61(M):
    """(4.60)-(4.61) for the barrier foundation (4.49) under a follower moment: the Newton
    equilibrium is θ = xk with C x + D = M, x found here by brentq on the closed form of
    (4.49) along k; the package's C, D (4.48) satisfy (4.61) there."""
    model = _potential_model(**BARRIER, follower=M)
    b = BARRIER["beta"] * (1 - 1e-12)
    x = _barrier_root(M, -b, b)
    sol = _solve(model, jnp.array([0.05, -0.03, 0.3 * np.sign(M)]))
    assert bool(sol.ok) and float(sol.residual) <= 1e-12 and int(sol.num_steps) >= 2
    np.testing.assert_allclose(np.asarray(sol.theta), x * KN, rtol=0, atol=1e-12)
    C, D = rbo.transverse_coefficients(model.foundation, sol.theta)
    assert abs(float(C) * x + float(D) - M) <= 1e-12 * max(1.0, abs(M))


def test_equilibrium_not_converged_raises_and_status():
    """One Newton step from far away cannot converge: ``equilibrium`` raises with the
    message, ``solve_equilibrium`` returns the status instead. From the equilibrium (4.62)
    itself one step suffices and ``equilibrium`` returns it."""
    model = _potential_model(follower=0.3)
    guess = jnp.array([0.9, -0.7, 1.2])
    sol = _solve(model, guess, max_steps=1)
    assert sol.status == EquilibriumStatus.not_converged and not bool(sol.ok)
    assert float(sol.residual) > 1e-3
    with pytest.raises(eqx.EquinoxRuntimeError, match="did not converge"):
        jax.block_until_ready(_equilibrium(model, guess, max_steps=1))
    theta = _equilibrium(model, 0.15 * K, max_steps=1)
    np.testing.assert_allclose(np.asarray(theta), 0.15 * KN, rtol=0, atol=1e-15)
    assert bool(_solve(model, guess).ok)


def test_equilibrium_leaving_the_barrier_domain_4_49():
    """Outside the domain of (4.49) (k·θ > β) the moment balance has another root; Newton
    started there finds it and reports ``domain_error``, while the root inside the domain is
    found from a guess inside."""
    M = 3.5
    model = _potential_model(**BARRIER, follower=M)
    x_out = _barrier_root(M, 3.0, 3.6)
    x_in = _barrier_root(M, 0.0, BARRIER["beta"] * (1 - 1e-12))
    assert x_out > BARRIER["beta"] > x_in
    sol = _solve(model, jnp.array([0.0, 0.0, 3.3]))
    assert sol.status == EquilibriumStatus.domain_error and not bool(sol.ok)
    np.testing.assert_allclose(np.asarray(sol.theta), x_out * KN, atol=1e-10)
    sol_in = _solve(model, jnp.array([0.0, 0.0, 0.5]))
    assert bool(sol_in.ok)
    np.testing.assert_allclose(np.asarray(sol_in.theta), x_in * KN, atol=1e-12)


def _well_at_2pi(s):
    """U = ½(θ² − 4π²)²: its minimum is the sphere |θ| = 2π, where Z is singular (4.11)."""
    return 0.5 * (s - 4 * jnp.pi**2) ** 2


def test_equilibrium_at_singular_point_of_Z_4_11():
    """Newton converging to |θ| = 2π, a singular point of Z (ERRATA 3), is reported."""
    model = rbo.RigidBodyOscillator(jnp.eye(3), rbo.IsotropicFoundation(_well_at_2pi))
    sol = _solve(model, jnp.array([0.1, 0.2, 6.1]))
    assert sol.status == EquilibriumStatus.singular_point and not bool(sol.ok)
    assert abs(float(jnp.linalg.norm(sol.theta)) - 2 * np.pi) <= 1e-6


# ---------------------------------------------------------------------------------------------
# The Nikolai problem: linearization (4.66)-(4.67) and roots (4.69), (4.72), (4.74)
# ---------------------------------------------------------------------------------------------


def _printed_variational_matrix(A1, A3, c, d, M):
    r"""The 6×6 matrix of (4.66)-(4.67) in (φ, η), coded from the printed equations:
    A·η̇ = −[cφ + (d−c)(k·φ)k + M(1 − c/d)(½k×φ + (1−g)/θ0 (φ − (k·φ)k))],
    φ̇ = η + ½(M/d)k×η − (1 − g)(η − (k·η)k)."""
    theta0 = M / d
    g = _g(theta0)
    h = (1 - g) / theta0 if theta0 != 0 else 0.0
    E, kk, kx = np.eye(3), np.outer(KN, KN), _skew(KN)
    A = A1 * (E - kk) + A3 * kk
    stiff = c * E + (d - c) * kk + M * (1 - c / d) * (0.5 * kx + h * (E - kk))
    top = np.hstack([np.zeros((3, 3)), E + 0.5 * theta0 * kx - (1 - g) * (E - kk)])
    bottom = np.hstack([-np.linalg.solve(A, stiff), np.zeros((3, 3))])
    return np.vstack([top, bottom])


def _nikolai_K(c, d, M):
    """K of (4.69), coded from the print."""
    g = _g(M / d)
    return c * (g**2 + M**2 / (4 * d**2)) - M**2 / (4 * d) + (1 - g) * g * d


@pytest.mark.parametrize(
    "A1, A3, c, d, M",
    [
        (1.0, 0.6, 1.0, 2.0, 0.3),
        (0.7, 1.5, 2.5, 0.8, -1.1),
        (1.2, 1.2, 1.0, 3.0, 2.5),
        (1.0, 0.6, 1.0, 2.0, 0.0),
    ],
)
def test_analytic_nikolai_spectrum_is_printed_polynomial_4_69(A1, A3, c, d, M):
    """rbo_jax.analytic.nikolai_spectrum solves the printed (4.69):
    (A1p² + K)² + M²/4 = 0 with K = c(g² + M²/4d²) − M²/4d + (1−g)gd, and A3p² + d = 0
    (numpy.roots, which is accurate to ~√eps only at the double roots of M = 0)."""
    Kb = _nikolai_K(c, d, M)
    bending = np.roots([A1**2, 0.0, 2 * A1 * Kb, 0.0, Kb**2 + M**2 / 4])
    torsion = np.roots([A3, 0.0, d])
    p = np.asarray(_nikolai_spectra(*jnp.asarray([[A1], [A3], [c], [d], [M]])))[0]
    assert _match_error(p, np.concatenate([bending, torsion])) <= 1e-7
    resid = np.abs((A1 * p[:4] ** 2 + Kb) ** 2 + M**2 / 4)
    assert resid.max() <= 1e-13 * (Kb**2 + M**2)
    np.testing.assert_allclose(A3 * p[4:] ** 2 + d, 0.0, atol=1e-14)


_A1S, _A3S, _CS, _DS = (1.0, 0.7), (0.6, 1.5), (1.0, 2.5), (2.0, 0.8)
_MS = (0.0, 1e-8, -1e-8, 0.3, -0.7, 1.5)
_GRID = np.array(list(itertools.product(_A1S, _A3S, _CS, _DS, _MS)))


@jax.jit
def _nikolai_grid(params):
    def one(q):
        A1, A3, c, d, M = q
        model = _nikolai_model(A1, A3, c, d, M)
        theta_eq = (M / d) * K  # (4.62)
        sol = rbo.solve_equilibrium(model, jnp.array([0.2, -0.15, 0.5 * M / d + 0.1]))
        return (
            rbo.linearize(model, theta_eq),
            rbo.spectrum(model, theta_eq),
            rbo.fast_spectrum(model, theta_eq),
            sol.theta,
            sol.ok,
        )

    return jax.vmap(one)(params)


@pytest.fixture(scope="module")
def nikolai_grid():
    """(linearize, spectrum, fast_spectrum, Newton's equilibrium and success flag, the roots
    (4.69) of rbo_jax.analytic) on the grid."""
    out = _nikolai_grid(jnp.asarray(_GRID)) + (_nikolai_spectra(*jnp.asarray(_GRID.T)),)
    return tuple(np.asarray(x) for x in out)


def test_equilibrium_follower_quadratic_is_M_over_d_k_4_62(nikolai_grid):
    """(4.62): under a follower moment (4.57) the quadratic foundation (4.50) is in equilibrium
    at θ = (M/d)k; Newton finds it from a guess off the axis, over the whole grid."""
    theta, ok = nikolai_grid[3], nikolai_grid[4]
    assert np.all(ok)
    np.testing.assert_allclose(theta, _GRID[:, 4:5] / _GRID[:, 3:4] * KN, rtol=0, atol=1e-12)


def test_newton_traces_the_equilibrium_residual_once_per_evaluation_4_61():
    """The balance (4.61) of an isotropic foundation U = ½c|θ|² (its moment -cθ) and a follower
    moment M k (Q(θ)·k = k for θ ∥ k) is θ = (M/c) k. ``solve_equilibrium`` traces the residual at
    most three times (the shape of its Jacobian, one Newton evaluation giving the value and the
    Jacobian together, the final residual): a user's energy function is called that often."""
    calls = []
    c, M = 1.3, 0.4

    def energy(s):  # s = |θ|²; a fresh closure: a program of its own
        calls.append(1)  # called while traced: no tracer kept
        return 0.5 * c * s

    k = jnp.array([0.0, 0.0, 1.0])
    model = rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(1.0, 0.6, k),
        rbo.IsotropicFoundation(energy),
        [rbo.FollowerMoment(M, k)],
    )
    sol = rbo.solve_equilibrium(model, jnp.array([0.05, -0.02, 0.1]))
    assert bool(sol.ok)
    np.testing.assert_allclose(sol.state, M / c * np.asarray(k), rtol=0, atol=1e-12)
    assert 1 <= len(calls) <= 3, len(calls)


@pytest.mark.parametrize("solver", ["dense", "tridiagonal"])
def test_value_and_jacobian_trace_the_function_once(solver):
    """A linear solver's value and Jacobian come from one trace of the function, and equal its
    value and the Jacobian of its separate forms (dense: forward mode over the flattened
    unknowns; block-tridiagonal: the blocks of the full Jacobian)."""
    from rbo_jax import solvers

    traces = []

    def fn(x):  # (N, m) -> (N, m), neighbours coupled
        traces.append(1)
        left = jnp.concatenate([jnp.zeros_like(x[:1]), x[:-1]])
        right = jnp.concatenate([x[1:], jnp.zeros_like(x[:1])])
        return jnp.sin(x) * x[:, ::-1] + 0.3 * left**2 - 0.7 * right * x

    x = jnp.asarray(np.random.default_rng(3).normal(size=(4, 3)))
    linear = solvers.Dense() if solver == "dense" else solvers.Tridiagonal()
    value, J = jax.jit(lambda x: linear.value_and_jacobian(fn, x))(x)
    assert len(traces) == 1
    np.testing.assert_allclose(value, fn(x), rtol=1e-15, atol=1e-15)
    full = np.asarray(jax.jacfwd(fn)(x)).reshape(12, 12)
    if solver == "tridiagonal":
        L, D, U = (np.asarray(b) for b in J)
        blocks = np.zeros((12, 12))
        for i in range(4):
            blocks[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = D[i]
            if i > 0:
                blocks[3 * i : 3 * i + 3, 3 * i - 3 : 3 * i] = L[i]
            if i < 3:
                blocks[3 * i : 3 * i + 3, 3 * i + 3 : 3 * i + 6] = U[i]
        J = blocks
    np.testing.assert_allclose(J, full, rtol=1e-14, atol=1e-14)


def test_linearize_is_printed_system_4_66_4_67(nikolai_grid):
    """The autodiff Jacobian at θ = (M/d)k is the printed variational system (4.66)-(4.67),
    over the whole grid."""
    jac = nikolai_grid[0]
    for row, J in zip(_GRID, jac):
        np.testing.assert_allclose(
            J, _printed_variational_matrix(*row), rtol=0, atol=1e-13, err_msg=str(row)
        )


def test_spectrum_and_fast_spectrum_match_4_69_on_a_grid(nikolai_grid):
    """spectrum and fast_spectrum at θ = (M/d)k equal the six roots of (4.69) to 1e-10 over a
    grid of (A1, A3, c, d, M), M = 0 and M = ±1e-8 included."""
    p, fast, exact_all = nikolai_grid[1], nikolai_grid[2], nikolai_grid[5]
    for row, pi, fi, exact in zip(_GRID, p, fast, exact_all):
        assert _match_error(pi, exact) <= 1e-10, row
        assert _match_error(fi, exact) <= 1e-10, row
        # spectrum is sorted lexicographically; fast_spectrum is (p1, p2, p3, -p1, -p2, -p3)
        np.testing.assert_array_equal(pi, np.sort_complex(pi))
        np.testing.assert_array_equal(fi[3:], -fi[:3])


def test_nikolai_paradox_every_nonzero_load_flutters_4_69(nikolai_grid):
    """Some root has Re p > 0 for every M ≠ 0, however small (M = ±1e-8 included): the
    abscissa is that of (4.69) (≈ |M|/(4√(A1 c)) for small M); M = 0 is marginally stable.
    (classify with rtol = 1e-12: its default 1e-9·max|p| is of the order of Re p at |M| = 1e-8.)"""
    p, exact_all = nikolai_grid[1], nikolai_grid[5]
    for row, pi, exact in zip(_GRID, p, exact_all):
        A1, A3, c, d, M = row
        a_exact = float(np.max(exact.real))
        kind, a = _kind(pi, rtol=1e-12)
        if M == 0:
            assert abs(a) <= 1e-14 and kind == StabilityKind.marginally_stable, row
            continue
        assert a > 0 and kind == StabilityKind.flutter, row
        assert abs(a - a_exact) <= 1e-3 * a_exact + 1e-15, row
        if abs(M) < 1e-6:
            np.testing.assert_allclose(a, abs(M) / (4 * np.sqrt(A1 * c)), rtol=1e-6)
        else:
            assert _kind(pi)[0] == StabilityKind.flutter


def _linear_theory_4_74(A1, A3, c, d):
    """Eigenvalues of the linear equations (4.73): Aθ̈ + [c(E − k⊗k) + d k⊗k]θ = Mk."""
    E, kk = np.eye(3), np.outer(KN, KN)
    A = A1 * (E - kk) + A3 * kk
    Klin = c * (E - kk) + d * kk
    L = np.block([[np.zeros((3, 3)), E], [-np.linalg.solve(A, Klin), np.zeros((3, 3))]])
    return np.linalg.eigvals(L)


def test_linear_theory_4_74_misses_the_paradox(nikolai_grid):
    """The linear theory (4.73)-(4.74) has the roots ±i√(d/A3), ±i√(c/A1) (double), none with
    Re p > 0; at M = 1e-8 the spectrum is within 1e-7 of them and yet has Re p > 0."""
    p = nikolai_grid[1]
    rows = [(row, pi) for row, pi in zip(_GRID, p) if row[4] == 1e-8]
    assert len(rows) == 16
    for row, pi in rows:
        A1, A3, c, d, M = row
        lin = _linear_theory_4_74(A1, A3, c, d)
        w = np.array([np.sqrt(d / A3), np.sqrt(c / A1), np.sqrt(c / A1)])
        assert _match_error(lin, np.concatenate([1j * w, -1j * w])) <= 1e-12
        assert np.max(np.abs(lin.real)) <= 1e-14
        assert _match_error(pi, lin) <= 1e-7
        assert np.max(pi.real) > 0


def _vmap_M(f):
    return jax.jit(jax.vmap(f, (None, None, None, 0)))


def test_small_load_form_4_72_converges_to_4_69_like_M_cubed():
    """(4.72) is the small-|M|/d expansion of (4.69) (ERRATA 5): the root error decreases at
    least like M³ (fitted log-log slope)."""
    A1, c, d = 1.0, 1.3, 2.0
    Ms = np.logspace(-2.5, -0.5, 9) * d
    small = _vmap_M(rbo.nikolai_bending_roots_small_load)(A1, c, d, Ms)
    exact = _vmap_M(rbo.nikolai_bending_roots)(A1, c, d, Ms)
    err = np.array([_match_error(p, q) for p, q in zip(np.asarray(small), np.asarray(exact))])
    assert err[-1] > 1e-6  # not trivially equal
    slope = np.polyfit(np.log(Ms), np.log(err), 1)[0]
    assert slope >= 3.0, slope


# ---------------------------------------------------------------------------------------------
# Dead, follower and semi-tangential moments (4.75), (4.78)/(4.82)
# ---------------------------------------------------------------------------------------------

LOADS_4_75 = {  # name: (keyword arguments of _potential_model for magnitude M, l1, l2)
    "dead": (lambda M: dict(dead=M), 1.0, 0.0),
    "follower": (lambda M: dict(follower=M), 0.0, 1.0),
    "dead-4.75": (lambda M: dict(semi=M, l1=1.0, l2=0.0), 1.0, 0.0),
    "follower-4.75": (lambda M: dict(semi=M, l1=0.0, l2=1.0), 0.0, 1.0),
    "mixed": (lambda M: dict(semi=M, l1=1.0, l2=0.4), 1.0, 0.4),
    "semi": (lambda M: dict(semi=M, l1=1.0, l2=1.0), 1.0, 1.0),
    "semi-half": (lambda M: dict(semi=M, l1=0.5, l2=0.5), 0.5, 0.5),
}


@pytest.mark.parametrize("M", [0.05, -0.8])
@pytest.mark.parametrize("load", list(LOADS_4_75))
@pytest.mark.parametrize("foundation", ["quadratic", "barrier"])
def test_semi_tangential_family_4_75_stability(foundation, load, M):
    """(4.82): [(1 − cosϑ)F]˙ = γM(l1 − l2)(1 − cosϑ) makes the equilibrium θ = xk unstable
    whenever M(l1 − l2) ≠ 0, for any transversely isotropic foundation: dead, follower and
    mixed moments flutter. The semi-tangential moment l1 = l2 has a symmetric stiffness at the
    equilibrium (circulatory part 0) and a marginally stable spectrum (every Re p = 0)."""
    params = dict(BARRIER) if foundation == "barrier" else dict(c=1.0, d=2.0)
    make_kwargs, l1, l2 = LOADS_4_75[load]
    model = _potential_model(**params, **make_kwargs(M))
    if foundation == "barrier":
        b = BARRIER["beta"] * (1 - 1e-12)
        theta_eq = _barrier_root(M, -b, b) * K
    else:
        theta_eq = (M / 2.0) * K  # (4.62): on the axis every moment (4.75) is M k
    out = _analyse(model, theta_eq)
    assert float(out["moment"]) <= 1e-12
    p = np.asarray(out["p"])
    kind, a = _kind(p)
    circ = np.abs(np.asarray(out["form"].circulatory)).max()
    if l1 != l2:
        assert kind == StabilityKind.flutter
        assert a > 1e-3 * abs(M)
        assert circ > 0.1 * abs(M)
        if foundation == "quadratic" and l1 * l2 == 0:  # dead or follower: (4.69)
            assert _match_error(p, rbo.nikolai_spectrum(1.0, 0.6, 1.0, 2.0, M)) <= 1e-10
    else:
        assert kind == StabilityKind.marginally_stable
        assert abs(a) <= 1e-13
        assert circ <= 1e-14
    assert _match_error(out["fast"], p) <= 1e-12


def _loop_work(moment, center, radius, n=400):
    """Work ∮ M_ex·ω dt of a world-frame moment M_ex(Q) along a closed loop of turn-vectors
    θ(s) = center + radius·(cos s, 0.3 sin 2s, sin s), with Q(θ) and ω (Q̇Qᵀ = ω×) from scipy's
    rotations: zero for every loop iff the moment is conservative (4.21)-(4.23)."""

    def theta(s):
        return center + radius * np.array([np.cos(s), 0.3 * np.sin(2 * s), np.sin(s)])

    s = np.linspace(0.0, 2 * np.pi, n + 1)[:-1]
    h = 1e-6
    total = 0.0
    for si in s:
        Q = Rotation.from_rotvec(theta(si)).as_matrix()
        dQ = (
            Rotation.from_rotvec(theta(si + h)).as_matrix()
            - Rotation.from_rotvec(theta(si - h)).as_matrix()
        ) / (2 * h)
        W = dQ @ Q.T
        omega = np.array([W[2, 1], W[0, 2], W[1, 0]])
        total += moment(Q, theta(si)) @ omega
    return total * (s[1] - s[0])  # trapezoid rule, spectrally accurate on a periodic integrand


def test_semi_tangential_moment_is_not_conservative_off_the_axis():
    """What the test above finds on the axis does not extend off it: the semi-tangential moment
    (4.75), M(k + P·k)/|k + P·k| (l1 = l2), does net work around a closed loop of orientations
    off the axis, like the follower moment — it has no potential, although its linearization
    at θ ∥ k is symmetric. Control: the conservative moment −cθ of U = ½cθ² (4.23) does none.
    (Computed with scipy rotations only.)"""
    center = np.array([0.3, 0.1, 0.4])
    semi = _loop_work(lambda Q, th: (KN + Q @ KN) / np.linalg.norm(KN + Q @ KN), center, 0.2)
    follower = _loop_work(lambda Q, th: Q @ KN, center, 0.2)
    elastic = _loop_work(lambda Q, th: -1.3 * th, center, 0.2)
    assert abs(elastic) <= 1e-9
    assert abs(semi) > 1e-3 and abs(follower) > 1e-3
    # the package's moment is the formula used here
    th = jnp.asarray(center)
    Q = Rotation.from_rotvec(center).as_matrix()
    np.testing.assert_allclose(
        np.asarray(rbo.SemiTangentialMoment(1.0, K).moment(0.0, th, th)),
        (KN + Q @ KN) / np.linalg.norm(KN + Q @ KN),
        rtol=1e-14,
    )


# ---------------------------------------------------------------------------------------------
# Second-order form
# ---------------------------------------------------------------------------------------------


def _quadratic_eigenvalues(form):
    """Roots of det(p²M + pC + K) = 0 from the returned matrices, by a 6×6 companion."""
    Mm = np.asarray(form.mass)
    C = np.asarray(form.damping) + np.asarray(form.gyroscopic)
    Kf = np.asarray(form.stiffness) + np.asarray(form.circulatory)
    np.testing.assert_array_equal(np.asarray(form.full_stiffness), Kf)
    comp = np.block(
        [[np.zeros((3, 3)), np.eye(3)], [-np.linalg.solve(Mm, Kf), -np.linalg.solve(Mm, C)]]
    )
    return np.linalg.eigvals(comp)


M_LOAD = (0.2, -0.1, 0.3)

SECOND_ORDER_CASES = {
    # name: (model, equilibrium: a vector, or None to solve by Newton)
    "follower": (lambda: _potential_model(follower=0.7), 0.35 * K),
    "follower+friction": (lambda: _velocity_model(M=0.7, b=0.15), 0.35 * K),
    "gyroscopic": (lambda: _velocity_model(gamma=0.4), jnp.zeros(3)),
    "no load": (lambda: _potential_model(), jnp.zeros(3)),
    # V = −m·θ on the barrier foundation: a non-axial equilibrium ∇U = m
    "barrier+potential": (lambda: _potential_model(**BARRIER, m=M_LOAD), None),
}


@pytest.fixture(scope="module", params=list(SECOND_ORDER_CASES))
def second_order_case(request):
    make, theta_eq = SECOND_ORDER_CASES[request.param]
    model = make()
    if theta_eq is None:
        sol = _solve(model, jnp.array([0.1, -0.1, 0.2]))
        assert bool(sol.ok)
        theta_eq = sol.theta
    out = _analyse(model, theta_eq)
    assert float(out["moment"]) <= 1e-12
    return request.param, model, theta_eq, out


def test_second_order_form_has_the_spectrum(second_order_case):
    """det(p²M + p(D + G) + (K_s + K_c)) = 0 has the roots of the first-order spectrum; the
    parts have the stated symmetries; fast_spectrum agrees (both of its branches)."""
    name, model, theta_eq, out = second_order_case
    form = out["form"]
    for part in ("mass", "damping", "stiffness"):
        X = np.asarray(getattr(form, part))
        np.testing.assert_array_equal(X, X.T)
    for part in ("gyroscopic", "circulatory"):
        X = np.asarray(getattr(form, part))
        np.testing.assert_array_equal(X, -X.T)
    assert np.all(np.linalg.eigvalsh(np.asarray(form.mass)) > 0)
    p = np.asarray(out["p"])
    scale = np.max(np.abs(p))
    assert _match_error(_quadratic_eigenvalues(form), p) <= 1e-12 * scale
    assert _match_error(out["fast"], p) <= 1e-12 * scale


def test_second_order_form_parts(second_order_case):
    """Potential problems (no load; the load V = −m·θ (4.52) on the barrier foundation (4.49),
    at its non-axial equilibrium): K_c = 0 and K_s = ∂²(U + V)/∂θ² (jax.hessian) at the
    equilibrium. The follower moment has K_c ≠ 0. Friction (4.84) gives D = b Z⁻¹Z⁻ᵀ
    (symmetric positive definite) and G = 0 at Ω = 0; the gyroscopic torque γk×ω gives D = 0,
    G = −γ[k×]."""
    name, model, theta_eq, out = second_order_case
    form = out["form"]
    circ = np.abs(np.asarray(form.circulatory)).max()
    D, G = np.asarray(form.damping), np.asarray(form.gyroscopic)
    if name in ("barrier+potential", "no load"):
        H = np.asarray(out["hessian"])
        np.testing.assert_allclose(np.asarray(form.stiffness), H, rtol=0, atol=1e-12)
        assert circ <= 1e-14
    if name == "barrier+potential":
        th = np.asarray(theta_eq)
        assert abs(th[2]) > 0.1 and np.linalg.norm(th[:2]) > 0.1  # genuinely off the axis
        assert np.abs(H - np.diag(np.diag(H))).max() > 0.01  # and a non-trivial Hessian
    if name.startswith("follower"):
        assert circ > 0.1
    if name == "follower+friction":
        Zinv = np.asarray(rbo.integrating_tensor_inv(theta_eq))
        np.testing.assert_allclose(D, 0.15 * Zinv @ Zinv.T, rtol=0, atol=1e-14)
        assert np.abs(Zinv @ Zinv.T - np.eye(3)).max() > 0.01
        assert np.all(np.linalg.eigvalsh(D) > 0)
        assert np.abs(G).max() <= 1e-15
    elif name == "gyroscopic":
        np.testing.assert_allclose(G, -0.4 * _skew(KN), rtol=0, atol=1e-15)
        assert np.abs(D).max() <= 1e-15
    else:
        assert np.abs(D).max() == 0 and np.abs(G).max() == 0


# ---------------------------------------------------------------------------------------------
# Classification
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "p, kind, abscissa",
    [
        ([-0.1 + 1j, -0.1 - 1j, -0.2], StabilityKind.asymptotically_stable, -0.1),
        ([1e-12 + 1j, -1e-12 - 1j, 2j, -2j], StabilityKind.marginally_stable, 1e-12),
        ([0.0, 0.0], StabilityKind.marginally_stable, 0.0),
        ([0.5, -0.5, 1j, -1j], StabilityKind.divergence, 0.5),
        ([0.3 + 1j, 0.3 - 1j, -0.3 + 1j, -0.3 - 1j], StabilityKind.flutter, 0.3),
        ([1e-6 + 1j, 1e-6 - 1j, -1e-6 + 1j], StabilityKind.flutter, 1e-6),
        ([np.nan + 0j, 1j], StabilityKind.undefined, np.nan),
    ],
    ids=["asymptotic", "marginal", "zero", "divergence", "flutter", "weak-flutter", "nan"],
)
def test_classify_hand_made_spectra(p, kind, abscissa):
    """classify and spectral_abscissa on spectra written down by hand."""
    p = jnp.asarray(np.array(p, dtype=complex))
    k, a = rbo.classify(p)
    assert k == kind
    np.testing.assert_allclose(float(a), abscissa, rtol=1e-15, atol=0)
    np.testing.assert_allclose(float(rbo.spectral_abscissa(p)), abscissa, rtol=1e-15, atol=0)


def test_classify_rtol_is_relative_to_max_abs_p():
    """Re p = 1e-6 with max|p| ≈ 1 is flutter at rtol = 1e-9 and marginal at rtol = 1e-5, at
    any scale of p."""
    p = jnp.asarray([1e-6 + 1j, 1e-6 - 1j, -1e-6 + 1j, -1e-6 - 1j])
    assert rbo.classify(p)[0] == StabilityKind.flutter
    assert rbo.classify(p, rtol=1e-5)[0] == StabilityKind.marginally_stable
    assert rbo.classify(1e3 * p, rtol=1e-5)[0] == StabilityKind.marginally_stable
    assert rbo.classify(1e3 * p)[0] == StabilityKind.flutter


CLASSIFY_MODELS = {
    # name: (model, θ_eq, exact spectrum)
    # friction (4.84) without load: A1p² + bp + c = 0 (bending, twice), A3p² + bp + d = 0
    "asymptotically_stable": (
        lambda: _velocity_model(b=0.2),
        jnp.zeros(3),
        lambda: np.concatenate(
            [np.roots([1.0, 0.2, 1.0]), np.roots([1.0, 0.2, 1.0]), np.roots([0.6, 0.2, 2.0])]
        ),
    ),
    # (4.50) without load: ±i√(c/A1) (twice), ±i√(d/A3)
    "marginally_stable": (
        lambda: _potential_model(),
        jnp.zeros(3),
        lambda: np.array([1j, -1j, 1j, -1j, 1j * np.sqrt(2 / 0.6), -1j * np.sqrt(2 / 0.6)]),
    ),
    # isotropic ½cθ² (c = d = 1) with V = −½eθ², e = 1.6 > c: p² = (e − c)/A, real
    "divergence": (
        lambda: _potential_model(A1=1.3, A3=1.3, c=1.0, d=1.0, e=1.6),
        jnp.zeros(3),
        lambda: np.repeat([np.sqrt(0.6 / 1.3), -np.sqrt(0.6 / 1.3)], 3),
    ),
    # follower moment M = 0.4 at θ = (M/d)k: (4.69)
    "flutter": (
        lambda: _potential_model(follower=0.4),
        0.2 * K,
        lambda: np.asarray(rbo.nikolai_spectrum(1.0, 0.6, 1.0, 2.0, 0.4)),
    ),
}


@pytest.mark.parametrize("name", list(CLASSIFY_MODELS))
def test_classify_models(name):
    """The four kinds on models whose spectra are known in closed form."""
    make, theta_eq, exact = CLASSIFY_MODELS[name]
    expected = exact()
    p = np.asarray(_analyse(make(), theta_eq)["p"])
    assert _match_error(p, expected) <= 1e-12
    kind, a = _kind(p)
    assert kind == getattr(StabilityKind, name)
    np.testing.assert_allclose(a, np.max(expected.real), rtol=0, atol=1e-13)
    np.testing.assert_allclose(float(rbo.spectral_abscissa(p)), np.max(expected.real), atol=1e-13)


def test_classify_undefined_for_nan_input():
    """A NaN turn-vector gives a NaN spectrum, classified undefined (not stable)."""
    p = np.asarray(_analyse(_potential_model(follower=0.4), jnp.array([np.nan, 0.0, 0.2]))["p"])
    assert np.any(np.isnan(p))
    assert _kind(p)[0] == StabilityKind.undefined
