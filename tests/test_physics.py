"""Physics of the rigid body oscillator checked on simulated trajectories.

Each test checks an exact result of the paper (equation numbers in the names) or an invariant
against an independent computation (scipy, closed forms evaluated here).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from rbo_jax.foundations import (
    BarrierFoundation,
    IsotropicFoundation,
    QuadraticFoundation,
    transverse_coefficients,
)
from rbo_jax.inertia import principal_inertia, transversely_isotropic_inertia
from rbo_jax.kinematics import integrating_tensor, turn_tensor
from rbo_jax.loads import FollowerMoment, Friction, SemiTangentialMoment
from rbo_jax.model import RigidBodyOscillator
from rbo_jax.simulate import simulate

K = jnp.array([0.0, 0.0, 1.0])
TIGHT = dict(rtol=1e-12, atol=1e-12)


def _gauss_legendre_times(t1, n_intervals, n_nodes=8):
    """Composite Gauss-Legendre nodes and weights on [0, t1] (for ∫ f dt along a trajectory)."""
    x, w = np.polynomial.legendre.leggauss(n_nodes)
    edges = np.linspace(0.0, t1, n_intervals + 1)
    h = np.diff(edges)[:, None]
    nodes = (edges[:-1, None] + 0.5 * h * (x[None, :] + 1)).ravel()
    weights = (0.5 * h * w[None, :]).ravel()
    return nodes, weights


# ---------------------------------------------------------------------------------------------
# Energy (4.124)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("inertia_kind", ["transversely_isotropic", "general"])
def test_energy_conserved_over_100_periods_4_124(inertia_kind):
    """K + U is conserved without friction and external moments (4.124): relative drift
    ≤ 1e-9 over 100 periods of the barrier foundation (4.49)."""
    if inertia_kind == "transversely_isotropic":
        A = transversely_isotropic_inertia(1.0, 0.6, K)
    else:
        axes = turn_tensor(jnp.array([0.3, -0.5, 0.9])).T  # rows: principal axes
        A = principal_inertia(jnp.array([1.0, 1.3, 0.7]), axes)
    model = RigidBodyOscillator(A, BarrierFoundation(1.0, 2.0, 2.0, 1.5, K))
    period = 2 * np.pi  # bending frequency sqrt(c/A1) = 1 at small amplitude
    ts = jnp.linspace(0.0, 100 * period, 401)
    traj = simulate(model, jnp.array([0.8, -0.3, 0.5]), jnp.array([0.2, 1.1, -0.7]), ts, **TIGHT)
    E = np.asarray(traj.energy)
    assert np.all(np.isfinite(E))
    # the motion is genuinely 3-D and large
    assert np.max(np.linalg.norm(np.asarray(traj.theta), axis=1)) > 1.0
    assert np.max(np.abs(E - E[0])) / abs(E[0]) <= 1e-9


def test_friction_dissipates_energy_at_rate_b_omega_squared_4_84():
    """With friction (4.84), dE/dt = M_ex·ω = −b|ω|²: E(0) − E(T) = ∫ b|ω|² dt."""
    b = 0.05
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(1.0, 0.6, K), QuadraticFoundation(1.0, 2.0, K), Friction(b)
    )
    nodes, weights = _gauss_legendre_times(10.0, 20)
    ts = jnp.asarray(np.concatenate([[0.0], nodes, [10.0]]))
    traj = simulate(model, jnp.array([0.8, -0.3, 0.5]), jnp.array([0.2, 1.1, -0.7]), ts, **TIGHT)
    E = np.asarray(traj.energy)
    w2 = np.sum(np.asarray(traj.omega) ** 2, axis=1)[1:-1]
    dissipated = b * np.sum(weights * w2)
    assert dissipated > 0.1 * E[0]
    np.testing.assert_allclose(E[0] - E[-1], dissipated, rtol=1e-9)


# ---------------------------------------------------------------------------------------------
# The balance (4.78)/(4.82) for semi-tangential loads (4.75)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "l1, l2",
    [(1.0, 0.0), (0.0, 1.0), (1.0, 1.0), (1.0, 0.4)],
    ids=["dead", "follower", "semi", "mixed"],
)
def test_balance_4_78_semi_tangential_barrier(l1, l2):
    r"""(4.78): d/dt[A1(ω−Ω)·k + (A1−A3)(k·Ω)(1−cosϑ)] = γM(l1−l2)(1−cosϑ), cosϑ = k·P·k,
    along trajectories of the barrier foundation (4.49), for any transversely isotropic
    foundation. The right side is integrated along the path by composite Gauss-Legendre."""
    A1, A3, M = 1.0, 0.6, 0.35
    load = SemiTangentialMoment(M, K, l1, l2)
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, K), BarrierFoundation(1.0, 1.7, 1.8, 1.4, K), load
    )
    T = 8.0
    nodes, weights = _gauss_legendre_times(T, 16)
    ts = jnp.asarray(np.concatenate([[0.0], nodes, [T]]))
    traj = simulate(model, jnp.array([0.5, -0.4, 0.3]), jnp.array([0.3, 0.9, 0.6]), ts, **TIGHT)
    P = traj.turn_tensor
    cos_vartheta = jnp.einsum("i,nij,j->n", K, P, K)
    Omega, omega = traj.Omega, traj.omega
    G = A1 * (omega - Omega) @ K + (A1 - A3) * (Omega @ K) * (1 - cos_vartheta)
    gamma = jax.vmap(load.gamma)(traj.theta)
    rhs = np.asarray(gamma * M * (l1 - l2) * (1 - cos_vartheta))[1:-1]
    lhs = float(G[-1] - G[0])
    integral = float(np.sum(weights * rhs))
    scale = float(jnp.max(jnp.abs(G))) + abs(integral)
    assert scale > 1e-2
    assert abs(lhs - integral) <= 1e-9 * scale
    if l1 != l2:
        assert abs(integral) > 1e-3  # the right side is not trivially zero


# ---------------------------------------------------------------------------------------------
# The simplest oscillator (4.83)-(4.101)
# ---------------------------------------------------------------------------------------------

A_SIMPLE, C0, C2 = 1.3, 1.0, 0.4


def _F(s):
    """u(θ²) of (4.83): u = ½c0θ² + ¼c2θ⁴, so c(θ²) = 2u'(θ²) = c0 + c2θ²."""
    return 0.5 * C0 * s + 0.25 * C2 * s**2


