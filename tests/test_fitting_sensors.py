"""Sensor data as it comes (issue 51 A): quaternions of either sign, NaN for missing samples,
channels on different clocks, a gyroscope's constant bias fitted with the parameters."""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rbo_jax.fitting import TrajectoryData, fit, residuals, synthetic_sensor_data
from rbo_jax.foundations import QuadraticFoundation
from rbo_jax.inertia import transversely_isotropic_inertia
from rbo_jax.kinematics import turn_tensor
from rbo_jax.loads import Friction
from rbo_jax.model import RigidBodyOscillator

K = jnp.array([0.0, 0.0, 1.0])
A = transversely_isotropic_inertia(1.0, 0.6, K)
TRUE = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K), loads=(Friction(0.05),))
BIAS = np.array([0.02, -0.015, 0.01])


def test_quaternion_is_the_turn_tensor_of_either_sign():
    """q = (cos(|θ|/2), sin(|θ|/2) θ/|θ|) of Q(θ) = exp(θ×E): the data's Q equals turn_tensor,
    for q and -q, and agrees with SciPy's scalar-first convention."""
    rng = np.random.default_rng(0)
    theta = rng.normal(size=(6, 3))
    q = Rotation.from_rotvec(theta).as_quat(scalar_first=True)
    q *= np.array([1, -1, 1, -1, 1, -1.0])[:, None] * 3.0  # either sign, any positive norm
    d = TrajectoryData(np.arange(6.0), quaternion=q, Omega0=np.zeros(3))
    expected = np.stack([np.asarray(turn_tensor(jnp.asarray(t))) for t in theta])
    np.testing.assert_allclose(np.asarray(d.Q), expected, atol=1e-14)
    np.testing.assert_allclose(np.asarray(d.theta0), theta[0], atol=1e-12)


def test_nan_marks_a_missing_sample_and_the_rest_still_counts():
    ts = np.linspace(0.0, 1.0, 5)
    th = np.full((5, 3), 0.1)
    Om = np.ones((5, 3))
    th[1, 0] = np.nan  # the attitude of sample 1 is missing whole
    Om[2, 1] = np.nan  # one component of Ω at sample 2
    d = TrajectoryData(ts, theta=th, Omega=Om, sigma_theta=0.1, sigma_Omega=0.2)
    np.testing.assert_array_equal(np.asarray(d.attitude_weight), [1, 0, 1, 1, 1])
    np.testing.assert_array_equal(np.asarray(d.Omega_weight)[2], [1, 0, 1])
    assert np.all(np.isfinite(np.asarray(d.theta))) and np.all(np.isfinite(np.asarray(d.Omega)))
    # on the data's own values the residuals of the missing entries are zero
    model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    r = np.asarray(residuals(model, d, integrator="fast_simulate")).reshape(2, 5, 3)
    assert np.all(r[0, 1] == 0) and r[1, 2, 1] == 0 and np.all(np.isfinite(r))
    assert np.all(r[0, 2:] != 0)  # the model moves: the observed entries count


def test_bad_sensor_data_is_refused_naming_the_argument():
    ts = np.linspace(0.0, 1.0, 4)
    q = np.tile([1.0, 0, 0, 0], (4, 1))
    with pytest.raises(ValueError, match="quaternion must have shape"):
        TrajectoryData(ts, quaternion=q[:, :3], Omega0=np.zeros(3))
    with pytest.raises(ValueError, match="quaternion has zero norm at sample 2"):
        TrajectoryData(ts, quaternion=np.where(np.arange(4)[:, None] == 2, 0.0, q))
    with pytest.raises(ValueError, match="quaternion is all NaN"):
        TrajectoryData(ts, quaternion=np.full((4, 4), np.nan), Omega=np.zeros((4, 3)))
    with pytest.raises(ValueError, match="Omega is all NaN"):
        TrajectoryData(ts, quaternion=q, Omega=np.full((4, 3), np.nan))
    with pytest.raises(ValueError, match="ts must be strictly increasing"):
        TrajectoryData(ts[[0, 2, 1, 3]], quaternion=q, Omega0=np.zeros(3))
    with pytest.raises(ValueError, match="attitude once"):
        TrajectoryData(ts, quaternion=q, theta=np.zeros((4, 3)), Omega0=np.zeros(3))
    with pytest.raises(ValueError, match="Omega_bias given but Omega"):
        TrajectoryData(ts, quaternion=q, Omega0=np.zeros(3), Omega_bias="fit")
    with pytest.raises(ValueError, match="Omega_bias must be"):
        TrajectoryData(ts, quaternion=q, Omega=np.zeros((4, 3)), Omega_bias="yes")
    with pytest.raises(ValueError, match="quaternion must be a pair"):
        TrajectoryData.merge(quaternion=q, Omega=(ts, np.zeros((4, 3))))


