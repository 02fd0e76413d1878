"""The equations of motion of :class:`RigidBodyOscillator`, eqs. (4.41)–(4.56).

The vector fields are checked against an independent NumPy transcription of the paper's
equations (written here from the text, with hand-derived gradients), and the left and right
forms against each other. No expected value is produced by the code under test.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rbo_jax as rbo
from rbo_jax.foundations import BarrierFoundation, QuadraticFoundation
from rbo_jax.inertia import principal_inertia, transversely_isotropic_inertia
from rbo_jax.kinematics import turn_tensor
from rbo_jax.loads import (
    CallableLoad,
    DeadMoment,
    FollowerMoment,
    Friction,
    PotentialLoad,
)
from rbo_jax.model import RigidBodyOscillator

# ---------------------------------------------------------------------------------------------
# Independent NumPy transcription of the paper.
# ---------------------------------------------------------------------------------------------


def np_skew(a):
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def np_Q(theta):
    """Turn-tensor (4.3)-(4.4): E + sinθ/θ R + (1-cosθ)/θ² R², R = θ×E."""
    th = np.linalg.norm(theta)
    R = np_skew(theta)
    return np.eye(3) + np.sin(th) / th * R + (1 - np.cos(th)) / th**2 * R @ R


def np_Z(theta):
    """Integrating tensor (4.11)."""
    th = np.linalg.norm(theta)
    g = th * np.sin(th) / (2 * (1 - np.cos(th)))
    R = np_skew(theta)
    return np.eye(3) - 0.5 * R + (1 - g) / th**2 * R @ R


def np_theta_dot_right(theta, Omega):
    """Explicit form (4.16)/(4.56): Ω + ½θ×Ω + (1-g)/θ² θ×(θ×Ω)."""
    th = np.linalg.norm(theta)
    g = th * np.sin(th) / (2 * (1 - np.cos(th)))
    return (
        Omega
        + 0.5 * np.cross(theta, Omega)
        + (1 - g) / th**2 * np.cross(theta, np.cross(theta, Omega))
    )


# Parameters of the test model.
C, D, ALPHA, BETA = 1.3, 2.1, 2.5, 1.9
K_F = np.array([0.2, -0.3, 1.0]) / np.linalg.norm([0.2, -0.3, 1.0])  # foundation axis
M_DEAD, K_DEAD = 0.4, np.array([1.0, 0.5, -0.2]) / np.linalg.norm([1.0, 0.5, -0.2])
M_FOL, K_FOL = -0.7, np.array([0.0, 1.0, 0.3]) / np.linalg.norm([0.0, 1.0, 0.3])
B_FRICTION = 0.15
V_STIFF, E_V = 0.35, np.array([0.6, 0.0, 0.8])  # V = ½ v (e·θ)², a PotentialLoad (4.52)
F_AMP = np.array([0.3, -0.2, 0.1])
MOMENTS = np.array([1.0, 1.4, 0.7])
AXES = np_Q(np.array([0.4, -0.7, 0.2])).T  # rows: principal axes d_i


def np_inertia():
    """(4.39): A = Σ A_i d_i ⊗ d_i."""
    return sum(m * np.outer(d, d) for m, d in zip(MOMENTS, AXES))


def np_barrier_energy(theta):
    """U of (4.49) as printed."""
    x = K_F @ theta
    t = theta @ theta
    return 0.5 * ALPHA**2 * C * t / (ALPHA**2 - t + x**2) + 0.5 * BETA**2 * (D - C) * x**2 / (
        BETA**2 - x**2
    )


def np_barrier_gradient(theta):
    """dU/dθ of (4.49) by hand: U = ½c t/a + ½(d-c)x²/b, t = θ², x = k·θ,
    a = 1 - (t - x²)/α², b = 1 - x²/β²."""
    x = K_F @ theta
    t = theta @ theta
    a = 1 - (t - x**2) / ALPHA**2
    b = 1 - x**2 / BETA**2
    dU_dt = 0.5 * C / a + 0.5 * C * t / (a**2 * ALPHA**2)
    dU_dx = -C * t * x / (a**2 * ALPHA**2) + (D - C) * x / b**2
    return 2 * dU_dt * theta + dU_dx * K_F


def np_V(theta):
    return 0.5 * V_STIFF * (E_V @ theta) ** 2


def np_V_gradient(theta):
    return V_STIFF * (E_V @ theta) * E_V


def np_callable_moment(t, theta, omega):
    return np.sin(2 * t) * F_AMP + 0.05 * np.cross(theta, omega)


def np_vector_field(t, theta, Omega):
    """(4.55)-(4.56): A·Ω̇ + Ω×A·Ω + Z·d(U+V)/dθ = Pᵀ·M_ex, θ̇ = Zᵀ·Ω (explicit (4.56))."""
    A = np_inertia()
    P = np_Q(theta)
    omega = P @ Omega
    M_ex = (
        M_DEAD * K_DEAD
        + M_FOL * P @ K_FOL
        - B_FRICTION * omega
        + np_callable_moment(t, theta, omega)
    )
    dUV = np_barrier_gradient(theta) + np_V_gradient(theta)
    rhs = P.T @ M_ex - np_Z(theta) @ dUV - np.cross(Omega, A @ Omega)
    return np_theta_dot_right(theta, Omega), np.linalg.solve(A, rhs)


# ---------------------------------------------------------------------------------------------
# The model under test.
# ---------------------------------------------------------------------------------------------


def _V(theta):
    return 0.5 * V_STIFF * (jnp.asarray(E_V) @ theta) ** 2


def _callable_moment(t, theta, omega):
    return jnp.sin(2 * t) * jnp.asarray(F_AMP) + 0.05 * jnp.cross(theta, omega)


@pytest.fixture(scope="module")
def model():
    return RigidBodyOscillator(
        principal_inertia(jnp.asarray(MOMENTS), jnp.asarray(AXES)),
        BarrierFoundation(C, D, ALPHA, BETA, jnp.asarray(K_F) * 3.0),  # k normalised on input
        [
            DeadMoment(M_DEAD, jnp.asarray(K_DEAD)),
            FollowerMoment(M_FOL, jnp.asarray(K_FOL)),
            Friction(B_FRICTION),
            PotentialLoad(_V),
            CallableLoad(_callable_moment),
        ],
    )


def _random_states(n, seed=0):
    """States inside the barriers, |θ| ∈ [0.05, 1.3], away from the singular spheres."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    theta = axes * rng.uniform(0.05, 1.3, size=(n, 1))
    Omega = rng.normal(size=(n, 3))
    t = rng.uniform(-3.0, 3.0, size=n)
    return t, theta, Omega


