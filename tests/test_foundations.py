"""Tests of rbo_jax.foundations: energies (4.24), (4.49), (4.50), potential moment (4.21)-(4.26),
(4.46)-(4.51) and the transversely isotropic invariance (4.130).

Reference values are computed independently of the code under test: closed forms of the paper
written out here in NumPy (the turn-tensor (4.3) by Rodrigues' formula, Z (4.11), Z^{-1} (4.20)),
hand-derived partial derivatives, mpmath numerical derivatives and finite differences.
"""

import equinox as eqx
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
from helpers import finite_difference_jacobian
from hypothesis import given
from scipy.spatial.transform import Rotation

import rbo_jax as rbo

RNG = np.random.default_rng(20240611)


# --------------------------------------------------------------------------------------------
# Independent NumPy references.
# --------------------------------------------------------------------------------------------


def np_skew(a):
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def np_Q(theta):
    """Turn-tensor Q(θ) = exp(θ×E) (4.3), from scipy's rotation vectors."""
    return Rotation.from_rotvec(np.asarray(theta, dtype=float)).as_matrix()


def np_Z(theta):
    """Integrating tensor (4.11), E − R/2 + (1 − g)/θ² R², g = θ sinθ / (2(1 − cosθ))."""
    theta = np.asarray(theta, dtype=float)
    th = np.linalg.norm(theta)
    R = np_skew(theta)
    g = th * np.sin(th) / (2 * (1 - np.cos(th)))
    return np.eye(3) - 0.5 * R + (1 - g) / th**2 * R @ R


def np_Zinv(theta):
    """Inverse integrating tensor (4.20)."""
    theta = np.asarray(theta, dtype=float)
    th = np.linalg.norm(theta)
    R = np_skew(theta)
    return np.eye(3) + (1 - np.cos(th)) / th**2 * R + (th - np.sin(th)) / th**3 * R @ R


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def random_unit(rng=RNG):
    return unit(rng.normal(size=3))


def random_thetas(n, max_angle=2.5, rng=RNG):
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return axes * rng.uniform(0.05, max_angle, size=(n, 1))


def np_quadratic_U(theta, c, d, k):
    """(4.50)."""
    x = k @ theta
    return 0.5 * c * (theta @ theta - x**2) + 0.5 * d * x**2


def barrier_U_of(t, x, c, d, alpha, beta):
    """(4.49) as printed, a function of θ² = t and k·θ = x (works with mpmath numbers)."""
    a2, b2 = alpha**2, beta**2
    return 0.5 * a2 * c * t / (a2 - t + x**2) + 0.5 * b2 * (d - c) * x**2 / (b2 - x**2)


# Eager op-by-op dispatch is slow; compile once per foundation type.
PM = eqx.filter_jit(rbo.potential_moment)

K = unit([0.3, -0.4, 0.85])
C_, D_, ALPHA, BETA = 1.3, 2.1, 2.2, 1.7


def _barrier_thetas(n):
    """Turn-vectors well inside the domain of BarrierFoundation(C_, D_, ALPHA, BETA, K)."""
    out = []
    while len(out) < n:
        th = random_thetas(1, max_angle=2.0)[0]
        x = K @ th
        if th @ th - x**2 < 0.8 * ALPHA**2 and x**2 < 0.8 * BETA**2:
            out.append(th)
    return np.array(out)


THETAS = random_thetas(12)
BARRIER_THETAS = _barrier_thetas(12)


# User-supplied F(x, t), x = k·θ, t = θ², with hand-derived partial derivatives (F_x, F_t).
TI_FUNCTIONS = {
    "polynomial": (
        lambda x, t: 0.5 * t + 0.3 * x**2 + 0.1 * x * t**2,
        lambda x, t: (0.6 * x + 0.1 * t**2, 0.5 + 0.2 * x * t),
    ),
    "transcendental": (
        lambda x, t: jnp.exp(0.2 * x) * jnp.log1p(t) + jnp.sin(x),
        lambda x, t: (0.2 * np.exp(0.2 * x) * np.log1p(t) + np.cos(x), np.exp(0.2 * x) / (1 + t)),
    ),
    "odd_in_x": (
        lambda x, t: x * t + x**3,
        lambda x, t: (t + 3 * x**2, x),
    ),
}


