"""Stability maps and critical loads (rbo_jax.stability_map, a preset of the batch engine).

Expected values: per-point spectra from rbo_jax.spectrum (the map must reproduce them),
equilibria found by scipy's brentq, the closed forms (4.62), (4.69), and the small-load limit
of the damped Nikolai problem derived in a docstring below.
"""

from __future__ import annotations

import resource

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import spectrum_match_error
from scipy.optimize import brentq

import rbo_jax as rbo
from rbo_jax.batch import STABILITY_KIND_NAMES
from rbo_jax.stability import StabilityKind

K = jnp.array([0.0, 0.0, 1.0])
KN = np.array([0.0, 0.0, 1.0])


_match_error = spectrum_match_error


def _assert_same_spectra(p, q, atol):
    """Per grid point, the same eigenvalues as multisets (sorting by real part may order
    conjugate pairs with Re p ≈ ±1e-17 either way); NaN at the same points."""
    p, q = np.asarray(p).reshape(-1, 6), np.asarray(q).reshape(-1, 6)
    np.testing.assert_array_equal(np.isnan(p), np.isnan(q))
    for a, b in zip(p, q):
        if not np.any(np.isnan(a)):
            assert _match_error(a, b) <= atol


# ---------------------------------------------------------------------------------------------
# A map with failing points: a saturating isotropic foundation under a follower moment
# ---------------------------------------------------------------------------------------------


def _saturating(s):
    """U = F(θ²) = ½ log(1 + θ²): the elastic moment |2F'(θ²)θ| = |θ|/(1 + θ²) is at most ½,
    so under a follower moment |M| > ½ no equilibrium exists."""
    return 0.5 * jnp.log1p(s)


def saturating_model(M, A3):
    return rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(1.0, A3, K),
        rbo.IsotropicFoundation(_saturating),
        rbo.FollowerMoment(M, K),
    )


def saturating_theta_eq(M, A3):
    """θ = xk with x/(1 + x²) = M (4.61), the root through 0: x = 2M/(1 + √(1 − 4M²)); NaN
    where |M| > ½."""
    return 2 * M / (1 + jnp.sqrt(1 - 4 * M**2)) * K


def _saturating_root(M):
    """The same root by brentq, independently of the closed form."""
    if M == 0:
        return 0.0
    return brentq(lambda x: x / (1 + x * x) - M, -1.0, 1.0, xtol=1e-15, rtol=1e-15)


SAT_AXES = {"M": np.array([0.0, 0.2, -0.35, 0.45, 0.55, 1.0, 0.7]), "A3": np.array([0.5, 1.3])}


@pytest.fixture(scope="module")
def saturating_map():
    """Newton's equilibria (the default), 14 points in chunks of 4: the last chunk is padded."""
    return rbo.stability_map(saturating_model, SAT_AXES, chunk_size=4)


@jax.jit
def _spectrum(model, theta):
    return rbo.spectrum(model, theta)


def test_map_layout(saturating_map):
    """Dimensions, coordinates, dtypes and attributes of the Dataset."""
    ds = saturating_map
    assert dict(ds.sizes) == {"M": 7, "A3": 2, "mode": 6, "component": 3}
    np.testing.assert_array_equal(ds["M"].values, SAT_AXES["M"])
    np.testing.assert_array_equal(ds["A3"].values, SAT_AXES["A3"])
    np.testing.assert_array_equal(ds["mode"].values, np.arange(6))
    assert list(ds["component"].values) == ["x", "y", "z"]
    assert ds["eigenvalues"].dims == ("M", "A3", "mode")
    assert ds["theta_eq"].dims == ("M", "A3", "component")
    for name in ("spectral_abscissa", "kind", "equilibrium_status"):
        assert ds[name].dims == ("M", "A3")
    assert ds["eigenvalues"].dtype == np.complex128
    assert ds["kind"].dtype == np.int8 and ds["equilibrium_status"].dtype == np.int8
    assert ds["kind"].attrs["flag_meanings"].split() == [
        "asymptotically_stable",
        "marginally_stable",
        "divergence",
        "flutter",
        "undefined",
    ]
    assert ds["kind"].attrs["flag_values"] == [0, 1, 2, 3, 4]
    assert list(STABILITY_KIND_NAMES) == ds["kind"].attrs["flag_meanings"].split()
    assert ds["equilibrium_status"].attrs["flag_meanings"].split()[0] == "successful"
    assert ds.attrs["classify_rtol"] == 1e-9