def _c_of(s):
    return C0 + C2 * s


@pytest.fixture(scope="module")
def simplest_trajectory():
    b = 0.08
    model = RigidBodyOscillator(A_SIMPLE * jnp.eye(3), IsotropicFoundation(_F), Friction(b))
    theta0 = jnp.array([0.9, 0.2, -0.4])
    Omega0 = jnp.array([0.1, 0.8, 0.5])
    ts = jnp.linspace(0.0, 15.0, 301)
    traj = simulate(model, theta0, Omega0, ts, **TIGHT)
    return traj, b


def test_integral_4_94_omega_minus_Omega_decays(simplest_trajectory):
    """(4.94): ω − Ω = (ω0 − Ω0) exp(−bt/A) for A = A E, isotropic foundation, friction."""
    traj, b = simplest_trajectory
    diff = np.asarray(traj.omega - traj.Omega)
    expected = diff[0][None, :] * np.exp(-b * np.asarray(traj.ts) / A_SIMPLE)[:, None]
    assert np.linalg.norm(diff[0]) > 0.1
    np.testing.assert_allclose(diff, expected, atol=1e-9 * np.linalg.norm(diff[0]))


def test_integral_4_96_turn_vector_stays_in_plane(simplest_trajectory):
    """(4.96): θ(t)·e = 0 with e = (ω0 − Ω0)/|ω0 − Ω0|."""
    traj, _ = simplest_trajectory
    d0 = np.asarray(traj.omega[0] - traj.Omega[0])
    e = d0 / np.linalg.norm(d0)
    assert abs(np.asarray(traj.theta[0]) @ e) < 1e-14
    assert np.max(np.abs(np.asarray(traj.theta) @ e)) <= 1e-9