def all_foundations():
    F = TI_FUNCTIONS["transcendental"][0]
    return {
        "quadratic": rbo.QuadraticFoundation(C_, D_, K),
        "barrier": rbo.BarrierFoundation(C_, D_, ALPHA, BETA, K),
        "transversely_isotropic": rbo.TransverselyIsotropicFoundation(F, K),
        "isotropic": rbo.IsotropicFoundation(lambda t: 0.7 * t + 0.05 * t**2),
        "sum": rbo.QuadraticFoundation(C_, D_, K) + rbo.BarrierFoundation(C_, D_, ALPHA, BETA, K),
    }


FOUNDATIONS = all_foundations()
TI_NAMES = ["quadratic", "barrier", "transversely_isotropic", "sum"]


# --------------------------------------------------------------------------------------------
# Energies.
# --------------------------------------------------------------------------------------------


def test_quadratic_energy_4_50_and_axis_normalisation():
    k_raw = np.array([0.0, 3.0, 4.0])
    f = rbo.QuadraticFoundation(C_, D_, k_raw)
    np.testing.assert_allclose(f.k, [0.0, 0.6, 0.8], rtol=0, atol=1e-15)
    assert f.c.dtype == jnp.float64 and f.k.dtype == jnp.float64
    for th in THETAS:
        np.testing.assert_allclose(
            f.energy(th), np_quadratic_U(th, C_, D_, unit(k_raw)), rtol=1e-13
        )
        np.testing.assert_allclose(f(th), f.energy(th), rtol=0, atol=0)


def test_barrier_energy_4_49_as_printed():
    f = FOUNDATIONS["barrier"]
    for th in BARRIER_THETAS:
        expected = barrier_U_of(th @ th, K @ th, C_, D_, ALPHA, BETA)
        np.testing.assert_allclose(f.energy(th), expected, rtol=1e-13)


def test_isotropic_and_transversely_isotropic_energy():
    F = TI_FUNCTIONS["polynomial"][0]
    ti = rbo.TransverselyIsotropicFoundation(F, 2.0 * K)  # argument order (k·θ, θ²), (4.24)
    iso = rbo.IsotropicFoundation(lambda t: jnp.cos(t))
    for th in THETAS[:4]:
        np.testing.assert_allclose(ti.energy(th), F(K @ th, th @ th), rtol=1e-13)
        np.testing.assert_allclose(iso(th), np.cos(th @ th), rtol=1e-13)


# --------------------------------------------------------------------------------------------
# Potential moment: closed forms (4.25), (4.47)-(4.48), (4.51) and the isotropic case.
# --------------------------------------------------------------------------------------------