N_STATES = 8


@pytest.fixture(scope="module")
def states():
    return _random_states(N_STATES)


def test_inertia_is_4_39(model):
    np.testing.assert_allclose(np.asarray(model.inertia), np_inertia(), rtol=1e-14, atol=1e-14)


def test_vector_field_matches_numpy_transcription_4_55_4_56(model, states):
    """The right form (4.55)–(4.56) for a general SPD inertia (rotated principal axes), the barrier
    foundation (4.49), a potential load (4.52) and dead + follower + friction + time-dependent
    callable moments, against the NumPy transcription at random states."""
    t, theta, Omega = states
    f = jax.jit(jax.vmap(lambda t, th, Om: model.vector_field(t, (th, Om))))
    theta_dot, Omega_dot = f(jnp.asarray(t), jnp.asarray(theta), jnp.asarray(Omega))
    for i in range(N_STATES):
        ref_theta_dot, ref_Omega_dot = np_vector_field(t[i], theta[i], Omega[i])
        np.testing.assert_allclose(theta_dot[i], ref_theta_dot, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(Omega_dot[i], ref_Omega_dot, rtol=1e-10, atol=1e-11)
    # the loads are not negligible at these states, so the comparison is sensitive to them
    P = [np_Q(th) for th in theta]
    omega = [p @ Om for p, Om in zip(P, Omega)]
    loads = [
        M_DEAD * K_DEAD + M_FOL * p @ K_FOL - B_FRICTION * w + np_callable_moment(ti, th, w)
        for ti, th, p, w in zip(t, theta, P, omega)
    ]
    assert np.min(np.linalg.norm(loads, axis=1)) > 1e-2


def test_left_form_is_derivative_of_kinetic_moment_4_53_4_54(model, states):
    """Along the right-form flow, d/dt L with L = P·A·Ω (4.44) (by jax.jvp) equals the L̇ of the
    left form (4.53), and both forms give the same θ̇ ((4.13): Z·ω = Zᵀ·Ω, (4.54) vs (4.56))."""
    t, theta, Omega = states
    A = model.inertia

    def L_of(th, Om):
        return turn_tensor(th) @ (A @ Om)

    @jax.jit
    @jax.vmap
    def both(t, th, Om):
        rates = model.vector_field(t, (th, Om))
        L, L_dot = jax.jvp(L_of, (th, Om), rates)
        theta_dot_left, L_dot_left = model.left_vector_field(t, (th, L))
        return rates[0], theta_dot_left, L_dot, L_dot_left

    theta_dot, theta_dot_left, L_dot, L_dot_left = both(
        jnp.asarray(t), jnp.asarray(theta), jnp.asarray(Omega)
    )
    np.testing.assert_allclose(theta_dot_left, theta_dot, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(L_dot_left, L_dot, rtol=1e-10, atol=1e-11)


def test_kinetic_moment_4_43_4_44_and_inverse(model, states):
    """L = P·A·Ω (4.44) = P·A·Pᵀ·ω (4.43); Omega_from_kinetic_moment inverts it; ω = P·Ω."""
    _, theta, Omega = states
    A = np_inertia()
    for th, Om in zip(theta, Omega):
        P = np_Q(th)
        L = np.asarray(model.kinetic_moment(jnp.asarray(th), jnp.asarray(Om)))
        np.testing.assert_allclose(L, P @ A @ Om, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(L, P @ A @ P.T @ (P @ Om), rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(
            model.omega(jnp.asarray(th), jnp.asarray(Om)), P @ Om, rtol=1e-13, atol=1e-13
        )
        np.testing.assert_allclose(
            model.Omega_from_kinetic_moment(jnp.asarray(th), jnp.asarray(L)),
            Om,
            rtol=1e-12,
            atol=1e-12,
        )


def test_Omega_from_rate_inverts_Z_transpose_4_19(model, states):
    """Ω = Z⁻ᵀ·θ̇ (4.19) undoes θ̇ = Zᵀ·Ω (4.14), with Z from the NumPy transcription of (4.11)."""
    _, theta, Omega = states
    for th, Om in zip(theta, Omega):
        theta_dot = np_Z(th).T @ Om
        np.testing.assert_allclose(
            model.Omega_from_rate(jnp.asarray(th), jnp.asarray(theta_dot)),
            Om,
            rtol=1e-12,
            atol=1e-12,
        )


def test_inertia_world_4_41(model, states):
    """A^(t) = P·A·Pᵀ (4.41) for the general inertia."""
    _, theta, _ = states
    A = np_inertia()
    for th in theta:
        P = np_Q(th)
        np.testing.assert_allclose(
            model.inertia_world(jnp.asarray(th)), P @ A @ P.T, rtol=1e-13, atol=1e-13
        )


def test_transversely_isotropic_inertia_world_4_42_4_43_4_45(states):
    """For A = A1(E − k⊗k) + A3 k⊗k (4.40): A^(t) = A1(E − k'⊗k') + A3 k'⊗k' (4.42) with
    k' = P·k; L = A1 ω + (A3 − A1)(k'·ω) k' (4.43); k'·ω = k·Ω (4.45)."""
    A1, A3 = 1.2, 0.5
    k = np.array([0.3, 0.4, -0.5]) / np.linalg.norm([0.3, 0.4, -0.5])
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, jnp.asarray(k)), QuadraticFoundation(1.0, 2.0, k)
    )
    _, theta, Omega = states
    for th, Om in zip(theta, Omega):
        kp = np_Q(th) @ k
        omega = np_Q(th) @ Om
        expected = A1 * (np.eye(3) - np.outer(kp, kp)) + A3 * np.outer(kp, kp)
        np.testing.assert_allclose(
            model.inertia_world(jnp.asarray(th)), expected, rtol=1e-13, atol=1e-13
        )
        L = model.kinetic_moment(jnp.asarray(th), jnp.asarray(Om))
        np.testing.assert_allclose(
            L, A1 * omega + (A3 - A1) * (kp @ omega) * kp, rtol=1e-13, atol=1e-13
        )
        np.testing.assert_allclose(kp @ omega, k @ Om, rtol=1e-13, atol=1e-13)


def test_energy_is_K_plus_U_plus_V(model, states):
    """K = ½Ω·A·Ω, U of (4.49), V of the potential load (4.52); energy = K + U + V."""
    _, theta, Omega = states
    A = np_inertia()
    for th, Om in zip(theta, Omega):
        K = 0.5 * Om @ A @ Om
        U = np_barrier_energy(th)
        V = np_V(th)
        th_j, Om_j = jnp.asarray(th), jnp.asarray(Om)
        np.testing.assert_allclose(model.kinetic_energy(Om_j), K, rtol=1e-13)
        np.testing.assert_allclose(model.potential_energy(th_j), U + V, rtol=1e-13)
        np.testing.assert_allclose(model.energy(th_j, Om_j), K + U + V, rtol=1e-13)


def test_domain_margin_of_barrier_foundation(model):
    """> 0 inside the barriers of (4.49), ≤ 0 beyond the bending barrier θ_⊥ = α."""
    perp = np.cross(K_F, [1.0, 0.0, 0.0])
    perp /= np.linalg.norm(perp)
    assert float(model.domain_margin(jnp.asarray(0.9 * ALPHA * perp))) > 0
    assert float(model.domain_margin(jnp.asarray(1.1 * ALPHA * perp))) <= 0


# ---------------------------------------------------------------------------------------------
# Construction.
# ---------------------------------------------------------------------------------------------

K = jnp.array([0.0, 0.0, 1.0])
THETA = jnp.array([0.4, -0.2, 0.7])
OMEGA = jnp.array([0.3, 1.1, -0.5])


def test_built_inside_vmap_over_c():
    """The model may be built inside jax.vmap (traced stiffness), and gives per-c results equal to
    models built one by one."""
    cs = jnp.array([0.5, 1.0, 2.0])
    A = transversely_isotropic_inertia(1.0, 0.6, K)

    def rates(c):
        model = RigidBodyOscillator(A, QuadraticFoundation(c, 2.0, K), Friction(0.1))
        return model.vector_field(0.0, (THETA, OMEGA))

    batched = jax.jit(jax.vmap(rates))(cs)
    single_rates = jax.jit(rates)
    for i, c in enumerate(cs):
        single = single_rates(c)
        np.testing.assert_allclose(batched[0][i], single[0], rtol=1e-14)
        np.testing.assert_allclose(batched[1][i], single[1], rtol=1e-14)
    assert np.ptp(np.asarray(batched[1])[:, 0]) > 1e-3  # c does enter


def _dead(t, theta, omega):
    return 0.4 * jnp.array([1.0, 0.0, 0.0])


@pytest.mark.parametrize("form", ["single", "list", "tuple", "callable", "mixed"])
def test_loads_single_sequence_or_callable(form):
    """Loads may be one load, a list/tuple, a plain callable f(t, θ, ω) (wrapped in CallableLoad)
    or a mix; they add up."""
    A = transversely_isotropic_inertia(1.0, 0.6, K)
    F = QuadraticFoundation(1.0, 2.0, K)
    dead = DeadMoment(0.4, jnp.array([1.0, 0.0, 0.0]))
    loads = {
        "single": dead,
        "list": [dead],
        "tuple": (dead,),
        "callable": _dead,
        "mixed": [DeadMoment(0.1, jnp.array([1.0, 0.0, 0.0])), Friction(0.0), _dead],
    }[form]
    model = RigidBodyOscillator(A, F, loads)
    assert isinstance(model.loads, tuple)
    if form == "callable":
        assert len(model.loads) == 1 and isinstance(model.loads[0], CallableLoad)
    expected = 0.5 if form == "mixed" else 0.4
    bare = RigidBodyOscillator(A, F)
    diff = model.world_moment(0.0, THETA, OMEGA) - bare.world_moment(0.0, THETA, OMEGA)
    np.testing.assert_allclose(diff, [expected, 0.0, 0.0], atol=1e-15)


@pytest.mark.parametrize(
    "foundation",
    [lambda theta: theta @ theta, Friction(0.1), None, 1.0],
    ids=["function", "load", "none", "number"],
)
def test_non_foundation_is_refused(foundation):
    with pytest.raises(TypeError, match="foundation must be an rbo_jax foundation"):
        RigidBodyOscillator(jnp.eye(3), foundation)


def test_foundation_as_load_is_refused():
    F = QuadraticFoundation(1.0, 2.0, K)
    with pytest.raises(TypeError, match="PotentialLoad"):
        RigidBodyOscillator(jnp.eye(3), F, [F])


@pytest.mark.parametrize(
    "A, match",
    [
        (jnp.diag(jnp.array([1.0, 1.0, -1.0])), "positive definite"),
        (jnp.diag(jnp.array([1.0, 0.0, 1.0])), "positive definite"),
        (jnp.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "symmetric"),
        (jnp.diag(jnp.array([1.0, jnp.nan, 1.0])), "finite"),
    ],
    ids=["indefinite", "singular", "asymmetric", "nan"],
)
def test_inertia_not_spd_is_refused(A, match):
    with pytest.raises(ValueError, match=match):
        RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))