def test_merge_puts_channels_on_one_time_axis():
    """A gyro on its own clock: the union of the times, NaN (missing) where a channel has no
    sample; t0 is the first time of either channel."""
    tq = np.array([0.0, 0.1, 0.2])
    tg = np.array([0.05, 0.1, 0.15, 0.25])
    q = np.tile([1.0, 0, 0, 0], (3, 1))
    g = np.arange(12.0).reshape(4, 3)
    d = TrajectoryData.merge(quaternion=(tq, q), Omega=(tg, g), Omega_bias=np.zeros(3))
    np.testing.assert_allclose(np.asarray(d.ts), [0.0, 0.05, 0.1, 0.15, 0.2, 0.25])
    np.testing.assert_array_equal(np.asarray(d.attitude_weight), [1, 0, 1, 0, 1, 0])
    np.testing.assert_array_equal(np.asarray(d.Omega_weight)[:, 0], [0, 1, 1, 1, 0, 1])
    np.testing.assert_allclose(np.asarray(d.Omega)[2], g[1])
    assert float(d.t0) == 0.0
    assert d.initial_state_guessed  # Ω0 from the gyro's first sample, at t = 0.05
    model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    with pytest.warns(UserWarning, match="initial state was taken from a sample after t0"):
        try:
            fit(model, d, lambda m: m.foundation.c, max_steps=0)
        except ValueError:
            pass  # max_steps = 0 is refused after the warning


def _rig(th0, Om0, seed, T=3.0):
    """A motion-capture system (quaternions at 50 Hz with a jitter of half a period, either
    sign, 5 % dropped) and a gyroscope at 100 Hz on its own clock with a bias, white noise and
    a 0.3 s gap."""
    return synthetic_sensor_data(
        TRUE,
        th0,
        Om0,
        T,
        quaternion_rate=50.0,
        gyro_rate=100.0,
        bias=BIAS,
        jitter=0.5,
        dropped=0.05,
        gaps=((1.0, 1.3),),
        seed=seed,
    )


def test_synthetic_sensor_data_follows_its_sensor_model():
    """The synthetic rig's records: the clocks, the dropped samples and the gap as NaN, and the
    whitened residuals at the truth (model, bias, initial state) N(0, 1) over the observed
    components: their mean square 1 within its sampling error (χ² of ~1,600 components)."""
    th0, Om0 = np.array([0.5, -0.2, 0.3]), np.array([0.1, 0.8, -0.5])
    data = _rig(th0, Om0, 5)
    q_seen = np.asarray(data.attitude_weight) > 0
    g_seen = np.all(np.asarray(data.Omega_weight) > 0, axis=1)
    assert q_seen.sum() == pytest.approx(0.95 * 150, abs=12) and q_seen[0]
    ts = np.asarray(data.ts)
    assert not g_seen[(ts > 1.0) & (ts < 1.3)].any() and g_seen.sum() == 300 - 30
    assert data.fit_Omega_bias and float(data.t0) == 0.0
    r = np.asarray(residuals(TRUE, data, th0, Om0, Omega_bias=BIAS, rtol=1e-12, atol=1e-12))
    n = 3 * (q_seen.sum() + g_seen.sum())
    assert np.sum(r**2) / n == pytest.approx(1.0, abs=4 * np.sqrt(2 / n))
    with pytest.raises(ValueError, match="gyro_rate"):
        synthetic_sensor_data(TRUE, th0, Om0, 1.0, gyro_rate=-1.0)
    with pytest.raises(ValueError, match="dropped"):
        synthetic_sensor_data(TRUE, th0, Om0, 1.0, dropped=1.0)
    with pytest.raises(ValueError, match="bias"):
        synthetic_sensor_data(TRUE, th0, Om0, 1.0, bias=(0.0, 1.0))


START = RigidBodyOscillator(A, QuadraticFoundation(1.3, 1.5, K), loads=(Friction(0.08),))


def _select(m):
    return m.foundation.c, m.foundation.d, m.loads[0].b