def test_quadratic_moment_4_51():
    f = FOUNDATIONS["quadratic"]
    pm = PM
    for th in THETAS:
        expected = -C_ * th - (D_ - C_) * (K @ th) * np_Z(th).T @ K
        np.testing.assert_allclose(pm(f, th), expected, rtol=1e-12, atol=1e-13)
        C, D = rbo.transverse_coefficients(f, th)
        np.testing.assert_allclose([C, D], [C_, (D_ - C_) * (K @ th)], rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("name", sorted(TI_FUNCTIONS))
def test_transversely_isotropic_moment_4_25(name):
    F, dF = TI_FUNCTIONS[name]
    f = rbo.TransverselyIsotropicFoundation(F, K)
    pm = PM
    for th in THETAS:
        Fx, Ft = dF(K @ th, th @ th)
        expected = -2 * Ft * th - Fx * np_Z(th).T @ K  # (4.25)
        np.testing.assert_allclose(pm(f, th), expected, rtol=1e-12, atol=1e-13)
        C, D = rbo.transverse_coefficients(f, th)  # (4.48): C = 2 ∂F/∂θ², D = ∂F/∂(k·θ)
        np.testing.assert_allclose([C, D], [2 * Ft, Fx], rtol=1e-13, atol=1e-14)


def _barrier_C_D_mpmath(th):
    """C = 2 ∂U/∂(θ²), D = ∂U/∂(k·θ) of (4.48) for the printed (4.49), by mpmath differentiation."""
    with mpmath.workdps(40):
        t0, x0 = mpmath.mpf(float(th @ th)), mpmath.mpf(float(K @ th))
        alpha, beta = mpmath.mpf(ALPHA), mpmath.mpf(BETA)
        U = lambda t, x: barrier_U_of(t, x, C_, D_, alpha, beta)  # noqa: E731
        C = 2 * mpmath.diff(U, (t0, x0), (1, 0))
        D = mpmath.diff(U, (t0, x0), (0, 1))
        return float(C), float(D)


def test_barrier_moment_4_47_with_C_D_of_4_48():
    f = FOUNDATIONS["barrier"]
    pm = PM
    for th in BARRIER_THETAS[:6]:
        C, D = _barrier_C_D_mpmath(th)
        np.testing.assert_allclose(rbo.transverse_coefficients(f, th), [C, D], rtol=1e-12)
        expected = -C * th - D * np_Z(th).T @ K  # (4.47)
        np.testing.assert_allclose(pm(f, th), expected, rtol=1e-11, atol=1e-12)


def test_isotropic_moment():
    """U = F(θ²) ⇒ M = −2F'(θ²)θ (section 4.2.3)."""
    f = rbo.IsotropicFoundation(lambda t: jnp.sin(t) + 0.5 * t**2)
    for th in THETAS:
        t = th @ th
        np.testing.assert_allclose(PM(f, th), -2 * (np.cos(t) + t) * th, rtol=1e-12, atol=1e-13)
        C, D = rbo.transverse_coefficients(f, th)
        np.testing.assert_allclose([C, D], [2 * (np.cos(t) + t), 0.0], rtol=1e-13, atol=0)


def test_potential_moment_of_linear_potential():
    """U = C k·θ ⇒ M = −C(k + θ×k/2 + (1−g)/θ² θ×(θ×k)) (example after (4.23))."""
    Cc = 0.8
    U = lambda x: Cc * jnp.dot(K, x)  # noqa: E731
    for th in THETAS:
        g = np.linalg.norm(th) * np.sin(np.linalg.norm(th)) / (2 * (1 - np.cos(np.linalg.norm(th))))
        expected = -Cc * (
            K + 0.5 * np.cross(th, K) + (1 - g) / (th @ th) * np.cross(th, np.cross(th, K))
        )
        got = PM(U, th)
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-13)


def test_potential_moment_at_zero_is_finite_stiffness():
    """At θ = 0, M = 0 and dM/dθ = −(c(E − k⊗k) + d k⊗k) for (4.50) (Z(0) = E)."""
    f = FOUNDATIONS["quadratic"]
    zero = jnp.zeros(3)
    np.testing.assert_array_equal(PM(f, zero), np.zeros(3))
    expected = -(C_ * (np.eye(3) - np.outer(K, K)) + D_ * np.outer(K, K))
    J = jax.jit(jax.jacrev(lambda th: rbo.potential_moment(f, th)))(zero)  # reverse mode: NaN-prone
    np.testing.assert_allclose(J, expected, rtol=1e-13, atol=1e-15)


# --------------------------------------------------------------------------------------------
# Properties (4.21), (4.26), (4.130).
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", TI_NAMES)
def test_property_4_26_transversely_isotropic(name):
    """(k − k')·M = 0, k' = Q(θ)·k, for every transversely isotropic U (4.26)."""
    f = FOUNDATIONS[name]
    thetas = BARRIER_THETAS if name in ("barrier", "sum") else THETAS
    moments = jax.jit(jax.vmap(lambda th: rbo.potential_moment(f, th)))(thetas)
    for th, M in zip(thetas, np.asarray(moments)):
        assert np.linalg.norm(M) > 1e-3
        k_prime = np_Q(th) @ K
        assert abs((K - k_prime) @ M) < 1e-12 * np.linalg.norm(M)
    # Control: a generic direction a is not preserved unless the energy is isotropic.
    th, M = thetas[0], np.asarray(moments[0])
    a = unit([1.0, 0.2, -0.3])
    assert abs((a - np_Q(th) @ a) @ M) > 1e-6