def test_integral_4_99_precession_rate(simplest_trajectory):
    """(4.99): ψ̇ = (1 − cos θ0)/(1 − cos θ) ψ̇0 exp(−bt/A), ψ̇ from θ×θ̇ = ψ̇θ²e (4.98)."""
    traj, b = simplest_trajectory
    theta = traj.theta
    theta_dot = jax.vmap(lambda th, Om: integrating_tensor(th).T @ Om)(theta, traj.Omega)
    d0 = np.asarray(traj.omega[0] - traj.Omega[0])
    e = d0 / np.linalg.norm(d0)
    n2 = np.sum(np.asarray(theta) ** 2, axis=1)
    psi_dot = (np.cross(np.asarray(theta), np.asarray(theta_dot)) @ e) / n2
    n = np.sqrt(n2)
    expected = (
        (1 - np.cos(n[0]))
        / (1 - np.cos(n))
        * psi_dot[0]
        * np.exp(-b * np.asarray(traj.ts) / A_SIMPLE)
    )
    assert abs(psi_dot[0]) > 0.1
    np.testing.assert_allclose(psi_dot, expected, rtol=1e-8)


def test_reduced_nutation_equation_4_101(simplest_trajectory):
    """(4.101): Aθ̈ + bθ̇ + [c(θ²) − A sinθ/θ ((1−cosθ0)/(1−cosθ))² ψ̇0² e^{−2bt/A}]θ = 0,
    integrated independently with scipy (DOP853), reproduces |θ(t)| of the 3-D solution."""
    traj, b = simplest_trajectory
    theta = np.asarray(traj.theta)
    n = np.linalg.norm(theta, axis=1)
    theta_dot0 = np.asarray(integrating_tensor(traj.theta[0]).T @ traj.Omega[0])
    n_dot0 = theta[0] @ theta_dot0 / n[0]  # θ·θ̇ = θ θ̇ (after (4.18))
    d0 = np.asarray(traj.omega[0] - traj.Omega[0])
    e = d0 / np.linalg.norm(d0)
    psi_dot0 = np.cross(theta[0], theta_dot0) @ e / n[0] ** 2
    A = A_SIMPLE

    def rhs(t, y):
        x, v = y
        centrifugal = (
            A
            * np.sin(x)
            / x
            * ((1 - np.cos(n[0])) / (1 - np.cos(x))) ** 2
            * psi_dot0**2
            * np.exp(-2 * b * t / A)
        )
        return [v, -(b * v + (_c_of(x**2) - centrifugal) * x) / A]

    ts = np.asarray(traj.ts)
    sol = solve_ivp(
        rhs, (ts[0], ts[-1]), [n[0], n_dot0], method="DOP853", t_eval=ts, rtol=1e-12, atol=1e-12
    )
    assert sol.success
    assert np.ptp(n) > 0.1  # the nutation is not trivial
    np.testing.assert_allclose(n, sol.y[0], atol=1e-8)


def test_plane_oscillations_4_87():
    """(4.87): for θ0 × Ω0 = 0 the motion stays on the line of θ0 and |θ| obeys
    Aθ̈ + bθ̇ + c(θ²)θ = 0 (solved independently with scipy)."""
    b = 0.1
    model = RigidBodyOscillator(A_SIMPLE * jnp.eye(3), IsotropicFoundation(_F), Friction(b))
    n_axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    x0, v0 = 2.5, -0.7
    ts = jnp.linspace(0.0, 12.0, 121)
    traj = simulate(model, jnp.asarray(x0 * n_axis), jnp.asarray(v0 * n_axis), ts, **TIGHT)
    theta = np.asarray(traj.theta)
    assert np.max(np.linalg.norm(np.cross(theta, n_axis), axis=1)) <= 1e-12
    sol = solve_ivp(
        lambda t, y: [y[1], -(b * y[1] + _c_of(y[0] ** 2) * y[0]) / A_SIMPLE],
        (0.0, 12.0),
        [x0, v0],
        method="DOP853",
        t_eval=np.asarray(ts),
        rtol=1e-12,
        atol=1e-12,
    )
    np.testing.assert_allclose(theta @ n_axis, sol.y[0], atol=1e-9)


