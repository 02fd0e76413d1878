"""Generalized Hopf (Bautin) points (issue 23): the second Lyapunov coefficient against the
normal form through nonlinear changes of coordinates, and the Bautin point of the damped Nikolai
problem (4.57), (4.84) on its Hopf curve M = 2b sqrt(K(M)/A1) (K of (4.69)), where soft flutter
turns hard; its derivatives by the implicit function theorem against finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
from helpers import damped_nikolai

import rbo_jax as rbo

C, D, A1 = 1.0, 2.0, 1.0


nikolai = damped_nikolai  # (4.57), (4.84); d = D, A1 = A1


def critical_moment(b, c=C):
    """The root of M = 2b sqrt(K(M)/A1), K of (4.69), by Brent's method on the closed form."""

    def f(M):
        return M - 2 * b * np.sqrt(float(rbo.nikolai_bending_stiffness(c, D, M)) / A1)

    return scipy.optimize.brentq(f, 1e-9, 1.0, xtol=1e-15)


# --------------------------------------------------------------------------------------------
# The second Lyapunov coefficient
# --------------------------------------------------------------------------------------------

W, G1, A2, B2, LAM = 1.3, 0.7, -0.3, 0.2, 0.8


def _normal_form(Y):
    """z' = i W z + i G1 z|z|^2 + (A2 + i B2) z|z|^4 (z = x + iy; l1 = 0 since G1 is
    imaginary) and a stable direction s' = -LAM s + x y driven by it."""
    x, y, s = Y[0], Y[1], Y[2]
    r2 = x * x + y * y
    dx = -W * y - G1 * y * r2 + (A2 * x - B2 * y) * r2 * r2
    dy = W * x + G1 * x * r2 + (A2 * y + B2 * x) * r2 * r2
    return jnp.stack([dx, dy, -LAM * s + x * y])


# Near-identity shears X_i += f(X), each with an explicit inverse: a nonlinear change of
# coordinates that mixes the centre and stable directions (curved centre manifold, quadratic and
# cubic terms everywhere), with the identity as its linear part.
_SHEARS = (
    (2, lambda Y: 0.4 * Y[0] ** 2 - 0.7 * Y[0] * Y[1]),
    (0, lambda Y: 0.3 * Y[2] ** 2 + 0.9 * Y[2] * Y[1] - 0.2 * Y[1] ** 3),
    (1, lambda Y: 0.6 * Y[0] * Y[2] + 0.5 * Y[0] ** 3 + 0.3 * Y[0] ** 2),
)


def _transformed(X):
    Y = X
    for i, f in reversed(_SHEARS):
        Y = Y.at[i].add(-f(Y))

    def phi(Y):
        for i, f in _SHEARS:
            Y = Y.at[i].add(f(Y))
        return Y

    return jax.jvp(phi, (Y,), (_normal_form(Y),))[1]


@pytest.mark.slow  # cost: ~12 s, a fifth-order jet compiled
def test_second_lyapunov_is_invariant_under_changes_of_coordinates():
    """With x = zq + conj(zq), |q| = 1, q = (1, -i, 0)/sqrt2, the quintic coefficient of w = z/sqrt2
    is 4(A2 + iB2), so l2 = Re G32/(12 W) = 4 A2/W; at l1 = 0 it is an invariant of smooth
    changes of coordinates, and a stable direction slaved to the centre leaves it unchanged."""
    q = jnp.asarray(np.array([1.0, -1.0j, 0.0]) / np.sqrt(2.0))
    x0 = jnp.zeros(3)
    assert float(rbo.first_lyapunov_coefficient(_transformed, x0, W, q, q)) == pytest.approx(
        0.0, abs=1e-12
    )
    l2 = jax.jit(lambda x: rbo.second_lyapunov_coefficient(_transformed, x, W, q, q))(x0)
    assert float(l2) == pytest.approx(4 * A2 / W, rel=1e-8)


# --------------------------------------------------------------------------------------------
# The Bautin point of the damped Nikolai problem
# --------------------------------------------------------------------------------------------

B = 0.1


@pytest.fixture(scope="module")
def bautin():
    return rbo.bautin_point(nikolai, {"b": B, "c": C}, ("M", "A3"), (0.2, 1.2))