def test_property_4_26_isotropic_any_vector():
    """Isotropic U: (a − Q(θ)·a)·M = 0 for every a (after (4.26))."""
    f = FOUNDATIONS["isotropic"]
    for th in THETAS:
        M = np.asarray(PM(f, th))
        for a in RNG.normal(size=(4, 3)):
            assert abs((a - np_Q(th) @ a) @ M) < 1e-12 * np.linalg.norm(M) * np.linalg.norm(a)


_energies = {name: jax.jit(lambda th, f=f: f.energy(th)) for name, f in FOUNDATIONS.items()}


@pytest.mark.parametrize("name", TI_NAMES)
@given(
    alpha=st.floats(-np.pi, np.pi),
    direction=st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1),
    angle=st.floats(0.0, 1.2),
)
def test_invariance_4_130(name, alpha, direction, angle):
    """U(Q(αk)·θ) = U(θ) for any α (4.130, Appendix D)."""
    th = unit(direction) * angle
    Q = np_Q(alpha * K)
    U = _energies[name]
    np.testing.assert_allclose(U(Q @ th), U(th), rtol=1e-12, atol=1e-14)


def test_invariance_4_130_fails_for_anisotropic_energy():
    """Control for the test above: an energy depending on θ₁ alone is not invariant about K."""
    U = lambda th: th[0] ** 2  # noqa: E731
    th = np.array([0.3, 0.5, -0.2])
    assert abs(U(np_Q(0.7 * K) @ th) - U(th)) > 1e-3


def _path(s):
    """A smooth curve θ(s) through generic turn-vectors (|θ| < 2 on s ∈ [0, 1])."""
    return (
        jnp.array([0.3, -0.2, 0.1])
        + s * jnp.array([0.5, 0.4, -0.3])
        + s**2 * jnp.array([-0.2, 0.3, 0.25])
    )


def _plain_U(th):
    return jnp.dot(th, th) * jnp.dot(K, th) + jnp.sin(th[0])


@pytest.mark.parametrize("name", sorted(FOUNDATIONS) + ["plain_function"])
def test_potential_property_4_21(name):
    """dU/ds = −M·ω along a path, ω = Z^{-1}·dθ/ds (4.21), (4.19)."""
    U = _plain_U if name == "plain_function" else FOUNDATIONS[name].energy

    @jax.jit
    def along_path(s):
        th, th_dot = jax.jvp(_path, (s,), (1.0,))
        _, dU_ds = jax.jvp(lambda s_: U(_path(s_)), (s,), (1.0,))
        return th, th_dot, dU_ds, rbo.potential_moment(U, th)

    for s in (0.0, 0.35, 0.8):
        th, th_dot, dU_ds, M = map(np.asarray, along_path(s))
        omega = np_Zinv(th) @ th_dot
        np.testing.assert_allclose(-(M @ omega), dU_ds, rtol=1e-12, atol=1e-13)
        assert abs(dU_ds) > 1e-4


# --------------------------------------------------------------------------------------------
# Barrier: limit (4.49) → (4.50), domain of definition.
# --------------------------------------------------------------------------------------------