@pytest.fixture(scope="module")
def rig():
    datas = [
        _rig([0.5, -0.2, 0.3], [0.1, 0.8, -0.5], 1),
        _rig([0.1, 0.4, -0.2], [-0.4, 0.2, 0.7], 2),
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the initial state is fitted: no warning
        return datas, fit(START, datas, _select, fit_initial_state=True)


def test_two_experiments_with_a_gyro_bias_recovered_within_3_standard_errors(rig):
    """Noisy, irregular, gappy quaternions and a biased gyroscope of two experiments, unknown
    initial states: c, d of (4.41), the friction b of (4.84) and the bias all within 3 standard
    errors of the truth (issue 51's target)."""
    _, res = rig
    assert res.converged, res.message
    assert res.names == ("foundation.c", "foundation.d", "loads[0].b")
    z = (np.array([float(p) for p in res.params]) - [1.0, 2.0, 0.05]) / np.array(res.stderr)
    assert np.all(np.abs(z) < 3), z
    zb = (res.Omega_bias - BIAS) / res.Omega_bias_standard_errors
    assert np.all(np.abs(zb) < 3), zb
    assert res.residual_rms == pytest.approx(1.0, abs=0.1)  # over the observed components only
    ds = res.to_xarray()
    assert list(ds.parameter.values) == ["foundation.c", "foundation.d", "loads[0].b"]
    assert "Omega_bias[2]" in list(ds.parameter_all.values)


@pytest.mark.slow  # cost: ~25 s of compilation (the re-fits' program)
def test_profile_likelihood_interval_matches_wald_where_quadratic(rig):
    """The profile of b (4.84), every other quantity re-fitted: Δℓ ≥ 0 with its minimum at the
    fit, ≈ ½((v - b̂)/se)² on this near-quadratic problem, and the χ² interval (Δ = 1.92) within
    30 % of ±1.96 standard errors (issue 51, C)."""
    from rbo_jax import profile_likelihood

    datas, res = rig
    est, se = float(res.params[2]), float(res.stderr[2])
    values = est + se * np.linspace(-3.0, 3.0, 7)
    ds = profile_likelihood(START, datas, _select, "loads[0].b", values, start=res)
    assert bool(ds.converged.all())
    delta = ds.delta.values
    assert np.all(delta >= -1e-6) and abs(delta[3]) < 1e-6
    np.testing.assert_allclose(delta, 0.5 * np.linspace(-3.0, 3.0, 7) ** 2, rtol=0.3, atol=1e-3)
    lo, hi = ds.attrs["lower"], ds.attrs["upper"]
    assert abs((hi - lo) / (2 * 1.96 * se) - 1) < 0.3 and lo < est < hi
    assert set(ds.data_vars) >= {"foundation.c", "foundation.d", "Omega_bias", "theta0"}
    with pytest.raises(ValueError, match="name must be one of"):
        profile_likelihood(START, datas, _select, "foundation.k", values, start=res)
    with pytest.raises(ValueError, match="must be positive"):
        profile_likelihood(START, datas, _select, "loads[0].b", -values, start=res)


@pytest.mark.slow  # cost: two fits' compilations, ~10 s
def test_residual_variance_counts_the_observed_components_only():
    """Without ``sigma_*`` the standard errors use the residual variance |r|²/(m - p): m counts
    the observed components, not the zeros of missing samples (two thirds of the merged rig's
    attitude entries). With the noise levels right, s ≈ 1 and the standard errors agree with
    those of the given sigmas."""
    th0, Om0 = np.array([0.5, -0.2, 0.3]), np.array([0.1, 0.8, -0.5])
    kw = dict(quaternion_rate=50.0, gyro_rate=100.0, bias=BIAS, dropped=0.1, seed=7)
    known = synthetic_sensor_data(TRUE, th0, Om0, 3.0, sigma_theta=0.02, sigma_Omega=0.02, **kw)
    seen = np.asarray(known.attitude_weight) > 0
    Q = np.where(seen[:, None, None], np.asarray(known.Q), np.nan)
    Omega = np.where(np.asarray(known.Omega_weight) > 0, np.asarray(known.Omega), np.nan)
    unknown = TrajectoryData(np.asarray(known.ts), Q=Q, Omega=Omega, Omega_bias="fit")
    fits = [fit(START, d, _select, fit_initial_state=True) for d in (known, unknown)]
    for a, b in zip(fits[0].stderr, fits[1].stderr):
        assert float(b) == pytest.approx(float(a), rel=0.1)


def test_profile_interval_is_exact_for_a_quadratic_profile_on_a_coarse_grid():
    """The χ² bounds interpolate the root √(2Δℓ): for Δℓ = ½((v - v̂)/se)² on values one
    standard error apart they are v̂ ± z·se exactly (z = 1.645 at 90 %, 1.96 at 95 %), also
    from an asymmetric grid; NaN where the values never reach the threshold."""
    from rbo_jax.fitting._profile import _interval

    est, se = 0.05, 0.004
    for level, z in ((0.9, 1.6448536269514722), (0.95, 1.959963984540054)):
        threshold = 0.5 * z**2
        for grid in (np.arange(-3.0, 3.5, 1.0), np.array([-2.3, -0.7, 0.4, 1.1, 2.9])):
            v = est + se * grid
            lo, hi = _interval(v, 0.5 * grid**2, threshold, est)
            assert lo == pytest.approx(est - z * se, rel=1e-12)
            assert hi == pytest.approx(est + z * se, rel=1e-12)
    lo, hi = _interval(est + se * np.array([-1.0, 1.0, 3.0]), np.array([0.5, 0.5, 4.5]), 1.92, est)
    assert np.isnan(lo) and hi == pytest.approx(est + 1.96 * se, rel=1e-3)