@pytest.mark.slow  # cost: ~12 s of compilation for one error
def test_inertia_not_spd_is_refused_inside_jit():
    """A traced inertia is checked by the solvers (RigidBodyOscillator.parameter_status): with
    throw=True simulate raises the message, with throw=False the point is invalid_parameters with
    NaN samples and the rest of the batch completes."""

    def final(a3, throw):
        A = jnp.diag(jnp.stack([jnp.ones(()), jnp.ones(()), a3]))
        model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
        traj = rbo.simulate(model, THETA, OMEGA, jnp.array([0.0, 0.5]), throw=throw)
        return traj.theta[-1], traj.status

    good = jax.jit(lambda a: final(a, True))(jnp.asarray(0.5))
    assert np.all(np.isfinite(np.asarray(good[0])))
    with pytest.raises(Exception, match="positive definite"):
        jax.block_until_ready(jax.jit(lambda a: final(a, True))(jnp.asarray(-0.5)))
    theta, status = jax.jit(jax.vmap(lambda a: final(a, False)))(jnp.array([0.5, -0.5]))
    assert np.all(np.isfinite(np.asarray(theta[0]))) and np.all(np.isnan(np.asarray(theta[1])))
    from rbo_jax._enumeration import code

    assert list(np.asarray(code(status))) == [
        int(code(rbo.SolveStatus.successful)),
        int(code(rbo.SolveStatus.invalid_parameters)),
    ]
    ok, which, messages = RigidBodyOscillator(
        jnp.diag(jnp.array([1.0, 1.0, 0.5])), QuadraticFoundation(1.0, 2.0, K)
    ).parameter_status()
    assert bool(ok) and any("positive definite" in m for m in messages)