def test_barrier_reduces_to_quadratic_4_50():
    q = FOUNDATIONS["quadratic"]
    th = THETAS[3]
    Uq, Mq = q.energy(th), PM(q, th)
    errors = []
    for scale in (1e2, 1e3, 1e4):
        b = rbo.BarrierFoundation(C_, D_, scale, 1.3 * scale, K)
        errors.append(abs(b.energy(th) - Uq))
        np.testing.assert_allclose(PM(b, th), Mq, rtol=30 / scale**2)
    # The error is O(1/α²), as for the printed (4.49); not O(1) (which a reading of (4.49)
    # with θ⊥² in the first numerator would give).
    assert 0.5e2 < errors[0] / errors[1] < 2e2 and 0.5e2 < errors[1] / errors[2] < 2e2
    b_inf = rbo.BarrierFoundation(C_, D_, np.inf, np.inf, K)
    np.testing.assert_allclose(b_inf.energy(th), Uq, rtol=1e-15)
    np.testing.assert_allclose(PM(b_inf, th), Mq, rtol=1e-14, atol=1e-15)
    # Parameter gradients stay finite with the barriers switched off (d/dalpha = d/dbeta = 0).
    grads = eqx.filter_jit(eqx.filter_grad(lambda f: jnp.sum(rbo.potential_moment(f, th))))(b_inf)
    np.testing.assert_array_equal([grads.alpha, grads.beta], [0.0, 0.0])
    np.testing.assert_allclose(grads.c, -np.sum(th - (K @ th) * np_Z(th).T @ K), rtol=1e-12)


def _perp_theta(norm):
    perp = unit(np.cross(K, [1.0, 0.0, 0.0]))
    return norm * perp


@pytest.mark.parametrize(
    "theta, expected_margin",
    [
        (0.5 * ALPHA * unit(np.cross(K, [1.0, 0.0, 0.0])), 0.75),
        (0.5 * BETA * K, 0.75),
        (np.zeros(3), 1.0),
    ],
)
def test_barrier_domain_margin_inside(theta, expected_margin):
    f = FOUNDATIONS["barrier"]
    np.testing.assert_allclose(f.domain_margin(theta), expected_margin, rtol=1e-14)
    assert np.isfinite(f(theta))
    assert np.all(np.isfinite(PM(f, theta)))


@pytest.mark.parametrize(
    "theta, expected_margin",
    [
        (1.5 * ALPHA * unit(np.cross(K, [1.0, 0.0, 0.0])), 1 - 1.5**2),  # bending barrier
        (1.2 * BETA * K, 1 - 1.2**2),  # torsion barrier
    ],
)
def test_barrier_domain_errors(theta, expected_margin):
    f = FOUNDATIONS["barrier"]
    np.testing.assert_allclose(f.domain_margin(theta), expected_margin, rtol=1e-13)
    assert np.isfinite(f.energy(theta))  # the raw formula does not check
    with pytest.raises(Exception, match="BarrierFoundation.*alpha.*beta"):
        f(theta)
    with pytest.raises(Exception, match="outside the domain"):
        jax.jit(lambda th: f(th))(theta)
    with pytest.raises(Exception, match="outside the domain"):
        rbo.potential_moment(f, theta)
    # Also a sum containing the barrier.
    with pytest.raises(Exception, match="SumFoundation.*BarrierFoundation"):
        (FOUNDATIONS["quadratic"] + f)(theta)


def test_domain_margin_everywhere_defined_and_sum():
    th = np.array([10.0, -3.0, 7.0])
    for name in ("quadratic", "transversely_isotropic", "isotropic"):
        assert FOUNDATIONS[name].domain_margin(th) == np.inf
    s = FOUNDATIONS["sum"]
    inside = BARRIER_THETAS[0]
    np.testing.assert_allclose(
        s.domain_margin(inside), FOUNDATIONS["barrier"].domain_margin(inside), rtol=0
    )
    assert s.domain_margin(th) < 0


# --------------------------------------------------------------------------------------------
# Sums.
# --------------------------------------------------------------------------------------------


