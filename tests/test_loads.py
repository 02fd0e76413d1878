"""Tests of rbo_jax.loads: external moments (4.52), (4.57), (4.75) (ERRATA 9), (4.84).

References are independent of the code under test: the turn-tensor from scipy's rotation vectors
(Q(θ) = exp(θ×E), (4.3)), Z (4.11) written out in NumPy, and finite differences.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import finite_difference_jacobian
from scipy.spatial.transform import Rotation

import rbo_jax as rbo

RNG = np.random.default_rng(75)
K = np.array([0.2, -0.5, 0.9]) / np.linalg.norm([0.2, -0.5, 0.9])
THETAS = RNG.normal(size=(6, 3)) * 0.9
OMEGAS = RNG.normal(size=(6, 3))


def np_Q(theta):
    """Turn-tensor (4.3)."""
    return Rotation.from_rotvec(np.asarray(theta, dtype=float)).as_matrix()


def np_Z(theta):
    """Integrating tensor (4.11)."""
    theta = np.asarray(theta, dtype=float)
    th = np.linalg.norm(theta)
    R = np.array(
        [[0.0, -theta[2], theta[1]], [theta[2], 0.0, -theta[0]], [-theta[1], theta[0], 0.0]]
    )
    g = th * np.sin(th) / (2 * (1 - np.cos(th)))
    return np.eye(3) - 0.5 * R + (1 - g) / th**2 * R @ R


@eqx.filter_jit
def moment(load, t, theta, omega):
    return load.moment(t, theta, omega)


def test_dead_moment():
    """M_ex = M k: (4.75) with l1 = 1, l2 = 0; independent of θ, ω and t."""
    load = rbo.DeadMoment(-2.5, 3.0 * K)
    np.testing.assert_allclose(load.k, K, rtol=1e-15)
    for t, th, om in zip(range(6), THETAS, OMEGAS):
        np.testing.assert_allclose(moment(load, float(t), th, om), -2.5 * K, rtol=1e-15)
    assert load.potential_energy(THETAS[0]) == 0.0


def test_follower_moment_4_57():
    """M_ex = M P·k with P = Q(θ) (4.57): the dead moment carried along by the body."""
    load, dead = rbo.FollowerMoment(1.7, K), rbo.DeadMoment(1.7, K)
    for th, om in zip(THETAS, OMEGAS):
        M = moment(load, 0.3, th, om)
        np.testing.assert_allclose(M, 1.7 * np_Q(th) @ K, rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(
            M, np_Q(th) @ np.asarray(moment(dead, 0.3, th, om)), rtol=1e-13, atol=1e-14
        )
        # In the body frame the follower moment is constant: P^T·M_ex = M k.
        np.testing.assert_allclose(np_Q(th).T @ np.asarray(M), 1.7 * K, rtol=1e-13, atol=1e-14)
    assert load.potential_energy(THETAS[0]) == 0.0


@pytest.mark.parametrize("l1, l2", [(1.0, 1.0), (1.0, 0.0), (0.0, 1.0), (2.0, 0.5), (-1.0, 3.0)])
def test_semi_tangential_moment_4_75(l1, l2):
    """γM(l1 k + l2 P·k), γ = (l1² + l2² + 2 l1 l2 k·P·k)^(−1/2) (4.75, ERRATA 9): |M_ex| = |M|."""
    M = -1.3
    load = rbo.SemiTangentialMoment(M, K, l1, l2)
    for th, om in zip(THETAS, OMEGAS):
        P = np_Q(th)
        gamma = (l1**2 + l2**2 + 2 * l1 * l2 * K @ P @ K) ** -0.5
        expected = gamma * M * (l1 * K + l2 * P @ K)
        got = np.asarray(moment(load, 0.0, th, om))
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(np.linalg.norm(got), abs(M), rtol=1e-13)
        np.testing.assert_allclose(eqx.filter_jit(load.gamma)(th), gamma, rtol=1e-12)
    assert load.potential_energy(THETAS[0]) == 0.0


def test_semi_tangential_special_cases_are_dead_and_follower():
    for th in THETAS[:3]:
        np.testing.assert_allclose(
            moment(rbo.SemiTangentialMoment(0.9, K, 1.0, 0.0), 0.0, th, th),
            moment(rbo.DeadMoment(0.9, K), 0.0, th, th),
            rtol=1e-14,
        )
        np.testing.assert_allclose(
            moment(rbo.SemiTangentialMoment(0.9, K, 0.0, 1.0), 0.0, th, th),
            moment(rbo.FollowerMoment(0.9, K), 0.0, th, th),
            rtol=1e-14,
            atol=1e-15,
        )
        # Default l1 = l2 = 1: the bisector of k and P·k.
        got = np.asarray(moment(rbo.SemiTangentialMoment(0.9, K), 0.0, th, th))
        bisector = K + np_Q(th) @ K
        np.testing.assert_allclose(got, 0.9 * bisector / np.linalg.norm(bisector), rtol=1e-13)


def test_semi_tangential_degenerate_direction_raises():
    """l1 k + l2 P·k = 0: l1 = l2 with P·k = −k (half turn about an axis ⊥ k), or l1 = −l2 at
    θ = 0. The moment is undefined there: an error, not NaN."""
    m = np.cross(K, [1.0, 0.0, 0.0])
    half_turn = np.pi * m / np.linalg.norm(m)
    np.testing.assert_allclose(np_Q(half_turn) @ K, -K, atol=1e-15)
    with pytest.raises(Exception, match="direction of the moment"):
        moment(rbo.SemiTangentialMoment(1.0, K), 0.0, half_turn, np.zeros(3))
    with pytest.raises(Exception, match="direction of the moment"):
        moment(rbo.SemiTangentialMoment(1.0, K, 2.0, -2.0), 0.0, np.zeros(3), np.zeros(3))
    # Close to, but not at, the degenerate configuration the moment is finite with |M_ex| = |M|.
    near = half_turn * (1 - 1e-6)
    got = np.asarray(moment(rbo.SemiTangentialMoment(1.0, K), 0.0, near, np.zeros(3)))
    np.testing.assert_allclose(np.linalg.norm(got), 1.0, rtol=1e-12)


def test_friction_4_84():
    load = rbo.Friction(0.35)
    for th, om in zip(THETAS, OMEGAS):
        np.testing.assert_allclose(moment(load, 1.0, th, om), -0.35 * om, rtol=1e-15)
    np.testing.assert_array_equal(rbo.Friction(0).moment(0.0, THETAS[0], OMEGAS[0]), np.zeros(3))
    assert load.potential_energy(THETAS[0]) == 0.0
    with pytest.raises(ValueError, match="parameter b must be >= 0"):
        rbo.Friction(-0.1)
    with pytest.raises(ValueError, match="omega must have shape"):
        load.moment(0.0, THETAS[0], np.zeros(2))


def test_potential_load_4_52():
    """−Zᵀ·dV/dθ (4.52) with a hand-derived gradient; potential_energy is V."""
    a, kappa = np.array([0.4, 0.1, -0.7]), 1.9

    def V(th):
        return 0.5 * kappa * jnp.dot(a, th) ** 2 + jnp.dot(th, th) ** 2

    load = rbo.PotentialLoad(V)
    for th, om in zip(THETAS, OMEGAS):
        dV = kappa * (a @ th) * a + 4 * (th @ th) * th
        got = moment(load, 0.0, th, om)
        np.testing.assert_allclose(got, -np_Z(th).T @ dV, rtol=1e-12)
        np.testing.assert_array_equal(got, eqx.filter_jit(rbo.potential_moment)(V, th))
        np.testing.assert_allclose(load.potential_energy(th), V(th), rtol=1e-15)
    # A foundation used as the potential V: its moment is (4.51).
    c, d = 0.8, 1.4
    qload = rbo.PotentialLoad(rbo.QuadraticFoundation(c, d, K))
    for th in THETAS:
        expected = -c * th - (d - c) * (K @ th) * np_Z(th).T @ K
        np.testing.assert_allclose(moment(qload, 0.0, th, th), expected, rtol=1e-12, atol=1e-13)
        x = K @ th
        np.testing.assert_allclose(
            qload.potential_energy(th), 0.5 * c * (th @ th - x**2) + 0.5 * d * x**2, rtol=1e-13
        )


def test_callable_load_time_dependent_forcing():
    nu = 2.3

    def forcing(t, theta, omega):
        return jnp.sin(nu * t) * jnp.asarray(K) - 0.1 * omega

    load = rbo.as_load(forcing)
    assert isinstance(load, rbo.CallableLoad)
    for t in (0.0, 0.4, 1.7):
        np.testing.assert_allclose(
            moment(load, t, THETAS[0], OMEGAS[0]),
            np.sin(nu * t) * K - 0.1 * OMEGAS[0],
            rtol=1e-14,
            atol=1e-15,
        )
    assert load.potential_energy(THETAS[0]) == 0.0
    # Plain jax.jit works as well (the user function is part of the tree structure).
    jitted = jax.jit(lambda ld, t: ld.moment(t, THETAS[0], OMEGAS[0]))
    np.testing.assert_allclose(jitted(load, 0.4), np.sin(nu * 0.4) * K - 0.1 * OMEGAS[0])
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        rbo.CallableLoad(lambda t, th, om: jnp.zeros(2)).moment(0.0, THETAS[0], OMEGAS[0])


def test_as_load():
    dead = rbo.DeadMoment(1.0, K)
    assert rbo.as_load(dead) is dead
    with pytest.raises(TypeError, match="float"):
        rbo.as_load(3.0)
    with pytest.raises(TypeError, match="foundation"):
        rbo.as_load(rbo.QuadraticFoundation(1.0, 1.0, K))
    with pytest.raises(TypeError, match="fn must be callable"):
        rbo.CallableLoad("not callable")
    with pytest.raises(TypeError, match="V must be callable"):
        rbo.PotentialLoad(None)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: rbo.DeadMoment(np.nan, K), "parameter M must be finite"),
        (lambda: rbo.FollowerMoment(1.0, np.zeros(3)), "axis k must be a nonzero"),
        (lambda: rbo.FollowerMoment(np.ones(2), K), "parameter M must be a scalar"),
        (lambda: rbo.SemiTangentialMoment(1.0, K, 0.0, 0.0), "l1 and l2 must not both be zero"),
        (lambda: rbo.SemiTangentialMoment(1.0, K, np.inf, 1.0), "parameter l1 must be finite"),
        (lambda: rbo.Friction(np.inf), "parameter b must be >= 0"),
    ],
)
def test_construction_errors_name_the_parameter(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_construction_inside_transformations():
    th, om = THETAS[1], OMEGAS[1]
    Ms = jnp.array([-1.0, 0.0, 2.0])
    out = jax.jit(jax.vmap(lambda M: rbo.FollowerMoment(M, K).moment(0.0, th, om)))(Ms)
    np.testing.assert_allclose(out, np.asarray(Ms)[:, None] * (np_Q(th) @ K)[None, :], rtol=1e-13)
    ls = jnp.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    out = jax.jit(
        jax.vmap(lambda ll: rbo.SemiTangentialMoment(2.0, K, ll[0], ll[1]).moment(0.0, th, om))
    )(ls)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), [2.0, 2.0, 2.0], rtol=1e-13)

    # traced bad values are named by the parameter checks (which the solvers use)
    def failed(make):
        return [m for v, m in make().parameter_checks() if not bool(v)]

    checks = jax.jit(
        lambda ll: [v for v, _ in rbo.SemiTangentialMoment(2.0, K, ll[0], ll[1]).parameter_checks()]
    )(jnp.zeros(2))
    names = [m for _, m in rbo.SemiTangentialMoment(2.0, K).parameter_checks()]
    assert [m for m, v in zip(names, checks) if not bool(v)] == [
        "SemiTangentialMoment: the parameters l1 and l2 must not both be zero"
    ]
    assert failed(lambda: rbo.Friction(0.5)) == []
    flags = jax.jit(lambda b: [v for v, _ in rbo.Friction(b).parameter_checks()])(-1.0)
    assert not bool(flags[0])
    with pytest.raises(ValueError, match="parameter b must be >= 0"):
        rbo.Friction(-1.0)


def test_parameter_and_state_gradients_match_finite_differences():
    """d/d(M, l1, l2, b, θ) of semi-tangential (4.75) + friction (4.84): jacrev = FD."""
    om = OMEGAS[2]

    @jax.jit
    def fn(p):  # p = (M, l1, l2, b, θ)
        st = rbo.SemiTangentialMoment(p[0], K, p[1], p[2]).moment(0.0, p[4:], om)
        return st + rbo.Friction(p[3]).moment(0.0, p[4:], om)

    p0 = jnp.concatenate([jnp.array([1.3, 0.7, 1.1, 0.2]), jnp.asarray(THETAS[2])])
    J = jax.jit(jax.jacrev(fn))(p0)
    np.testing.assert_allclose(J, finite_difference_jacobian(fn, p0), rtol=1e-8, atol=1e-10)
    assert np.all(np.abs(np.asarray(J)).max(axis=0) > 1e-3)


@pytest.mark.parametrize(
    "make",
    [
        lambda: rbo.DeadMoment(0.7, K),
        lambda: rbo.FollowerMoment(-0.4, K),
        lambda: rbo.SemiTangentialMoment(0.5, K, 1.0, 0.6),
        lambda: rbo.Friction(0.3),
        lambda: rbo.PotentialLoad(lambda th: 0.5 * jnp.sum(th**2) + jnp.sin(th[0]) * th[2]),
        lambda: rbo.as_load(lambda t, th, w: jnp.array([jnp.cos(t), th[0], w[2]])),
    ],
    ids=["dead", "follower", "semi", "friction", "potential", "callable"],
)
def test_body_moment_is_the_world_moment_in_the_body_frame(make):
    """body_moment(t, θ, Ω, P) = Pᵀ·M_ex(t, θ, P·Ω), P = Q(θ) (4.3) with P given as a
    component-wise :class:`rbo_jax.Turn`: the right-hand side of (4.55), whether a load uses the
    default or its own body-frame form (follower: M k; friction: −bΩ; potential: −Z·dV/dθ through
    Zᵀ = P·Z (4.13); semi-tangential: γM(l1 Pᵀ·k + l2 k))."""
    load = make()
    for theta, Omega in zip(THETAS, OMEGAS):
        P = np_Q(theta)
        expected = P.T @ np.asarray(moment(load, 0.3, jnp.asarray(theta), jnp.asarray(P @ Omega)))
        turn = rbo.Turn(jnp.asarray(theta))
        got = load.body_moment(0.3, jnp.asarray(theta), jnp.asarray(Omega), turn)
        np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-13, atol=1e-14)


def test_body_potential_moment_4_13_4_23():
    """−Z·dU/dθ = Pᵀ·(−Zᵀ·dU/dθ) (4.23) by Zᵀ = P·Z (4.13), Z and P from NumPy/scipy."""
    U = rbo.BarrierFoundation(1.0, 2.0, 2.0, 1.5, K).energy
    for theta in THETAS:
        grad = np.asarray(jax.grad(U)(jnp.asarray(theta)))
        got = np.asarray(rbo.body_potential_moment(U, jnp.asarray(theta)))
        np.testing.assert_allclose(got, -np_Z(theta) @ grad, rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(
            got, np_Q(theta).T @ (-np_Z(theta).T @ grad), rtol=1e-12, atol=1e-14
        )