# ---------------------------------------------------------------------------------------------
# Regular precession (4.110)-(4.113), (4.106)
# ---------------------------------------------------------------------------------------------


def _precession_rate(C, vartheta, A1, A3):
    """ψ̇ of (4.113): ψ̇² = Cϑ / (sinϑ [A3(1 − cosϑ) + A1 cosϑ])."""
    return np.sqrt(
        C * vartheta / (np.sin(vartheta) * (A3 * (1 - np.cos(vartheta)) + A1 * np.cos(vartheta)))
    )


@pytest.mark.parametrize(
    "A1, A3, vartheta, foundation",
    [
        (1.0, 0.6, 0.7, "quadratic"),
        (1.0, 0.6, 1.9, "barrier"),
        (0.8, 1.5, 1.2, "quadratic"),
        (1.1, 1.1, 2.4, "quadratic"),  # A1 = A3: (4.106)
    ],
)
def test_regular_precession_4_113(A1, A3, vartheta, foundation):
    """Started on the regular precession (4.110)-(4.112) with the rate (4.113) ((4.106) for
    A1 = A3), the body keeps |θ| = ϑ, k·θ = 0, and θ(t) = ϑ Q(ψ̇t k)·p."""
    if foundation == "quadratic":
        f = QuadraticFoundation(1.2, 2.0, K)
    else:
        f = BarrierFoundation(1.2, 2.0, 2.5, 1.5, K)
    p = jnp.array([1.0, 0.0, 0.0])
    theta0 = vartheta * p
    C, D = transverse_coefficients(f, theta0)
    assert float(D) == 0.0  # the restriction before (4.113)
    if A1 == A3:  # (4.106): ψ̇² = c(θ0²)θ0/(A sinθ0)
        psi_dot = np.sqrt(float(C) * vartheta / (A1 * np.sin(vartheta)))
    else:
        psi_dot = _precession_rate(float(C), vartheta, A1, A3)
    omega0 = psi_dot * ((1 - np.cos(vartheta)) * K + np.sin(vartheta) * jnp.cross(K, p))  # (4.112)
    Omega0 = turn_tensor(theta0).T @ omega0
    model = RigidBodyOscillator(transversely_isotropic_inertia(A1, A3, K), f)
    T = 3 * 2 * np.pi / psi_dot
    ts = jnp.linspace(0.0, T, 61)
    traj = simulate(model, theta0, Omega0, ts, **TIGHT)
    expected = jax.vmap(lambda t: turn_tensor(psi_dot * t * K) @ theta0)(ts)
    np.testing.assert_allclose(np.asarray(traj.theta), np.asarray(expected), atol=1e-8)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(traj.theta), axis=1), vartheta, rtol=1e-9)


def test_wrong_precession_rate_does_not_precess_regularly():
    """Control for the test above: 5 % off the rate (4.113), |θ| does not stay constant."""
    A1, A3, vartheta = 1.0, 0.6, 0.7
    f = QuadraticFoundation(1.2, 2.0, K)
    p = jnp.array([1.0, 0.0, 0.0])
    psi_dot = 1.05 * _precession_rate(1.2, vartheta, A1, A3)
    theta0 = vartheta * p
    omega0 = psi_dot * ((1 - np.cos(vartheta)) * K + np.sin(vartheta) * jnp.cross(K, p))
    model = RigidBodyOscillator(transversely_isotropic_inertia(A1, A3, K), f)
    ts = jnp.linspace(0.0, 3 * 2 * np.pi / psi_dot, 61)
    traj = simulate(model, theta0, turn_tensor(theta0).T @ omega0, ts, **TIGHT)
    assert np.ptp(np.linalg.norm(np.asarray(traj.theta), axis=1)) > 1e-3