def test_sum_foundation():
    q, b, i = FOUNDATIONS["quadratic"], FOUNDATIONS["barrier"], FOUNDATIONS["isotropic"]
    s = (q + b) + (i + q)
    assert isinstance(s, rbo.SumFoundation) and len(s.terms) == 4
    assert all(not isinstance(t, rbo.SumFoundation) for t in s.terms)
    th = BARRIER_THETAS[1]
    np.testing.assert_allclose(
        s.energy(th), 2 * q.energy(th) + b.energy(th) + i.energy(th), rtol=1e-14
    )
    expected = sum(np.asarray(PM(f, th)) for f in (q, b, i, q))
    np.testing.assert_allclose(PM(s, th), expected, rtol=1e-13, atol=1e-14)
    C, D = rbo.transverse_coefficients(s, th)
    np.testing.assert_allclose(
        -C * th - D * np_Z(th).T @ K, expected, rtol=1e-12, atol=1e-13
    )  # (4.47)
    with pytest.raises(TypeError):
        q + 1.0
    with pytest.raises(TypeError, match="AbstractFoundation"):
        rbo.SumFoundation((q, "not a foundation"))
    with pytest.raises(ValueError, match="at least one"):
        rbo.SumFoundation(())


def test_transverse_coefficients_refuses():
    q = FOUNDATIONS["quadratic"]
    other = rbo.QuadraticFoundation(C_, D_, [1.0, 0.0, 0.0])
    with pytest.raises(Exception, match="different axes"):
        rbo.transverse_coefficients(q + other, THETAS[0])

    class Custom(rbo.AbstractFoundation):
        def energy(self, theta):
            return jnp.sum(theta**4)

        def domain_margin(self, theta):
            return jnp.inf

    with pytest.raises(TypeError, match="Custom"):
        rbo.transverse_coefficients(Custom(), THETAS[0])
    # A user subclass still works everywhere else.
    th = THETAS[0]
    np.testing.assert_allclose(PM(Custom(), th), -np_Z(th).T @ (4 * th**3), rtol=1e-12)


# --------------------------------------------------------------------------------------------
# Construction: validation, transformations, no recompilation, parameter gradients.
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: rbo.QuadraticFoundation(-1.0, 1.0, K), r"QuadraticFoundation.*parameter c must"),
        (lambda: rbo.QuadraticFoundation(1.0, 0.0, K), r"parameter d must"),
        (lambda: rbo.QuadraticFoundation(np.nan, 1.0, K), r"parameter c must"),
        (lambda: rbo.QuadraticFoundation(1.0, 1.0, [0, 0, 0]), r"axis k must be a nonzero"),
        (lambda: rbo.QuadraticFoundation(1.0, 1.0, [1.0, 0.0]), r"axis k must have shape"),
        (lambda: rbo.QuadraticFoundation([1.0, 2.0], 1.0, K), r"parameter c must be a scalar"),
        (lambda: rbo.BarrierFoundation(1.0, 1.0, -2.0, 1.0, K), r"parameter alpha must"),
        (lambda: rbo.BarrierFoundation(1.0, 1.0, 2.0, 0.0, K), r"parameter beta must"),
        (lambda: rbo.BarrierFoundation(0.0, 1.0, 2.0, 1.0, K), r"parameter c must"),
        (lambda: rbo.TransverselyIsotropicFoundation(lambda x, t: t, [0.0] * 3), r"axis k"),
    ],
)
def test_construction_errors_name_the_parameter(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_construction_type_errors():
    with pytest.raises(TypeError, match="F must be callable"):
        rbo.IsotropicFoundation(3.0)
    with pytest.raises(TypeError, match="F must be callable"):
        rbo.TransverselyIsotropicFoundation(3.0, K)


def test_construction_inside_vmap_jit_grad():
    th = THETAS[2]
    cs = jnp.array([0.5, 1.0, 2.0])
    energies = jax.jit(jax.vmap(lambda c: rbo.QuadraticFoundation(c, 1.0, K).energy(th)))(cs)
    np.testing.assert_allclose(
        energies, [np_quadratic_U(th, c, 1.0, K) for c in np.asarray(cs)], rtol=1e-13
    )
    ks = jnp.array([[0.0, 0.0, 2.0], [0.0, 3.0, 0.0]])

    def moment_of_axis(k):
        return rbo.potential_moment(rbo.QuadraticFoundation(1.0, 2.0, k), th)

    Ms = jax.jit(jax.vmap(moment_of_axis))(ks)
    for k, M in zip(np.asarray(ks), np.asarray(Ms)):
        k = unit(k)
        np.testing.assert_allclose(M, -th - (k @ th) * np_Z(th).T @ k, rtol=1e-12, atol=1e-13)
    # d/dc of (4.50) is ½θ⊥².
    dU_dc = jax.jit(jax.grad(lambda c: rbo.QuadraticFoundation(c, 1.0, K).energy(th)))(1.0)
    np.testing.assert_allclose(dU_dc, 0.5 * (th @ th - (K @ th) ** 2), rtol=1e-13)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda c: rbo.QuadraticFoundation(c, 1.0, K), "parameter c must be > 0"),
        (lambda c: rbo.BarrierFoundation(1.0, 1.0, c, 1.0, K), "parameter alpha must be > 0"),
        (lambda c: rbo.QuadraticFoundation(1.0, 1.0, c * K), "axis k must be a nonzero"),
    ],
)
def test_traced_bad_parameters_are_named_by_the_checks(make, match):
    """A foundation built from traced values cannot be checked at construction; its
    parameter_checks() evaluate the same requirements (the solvers use them), per point."""

    def valid(c):
        return jnp.stack([v for v, _ in make(c).parameter_checks()])

    flags = np.asarray(jax.jit(jax.vmap(valid))(jnp.array([1.0, 0.0])))
    messages = [m for _, m in make(1.0).parameter_checks()]
    assert np.all(flags[0]) and not np.all(flags[1])
    assert any(match in m for m, ok in zip(messages, flags[1]) if not ok)
    with pytest.raises(ValueError, match=match):  # concrete: at construction
        make(0.0)