def test_bautin_point_lies_on_the_hopf_curve_where_l1_changes_sign(bautin):
    """M_B = 2b sqrt(K(M_B)/A1) (the critical load does not depend on A3); l1 of hopf_point
    changes sign across A3_B and is linear in A3 (A3 enters only the gyroscopic term), so A3_B is
    also the root of the line through two independent Hopf points; l2 != 0 (negative: the cycles
    of the hard side fold back)."""
    assert bool(bautin.ok)
    M_B, A3_B = (float(v) for v in bautin.value)
    assert M_B == pytest.approx(critical_moment(B), rel=1e-10)
    assert float(bautin.frequency) == pytest.approx(
        np.sqrt(float(rbo.nikolai_bending_stiffness(C, D, M_B)) / A1), rel=1e-10
    )
    lo, hi = (rbo.hopf_point(nikolai, {"b": B, "c": C, "A3": a}, "M", 0.2) for a in (1.0, 1.6))
    l_lo, l_hi = float(lo.first_lyapunov), float(hi.first_lyapunov)
    assert l_lo < 0 < l_hi
    assert A3_B == pytest.approx(1.0 - l_lo * (1.6 - 1.0) / (l_hi - l_lo), abs=1e-9)
    assert abs(float(bautin.first_lyapunov)) < 1e-12
    assert float(bautin.lyapunov_slope) == pytest.approx((l_hi - l_lo) / 0.6, rel=1e-7)
    assert float(bautin.second_lyapunov) < -1e-5


def test_bautin_point_is_independent_of_the_guess_and_the_step(bautin):
    """A3_B to 1e-8 from another guess on either side of the sign change and other first steps
    of the secant."""
    for guess, step in (((0.19, 2.5), 1e-2), ((0.21, 0.5), 1e-4)):
        other = rbo.bautin_point(nikolai, {"b": B, "c": C}, ("M", "A3"), guess, step=step)
        assert bool(other.ok)
        np.testing.assert_allclose(np.asarray(other.value), np.asarray(bautin.value), atol=1e-8)
        assert float(other.second_lyapunov) == pytest.approx(
            float(bautin.second_lyapunov), rel=1e-6
        )


def test_bautin_point_gradient_matches_finite_differences(bautin):
    """d(M_B, A3_B)/db and d/dc by the implicit function theorem (jax.jacrev) against central
    differences of Bautin points solved again; dM_B/db also against the closed form."""

    def value(b, c):
        return rbo.bautin_point(nikolai, {"b": b, "c": c}, ("M", "A3"), (0.2, 1.3)).value

    J = np.stack(jax.jacrev(value, argnums=(0, 1))(jnp.asarray(B), jnp.asarray(C)), axis=1)
    h = 1e-5
    fd_b = (np.asarray(value(B + h, C)) - np.asarray(value(B - h, C))) / (2 * h)
    fd_c = (np.asarray(value(B, C + h)) - np.asarray(value(B, C - h))) / (2 * h)
    np.testing.assert_allclose(J[:, 0], fd_b, rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(J[:, 1], fd_c, rtol=1e-5, atol=1e-8)
    assert J[0, 0] == pytest.approx(
        (critical_moment(B + h) - critical_moment(B - h)) / (2 * h), rel=1e-6
    )
    assert abs(J[1, 0]) > 1e-3  # A3_B moves with the damping


def test_bautin_point_failures_are_statuses():
    """An equilibrium guess on the singular sphere |theta| = 2 pi (4.11): the Hopf solve fails and
    the status says so (NaN values), never an exception; bad arguments raise."""
    point = rbo.bautin_point(
        nikolai, {"b": B, "c": C}, ("M", "A3"), (0.2, 1.2), theta_guess=(0.0, 0.0, 2 * np.pi)
    )
    assert point.status == rbo.BautinStatus.hopf_failed
    assert np.all(np.isnan(np.asarray(point.value)))
    with pytest.raises(ValueError, match="parameters"):
        rbo.bautin_point(nikolai, {"b": B, "c": C}, ("M", "M"), (0.2, 1.2))
    with pytest.raises(ValueError, match="guess"):
        rbo.bautin_point(nikolai, {"b": B, "c": C}, ("M", "A3"), 0.2)
