"""Tests of :mod:`rbo_jax.kinematics`: the turn-vector kinematics of section 4.2, eqs. (4.1)-(4.20).

Every expected value comes from an independent source: a closed formula of the paper evaluated with
numpy, ``jax.scipy.linalg.expm``, ``scipy.spatial.transform.Rotation``, a Taylor polynomial, finite
differences, or a group identity. Accuracy against high-precision references (mpmath) is in
``test_kinematics_accuracy.py``.
"""

from __future__ import annotations

import functools
import itertools
import math
import re
import zlib

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import jax.scipy.linalg
import numpy as np
import pytest
from helpers import finite_difference_jacobian, random_rotation_vectors, tree_allclose
from hypothesis import given
from scipy.spatial.transform import Rotation

import rbo_jax as rbo
from rbo_jax import kinematics as kin

EPS = np.finfo(np.float64).eps
PI = math.pi
EYE = np.eye(3)

TRANSFORMS = {
    "value": lambda f: f,
    "jacfwd": jax.jacfwd,
    "jacrev": jax.jacrev,
    "hessian": jax.hessian,  # forward over reverse
    "hessian_ff": lambda f: jax.jacfwd(jax.jacfwd(f)),  # forward over forward: compiles faster
}


@functools.cache
def compiled(f, transform="value", vmap=False):
    """jit(transform(f)), optionally vmapped, cached so that each is compiled once per session:
    XLA compilation (of second derivatives above all) dominates the runtime of this file, so
    every test reuses these instead of calling functions eagerly or re-jitting them."""
    g = TRANSFORMS[transform](f)
    return jax.jit(jax.vmap(g) if vmap else g)


turn_tensor = compiled(rbo.turn_tensor)
turn_vector = compiled(rbo.turn_vector)
compose = compiled(rbo.compose)
composition_invariants = compiled(rbo.composition_invariants)
integrating_tensor = compiled(rbo.integrating_tensor)
integrating_tensor_inv = compiled(rbo.integrating_tensor_inv)
integrating_tensor_det = compiled(rbo.integrating_tensor_det)
distance_to_singularity = compiled(rbo.distance_to_singularity)
skew = compiled(rbo.skew)
vector_invariant = compiled(rbo.vector_invariant)
expm = compiled(jax.scipy.linalg.expm)

# --------------------------------------------------------------------------------------------
# Independent references and sample points.
# --------------------------------------------------------------------------------------------


def np_skew(a):
    """a×E as a matrix, written out independently of :func:`rbo_jax.skew`."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def levi_civita():
    e = np.zeros((3, 3, 3))
    for i, j, k in [(0, 1, 2), (1, 2, 0), (2, 0, 1)]:
        e[i, j, k], e[i, k, j] = 1.0, -1.0
    return e


# Generators of so(3): G[..., a] = e_a × E, i.e. G[i, j, a] = -ε_{aij} = -ε_{ija}.
GENERATORS = -levi_civita()
# d²/dθ_a dθ_b of R² = θ⊗θ − θ²E: δ_ia δ_jb + δ_ib δ_ja − 2 δ_ij δ_ab.
D2_R2 = (
    np.einsum("ia,jb->ijab", EYE, EYE)
    + np.einsum("ib,ja->ijab", EYE, EYE)
    - 2.0 * np.einsum("ij,ab->ijab", EYE, EYE)
)


def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def rodrigues_41(n, angle):
    """Q(θ n) by eq. (4.1): (1 − cos θ) n⊗n + cos θ E + sin θ n×E, θ of either sign."""
    n = unit(n)
    return (1 - np.cos(angle)) * np.outer(n, n) + np.cos(angle) * EYE + np.sin(angle) * np_skew(n)


def g_of(theta):
    """g = θ sin θ / (2(1 − cos θ)) = (θ/2) cot(θ/2) of eq. (4.11) (the second form has no
    cancellation at small θ)."""
    half = np.linalg.norm(theta) / 2
    return half / np.tan(half)


def principal(theta):
    """The principal turn-vector (angle reduced to (−π, π]) of a turn-vector."""
    th = np.linalg.norm(theta)
    reduced = th - 2 * PI * np.round(th / (2 * PI))
    return reduced / th * np.asarray(theta)


def random_axes(n, seed):
    """n uniformly random unit vectors (a fixed seed per call site: tests do not depend on
    the order in which they run)."""
    rng = np.random.default_rng(seed)
    return np.stack([unit(rng.normal(size=3)) for _ in range(n)])


GENERIC = np.array(random_rotation_vectors(jax.random.PRNGKey(0), 12, max_angle=3.0))
LARGE_ANGLES = np.array([3.5, 5.0, 2 * PI - 0.5, 7.0, 10.0, 20.0, 50.0])
LARGE = random_axes(len(LARGE_ANGLES), 1) * LARGE_ANGLES[:, None]
TINY_ANGLES = np.array([0.0, 1e-300, 1e-150, 1e-8, 1e-4])
TINY = random_axes(len(TINY_ANGLES), 2) * TINY_ANGLES[:, None]
NEAR_PI = random_axes(6, 3) * (PI + np.array([-1e-3, -1e-7, -1e-12, 1e-12, 1e-7, 1e-3]))[:, None]
SAMPLES = {"generic": GENERIC, "large": LARGE, "tiny": TINY, "near_pi": NEAR_PI}
ALL = np.concatenate(list(SAMPLES.values()))
DELTAS = [1e-3, 1e-6, 1e-9, 1e-12]


def assert_close(x, y, *, rtol=0.0, atol):
    np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol)


# --------------------------------------------------------------------------------------------
# Turn-tensor, eqs. (4.1)-(4.4), (4.8), (4.27).
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", SAMPLES)
def test_turn_tensor_orthogonal_eq_4_27(kind):
    """Q·Qᵀ = Qᵀ·Q = E and det Q = +1, eq. (4.27), for every θ (the angle is not reduced)."""
    for theta in SAMPLES[kind]:
        q = np.asarray(turn_tensor(theta))
        assert_close(q @ q.T, EYE, atol=4 * EPS * 3)
        assert_close(q.T @ q, EYE, atol=4 * EPS * 3)
        assert np.linalg.det(q) == pytest.approx(1.0, abs=1e-14)


@pytest.mark.parametrize("kind", SAMPLES)
def test_fixed_axis_eq_4_8(kind):
    """Q(θ)·θ = θ and R·θ = 0, R = θ×E, eq. (4.8)."""
    for theta in SAMPLES[kind]:
        scale = max(1.0, np.linalg.norm(theta))
        assert_close(turn_tensor(theta) @ theta, theta, atol=4 * EPS * scale)
        assert_close(skew(theta) @ theta, np.zeros(3), atol=4 * EPS * scale**2)


def test_skew_and_vector_invariant_eq_4_4():
    """(a×E)·b = a×b (4.4), and (a⊗b)_× = a×b, so (a×E)_× = −2a (convention of (4.7))."""
    a, b = np.random.default_rng(4).normal(size=(2, 3))
    assert_close(skew(a) @ b, np.cross(a, b), atol=1e-15)
    assert_close(skew(a), np_skew(a), atol=0)
    assert_close(vector_invariant(np.outer(a, b)), np.cross(a, b), atol=1e-15)
    assert_close(vector_invariant(skew(a)), -2 * a, atol=1e-15)
    assert_close(vector_invariant(np.outer(a, a)), np.zeros(3), atol=0)


@pytest.mark.parametrize("kind", ["generic", "large", "tiny", "near_pi"])
def test_turn_tensor_is_expm_eq_4_3(kind):
    """Q(θ) = exp(θ×E), eq. (4.3), against jax.scipy.linalg.expm."""
    for theta in SAMPLES[kind]:
        expected = expm(np_skew(theta))
        # expm's scaling and squaring loses accuracy with ‖R‖ (2.7e-13 at |θ| = 7, while Q(θ) is
        # within 3e-15 of an mpmath expm there): the tolerance is the reference's, not ours.
        scale = max(1.0, np.linalg.norm(theta)) ** 2
        assert_close(turn_tensor(theta), expected, atol=1e-14 * scale)


@pytest.mark.parametrize("angle", [-7.0, -PI, -1.0, -1e-3, 0.0, 1e-8, 0.5, 3.0, PI, 4.0, 12.0])
def test_turn_tensor_matches_rodrigues_eq_4_1(angle):
    """(4.3) with θ = θ n equals (4.1) with signed angle θ; also the action (4.2) on a vector and
    scipy's rotation matrix."""
    n = unit([0.3, -1.2, 0.7])
    Q = np.asarray(turn_tensor(angle * n))
    assert_close(Q, rodrigues_41(n, angle), atol=1e-15 * max(1, abs(angle)))
    assert_close(Q, Rotation.from_rotvec(angle * n).as_matrix(), atol=1e-14)
    a = np.array([0.4, 2.0, -1.0])
    a_turned = a @ n * n + np.cos(angle) * (a - a @ n * n) + np.sin(angle) * np.cross(n, a)  # (4.2)
    assert_close(Q @ a, a_turned, atol=1e-14)