def test_no_recompilation_when_parameters_change():
    traces = []

    @eqx.filter_jit
    def moment(foundation, th):
        traces.append(None)
        return rbo.potential_moment(foundation.energy, th)

    th = THETAS[0]
    for c, d, alpha in [(1.0, 2.0, 3.0), (1.5, 0.7, 2.5), (2.0, 1.0, np.inf)]:
        moment(rbo.BarrierFoundation(c, d, alpha, 4.0, K), th)
        moment(rbo.QuadraticFoundation(c, d, [1.0, c, 0.0]), th)
    assert len(traces) == 2  # once per foundation type

    @jax.jit
    def energy(foundation, th):  # plain jax.jit too: all leaves are arrays
        traces.append(None)
        return foundation.energy(th)

    energy(rbo.QuadraticFoundation(1, 2, K), th)
    energy(rbo.QuadraticFoundation(3.0, 4.0, np.array([1.0, 0.0, 0.0])), th)
    assert len(traces) == 3


def test_parameter_gradients_match_finite_differences():
    """d(energy, moment)/d(c, d, alpha, beta) of (4.49): reverse mode = finite differences."""
    th = BARRIER_THETAS[4]

    def fn(p):
        f = rbo.BarrierFoundation(p[0], p[1], p[2], p[3], K)
        return jnp.concatenate([f.energy(th)[None], rbo.potential_moment(f.energy, th)])

    p0 = jnp.array([C_, D_, ALPHA, BETA])
    rev = jax.jit(jax.jacrev(fn))(p0)
    fd = finite_difference_jacobian(jax.jit(fn), p0)
    np.testing.assert_allclose(rev, fd, rtol=1e-8, atol=1e-10)
    assert np.all(np.abs(np.asarray(rev)[:, 2:]) > 1e-6)  # alpha and beta matter here


class _PowerLaw(eqx.Module):
    a: jax.Array
    p: jax.Array

    def __call__(self, t):
        return self.a * t**self.p


def test_module_valued_F_is_differentiable():
    """F as an equinox Module: its float leaves are parameters (U = a (θ²)^p)."""
    th = THETAS[1]
    f = rbo.IsotropicFoundation(_PowerLaw(jnp.asarray(0.7), jnp.asarray(1.5)))
    grads = eqx.filter_grad(lambda f_: f_.energy(th))(f)
    t = th @ th
    np.testing.assert_allclose(grads.F.a, t**1.5, rtol=1e-13)
    np.testing.assert_allclose(grads.F.p, 0.7 * t**1.5 * np.log(t), rtol=1e-12)