# ---------------------------------------------------------------------------------------------
# The Nikolai problem (4.57)-(4.72)
# ---------------------------------------------------------------------------------------------


def _bending_roots_4_69(A1, c, d, M):
    """Roots p of (A1 p² + K)² + M²/4 = 0 (4.69), K = c(g² + M²/4d²) − M²/4d + (1−g)g d,
    g = θ0 sinθ0 / (2(1 − cosθ0)), θ0 = M/d (ERRATA 4)."""
    th0 = M / d
    g = th0 * np.sin(th0) / (2 * (1 - np.cos(th0)))
    Kc = c * (g**2 + M**2 / (4 * d**2)) - M**2 / (4 * d) + (1 - g) * g * d
    p2 = np.array([(-Kc + 0.5j * M) / A1, (-Kc - 0.5j * M) / A1])
    r = np.sqrt(p2)
    return np.concatenate([r, -r])


def test_follower_equilibrium_4_62_stays_put():
    """(4.60)-(4.62): θ = (M/d)k, Ω = 0 is an equilibrium under a follower moment (4.57) with
    the quadratic foundation (4.50)."""
    A1, A3, c, d, M = 1.0, 0.6, 1.0, 2.0, 0.7
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, K),
        QuadraticFoundation(c, d, K),
        FollowerMoment(M, K),
    )
    theta_eq = (M / d) * K
    th_dot, Om_dot = model.vector_field(0.0, (theta_eq, jnp.zeros(3)))
    assert float(jnp.max(jnp.abs(Om_dot))) <= 1e-15
    traj = simulate(model, theta_eq, jnp.zeros(3), jnp.linspace(0.0, 50.0, 11), **TIGHT)
    assert float(jnp.max(jnp.abs(traj.theta - theta_eq[None, :]))) <= 1e-13
    # a dead moment of the same size is not in equilibrium there
    th_dot, Om_dot = RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, K),
        QuadraticFoundation(c, d, K),
        SemiTangentialMoment(M, K, 1.0, 0.0),
    ).vector_field(0.0, (theta_eq + jnp.array([0.1, 0.0, 0.0]), jnp.zeros(3)))
    assert float(jnp.max(jnp.abs(Om_dot))) > 1e-3


def test_nikolai_growth_rate_matches_4_69():
    """The Nikolai paradox: from a 1e-9 perturbation of (4.62) the bending deviation grows at the
    rate max Re p of the roots of (4.69), although (4.74) predicts bounded motion."""
    A1, A3, c, d, M = 1.0, 0.6, 1.0, 2.0, 0.5
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, K),
        QuadraticFoundation(c, d, K),
        FollowerMoment(M, K),
    )
    theta_eq = (M / d) * K
    rate = float(np.max(_bending_roots_4_69(A1, c, d, M).real))
    assert rate > 0
    ts = jnp.linspace(0.0, 100.0, 401)
    traj = simulate(model, theta_eq + jnp.array([1e-9, 0.0, 0.0]), jnp.zeros(3), ts, **TIGHT)
    dev = np.linalg.norm(np.asarray(traj.theta - theta_eq[None, :])[:, :2], axis=1)
    t = np.asarray(ts)
    # amplitude envelope: max over windows of one oscillation period, then the log slope
    window = t > 30
    slope = np.polyfit(t[window], np.log(dev[window] + 1e-300), 1)[0]
    assert dev[-1] > 100 * dev[0]
    assert dev[-1] < 1e-2  # still linear: the measured rate is the linear one
    np.testing.assert_allclose(slope, rate, rtol=0.05)
