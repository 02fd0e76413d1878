"""Pseudo-arclength continuation of the Hopf boundary (issue 23): a boundary of the damped
Nikolai problem (4.57), (4.84) made to fold in the second parameter (natural continuation stops
at its turning point, arclength continuation passes it and locates it), and the Bautin and
Bogdanov-Takens points of the boundary in the stiffness c with a cubic anti-damping moment."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import rbo_jax as rbo

K_AXIS = (0.0, 0.0, 1.0)
A1, A3, C, D = 1.0, 0.6, 1.0, 2.0
B = 0.1  # friction of the second problem
M0 = 0.02  # the folded boundary's first point


def folded(M, beta):
    """Friction b = beta - (M - 0.3)^2: on the boundary M = 2b sqrt(K(M)/A1) (the damped
    bending equation's Routh-Hurwitz condition, K of (4.69)), so beta(M) = M/(2 sqrt(K/A1)) +
    (M - 0.3)^2, which has a minimum near M = 0.05 (b > 0 there)."""
    return rbo.nikolai_model(M, C, D, A1=A1, A3=A3, k=K_AXIS, friction=beta - (M - 0.3) ** 2)


def beta_on_boundary(M):
    K = float(rbo.nikolai_bending_stiffness(C, D, M))
    return M / (2 * np.sqrt(K / A1)) + (M - 0.3) ** 2


class CubicAntiDamping(eqx.Module):
    """The moment e|omega|^2 omega (a Module: e is a leaf). It leaves the linearization, hence
    the boundary, unchanged and shifts l1 by a multiple of e."""

    e: jax.Array

    def __call__(self, t, theta, omega):
        return self.e * jnp.dot(omega, omega) * omega


def stiffness_model(M, e, c):
    model = rbo.nikolai_model(M, c, D, A1=A1, A3=A3, k=K_AXIS, friction=B)
    loads = list(model.loads) + [rbo.CallableLoad(CubicAntiDamping(e))]
    return rbo.RigidBodyOscillator(model.inertia, model.foundation, loads)


@pytest.fixture(scope="module")
def minimum():
    """The turning point of the folded boundary: the minimum of beta(M), by Brent's method on
    the closed form."""
    r = scipy.optimize.minimize_scalar(
        beta_on_boundary, bounds=(0.01, 0.15), method="bounded", options={"xatol": 1e-12}
    )
    return float(r.x), float(r.fun)


@pytest.fixture(scope="module")
def arc():
    """From M0, first with decreasing beta, through the turning point, until beta > 0.1."""
    beta0 = beta_on_boundary(M0)
    return rbo.continue_hopf(
        folded, {}, "M", M0, "beta", [beta0, 0.08, 0.1], method="arclength", ds_max=0.02
    )


def test_arclength_passes_the_turning_point_of_the_boundary(arc, minimum):
    """Beta decreases, turns at the minimum of the closed form (reported as a turning point,
    the vertex of the parabola through three points: error O(s^3)) and increases again, while
    M keeps increasing; every point satisfies the closed form."""
    M, beta = arc["M"].values, arc["beta"].values
    assert arc.attrs["method"] == "arclength"
    assert arc.attrs["stop_reason"] == "beta left [0.08, 0.1]"
    assert np.all(arc["status"].values == 0)
    assert np.all(np.diff(M) > 0)
    np.testing.assert_allclose(beta, [beta_on_boundary(m) for m in M], rtol=0, atol=1e-9)
    i = int(np.argmin(beta))
    assert 2 <= i < M.size - 2 and beta[-1] > 0.1
    assert np.all(np.diff(beta[: i + 1]) < 0) and np.all(np.diff(beta[i:]) > 0)
    assert list(arc["special_type"].values) == ["turning_point"]
    M_min, beta_min = minimum
    assert float(arc["special_value"][0]) == pytest.approx(beta_min, abs=1e-5)
    assert float(arc["special_parameter"][0]) == pytest.approx(M_min, abs=1e-4)
    assert int(arc["special_index"][0]) in (i - 1, i)
    # the frequency sqrt(K/A1) of the bending roots; the transversality dRe p/dM changes sign
    K = np.array([float(rbo.nikolai_bending_stiffness(C, D, m)) for m in M])
    np.testing.assert_allclose(arc["frequency"].values, np.sqrt(K / A1), rtol=1e-10)
    np.testing.assert_allclose(arc["theta"].values[:, 2], M / D, atol=1e-12)
    trans = arc["transversality"].values
    assert np.all(trans[M < M_min - 1e-3] < 0) and np.all(trans[M > M_min + 1e-3] > 0)


def test_far_side_of_the_turning_point_matches_hopf_point(arc, minimum):
    """Beyond the turning point the frequency, l1 and transversality are those of
    rbo.hopf_point started there (the same compiled program)."""
    far = np.flatnonzero(arc["M"].values > minimum[0] + 0.02)
    assert far.size >= 2
    for j in far[-2:]:
        beta, M = float(arc["beta"][j]), float(arc["M"][j])
        h = rbo.hopf_point(folded, {"beta": beta}, "M", M)
        assert bool(h.ok)
        assert float(h.value) == pytest.approx(M, rel=1e-10)
        assert float(h.frequency) == pytest.approx(float(arc["frequency"][j]), rel=1e-10)
        l1 = float(arc["first_lyapunov"][j])
        assert float(h.first_lyapunov) == pytest.approx(l1, rel=1e-7)
        trans = float(arc["transversality"][j])
        assert float(h.transversality) == pytest.approx(trans, rel=1e-7)


def test_natural_continuation_stops_at_the_turning_point(minimum):
    """The natural mode solves at fixed beta: below the minimum there is no Hopf point near
    the curve, and the status turns to not_converged (the message of continue_hopf points to
    method="arclength")."""
    beta_min = minimum[1]
    values = np.linspace(beta_on_boundary(M0), 0.0868, 10)
    curve = rbo.continue_hopf(folded, {}, "M", M0, "beta", values)
    status = curve["status"].values
    ok = values > beta_min + 1e-4
    assert np.all(status[ok] == 0)
    code = curve["status"].attrs["flag_meanings"].split().index("not_converged")
    assert np.all(status[values < beta_min] == code)
    assert np.all(np.isnan(curve["M"].values[values < beta_min]))
    M = curve["M"].values[ok]
    np.testing.assert_allclose(values[ok], [beta_on_boundary(m) for m in M], atol=1e-9)
    assert 'method="arclength"' in rbo.continue_hopf.__doc__


@pytest.fixture(scope="module")
def stiffness_arc():
    """The boundary in the stiffness c from c = 1 towards 0, with e = 0.03: l1 changes sign
    near c = 0.6, and at c = 0 the frequency sqrt(K/A1) and M vanish (the double zero root of
    (A1 p^2 + bp + K)^2 + M^2/4 = 0)."""
    return rbo.continue_hopf(
        stiffness_model, {"e": 0.03}, "M", 0.2, "c", [1.0, -0.1], method="arclength"
    )


@pytest.mark.slow  # cost: the stiffness boundary's continuation, ~30 s
def test_bogdanov_takens_end_of_the_boundary(stiffness_arc):
    """The branch ends where the frequency vanishes: c = M = 0 in the closed form (K(c, 0) =
    c, M = 2b sqrt(K/A1)), located by extrapolation along the arclength."""
    ds = stiffness_arc
    M, c = ds["M"].values, ds["c"].values
    K = np.array([float(rbo.nikolai_bending_stiffness(ci, D, m)) for ci, m in zip(c, M)])
    np.testing.assert_allclose(M, 2 * B * np.sqrt(K / A1), rtol=0, atol=1e-10)
    np.testing.assert_allclose(ds["frequency"].values, np.sqrt(K / A1), rtol=1e-9)
    assert ds.attrs["stop_reason"] == "Bogdanov-Takens point: the frequency tends to 0"
    types = list(ds["special_type"].values)
    assert types[-1] == "bogdanov_takens"
    assert abs(float(ds["special_value"][-1])) < 1e-5  # c
    assert abs(float(ds["special_parameter"][-1])) < 1e-5  # M
    assert float(ds["special_frequency"][-1]) == 0.0
    assert int(ds["special_index"][-1]) == ds.sizes["point"] - 1
    assert float(ds["frequency"][-1]) < 0.01
    assert np.all(np.diff(c) < 0)


@pytest.mark.slow  # cost: the stiffness boundary's continuation, ~30 s
def test_bautin_point_where_l1_changes_sign(stiffness_arc):
    """The Bautin point lies between the two points where l1 changes sign, located exactly by
    rbo.bautin_point: there l1 of rbo.hopf_point is zero."""
    ds = stiffness_arc
    types = list(ds["special_type"].values)
    assert types.count("bautin") == 1
    k = types.index("bautin")
    i = int(ds["special_index"][k])
    l1 = ds["first_lyapunov"].values
    assert l1[0] > 0 > l1[-2]
    assert l1[i] > 0 > l1[i + 1]
    c_b, M_b = float(ds["special_value"][k]), float(ds["special_parameter"][k])
    assert float(ds["c"][i + 1]) < c_b < float(ds["c"][i])
    h = rbo.hopf_point(stiffness_model, {"e": 0.03, "c": c_b}, "M", M_b)
    assert float(h.value) == pytest.approx(M_b, abs=1e-3)
    assert abs(float(h.first_lyapunov)) < 0.1 * (l1[i] - l1[i + 1])
    # located by rbo.bautin_point, not only interpolated: on the curve, and l1 = 0 there
    assert float(h.value) == pytest.approx(M_b, abs=1e-10)
    assert abs(float(h.first_lyapunov)) < 1e-10
    assert float(ds["special_first_lyapunov"][k]) == 0.0


def test_arclength_arguments_are_checked():
    with pytest.raises(ValueError, match="'b'"):
        rbo.continue_hopf(
            lambda M, b, c: folded(M, c), {"b": np.array([0.1, 0.2])}, "M", 0.1, "c",
            [1.0, 0.5], method="arclength",
        )  # fmt: skip
    with pytest.raises(ValueError, match="two distinct"):
        rbo.continue_hopf(folded, {}, "M", 0.1, "beta", [0.1], method="arclength")
    with pytest.raises(ValueError, match="method"):
        rbo.continue_hopf(folded, {}, "M", 0.1, "beta", [0.1, 0.2], method="pseudo")