def test_map_failing_points_are_flagged_and_the_rest_completes(saturating_map):
    """Points without equilibrium (|M| > ½) are flagged: equilibrium_status ≠ 0, NaN
    eigenvalues, kind 'undefined'. Every other point has the equilibrium xk of (4.61) (brentq)
    and the spectrum, abscissa and classification of that point computed on its own."""
    ds = saturating_map
    undefined = STABILITY_KIND_NAMES.index("undefined")
    n_ok = 0
    for i, M in enumerate(SAT_AXES["M"]):
        for j, A3 in enumerate(SAT_AXES["A3"]):
            pt = ds.isel(M=i, A3=j)
            if abs(M) > 0.5:
                assert int(pt["equilibrium_status"]) != 0
                assert np.all(np.isnan(pt["eigenvalues"].values))
                assert np.isnan(float(pt["spectral_abscissa"]))
                assert int(pt["kind"]) == undefined
                continue
            n_ok += 1
            assert int(pt["equilibrium_status"]) == 0
            theta = pt["theta_eq"].values
            np.testing.assert_allclose(theta, _saturating_root(M) * KN, atol=1e-12)
            p = np.asarray(_spectrum(saturating_model(M, A3), jnp.asarray(theta)))
            _assert_same_spectra(pt["eigenvalues"].values, p, atol=1e-12)
            np.testing.assert_array_equal(
                pt["eigenvalues"].values, np.sort_complex(pt["eigenvalues"].values)
            )
            kind, a = rbo.classify(jnp.asarray(p))
            np.testing.assert_allclose(float(pt["spectral_abscissa"]), float(a), atol=1e-13)
            assert getattr(StabilityKind, STABILITY_KIND_NAMES[int(pt["kind"])]) == kind
            expected = "marginally_stable" if M == 0 else "flutter"
            assert STABILITY_KIND_NAMES[int(pt["kind"])] == expected
    assert n_ok == 8


@pytest.fixture(scope="module")
def closed_form_maps():
    """theta_eq_fn path, in chunks of 4 (padded) and in a single chunk of 14."""
    return {
        n: rbo.stability_map(
            saturating_model, SAT_AXES, theta_eq_fn=saturating_theta_eq, chunk_size=n
        )
        for n in (4, 14)
    }


def test_map_chunk_padding_equals_single_chunk(closed_form_maps):
    """14 points in chunks of 4 (the last one padded) give the single-chunk result."""
    padded, one = closed_form_maps[4], closed_form_maps[14]
    assert set(padded.data_vars) == set(one.data_vars)
    _assert_same_spectra(padded["eigenvalues"].values, one["eigenvalues"].values, atol=1e-14)
    for name in ("spectral_abscissa", "theta_eq"):
        np.testing.assert_allclose(
            padded[name].values, one[name].values, rtol=0, atol=1e-14, equal_nan=True, err_msg=name
        )
    for name in ("kind", "equilibrium_status"):
        np.testing.assert_array_equal(padded[name].values, one[name].values, err_msg=name)


def test_map_closed_form_equilibrium_equals_newton(saturating_map, closed_form_maps):
    """theta_eq_fn (the closed-form root) gives Newton's map wherever an equilibrium exists;
    where the closed form is NaN the points are 'undefined' too."""
    closed = closed_form_maps[14]
    ok = saturating_map["equilibrium_status"].values == 0
    assert ok.sum() == 8
    np.testing.assert_allclose(
        closed["theta_eq"].values[ok], saturating_map["theta_eq"].values[ok], rtol=0, atol=1e-13
    )
    assert np.all(np.isnan(closed["theta_eq"].values[~ok]))
    _assert_same_spectra(
        closed["eigenvalues"].values[ok], saturating_map["eigenvalues"].values[ok], atol=1e-12
    )
    assert np.all(np.isnan(closed["eigenvalues"].values[~ok]))
    np.testing.assert_array_equal(closed["kind"].values, saturating_map["kind"].values)


# ---------------------------------------------------------------------------------------------
# Critical load of the damped Nikolai problem
# ---------------------------------------------------------------------------------------------

A1, C_BEND, D_TORS = 1.0, 1.0, 2.0


def damped_model(b, M):
    return rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(A1, 0.6, K),
        rbo.QuadraticFoundation(C_BEND, D_TORS, K),
        (rbo.FollowerMoment(M, K), rbo.Friction(b)),
    )


def damped_theta_eq(b, M):
    return (M / D_TORS) * K  # (4.62): friction (4.84) vanishes at rest


B_AXIS = np.array([0.0, 0.01, 0.05, 0.1, 0.2, 2.0])


@pytest.fixture(scope="module")
def critical():
    return rbo.critical_load(damped_model, {"b": B_AXIS}, "M", 2.0, theta_eq_fn=damped_theta_eq)


@jax.jit
def _abscissa(b, M):
    return jnp.max(jnp.real(rbo.fast_spectrum(damped_model(b, M), damped_theta_eq(b, M))))