# --------------------------------------------------------------------------------------------
# Turn-vector: inverse of (4.3), principal branch.
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["generic", "tiny"])
def test_turn_vector_inverts_turn_tensor_below_pi(kind):
    """turn_vector(Q(θ)) = θ for |θ| < π (inverse of (4.3)), to relative accuracy, tiny θ too."""
    for theta in SAMPLES[kind]:
        got = np.asarray(turn_vector(turn_tensor(theta)))
        assert np.all(np.abs(got - theta) <= 8 * EPS * np.linalg.norm(theta))


def test_turn_vector_principal_branch_above_pi():
    """For |θ| > π, turn_vector(Q(θ)) is the principal vector (|·| ≤ π, angle reduced mod 2π) with
    the same Q (4.3)."""
    for theta in LARGE:
        got = np.asarray(turn_vector(turn_tensor(theta)))
        assert np.linalg.norm(got) <= PI
        assert_close(got, principal(theta), atol=1e-15 * np.linalg.norm(theta) + 2e-15)
        assert_close(turn_tensor(got), turn_tensor(theta), atol=1e-14)


@pytest.mark.parametrize("delta", DELTAS)
@pytest.mark.parametrize("side", [-1, 1])
def test_turn_vector_near_pi(delta, side):
    """Accuracy near π: θ = (π ± δ) n gives the principal vector ±(π − δ) n (continuity of (4.3)'s
    inverse from the inside, the branch jump from the outside), Q(result) = Q(θ) to ~1e-15."""
    for n in random_axes(3, 5):
        theta = (PI + side * delta) * n
        Q = turn_tensor(theta)
        got = np.asarray(turn_vector(Q))
        assert np.linalg.norm(got) <= PI
        assert_close(turn_tensor(got), Q, atol=2e-15)
        assert_close(got, principal(theta), atol=2e-15)


def test_turn_vector_exactly_pi():
    """At |θ| = π either ±θ may be returned; both have the same Q (4.3) and modulus π."""
    axes = np.concatenate([random_axes(4, 6), EYE, unit([1, 1, 0])[None], unit([1, -1, 1])[None]])
    for n in axes:
        theta = PI * n
        Q = turn_tensor(theta)
        got = np.asarray(turn_vector(Q))
        assert np.linalg.norm(got) <= PI * (1 + 4 * EPS)
        assert_close(turn_tensor(got), Q, atol=2e-15)
        assert min(np.abs(got - theta).max(), np.abs(got + theta).max()) <= 4e-15


def test_turn_vector_against_scipy():
    """turn_vector on random rotations (scipy's matrices) equals Rotation.as_rotvec (inverse of
    (4.3), independent reference)."""
    rots = Rotation.random(64, random_state=1)
    got = np.stack([np.asarray(turn_vector(m)) for m in rots.as_matrix()])
    assert_close(got, rots.as_rotvec(), atol=1e-14)


def test_turn_vector_projects_nearly_orthogonal_input():
    """A slightly non-orthogonal Q (rounding drift, violating (4.27) by 1e-10) is projected onto
    the nearby rotation."""
    theta = GENERIC[3]
    Q = np.asarray(turn_tensor(theta)) + 1e-10 * np.random.default_rng(7).normal(size=(3, 3))
    assert_close(turn_vector(Q), theta, atol=1e-9)


# --------------------------------------------------------------------------------------------
# Composition, eqs. (4.5)-(4.7).
# --------------------------------------------------------------------------------------------

PAIRS = [(GENERIC[i], GENERIC[-1 - i]) for i in range(5)] + [
    (LARGE[0], GENERIC[0]),
    (GENERIC[1], LARGE[3]),
    (LARGE[4], LARGE[5]),
    (TINY[2], GENERIC[2]),
    (TINY[3], TINY[4]),
    (NEAR_PI[0], NEAR_PI[5]),
    (NEAR_PI[2], GENERIC[4]),
]


@pytest.mark.parametrize("pair", range(len(PAIRS)))
def test_compose_is_turn_vector_of_product_eq_4_5(pair):
    """compose(φ, ψ) = turn_vector(Q(φ)·Q(ψ)), eq. (4.5), and is principal."""
    phi, psi = PAIRS[pair]
    got = np.asarray(compose(phi, psi))
    assert np.linalg.norm(got) <= PI * (1 + 4 * EPS)
    assert_close(got, turn_vector(turn_tensor(phi) @ turn_tensor(psi)), atol=5e-14)
    assert_close(turn_tensor(got), turn_tensor(phi) @ turn_tensor(psi), atol=5e-14)


def test_compose_against_scipy():
    """compose (4.5) agrees with scipy's composition (R(φ)·R(ψ)).as_rotvec() on random
    rotations."""
    r1, r2 = Rotation.random(32, random_state=2), Rotation.random(32, random_state=3)
    got = np.stack([np.asarray(compose(a, b)) for a, b in zip(r1.as_rotvec(), r2.as_rotvec())])
    assert_close(got, (r1 * r2).as_rotvec(), atol=1e-14)


@pytest.mark.parametrize("collinear", [True, False])
def test_compose_small_composed_angle(collinear):
    """Composed angle 1e-8 (φ, ψ of order 1 that nearly cancel): compose (4.5) keeps absolute
    accuracy and equals turn_vector(Q(φ)Q(ψ))."""
    target = 1e-8 * unit([1.0, -2.0, 0.5])
    for phi in GENERIC[:4]:
        if collinear:
            n = unit(phi)
            phi = 1.3 * n
            psi, target = -1.3 * n + 1e-8 * n, 1e-8 * n
        else:
            psi = (Rotation.from_rotvec(phi).inv() * Rotation.from_rotvec(target)).as_rotvec()
        got = compose(phi, psi)
        assert_close(got, target, atol=2.5e-15)
        assert_close(got, turn_vector(turn_tensor(phi) @ turn_tensor(psi)), atol=2.5e-15)


