"""Folds of limit cycles, period doubling and Neimark-Sacker points (issue 23, part C).

The damped Nikolai problem (follower moment (4.57), friction (4.84)) has its Hopf point at
M_c = 2b sqrt(K/A1) for every A3, but its first Lyapunov coefficient grows linearly with A3 and
changes sign near A3 = 1.335 (a Bautin point). On the hard side (A3 = 2, l1 = +0.0083) the
cycles born at M_c are unstable and exist below M_c; they grow until a fold of cycles at
M* = 0.17612 (amplitude ~1.3 rad), where they turn back as large stable cycles (amplitude
1.5 rad and more, approaching pi) that continue past M_c. Between M* and M_c rest and the large
cycle coexist (hard flutter with hysteresis)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import damped_nikolai

import rbo_jax as rbo
from rbo_jax.bifurcation import OrbitStatus
from rbo_jax.bifurcation._cycle_fold import fold_of_cycles
from rbo_jax.bifurcation._cycle_special import multiplier_crossings

K_AXIS = (0.0, 0.0, 1.0)
C, D, A1 = 1.0, 2.0, 1.0
PARAMS = {"b": 0.1, "c": C, "A3": 2.0}  # the hard side: l1 > 0
nikolai = damped_nikolai  # (4.57), (4.84) with d = D, A1 = A1


@pytest.fixture(scope="module")
def hopf():
    return rbo.hopf_point(nikolai, PARAMS, "M", 0.15)


@pytest.fixture(scope="module")
def cycles(hopf):
    return rbo.continue_limit_cycles(
        nikolai, PARAMS, "M", hopf, amplitude=0.02, ds_max=0.3, max_points=18
    )


@pytest.fixture(scope="module")
def fold_index(cycles):
    types = list(cycles["special_type"].values)
    assert types == ["fold"]
    return int(cycles["special_index"].values[0])


@pytest.fixture(scope="module")
def fold(cycles, fold_index):
    return fold_of_cycles(nikolai, PARAMS, "M", cycles.isel(point=fold_index))


@pytest.mark.slow  # cost: the module's shooting continuation of cycles (~15 s) and fold solves
def test_hard_side_cycles_turn_back_at_a_fold_below_the_hopf_point(hopf, cycles, fold_index):
    """The unstable small cycles born at M_c (l1 > 0) exist below it and grow until the fold;
    past it the branch turns back towards larger M as stable cycles whose amplitude keeps
    growing beyond a radian, and continues past M_c."""
    M_c = float(hopf.value)
    assert float(hopf.first_lyapunov) > 0 and not bool(hopf.supercritical)
    M = cycles["M"].values
    amp = cycles["amplitude"].values
    stable = cycles["stable"].values
    value = float(cycles["special_value"].values[0])
    i = fold_index
    assert value < M_c - 0.02
    # before the fold: M decreasing, unstable, amplitude growing
    assert np.all(np.diff(M[: i + 1]) < 0) and not np.any(stable[1 : i + 1])
    assert M[i] > value and M[i + 1] > value
    # after it: M increasing, stable, amplitude growing, large cycles past M_c
    assert np.all(np.diff(M[i + 1 :]) > 0) and np.all(stable[i + 1 :])
    assert np.all(np.diff(amp[1:]) > 0)
    assert amp[i + 1] > 1.0 and M[-1] > M_c and amp[-1] > 2.0
    assert np.all(cycles["trivial_multiplier_error"].values[1:] < 1e-7)
    assert cycles.attrs["stop_reason"] == "max_points"


@pytest.mark.slow  # cost: the module's shooting continuation of cycles (~15 s) and fold solves
def test_fold_solves_the_augmented_shooting_system(cycles, fold_index, fold):
    """Newton's method on the minimally augmented system converges from either neighbour of
    the fold and from the continuation's interpolated guess to the same point; there the cycle
    returns to its initial state after one period and two Floquet multipliers equal 1 (a
    Jordan block: their mean is 1 to the solver's accuracy, their split O(sqrt(accuracy)))."""
    assert bool(fold.ok), fold.status
    other = fold_of_cycles(nikolai, PARAMS, "M", cycles.isel(point=fold_index + 1))
    assert bool(other.ok)
    value = float(fold.value)
    assert float(other.value) == pytest.approx(value, abs=1e-8)
    assert float(cycles["special_value"].values[0]) == pytest.approx(value, abs=1e-8)
    assert float(fold.period) == pytest.approx(float(other.period), abs=1e-7)
    assert float(fold.residual) < 1e-9
    model = nikolai(fold.value, **PARAMS)
    ts = jnp.stack([jnp.zeros(()), fold.period])
    traj = rbo.fast_simulate(model, fold.theta0, fold.Omega0, ts, rtol=1e-11, atol=1e-11)
    assert np.max(np.abs(np.asarray(traj.theta[-1] - fold.theta0))) < 1e-9
    assert np.max(np.abs(np.asarray(traj.Omega[-1] - fold.Omega0))) < 1e-9
    mu = np.asarray(
        rbo.floquet_multipliers(
            model, fold.theta0, fold.Omega0, fold.period, rtol=1e-11, atol=1e-11
        )
    )
    near_one = mu[np.argsort(np.abs(mu - 1.0))[:2]]
    assert abs(np.mean(near_one) - 1.0) < 1e-6
    assert np.max(np.abs(near_one - 1.0)) < 1e-4
    assert np.sort(np.abs(mu))[:4].max() < 0.9
    np.testing.assert_allclose(np.asarray(fold.multipliers), mu, atol=1e-8)


@pytest.mark.slow  # cost: the module's shooting continuation of cycles (~15 s) and fold solves
def test_between_the_fold_and_the_hopf_point_rest_and_the_large_cycle_coexist(
    hopf, cycles, fold_index, fold
):
    """At a load between the fold and M_c, a long fast_simulate run started on the large stable
    cycle stays on it (its amplitude over the last period is the cycle's), one started near
    rest (the equilibrium (4.62) turned by 0.05 rad) decays to it."""
    M = cycles["M"].values
    j = fold_index + 3
    assert float(fold.value) < M[j] < float(hopf.value) - 0.01
    model = nikolai(float(M[j]), **PARAMS)
    T = float(cycles["period"].values[j])
    ts = jnp.concatenate([jnp.zeros(1), 2000.0 + jnp.linspace(0.0, T, 65)[:-1]])
    solver = dict(rtol=1e-9, atol=1e-9, throw=False)
    th0, Om0 = cycles["theta0"].values[j], cycles["Omega0"].values[j]
    traj = rbo.fast_simulate(model, th0, Om0, ts, **solver)
    th = np.asarray(traj.theta[1:])
    amplitude = np.max(np.linalg.norm(th - th.mean(axis=0), axis=1))
    assert amplitude == pytest.approx(float(cycles["amplitude"].values[j]), rel=0.02)
    theta_eq = np.asarray(rbo.nikolai_equilibrium(float(M[j]), D, K_AXIS))
    start = theta_eq + np.array([0.05, 0.0, 0.0])
    traj = rbo.fast_simulate(model, start, np.zeros(3), ts, **solver)
    th = np.asarray(traj.theta[1:])
    assert np.all(np.isfinite(th))
    assert np.max(np.linalg.norm(th - theta_eq, axis=1)) < 0.05 * 0.05


@pytest.mark.slow  # cost: the module's shooting continuation of cycles (~15 s) and fold solves
def test_gradient_of_the_fold_against_finite_differences(cycles, fold_index, fold):
    """d M*/dp = -w^T G_p / w^T G_M (implicit function theorem at the fold, w the left null
    vector of the shooting Jacobian) against central differences of the located fold."""
    row = cycles.isel(point=fold_index)

    def value(p):
        return fold_of_cycles(nikolai, p, "M", row).value

    grad = jax.grad(value)(dict(PARAMS))
    assert float(value(dict(PARAMS))) == float(fold.value)
    for name, h in (("b", 1e-5), ("A3", 1e-4)):
        up = float(value({**PARAMS, name: PARAMS[name] + h}))
        down = float(value({**PARAMS, name: PARAMS[name] - h}))
        assert float(grad[name]) == pytest.approx((up - down) / (2 * h), rel=1e-5)
    # the fold scales with the friction like M_c = 2 b sqrt(K/A1): roughly proportional to b
    assert float(grad["b"]) == pytest.approx(float(fold.value) / PARAMS["b"], rel=0.05)


@pytest.mark.slow  # cost: the module's shooting continuation of cycles (~15 s) and fold solves
def test_an_iterate_through_the_singular_sphere_is_a_solve_failure(cycles, fold_index):
    """A guess on the singular sphere |theta| = 2 pi of (4.11), where the turn vector's
    equations are undefined: fast_simulate's failure is the fold's status, and its values are
    NaN, not the last iterate."""
    row = cycles.isel(point=fold_index)
    theta0 = np.asarray(row["theta0"].values)
    guess = {
        "theta0": (2 * np.pi - 1e-4) * theta0 / np.linalg.norm(theta0),
        "Omega0": row["Omega0"].values,
        "period": row["period"].values,
        "M": row["M"].values,
    }
    fold = fold_of_cycles(nikolai, PARAMS, "M", guess)
    assert fold.status == OrbitStatus.solve_failed
    assert np.isnan(float(fold.value)) and np.all(np.isnan(np.asarray(fold.theta0)))


def _ring(r, phi):
    return [r * np.exp(1j * phi), r * np.exp(-1j * phi)]


def test_multiplier_crossings_classify_period_doubling_and_neimark_sacker():
    """Constructed multiplier sets: a real multiplier through -1 (period doubling), a complex
    pair through the unit circle (Neimark-Sacker), both at once, a real positive one through 1
    (a fold or branch point: not reported), a collision of a pair on the negative axis outside
    the circle (no crossing), and the interpolation of log|mu|."""
    base = [0.3, 0.1 + 0.2j, 0.1 - 0.2j]
    pd = multiplier_crossings([-0.8, *base], [-1.25, *base])
    assert [k for k, _ in pd] == ["period_doubling"]
    assert pd[0][1] == pytest.approx(np.log(0.8) / (np.log(0.8) - np.log(1.25)))
    assert multiplier_crossings([-1.25, *base], [-0.8, *base])[0][0] == "period_doubling"
    ns = multiplier_crossings([*_ring(0.9, 1.0), 0.5], [*_ring(1.2, 1.1), 0.5])
    assert [k for k, _ in ns] == ["neimark_sacker"]
    assert ns[0][1] == pytest.approx(np.log(0.9) / (np.log(0.9) - np.log(1.2)))
    both = multiplier_crossings([-0.9, *_ring(0.95, 2.0)], [-1.1, *_ring(1.05, 2.0)])
    assert sorted(k for k, _ in both) == ["neimark_sacker", "period_doubling"]
    assert multiplier_crossings([0.9, *base], [1.1, *base]) == []  # real positive: a fold
    assert multiplier_crossings([*_ring(0.5, 1.0), -0.7], [*_ring(0.6, 1.0), -0.9]) == []
    collision = multiplier_crossings([*_ring(1.3, 3.1), 0.2], [-1.2, -1.4, 0.2])
    assert collision == []
    assert multiplier_crossings([np.nan, 0.5], [-1.2, 0.5]) == []
    # a sequence: the first crossing is found between the right pair of sets
    sequence = [[-r, *_ring(0.5, 1.0)] for r in np.linspace(0.7, 1.3, 7)]
    found = [i for i in range(6) if multiplier_crossings(sequence[i], sequence[i + 1])]
    assert found == [3]


@pytest.mark.slow  # cost: ~20 s, three shooting continuations
def test_fold_near_the_bautin_point_follows_the_second_lyapunov_coefficient():
    """Near the Bautin point the normal form rho' = rho(mu + l1 rho^2 + l2 rho^4) puts the fold of
    cycles at mu = l1^2/(4|l2|) on the stable side: M* - M_c = omega l1^2/(4 l2 sigma) (sigma the
    transversality), to leading order in l1. The folds located by the shooting continuation at
    A3 = A3_B + 0.04 and + 0.02 approach it, with an error halving with l1 (first order), so
    Richardson's extrapolation of the two lands on the prediction: an independent check of l2
    (normal form, fifth derivatives) on the rigid body itself."""
    bp = rbo.bautin_point(nikolai, {"b": PARAMS["b"], "c": C}, ("M", "A3"), (0.2, 1.3))
    l2 = float(bp.second_lyapunov)
    ratios = []
    for dA3 in (0.04, 0.02):
        params = {**PARAMS, "A3": float(bp.value[1]) + dA3}
        h = rbo.hopf_point(nikolai, params, "M", 0.2)
        l1, omega, sigma = (float(h.first_lyapunov), float(h.frequency), float(h.transversality))
        cycles = rbo.continue_limit_cycles(
            nikolai, params, "M", h, amplitude=0.01, ds_max=0.05, max_points=40
        )
        folds = cycles["special_value"].values[cycles["special_type"].values == "fold"]
        assert folds.size == 1 and folds[0] < float(h.value)
        ratios.append((folds[0] - float(h.value)) / (omega * l1**2 / (4 * l2 * sigma)))
    assert abs(ratios[0] - 1) < 0.2 and abs(ratios[1] - 1) < 0.6 * abs(ratios[0] - 1)
    assert 2 * ratios[1] - ratios[0] == pytest.approx(1.0, abs=0.02)