def test_critical_load_of_damped_nikolai_problem(critical):
    """Friction (4.84) removes the paradox below a critical follower load: M_cr(0) ≈ 0 (the
    undamped problem flutters at any M ≠ 0), M_cr increases with b, and for small b it is
    2b√(c/A1): the bending roots of (4.69) with friction, A1p² + bp + c ± iM/2 ≈ 0, cross
    the imaginary axis at p = i√(c/A1), M = 2b√(c/A1) (corrections O(b²)). For b = 2 the
    equilibrium is stable on the whole interval (0, 2]: inf."""
    cr = critical
    assert cr.dims == ("b",) and cr.name == "critical_M"
    np.testing.assert_array_equal(cr["b"].values, B_AXIS)
    values = cr.values
    assert 0 <= values[0] <= 1e-7
    assert np.all(np.diff(values[:-1]) > 0)
    small = slice(1, 5)
    estimate = 2 * B_AXIS[small] * np.sqrt(C_BEND / A1)
    np.testing.assert_array_less(np.abs(values[small] / estimate - 1), 0.5 * B_AXIS[small] ** 2)
    assert np.isinf(values[-1])


def test_abscissa_changes_sign_at_the_critical_load(critical):
    """max Re p < 0 just below the returned M_cr and > 0 just above it (b > 0); for b = 2,
    max Re p < 0 at load_max."""
    for b, M_cr in zip(B_AXIS[1:-1], critical.values[1:-1]):
        below = float(_abscissa(b, M_cr * (1 - 1e-3)))
        above = float(_abscissa(b, M_cr * (1 + 1e-3)))
        assert below < 0 < above, (b, M_cr, below, above)
    assert float(_abscissa(B_AXIS[-1], 2.0)) < 0


def test_map_classification_agrees_with_the_critical_load(critical):
    """Issue 49 F: at every point of a stability map (b, M) the classification (classify's
    test) is unstable exactly where M lies past the critical load of the same test."""
    M = np.linspace(0.05, 1.95, 9)
    ds = rbo.stability_map(damped_model, {"b": B_AXIS, "M": M}, theta_eq_fn=damped_theta_eq)
    assert np.all(ds["equilibrium_status"].values == 0)
    names = np.array(ds["kind"].attrs["flag_meanings"].split(), dtype=object)
    unstable = np.isin(names[ds["kind"].values], ["flutter", "divergence"])
    assert unstable.any() and not unstable.all()
    np.testing.assert_array_equal(unstable, M[None, :] > critical.values[:, None])


# ---------------------------------------------------------------------------------------------
# Input validation
# ---------------------------------------------------------------------------------------------


def nikolai_model(M, c, A3):
    """The Nikolai problem: quadratic foundation (4.50), follower moment (4.57), A1 = 1, d = 2."""
    return rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(1.0, A3, K),
        rbo.QuadraticFoundation(c, 2.0, K),
        rbo.FollowerMoment(M, K),
    )


@pytest.mark.parametrize(
    "axes, match",
    [
        ({}, "non-empty mapping"),
        ({"M": np.ones((2, 2))}, "1-D"),
        ({"M": np.array([])}, "non-empty 1-D"),
        ({"M": np.array([0.1, np.nan])}, "non-finite"),
        ({"M": np.array([0.1, np.inf])}, "non-finite"),
        ([0.1, 0.2], "mapping"),
    ],
    ids=["empty", "2-D", "empty-axis", "nan", "inf", "not-a-mapping"],
)
def test_stability_map_bad_axes(axes, match):
    with pytest.raises(ValueError, match=match):
        rbo.stability_map(lambda M: nikolai_model(M, 1.0, 0.6), axes)


def test_stability_map_and_critical_load_bad_arguments():
    with pytest.raises(ValueError, match="chunk_size"):
        rbo.stability_map(lambda M: nikolai_model(M, 1.0, 0.6), {"M": [0.1]}, chunk_size=0)
    with pytest.raises(ValueError, match="cannot also be an axis"):
        rbo.critical_load(damped_model, {"b": B_AXIS, "M": [0.1]}, "M", 1.0)
    with pytest.raises(ValueError, match="must exceed"):
        rbo.critical_load(damped_model, {"b": B_AXIS}, "M", 0.0)
    with pytest.raises(ValueError, match="non-empty"):
        rbo.critical_load(damped_model, {}, "M", 1.0)
    with pytest.raises(ValueError, match="non-finite"):
        rbo.critical_load(damped_model, {"b": [np.nan]}, "M", 1.0)
    with pytest.raises(TypeError, match="hashable"):
        rbo.stability_map(
            lambda M: nikolai_model(M, 1.0, 0.6), {"M": [0.1]}, max_steps=np.array([3, 4])
        )