@pytest.mark.parametrize("delta", DELTAS)
def test_compose_near_pi(delta):
    """Composed angle π − δ: compose (4.5) returns (π − δ) m accurately, equal to
    turn_vector(Q(φ)Q(ψ)) (the half-angle form of (4.6)-(4.7) stays conditioned where (4.7) loses
    the axis)."""
    m = unit([0.2, 1.0, -0.4])
    target = (PI - delta) * m
    for phi in GENERIC[:4]:
        psi = (Rotation.from_rotvec(phi).inv() * Rotation.from_rotvec(target)).as_rotvec()
        got = compose(phi, psi)
        assert_close(got, target, atol=1e-14)
        assert_close(got, turn_vector(turn_tensor(phi) @ turn_tensor(psi)), atol=1e-14)
    n = unit(GENERIC[5])
    assert_close(compose(1.1 * n, (PI - delta - 1.1) * n), (PI - delta) * n, atol=1e-14)


@pytest.mark.parametrize("pair", range(len(PAIRS)))
def test_composition_invariants_eq_4_6_4_7(pair):
    """(4.6): cos θ = (tr(Q(φ)Q(ψ)) − 1)/2; corrected (4.7) (ERRATA 2):
    sin θ/θ · θ = −½ (Q(φ)Q(ψ))_×; and both agree with θ = compose(φ, ψ)."""
    phi, psi = PAIRS[pair]
    P = np.asarray(turn_tensor(phi) @ turn_tensor(psi))
    cos_theta, sinc_theta = composition_invariants(phi, psi)
    assert float(cos_theta) == pytest.approx((np.trace(P) - 1) / 2, abs=1e-14)
    expected = -0.5 * np.array([P[1, 2] - P[2, 1], P[2, 0] - P[0, 2], P[0, 1] - P[1, 0]])
    assert_close(sinc_theta, expected, atol=1e-14)
    theta = np.asarray(compose(phi, psi))
    th = np.linalg.norm(theta)
    assert float(cos_theta) == pytest.approx(np.cos(th), abs=1e-14)
    assert_close(sinc_theta, np.sinc(th / PI) * theta, atol=1e-14)


# --------------------------------------------------------------------------------------------
# Integrating tensor, eqs. (4.11)-(4.13), (4.20).
# --------------------------------------------------------------------------------------------

REGULAR = np.concatenate([GENERIC, LARGE, TINY, NEAR_PI])  # all at distance ≥ 0.27 from 2πk


@pytest.mark.parametrize("kind", SAMPLES)
def test_integrating_tensor_inverse_eq_4_11_4_20(kind):
    """Z·Z⁻¹ = Z⁻¹·Z = E with Z from (4.11) and Z⁻¹ from (4.20)."""
    for theta in SAMPLES[kind]:
        Z, Zi = np.asarray(integrating_tensor(theta)), np.asarray(integrating_tensor_inv(theta))
        tol = 1e-15 * np.linalg.cond(Z) * max(1, np.linalg.norm(theta)) ** 2
        assert_close(Z @ Zi, EYE, atol=tol)
        assert_close(Zi @ Z, EYE, atol=tol)