# ---------------------------------------------------------------------------------------------
# A million points
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_million_point_map_bounded_memory():
    """A 10⁶-point map of the Nikolai problem (Newton's equilibria) in chunks of 50 000
    completes without the memory growing with the grid (peak RSS growth < 2 GB) and agrees with
    (4.62) and (4.69) at sampled points."""
    axes = {"M": np.linspace(-1.0, 1.0, 1000), "c": np.linspace(0.5, 2.0, 1000)}

    def model_fn(M, c):
        return nikolai_model(M, c, 0.6)

    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    ds = rbo.stability_map(model_fn, axes, chunk_size=50_000, theta_guess=jnp.array([0.0, 0, 0.1]))
    growth_gb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 2**20
    assert growth_gb < 2.0, growth_gb  # ~0.5 GB measured: outputs ~0.15 GB + one chunk
    assert ds["eigenvalues"].shape == (1000, 1000, 6)
    np.testing.assert_array_equal(ds["equilibrium_status"].values, 0)
    rng = np.random.default_rng(69)
    for i, j in rng.integers(0, 1000, size=(50, 2)):
        M, c = axes["M"][i], axes["c"][j]
        assert (
            _match_error(ds["eigenvalues"].values[i, j], rbo.nikolai_spectrum(1.0, 0.6, c, 2.0, M))
            <= 1e-10
        )
        np.testing.assert_allclose(ds["theta_eq"].values[i, j], (M / 2.0) * KN, atol=1e-12)
    flutter = STABILITY_KIND_NAMES.index("flutter")
    assert np.all(ds["kind"].values == flutter)  # no M = 0 on this axis: every point flutters


def test_equilibrium_stability_is_the_map_point_4_61_4_69():
    """rbo_jax.equilibrium_stability, the one place of equilibrium (4.61) -> spectrum (4.69) ->
    classification: the closed-form equilibrium (4.62) and Newton give the same point and the
    roots of (4.69); a failed equilibrium gives NaN and its status, not an exception."""
    M, c, d = 0.4, 1.2, 2.0
    model = rbo.nikolai_model(M, c, d, A3=0.7)
    closed = rbo.equilibrium_stability(model, theta_eq=rbo.nikolai_equilibrium(M, d))
    newton = rbo.equilibrium_stability(model, jnp.zeros(3))
    for r in (closed, newton):
        assert bool(r.ok)
        np.testing.assert_allclose(r.theta, [0.0, 0.0, M / d], atol=1e-12)
        assert spectrum_match_error(r.eigenvalues, rbo.nikolai_spectrum(1.0, 0.7, c, d, M)) < 1e-10
        assert rbo.StabilityKind[r.kind] == rbo.StabilityKind[rbo.StabilityKind.flutter]
    bad = rbo.equilibrium_stability(model, theta_eq=jnp.array([jnp.nan, 0.0, 0.0]))
    assert not bool(bad.ok) and bool(jnp.all(jnp.isnan(bad.eigenvalues)))
    assert rbo.StabilityKind[bad.kind] == rbo.StabilityKind[rbo.StabilityKind.undefined]


def test_critical_value_scans_then_bisects():
    """rbo_jax.maps.critical_value: the first change of a monotone flag to 1e-12, inf when the
    flag never turns, the lower end when it is already on; the flag is traced once (the scan
    and the bisection one loop: one copy of it compiled)."""
    from rbo_jax.maps import critical_value

    traced = []

    def flag(v):
        traced.append(v)
        return v > 0.3141592653

    x = float(critical_value(flag, 0.0, 1.0, n_scan=8, n_bisect=48))
    assert abs(x - 0.3141592653) < 1e-12
    assert len(traced) == 1
    assert float(critical_value(lambda v: v > 2.0, 0.0, 1.0)) == np.inf
    assert abs(float(critical_value(lambda v: v > -1.0, 0.0, 1.0, n_scan=4)) - 0.0) < 1e-12


def test_first_change_under_vmap_with_a_batched_start():
    """first_change's ``like`` (a sweep's point: the loop's state starts batched, so that
    jax.vmap batches its body once) changes no value, for any values of the point (inf, NaN)."""
    from rbo_jax.stability._point import first_change

    a = jnp.array([0.05, 0.5, 0.9, 2.0])  # 0.05: below the scan's first point
    point = {"a": a, "other": jnp.array([np.nan, -3.0, np.inf, 1.0])}

    def search(a, point=None):
        return first_change(lambda v: (v > a).astype(jnp.int32), 0.0, 1.0, n_scan=8, like=point)

    plain = jax.vmap(search)(a)
    seeded = jax.vmap(search)(a, point)
    for x, y in zip(plain, seeded):
        np.testing.assert_array_equal(np.asarray(y), np.asarray(x))
    np.testing.assert_allclose(np.asarray(seeded[0][:3]), [0.05, 0.5, 0.9], atol=1e-12)
    assert np.isinf(float(seeded[0][3]))