@pytest.mark.parametrize("kind", ["generic", "large", "near_pi"])
def test_integrating_tensor_closed_forms_eq_4_11_4_20(kind):
    """Z = E − R/2 + (1−g)/θ² R², g = θ sin θ/(2(1−cos θ)) (4.11), and
    Z⁻¹ = E + (1−cos θ)/θ² R + (θ−sin θ)/θ³ R² (4.20), written out with numpy."""
    for theta in SAMPLES[kind]:
        th = np.linalg.norm(theta)
        R = np_skew(theta)
        Z = EYE - R / 2 + (1 - g_of(theta)) / th**2 * R @ R
        Zi = EYE + (1 - np.cos(th)) / th**2 * R + (th - np.sin(th)) / th**3 * R @ R
        assert_close(integrating_tensor(theta), Z, rtol=1e-13, atol=1e-13)
        assert_close(integrating_tensor_inv(theta), Zi, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("kind", SAMPLES)
def test_integrating_tensor_det(kind):
    """det Z = θ²/(2(1 − cos θ)) (after (4.11), ERRATA 3) against jnp.linalg.det and the closed
    form; det Z⁻¹ = 1/det Z (4.20)."""
    for theta in SAMPLES[kind]:
        th = np.linalg.norm(theta)
        det = float(integrating_tensor_det(theta))
        assert det == pytest.approx(float(jnp.linalg.det(integrating_tensor(theta))), rel=1e-13)
        expected = th**2 / (4 * np.sin(th / 2) ** 2) if th > 0 else 1.0
        assert det == pytest.approx(expected, rel=1e-13)
        assert 1 / det == pytest.approx(
            float(jnp.linalg.det(integrating_tensor_inv(theta))), rel=1e-13
        )


def test_integrating_tensor_isotropic_eq_4_12():
    """Z(S·θ) = S·Z(θ)·Sᵀ for random rotations S (scipy), eq. (4.12); the same for Q and Z⁻¹."""
    S_all = Rotation.random(len(REGULAR), random_state=4).as_matrix()
    for theta, S in zip(REGULAR, S_all):
        scale = max(1, np.linalg.norm(theta)) ** 2
        for f in (integrating_tensor, integrating_tensor_inv, turn_tensor):
            assert_close(f(S @ theta), S @ np.asarray(f(theta)) @ S.T, atol=2e-14 * scale)


@pytest.mark.parametrize("kind", SAMPLES)
def test_integrating_tensor_transpose_eq_4_13(kind):
    """Zᵀ = Q·Z = Z·Q, eq. (4.13) (hence Z and Q commute)."""
    for theta in SAMPLES[kind]:
        Z, Q = np.asarray(integrating_tensor(theta)), np.asarray(turn_tensor(theta))
        tol = 1e-14 * max(1, np.linalg.norm(theta)) ** 2
        assert_close(Z.T, Q @ Z, atol=tol)
        assert_close(Z.T, Z @ Q, atol=tol)


@pytest.mark.parametrize("kind", SAMPLES)
def test_integrating_tensor_fixes_theta(kind):
    """Z(θ)·θ = θ and Z⁻¹(θ)·θ = θ (R·θ = 0, eq. (4.8), in (4.11) and (4.20))."""
    for theta in SAMPLES[kind]:
        tol = 1e-14 * max(1, np.linalg.norm(theta)) ** 3
        assert_close(integrating_tensor(theta) @ theta, theta, atol=tol)
        assert_close(integrating_tensor_inv(theta) @ theta, theta, atol=tol)


# --------------------------------------------------------------------------------------------
# Poisson equations along a curve, eqs. (4.9), (4.10), (4.14)-(4.19).
# --------------------------------------------------------------------------------------------

CURVES = {
    # name: (a, b, c, t0) for θ(t) = a + t b + t² c
    "generic": (
        np.array([0.3, -0.8, 0.5]),
        np.array([1.0, 0.4, -0.3]),
        np.array([-0.2, 0.5, 0.9]),
        0.4,
    ),
    "near_zero": (
        np.array([1e-3, -2e-3, 5e-4]),
        np.array([0.7, 0.1, -0.4]),
        np.array([0.3, 0.3, 0.2]),
        1e-3,
    ),
    "near_pi": (2.9 * unit([1, 1, 1]), np.array([0.5, -1.0, 0.2]), np.array([0.1, 0.0, 0.4]), 0.3),
    "above_pi": (
        4.5 * unit([-1, 2, 0.5]),
        np.array([0.2, 0.9, -1.1]),
        np.array([0.6, -0.2, 0.1]),
        0.5,
    ),
}


@jax.jit
def _jvp_along_curve(a, b, c, t0):
    """θ, θ̇, Q, dQ/dt and d|θ|/dt at t0 along θ(t) = a + t b + t² c (forward-mode jvp)."""

    def curve(t):
        return a + t * b + t**2 * c

    one = jnp.ones_like(t0)
    theta, theta_dot = jax.jvp(curve, (t0,), (one,))
    Q, Q_dot = jax.jvp(lambda t: rbo.turn_tensor(curve(t)), (t0,), (one,))
    norm_dot = jax.jvp(lambda t: jnp.linalg.norm(curve(t)), (t0,), (one,))[1]
    return theta, theta_dot, Q, Q_dot, norm_dot


def _curve_state(name):
    a, b, c, t0 = CURVES[name]
    return tuple(np.asarray(x) for x in _jvp_along_curve(a, b, c, jnp.asarray(t0)))


@pytest.mark.parametrize("curve", CURVES)
def test_left_poisson_eq_4_9_4_10_4_19(curve):
    """Along θ(t): ω := Z⁻¹·θ̇ (4.19) satisfies the left Poisson equation dQ/dt = ω×Q (4.9), and
    the angular velocity read off dQ/dt·Qᵀ satisfies θ̇ = Z·ω (4.10)."""
    theta, theta_dot, Q, Q_dot, _ = _curve_state(curve)
    omega = np.asarray(integrating_tensor_inv(theta)) @ theta_dot
    assert_close(Q_dot, np_skew(omega) @ Q, atol=1e-14)
    W = Q_dot @ Q.T
    assert_close(W, -W.T, atol=1e-14)  # dQ/dt·Qᵀ is skew because Q is orthogonal (4.27)
    omega_from_Q = np.array([W[2, 1], W[0, 2], W[1, 0]])
    assert_close(omega_from_Q, omega, atol=1e-14)
    assert_close(np.asarray(integrating_tensor(theta)) @ omega_from_Q, theta_dot, atol=1e-13)


@pytest.mark.parametrize("curve", CURVES)
def test_right_poisson_eq_4_14_4_19(curve):
    """Ω = Qᵀ·ω: θ̇ = Zᵀ·Ω (4.14), Ω = Z⁻ᵀ·θ̇ (4.19) and dQ/dt = Q·(Ω×E)."""
    theta, theta_dot, Q, Q_dot, _ = _curve_state(curve)
    W = Q.T @ Q_dot
    Omega_from_Q = np.array([W[2, 1], W[0, 2], W[1, 0]])
    Z = np.asarray(integrating_tensor(theta))
    Zi = np.asarray(integrating_tensor_inv(theta))
    omega = Zi @ theta_dot
    Omega = Q.T @ omega
    assert_close(Omega, Zi.T @ theta_dot, atol=1e-14)
    assert_close(Omega_from_Q, Omega, atol=1e-14)
    assert_close(Q_dot, Q @ np_skew(Omega), atol=1e-14)
    assert_close(Z.T @ Omega, theta_dot, atol=1e-13)


@pytest.mark.parametrize("curve", CURVES)
def test_explicit_forms_eq_4_15_to_4_18(curve):
    """The explicit forms (4.15)/(4.16) and (4.17)/(4.18), with g of (4.11) computed by numpy, and
    the identity θ·ω = θ·Ω = θ·θ̇ = θ θ̇ (θ θ̇ = |θ| d|θ|/dt)."""
    theta, theta_dot, Q, _, norm_dot = _curve_state(curve)
    omega = np.asarray(integrating_tensor_inv(theta)) @ theta_dot
    Omega = Q.T @ omega
    th = np.linalg.norm(theta)
    g = g_of(theta)
    c = (1 - g) / th**2
    rhs_415 = omega - 0.5 * np.cross(theta, omega) + c * np.cross(theta, np.cross(theta, omega))
    rhs_416 = Omega + 0.5 * np.cross(theta, Omega) + c * np.cross(theta, np.cross(theta, Omega))
    tol = 1e-13
    assert_close(rhs_415, theta_dot, atol=tol)
    assert_close(rhs_416, theta_dot, atol=tol)
    rhs_417 = g * omega - 0.5 * np.cross(theta, omega) + (1 - g) / th * norm_dot * theta
    rhs_418 = g * Omega + 0.5 * np.cross(theta, Omega) + (1 - g) / th * norm_dot * theta
    assert_close(rhs_417, theta_dot, atol=tol)
    assert_close(rhs_418, theta_dot, atol=tol)
    for x in (theta @ omega, theta @ Omega, theta @ theta_dot):
        assert x == pytest.approx(th * norm_dot, rel=1e-13, abs=1e-16)


# --------------------------------------------------------------------------------------------
# Small angles: values and derivatives of all orders at θ = 0 and |θ| = 1e-300 ... 1e-8.
# --------------------------------------------------------------------------------------------


def compose_flat(x):
    return rbo.compose(x[:3], x[3:])


def invariants_flat(x):
    cos_theta, sinc_theta = rbo.composition_invariants(x[:3], x[3:])
    return jnp.concatenate([cos_theta[None], sinc_theta])


def turn_vector_flat(x):
    return rbo.turn_vector(x.reshape(3, 3))


def vector_invariant_flat(x):
    return rbo.vector_invariant(x.reshape(3, 3))


def taylor_family(theta, c0, c1, d0, d1):
    """Value, jacobian and Hessian (exact, numpy) of the polynomial
    f(θ) = E + (c0 + c1 t) R + (d0 + d1 t) R², t = θ², R = θ×E, R² = θ⊗θ − tE: the Taylor
    polynomials of (4.3), (4.11), (4.20), whose remainders are O(θ⁵) (O(θ³) in the Hessian)."""
    theta = np.asarray(theta, dtype=np.float64)
    t = theta @ theta
    R = np_skew(theta)
    R2 = np.outer(theta, theta) - t * EYE
    a, b = c0 + c1 * t, d0 + d1 * t
    dR2 = (  # ∂R²/∂θ_k = e_k⊗θ + θ⊗e_k − 2θ_k E
        np.einsum("ik,j->ijk", EYE, theta)
        + np.einsum("i,jk->ijk", theta, EYE)
        - 2 * np.einsum("ij,k->ijk", EYE, theta)
    )
    S = c1 * R + d1 * R2
    dS = c1 * GENERATORS + d1 * dR2
    value = EYE + a * R + b * R2
    jac = 2 * np.einsum("ij,k->ijk", S, theta) + a * GENERATORS + b * dR2
    hess = (
        2 * np.einsum("ij,kl->ijkl", S, EYE)
        + 2 * np.einsum("k,ijl->ijkl", theta, dS)
        + 2 * np.einsum("l,ijk->ijkl", theta, dS)
        + b * D2_R2
    )
    return {"value": value, "jacfwd": jac, "jacrev": jac, "hessian": hess}


def _bch3_tensors():
    """log(exp φ exp ψ) to third order (Baker-Campbell-Hausdorff) in vector form (4.5),
    φ + ψ + ½ φ×ψ + (φ×(φ×ψ) + ψ×(ψ×φ))/12, as a polynomial A·x + B:xx + C:xxx in x = (φ, ψ)
    with B and C symmetric in their input indices; the remainder is O(|x|⁴)."""
    eps = levi_civita()
    T = np.einsum("kij,jlm->kilm", eps, eps)  # (a×(b×c))_k = T_kilm a_i b_l c_m
    A = np.concatenate([EYE, EYE], axis=1)
    B = np.zeros((3, 6, 6))
    B[:, :3, 3:] = 0.5 * eps
    C = np.zeros((3, 6, 6, 6))
    C[:, :3, :3, 3:] += T / 12  # φ×(φ×ψ)
    C[:, 3:, 3:, :3] += T / 12  # ψ×(ψ×φ)
    B = (B + np.swapaxes(B, 1, 2)) / 2
    C = sum(np.transpose(C, (0, *p)) for p in itertools.permutations((1, 2, 3))) / 6
    return A, B, C


def bch3(x):
    """Value, jacobian and Hessian (exact, numpy) of the third-order BCH polynomial."""
    A, B, C = _bch3_tensors()
    x = np.asarray(x, dtype=np.float64)
    value = A @ x + np.einsum("kab,a,b->k", B, x, x) + np.einsum("kabc,a,b,c->k", C, x, x, x)
    jac = A + 2 * np.einsum("kab,b->ka", B, x) + 3 * np.einsum("kabc,b,c->ka", C, x, x)
    hess = 2 * B + 6 * np.einsum("kabc,c->kab", C, x)
    return {"value": value, "jacfwd": jac, "jacrev": jac, "hessian_ff": hess}


SMALL_SCALES = [0.0, 1e-300, 1e-150, 1e-8]
# name: (function, Taylor coefficients (c0, c1, d0, d1) of f = E + (c0 + c1 t)R + (d0 + d1 t)R²)
SMALL = {
    # sin θ/θ = 1 − t/6, (1 − cos θ)/θ² = 1/2 − t/24 (4.3)
    "turn_tensor": (rbo.turn_tensor, (1.0, -1 / 6, 1 / 2, -1 / 24)),
    # (1 − g)/θ² = 1/12 + t/720 (4.11), ERRATA 3
    "integrating_tensor": (rbo.integrating_tensor, (-0.5, 0.0, 1 / 12, 1 / 720)),
    # (1 − cos θ)/θ² = 1/2 − t/24, (θ − sin θ)/θ³ = 1/6 − t/120 (4.20)
    "integrating_tensor_inv": (rbo.integrating_tensor_inv, (0.5, -1 / 24, 1 / 6, -1 / 120)),
}
DERIVATIVES = ["value", "jacfwd", "jacrev", "hessian"]


def _small_input(size, scale):
    return jnp.asarray(scale * unit([0.6, -0.3, 1.1, -0.2, 0.9, 0.4][:size]))


@pytest.mark.parametrize("transform", DERIVATIVES)
@pytest.mark.parametrize("name", SMALL)
def test_small_angles_match_taylor_eq_4_3_4_11_4_20(name, transform):
    """Values, jacobians (forward, reverse) and Hessians (jax.hessian) of Q (4.3), Z (4.11) and
    Z⁻¹ (4.20) are finite and equal to those of their Taylor polynomials at |θ| = 0, 1e-300, 1e-150,
    1e-8 (the off-diagonal entries, of order |θ|, to relative accuracy)."""
    f, coeffs = SMALL[name]
    for scale in SMALL_SCALES:
        theta = _small_input(3, scale)
        got = np.asarray(compiled(f, transform)(theta))
        ref = taylor_family(theta, *coeffs)[transform]
        assert np.all(np.isfinite(got)), scale
        assert_close(got, ref, atol=8 * EPS)
        if transform == "value":  # off-diagonal entries (R and R² parts) to relative accuracy
            off = ~np.eye(3, dtype=bool)
            assert_close(got[off], ref[off], atol=8 * EPS * scale)


@pytest.mark.parametrize(
    "name, alpha, c",
    [
        ("turn_tensor", 1.0, 1 / 2),
        ("integrating_tensor", -0.5, 1 / 12),
        ("integrating_tensor_inv", 0.5, 1 / 6),
    ],
)
def test_small_angle_exact_values_at_zero(name, alpha, c):
    """At θ = 0 exactly: f = E, ∂f/∂θ_a = α (e_a×E) (skew generators; α = 1, −½, ½ for Q, Z, Z⁻¹)
    and ∂²f/∂θ_a∂θ_b = c ∂²R²/∂θ_a∂θ_b (c = ½, 1/12, 1/6: Q ≈ E + R + R²/2 (4.3),
    Z ≈ E − R/2 + R²/12 (4.11), Z⁻¹ ≈ E + R/2 + R²/6 (4.20))."""
    f = SMALL[name][0]
    zero = jnp.zeros(3)
    assert_close(compiled(f)(zero), EYE, atol=0)
    for transform in ("jacfwd", "jacrev"):
        assert_close(compiled(f, transform)(zero), alpha * GENERATORS, atol=0)
    assert_close(compiled(f, "hessian")(zero), c * D2_R2, atol=1e-17)


@pytest.mark.parametrize("transform", ["value", "jacfwd", "jacrev", "hessian_ff"])
def test_small_angle_compose_bch_eq_4_5(transform):
    """compose (4.5) near the identity: value, jacobians and Hessian (forward over forward, which
    compiles fastest) finite and equal to those of the BCH series at |(φ, ψ)| = 0, 1e-300, 1e-150,
    1e-8."""
    for scale in SMALL_SCALES:
        x = _small_input(6, scale)
        got = np.asarray(compiled(compose_flat, transform)(x))
        ref = bch3(x)[transform]
        assert np.all(np.isfinite(got)), scale
        assert_close(got, ref, atol=8 * EPS)
        if transform == "value":
            assert np.all(np.abs(got - ref) <= 8 * EPS * scale)


def test_small_angle_compose_exact_at_zero():
    """compose at φ = ψ = 0: θ = 0, ∂θ/∂(φ, ψ) = (E, E), and the Hessian is the bilinear form of
    ½ φ×ψ (the second-order term of (4.7) at small angles)."""
    x = jnp.zeros(6)
    assert_close(compiled(compose_flat)(x), np.zeros(3), atol=0)
    for transform in ("jacfwd", "jacrev"):
        assert_close(compiled(compose_flat, transform)(x), np.concatenate([EYE, EYE], 1), atol=0)
    H = np.zeros((3, 6, 6))
    H[:, :3, 3:] = 0.5 * levi_civita()  # ∂²(½ φ×ψ)_k/∂φ_i∂ψ_j = ½ ε_kij
    H[:, 3:, :3] = np.swapaxes(H[:, :3, 3:], 1, 2)
    assert_close(compiled(compose_flat, "hessian_ff")(x), H, atol=0)


@pytest.mark.parametrize("scale", SMALL_SCALES)
def test_small_angle_turn_vector(scale):
    """turn_vector at Q = Q(θ), |θ| = 0, 1e-300, 1e-150, 1e-8: value θ to relative accuracy; by the
    chain rule through the jacobians (forward and reverse) and Hessians of turn_vector and Q, the
    round trip turn_vector∘turn_tensor has jacobian E and Hessian 0 (inverse of (4.3))."""
    theta = _small_input(3, scale)
    Q = turn_tensor(theta)
    x = jnp.ravel(Q)
    got = np.asarray(compiled(turn_vector_flat)(x))
    assert np.all(np.abs(got - np.asarray(theta)) <= 4 * EPS * scale)
    JQ = np.asarray(compiled(rbo.turn_tensor, "jacfwd")(theta)).reshape(9, 3)
    HQ = np.asarray(compiled(rbo.turn_tensor, "hessian")(theta)).reshape(9, 3, 3)
    Htv = np.asarray(compiled(turn_vector_flat, "hessian_ff")(x))
    assert np.all(np.isfinite(Htv))
    for transform in ("jacfwd", "jacrev"):
        Jtv = np.asarray(compiled(turn_vector_flat, transform)(x))
        assert np.all(np.isfinite(Jtv))
        assert_close(Jtv @ JQ, EYE, atol=4 * EPS)
        H = np.einsum("km,mab->kab", Jtv, HQ) + np.einsum("kmn,ma,nb->kab", Htv, JQ, JQ)
        assert_close(H, np.zeros((3, 3, 3)), atol=4 * EPS)


def test_turn_vector_derivatives_at_identity():
    """At Q = E: θ = 0, ∂θ/∂Q = −½ ∂Q_×/∂Q (θ ≈ axial vector of the skew part of Q, cf. (4.7) at
    small angles), and the Hessian is finite, symmetric and matches finite differences of the
    jacobian."""
    x = jnp.eye(3).ravel()
    assert_close(compiled(turn_vector_flat)(x), np.zeros(3), atol=0)
    expected = np.zeros((3, 3, 3))
    for k, (i, j) in enumerate([(2, 1), (0, 2), (1, 0)]):
        expected[k, i, j], expected[k, j, i] = 0.5, -0.5
    for transform in ("jacfwd", "jacrev"):
        assert_close(compiled(turn_vector_flat, transform)(x), expected.reshape(3, 9), atol=1e-16)
    H = np.asarray(compiled(turn_vector_flat, "hessian_ff")(x))
    assert np.all(np.isfinite(H))
    assert_close(H, np.swapaxes(H, 1, 2), atol=1e-15)
    fd = finite_difference_jacobian(compiled(turn_vector_flat, "jacfwd"), x, scale=0.1)
    assert_close(fd, H, atol=1e-9)


# --------------------------------------------------------------------------------------------
# Gradients: jacfwd = jacrev = finite differences; jit; vmap.
# --------------------------------------------------------------------------------------------

FLAT = {
    "turn_tensor": rbo.turn_tensor,
    "integrating_tensor": rbo.integrating_tensor,
    "integrating_tensor_inv": rbo.integrating_tensor_inv,
    "integrating_tensor_det": rbo.integrating_tensor_det,
    "distance_to_singularity": rbo.distance_to_singularity,
    "compose": compose_flat,
    "composition_invariants": invariants_flat,
    "turn_vector": turn_vector_flat,
    "skew": rbo.skew,
    "vector_invariant": vector_invariant_flat,
}
KINDS = ["random", "near_identity", "near_pi"]


def _point(name, kind):
    """A test point of the given kind, as the flat input of FLAT[name]."""
    rng = np.random.default_rng(zlib.crc32(f"{name}/{kind}".encode()))
    n1, n2 = unit(rng.normal(size=3)), unit(rng.normal(size=3))
    theta = {
        "random": rng.uniform(0.3, 3.0) * n1,
        "near_identity": 1e-7 * rng.normal(size=3),  # exp(randn·1e-7)
        "near_pi": (PI - 1e-3) * n1,
    }[kind]
    if name in ("turn_vector", "vector_invariant"):
        return np.asarray(turn_tensor(theta)).ravel()
    if name in ("compose", "composition_invariants"):
        if kind == "random":
            return np.concatenate([theta, rng.uniform(0.3, 3.0) * n2])
        if kind == "near_identity":
            return np.concatenate([theta, 1e-7 * rng.normal(size=3)])
        # composed angle π − 1e-3: split θ into two turns about different axes
        psi = (Rotation.from_rotvec(1.2 * n2).inv() * Rotation.from_rotvec(theta)).as_rotvec()
        return np.concatenate([1.2 * n2, psi])
    return theta


GRAD_FUNCS = [name for name in FLAT if name not in ("skew", "vector_invariant")]


@pytest.mark.parametrize("name", GRAD_FUNCS)
def test_gradients_three_ways(name):
    """jacfwd = jacrev = 4th-order finite differences at random, near-identity and near-π points
    (derivatives of (4.3), (4.5)-(4.7), (4.11), (4.20)), under jit."""
    f = FLAT[name]
    for kind in KINDS:
        if name == "distance_to_singularity" and kind == "near_identity":
            continue  # |θ| has a cone point at 0: nothing to compare finite differences with
        x = jnp.asarray(_point(name, kind))
        fwd = np.asarray(compiled(f, "jacfwd")(x))
        assert np.all(np.isfinite(fwd)), kind
        tol = max(1, np.abs(fwd).max())
        assert_close(compiled(f, "jacrev")(x), fwd, atol=1e-14 * tol)
        fd = finite_difference_jacobian(compiled(f), x, scale=1e-2 if kind == "near_pi" else 1.0)
        assert_close(fd, fwd, atol=1e-8 * tol)


def _batch(name):
    if name in ("turn_vector", "vector_invariant"):
        return np.stack([np.asarray(turn_tensor(t)).ravel() for t in ALL])
    if name in ("compose", "composition_invariants"):
        return np.concatenate([ALL, ALL[::-1]], axis=1)
    return ALL


def _value_and_jacrev(f):
    return lambda x: (f(x), jax.jacrev(f)(x))


VALUE_AND_JACREV = {name: _value_and_jacrev(f) for name, f in FLAT.items()}
# vmap of the jacobian too for turn_tensor (the coefficient functions' where/Horner batching) and
# turn_vector (batched argmax pivot and gather); the other jacobians use the same batching rules
# and would cost several seconds of compilation each.
VMAP_JACOBIAN = ["turn_tensor", "turn_vector"]


@pytest.mark.parametrize("name", FLAT)
def test_jit_and_vmap_match_python_loop(name):
    """vmap(f)(batch) (and vmap(jacrev(f))(batch)) equal Python loops over the batch, and jit(f)
    equals eager f, for every function of (4.3)-(4.20)."""
    f = FLAT[name]
    batch = jnp.asarray(_batch(name))
    loop = np.stack([np.asarray(compiled(f)(x)) for x in batch])
    tol = 16 * EPS * max(1, np.abs(loop).max())
    if name in VMAP_JACOBIAN:
        value, jac = compiled(VALUE_AND_JACREV[name], vmap=True)(batch)
        jac_loop = np.stack([np.asarray(compiled(f, "jacrev")(x)) for x in batch])
        assert_close(jac, jac_loop, atol=16 * EPS * max(1, np.abs(jac_loop).max()))
    else:
        value = compiled(f, vmap=True)(batch)
    assert_close(value, loop, atol=tol)
    x = batch[len(batch) // 2]
    assert_close(f(x), compiled(f)(x), atol=tol)  # eager


# --------------------------------------------------------------------------------------------
# Property tests (hypothesis): group identities.
# --------------------------------------------------------------------------------------------


def _axis(z, phi):
    r = math.sqrt(max(0.0, 1.0 - z * z))
    return np.array([r * math.cos(phi), r * math.sin(phi), z])


axes = st.builds(_axis, st.floats(-1, 1), st.floats(0, 2 * PI))
generic_turns = st.builds(lambda n, a: a * n, axes, st.floats(0, 3))
# exp(randn · 1e-7)-style: tiny vectors near the identity
near_identity_turns = st.builds(lambda v: 1e-7 * np.array(v), st.tuples(*[st.floats(-3, 3)] * 3))
near_pi_turns = st.builds(
    lambda n, e, s: (PI + s * 10.0**e) * n, axes, st.floats(-12, -2), st.sampled_from([-1, 1])
)
turns = st.one_of(generic_turns, near_identity_turns, near_pi_turns)


@given(turns, turns)
def test_property_compose_is_product_eq_4_5(phi, psi):
    """Q(compose(φ, ψ)) = Q(φ)·Q(ψ), eq. (4.5), and the result is principal."""
    theta = compose(phi, psi)
    assert float(jnp.linalg.norm(theta)) <= PI * (1 + 4 * EPS)
    assert_close(turn_tensor(theta), turn_tensor(phi) @ turn_tensor(psi), atol=1e-14)


@given(turns)
def test_property_compose_inverse(phi):
    """compose(φ, −φ) = compose(−φ, φ) = 0 (Q(−φ) = Qᵀ(φ), (4.3))."""
    assert_close(compose(phi, -phi), np.zeros(3), atol=2e-15)
    assert_close(compose(-phi, phi), np.zeros(3), atol=2e-15)


@given(turns)
def test_property_compose_identity(phi):
    """compose(φ, 0) = compose(0, φ) = principal(φ) (same turn-tensor (4.3))."""
    for got in (compose(phi, np.zeros(3)), compose(np.zeros(3), phi)):
        assert_close(turn_tensor(got), turn_tensor(phi), atol=2e-15)
        if np.linalg.norm(phi) < PI - 1e-9:
            assert_close(got, phi, atol=2e-15)


@given(turns, turns, turns)
def test_property_compose_associative(a, b, c):
    """compose is associative up to the branch at π: compare turn-tensors (4.5)."""
    left = compose(compose(a, b), c)
    right = compose(a, compose(b, c))
    assert_close(turn_tensor(left), turn_tensor(right), atol=1e-14)


@given(turns, turns)
def test_property_compose_transpose(phi, psi):
    """Q(compose(φ, ψ))ᵀ = Q(compose(−ψ, −φ)) ((Q(φ)Q(ψ))ᵀ = Q(−ψ)Q(−φ), (4.3), (4.5))."""
    assert_close(turn_tensor(compose(phi, psi)).T, turn_tensor(compose(-psi, -phi)), atol=1e-14)


@given(turns, turns)
def test_property_composition_invariants(phi, psi):
    """(4.6) and corrected (4.7) equal cos θ and sin θ/θ · θ of the composed turn."""
    cos_theta, sinc_theta = composition_invariants(phi, psi)
    P = np.asarray(turn_tensor(phi) @ turn_tensor(psi))
    assert float(cos_theta) == pytest.approx((np.trace(P) - 1) / 2, abs=1e-14)
    assert_close(sinc_theta, -0.5 * np.asarray(vector_invariant(P)), atol=1e-14)


@given(turns)
def test_property_turn_vector_roundtrip(theta):
    """turn_vector(Q(θ)) has the same turn-tensor (4.3), modulus ≤ π, and equals θ when |θ| < π."""
    Q = turn_tensor(theta)
    got = np.asarray(turn_vector(Q))
    assert np.linalg.norm(got) <= PI * (1 + 4 * EPS)
    assert_close(turn_tensor(got), Q, atol=2e-15)
    if np.linalg.norm(theta) < PI:
        assert_close(got, theta, atol=2e-15)


@given(turns, axes, st.floats(0, 3))
def test_property_integrating_tensor_eq_4_11_to_4_13(theta, axis, angle):
    """Z·Z⁻¹ = E, Zᵀ = QZ = ZQ (4.13), Z·θ = θ and isotropy Z(Sθ) = S Z Sᵀ (4.12)."""
    Z, Zi, Q = (
        np.asarray(f(theta)) for f in (integrating_tensor, integrating_tensor_inv, turn_tensor)
    )
    assert_close(Z @ Zi, EYE, atol=1e-14)
    assert_close(Z.T, Q @ Z, atol=1e-14)
    assert_close(Z.T, Z @ Q, atol=1e-14)
    assert_close(Z @ theta, theta, atol=1e-14)
    S = rodrigues_41(axis, angle)
    assert_close(integrating_tensor(S @ theta), S @ Z @ S.T, atol=1e-14)


# --------------------------------------------------------------------------------------------
# Singular points of Z: |θ| = 2πk, k ≥ 1.
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "modulus, expected",
    [
        (0.0, 2 * PI),
        (PI, PI),
        (2 * PI, 0.0),
        (2 * PI - 1e-6, 1e-6),
        (2 * PI + 1e-6, 1e-6),
        (4 * PI, 0.0),
        (5 * PI, PI),
        (3.0, 2 * PI - 3.0),
        (7.0, 7.0 - 2 * PI),
    ],
)
def test_distance_to_singularity(modulus, expected):
    """distance_to_singularity(θ) = min_{k≥1} | |θ| − 2πk | (singular spheres of (4.11))."""
    for n in np.concatenate([EYE[:1], random_axes(2, 8)]):
        assert float(distance_to_singularity(modulus * n)) == pytest.approx(expected, abs=1e-14)


def test_distance_to_singularity_gradient():
    """Gradient of the distance to the singular spheres of (4.11): finite at θ = 0 (cone point)
    and ∓n on either side of |θ| = 2π."""
    n = unit([1.0, 2.0, -0.5])
    grad = compiled(rbo.distance_to_singularity, "jacrev")
    assert np.all(np.isfinite(np.asarray(grad(jnp.zeros(3)))))
    jac = compiled(rbo.distance_to_singularity, "jacfwd")
    assert np.all(np.isfinite(np.asarray(jac(jnp.zeros(3)))))
    assert_close(grad(3.0 * n), -n, atol=1e-15)
    assert_close(grad(7.0 * n), n, atol=1e-15)


@pytest.mark.parametrize("k", [1, 2])
def test_integrating_tensor_singular_at_2pi_k(k):
    """At |θ| = 2πk, det Z = θ²/(2(1 − cos θ)) → ∞ (4.11): the singularity is detected (a huge or
    non-finite Z), not replaced by a plausible finite number; Z⁻¹ stays finite but singular."""
    n = unit([0.3, 0.4, -1.0])
    for rel in (0.0, 1e-12, -1e-12):
        theta = 2 * PI * k * (1 + rel) * n
        assert float(integrating_tensor_det(theta)) > 1e20  # +inf passes, NaN does not
        Z = np.asarray(integrating_tensor(theta))
        assert not np.all(np.abs(Z) < 1e10)
        Zi = np.asarray(integrating_tensor_inv(theta))
        assert np.all(np.isfinite(Zi))
        assert abs(np.linalg.det(Zi)) < 1e-20
    # Just off the singular sphere, Z is finite and still the inverse of Z⁻¹.
    theta = 2 * PI * k * (1 + 1e-6) * n
    Z, Zi = np.asarray(integrating_tensor(theta)), np.asarray(integrating_tensor_inv(theta))
    assert np.all(np.isfinite(Z))
    assert_close(Z @ Zi, EYE, atol=1e-6)


# --------------------------------------------------------------------------------------------
# Bad input.
# --------------------------------------------------------------------------------------------

VECTOR_INPUT_FUNCS = [
    "skew",
    "turn_tensor",
    "integrating_tensor",
    "integrating_tensor_inv",
    "integrating_tensor_det",
    "distance_to_singularity",
]


@pytest.mark.parametrize("shape", [(), (2,), (4,), (3, 1), (1, 3), (4, 4), (3, 3), (2, 3)])
@pytest.mark.parametrize("name", VECTOR_INPUT_FUNCS + ["compose", "composition_invariants"])
def test_bad_vector_shape_raises(name, shape):
    """Turn-vectors (4.3) are (3,) arrays: wrong shapes raise ValueError at trace time (also
    under jit), naming the shape."""
    f = getattr(rbo, name)
    x = jnp.ones(shape)
    args = (x,) if name in VECTOR_INPUT_FUNCS else (x, jnp.ones(3))
    for g in (f, jax.jit(f)):
        with pytest.raises(ValueError, match=re.escape(str(shape))):
            g(*args)
    if name in ("compose", "composition_invariants"):
        with pytest.raises(ValueError, match=re.escape(str(shape))):
            f(jnp.ones(3), x)


@pytest.mark.parametrize("shape", [(3,), (9,), (3, 4), (4, 4), (1, 3, 3), (3, 3, 1)])
@pytest.mark.parametrize("name", ["turn_vector", "vector_invariant"])
def test_bad_matrix_shape_raises(name, shape):
    """Tensor inputs (Q of (4.3)) must be (3, 3): ValueError at trace time naming the shape."""
    f = getattr(rbo, name)
    for g in (f, jax.jit(f)):
        with pytest.raises(ValueError, match=re.escape(str(shape))):
            g(jnp.ones(shape))


NONFINITE = [
    np.array([np.nan, 0.0, 0.0]),
    np.array([0.1, np.nan, 0.2]),
    np.array([np.inf, 0.0, 0.0]),
    np.array([0.0, 0.0, -np.inf]),
    np.array([np.nan, np.inf, 1.0]),
]


@pytest.mark.parametrize("bad", range(len(NONFINITE)))
@pytest.mark.parametrize(
    "name",
    VECTOR_INPUT_FUNCS[1:] + ["compose_left", "compose_right", "roundtrip", "invariants"],
)
def test_nonfinite_input_gives_nonfinite_output(name, bad):
    """NaN/inf θ gives non-finite output (every entry) of (4.3), (4.5)-(4.7), (4.11), (4.20) and
    of the distance to the singular spheres, never a plausible finite answer."""
    theta = NONFINITE[bad]
    ok = GENERIC[2]
    if name == "compose_left":
        out = compose(theta, ok)
    elif name == "compose_right":
        out = compose(ok, theta)
    elif name == "roundtrip":
        out = turn_vector(turn_tensor(theta))
    elif name == "invariants":
        out = jnp.concatenate(
            [composition_invariants(theta, ok)[0][None], composition_invariants(theta, ok)[1]]
        )
    else:
        out = compiled(getattr(rbo, name))(theta)
    assert not np.any(np.isfinite(np.asarray(out))), out


@pytest.mark.parametrize("entry", [(0, 0), (1, 2), (2, 1), (2, 2)])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_turn_vector_nonfinite_matrix(entry, value):
    """A NaN/inf entry anywhere in Q gives a non-finite turn-vector (inverse of (4.3))."""
    Q = np.array(turn_tensor(GENERIC[1])).copy()
    Q[entry] = value
    assert not np.any(np.isfinite(np.asarray(turn_vector(Q))))


def test_integer_input_is_converted_to_float():
    """Integer input works for every function of (4.3)-(4.20) and gives the same floating-point
    result as float input."""
    ints, floats = [1, -2, 1], np.array([1.0, -2.0, 1.0])
    for name in VECTOR_INPUT_FUNCS:
        got = getattr(rbo, name)(ints)
        assert jnp.issubdtype(got.dtype, jnp.floating)
        assert_close(got, getattr(rbo, name)(floats), atol=0)
    assert tree_allclose(
        rbo.compose(ints, [0, 1, 0]), rbo.compose(floats, np.array([0.0, 1.0, 0.0]))
    )
    assert tree_allclose(
        rbo.composition_invariants(ints, ints), rbo.composition_invariants(floats, floats)
    )
    got = rbo.turn_vector(np.eye(3, dtype=np.int32))
    assert got.dtype == jnp.float64
    assert_close(got, np.zeros(3), atol=0)
    assert_close(rbo.vector_invariant(np.eye(3, dtype=int)), np.zeros(3), atol=0)


def test_complex_input_raises():
    """Turn-vectors (4.3) are real: complex input raises TypeError."""
    with pytest.raises(TypeError, match="real"):
        rbo.turn_tensor(jnp.ones(3, dtype=jnp.complex128))


def test_private_coefficients_are_functions_of_t():
    """The private coefficient functions of t = θ² match their closed forms at a moderate angle:
    sin θ/θ, (1 − cos θ)/θ² (4.3), (θ − sin θ)/θ³ (4.20), (1 − g)/θ² (4.11), cos θ (4.6)
    (accuracy sweeps: test_kinematics_accuracy.py)."""
    th = 0.7
    t = jnp.asarray(th**2)
    assert float(kin.sinc(t)) == pytest.approx(np.sin(th) / th, rel=1e-15)
    assert float(kin.cosc(t)) == pytest.approx((1 - np.cos(th)) / th**2, rel=1e-14)
    assert float(kin._sinc3(t)) == pytest.approx((th - np.sin(th)) / th**3, rel=1e-13)
    assert float(kin.gcoef(t)) == pytest.approx((1 - th / 2 / np.tan(th / 2)) / th**2, rel=1e-13)
    assert float(kin._cos(t)) == pytest.approx(np.cos(th), rel=1e-15)


def test_solve3_is_a_linear_solve_and_its_derivative():
    """``kin.solve3`` (Cramer's rule, written out) against LAPACK's solve on batches of random
    3×3 systems and of inertia tensors (a body's: symmetric positive definite), with its
    derivative in ``A`` against the closed form $d(A^{-1}b) = -A^{-1}\\,dA\\,A^{-1}b$."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(16, 3, 3)) + 3.0 * EYE
    R = Rotation.random(16, random_state=4).as_matrix()
    inertia = np.einsum("bij,bj,bkj->bik", R, rng.uniform(1e-4, 2e-4, size=(16, 3)), R)
    b = rng.normal(size=(16, 3))
    for M in (A, inertia):
        x = np.asarray(kin.solve3(jnp.asarray(M), jnp.asarray(b)))
        ref = np.linalg.solve(M, b[..., None])[..., 0]
        np.testing.assert_allclose(x, ref, rtol=1e-12, atol=0.0)
    dA = rng.normal(size=A.shape)
    _, dx = jax.jvp(lambda M: kin.solve3(M, jnp.asarray(b)), (jnp.asarray(A),), (jnp.asarray(dA),))
    x = np.linalg.solve(A, b[..., None])
    expected = -np.linalg.solve(A, dA @ x)[..., 0]
    np.testing.assert_allclose(np.asarray(dx), expected, rtol=1e-11, atol=1e-13)
