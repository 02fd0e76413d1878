"""A rod's motion by the implicit midpoint rule (issue 50, A): the default for a stiff rod
(``method="auto"``), its order, its energy, and its checks."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rbo_jax import lattice
from rbo_jax.lattice import _rod_midpoint

EULER_BERNOULLI_1 = 3.51602  # the first frequency of a cantilever, in sqrt(EI/(rho A L^4))


def stiff_rod(n):
    """The issue's rod: slender, its shear and stretch 10^4 times its bending stiffness."""
    return lattice.rod(
        n, 1.0, bending=1.0, torsion=0.8, shear=1e4, stretch=1e4, mass=1.0, rotary=1e-4
    )


def released(rod, force=1e-3):
    """The rod's static shape under a tip force ``force`` along e1, at rest."""
    return lattice.equilibrium(rod.with_loads((lattice.TipForce((force, 0.0, 0.0)),)))


def first_frequency(ts, x):
    """Twice the mean spacing of the zero crossings of ``x`` about its mean, as a frequency."""
    y = x - x.mean()
    i = np.nonzero(np.sign(y[:-1]) != np.sign(y[1:]))[0]
    crossings = ts[i] - y[i] * (ts[i + 1] - ts[i]) / (y[i + 1] - y[i])
    return np.pi / np.mean(np.diff(crossings))


# ------------------------------------------------------------------------------------------
# The choice and the checks (no solve).
# ------------------------------------------------------------------------------------------


def test_auto_takes_the_midpoint_rule_for_a_stiff_rod_only():
    """The stiff rod's explicit stable step is far below the midpoint rule's step over four
    periods; a soft chain's (shear and stretch like its bending) is not, until the midpoint
    rule is given a step ``dt`` longer than that stable step. A chain of 20 soft bodies is
    stiff at the midpoint rule's step (its stable step 0.42 of it): ``Dopri8`` took 5.6x the
    midpoint rule's time there."""
    ts = np.linspace(0.0, 4 * 2 * np.pi / EULER_BERNOULLI_1, 201)
    stiff = stiff_rod(20)
    assert _rod_midpoint.auto(stiff, stiff.straight(), ts, None, False) == "midpoint"
    soft = lattice.rod(
        4, 1.0, bending=1.0, torsion=1.0, shear=3.0, stretch=3.0, mass=1.0, rotary=0.1
    )
    assert _rod_midpoint.auto(soft, soft.straight(), ts, None, False) == "explicit"
    assert _rod_midpoint.auto(soft, soft.straight(), ts, None, False, dt=0.2) == "midpoint"
    with pytest.raises(ValueError, match="dt must be finite and > 0"):  # not ignored
        lattice.simulate(soft, soft.straight(), ts, dt=-1.0)
    chain = lattice.rod(
        20, 1.0, bending=1.0, torsion=1.0, shear=3.0, stretch=3.0, mass=1.0, rotary=0.005
    )
    assert _rod_midpoint.auto(chain, chain.straight(), ts, None, False) == "midpoint"
    assert _rod_midpoint.auto(stiff, stiff.straight(), ts, object(), False) == "explicit"


def test_step_bound_is_above_the_stable_step():
    """``auto``'s bound from the stiffnesses and masses alone (a Rayleigh quotient) is an
    upper bound of the explicit stable step (a Gershgorin bound of the same eigenvalue) on
    stiff, soft, damped, bent and free rods; on the issue's rod it is below the midpoint
    rule's step over four periods, so ``auto`` chooses there without a program."""
    rng = np.random.default_rng(3)
    rods = [
        stiff_rod(12),
        lattice.rod(4, 1.0, bending=1.0, torsion=1.0, shear=3.0, stretch=3.0, mass=1.0,
                    rotary=0.1),
        lattice.rod(6, 2.0, bending=2.0, torsion=1.0, shear=50.0, stretch=80.0, mass=3.0,
                    rotary=0.01, damping=0.05, base="free"),
        lattice.circular_rod(10, 1.0, radius=0.01, density=1000.0, youngs_modulus=1e7),
    ]  # fmt: skip
    for rod in rods:
        s = rod.straight()
        bent = lattice.RodState(
            s.theta + 0.3 * rng.standard_normal(s.theta.shape), s.r, s.Omega, s.v
        )
        bound = _rod_midpoint.step_bound(rod)
        for state in (s, bent):
            h = float(_rod_midpoint.stable_step(rod, state))
            assert h <= bound, (h, bound)
    ts = np.linspace(0.0, 4 * 2 * np.pi / EULER_BERNOULLI_1, 201)
    assert _rod_midpoint.step_bound(rods[0]) < _rod_midpoint._midpoint_step(ts)


def test_the_chords_start_extrapolates_the_last_rates_by_their_lagrange_polynomial():
    """The chord's start (:mod:`rbo_jax.integrate.midpoint`): the last three steps' rates, each
    at its step's midpoint, extrapolated to the next step's midpoint. Exact for rates on a
    quadratic in time whatever the steps (error O(h^3) in the rate: O(h^4) in the start);
    3 s1 - 3 s2 + s3 on equal steps; the last rate alone after one step; zero before any."""
    from rbo_jax.integrate import midpoint as mp

    coef = np.random.default_rng(5).standard_normal((3, 2, 4))
    rate_at = lambda tau: coef[0] + coef[1] * tau + coef[2] * tau**2  # noqa: E731
    x0 = jnp.zeros((2, 4))
    rates = mp._no_rates(x0, jnp.asarray(0.07))
    np.testing.assert_array_equal(mp._extrapolated(rates, 0.1), np.zeros((2, 4)))
    ends = [-0.30, -0.23, -0.10, 0.0]  # three steps (0.07, 0.13, 0.10), t_n = 0
    for k, (a, b) in enumerate(zip(ends[:-1], ends[1:])):
        rates = mp._remember(rates, jnp.asarray(rate_at(0.5 * (a + b))), jnp.asarray(b - a))
        if k == 0:  # one rate: the start goes on at it
            np.testing.assert_allclose(mp._extrapolated(rates, 0.2), rate_at(-0.265))
    h = 0.11
    np.testing.assert_allclose(mp._extrapolated(rates, h), rate_at(0.5 * h), rtol=1e-12)
    s = [jnp.asarray(coef[i, 0]) for i in range(3)]
    equal = mp._no_rates(s[0], jnp.asarray(0.2))
    for r in s[::-1]:
        equal = mp._remember(equal, r, jnp.asarray(0.2))
    np.testing.assert_allclose(
        mp._extrapolated(equal, 0.2), 3 * s[0] - 3 * s[1] + s[2], rtol=1e-13, atol=1e-13
    )


@pytest.mark.parametrize(
    ("kwargs", "match"), [({"dt": 0.0}, "dt"), ({"max_steps": 10}, "max_steps")]
)
def test_midpoint_bad_step_or_too_many_steps_raise_before_any_solve(kwargs, match):
    rod = stiff_rod(4)
    with pytest.raises(ValueError, match=match):
        lattice.simulate(
            rod, rod.straight(), jnp.linspace(0.0, 1.0, 3), method="midpoint", **kwargs
        )


# ------------------------------------------------------------------------------------------
# Physics.
# ------------------------------------------------------------------------------------------


@pytest.mark.slow  # a 61-body rod over four periods, 1,600 implicit steps (~20 s compiled)
def test_released_cantilever_with_the_defaults_has_euler_bernoulli_frequency_and_energy():
    """Issue 50's case: the stiff rod of 60 segments released from its static shape under a
    small tip force, four periods of its first bending mode, ``lattice.simulate`` with no
    options. It reaches the end; the first frequency is Euler–Bernoulli's 3.51602 within 1 %
    (the rod's own, Timoshenko's with 60 segments, lies 0.27 % below it); the energy is kept to
    1e-4 (the midpoint rule keeps a linear rod's energy to its Newton tolerance)."""
    rod = stiff_rod(60)
    s0 = released(rod)
    ts = jnp.linspace(0.0, 4 * 2 * np.pi / EULER_BERNOULLI_1, 801)
    traj = lattice.simulate(rod, s0, ts)
    assert bool(traj.ok)
    assert int(traj.num_steps) == 1600  # the midpoint rule's: two steps a sample interval
    w = first_frequency(np.asarray(ts), np.asarray(traj.states.r[:, -1, 0]))
    assert abs(w / EULER_BERNOULLI_1 - 1.0) < 1e-2
    E = np.asarray(traj.energy)
    assert np.max(np.abs(E - E[0])) <= 1e-4 * abs(E[0])


@pytest.mark.slow  # a Dopri8 reference and one midpoint program run at three steps
def test_midpoint_rule_is_second_order_against_dopri8():
    """A damped rod under a follower tip force, released with random velocities (a nonlinear,
    non-conservative motion): the error of the midpoint rule at t = 0.4 against Dopri8 at
    rtol 1e-12 falls 4x as the step halves (second order), and the states converge to it."""
    tip = lattice.TipForce(jnp.array([0.0, 0.5, -1.0]), follower=True)
    rod = lattice.rod(
        3, 1.0, bending=1.0, torsion=1.0, shear=400.0, stretch=600.0, mass=1.0,
        rotary=1e-3, damping=0.01, loads=(tip,),
    )  # fmt: skip
    rng = np.random.default_rng(7)
    s = rod.straight()
    s0 = lattice.RodState(
        s.theta, s.r, 0.3 * rng.standard_normal(s.theta.shape), 0.3 * rng.standard_normal(s.r.shape)
    )
    ts = jnp.array([0.0, 0.4])
    ref = lattice.simulate(rod, s0, ts, method="explicit", rtol=1e-12, atol=1e-13)

    def flat(traj):
        return np.concatenate([np.ravel(x[-1]) for x in jax.tree_util.tree_leaves(traj.states)])

    errors = []
    for dt in (4e-3, 2e-3, 1e-3):
        traj = lattice.simulate(rod, s0, ts, method="midpoint", dt=dt, rtol=1e-12, atol=1e-14)
        assert bool(traj.ok)
        errors.append(np.max(np.abs(flat(traj) - flat(ref))))
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert np.all((ratios > 3.6) & (ratios < 4.4)), (errors, ratios)
    assert errors[-1] < 1e-3 * np.max(np.abs(flat(ref)))


def _pendulums(t, x, k):
    """Three pendulums in a row, weakly coupled: (q, p) per block."""
    q, p = x[:, 0], x[:, 1]
    z = jnp.zeros(1)
    lap = jnp.concatenate([q[1:], z]) + jnp.concatenate([z, q[:-1]]) - 2 * q
    return jnp.stack([p, -k * jnp.sin(q) + 0.1 * lap], -1)


def _pendulum_run(k):
    """Large swings of three pendulums at a step of about a third of their period (one step
    per interval): the Newton iterations of a whole step do not converge (at a sixth of it,
    the step of this test before 2026-12-03, they did: it never split a step)."""
    from rbo_jax.integrate import midpoint as mp

    x0 = jnp.stack([jnp.array([2.5, 2.0, 1.5]), jnp.zeros(3)], -1)
    ts = jnp.linspace(0.0, 12.0, 7)
    counts, steps = jnp.ones(6, jnp.int32), jnp.full(6, 2.0)
    tol = dict(rtol=1e-12, atol=1e-14)
    return mp.midpoint(_pendulums, x0, ts, counts, steps, args=k, max_count=1, **tol)


def test_a_step_whose_newton_fails_is_split_into_substeps(monkeypatch):
    """Without substeps the solve fails (the whole step's chord iterations and its new
    matrices are tried, then given up); with them (``MAX_SUBSTEPS``) it completes."""
    from rbo_jax.integrate import midpoint as mp

    xs, ok, _ = _pendulum_run(1.0)
    assert bool(ok) and np.all(np.isfinite(np.asarray(xs)))
    monkeypatch.setattr(mp, "MAX_SUBSTEPS", 1)
    assert not bool(_pendulum_run(1.0)[1])


@pytest.mark.slow  # reverse and forward mode of the substeps: two programs (~10 s)
def test_gradient_through_substeps_matches_central_differences():
    """``jax.grad`` through the substeps' implicit derivatives (one after the other) equals
    central differences and forward mode."""

    def end(k):
        return _pendulum_run(k)[0][-1, 0, 0]

    grad = float(jax.grad(end)(1.0))
    fd = (float(end(1.0 + 1e-6)) - float(end(1.0 - 1e-6))) / 2e-6
    assert abs(grad / fd - 1) < 1e-6
    assert abs(float(jax.jacfwd(end)(1.0)) / grad - 1) < 1e-9


# ------------------------------------------------------------------------------------------
# Steps longer than the samples: a uniform grid of steps, the samples interpolated.
# ------------------------------------------------------------------------------------------


def test_hermite_samples_keep_quadratics_exact_and_converge_at_third_order():
    """The cubic Hermite samples with central-difference slopes (one-sided, second order at
    the ends) return every grid state exactly, reproduce a quadratic exactly, and their error
    on a smooth curve falls 8x as the grid's step halves (O(H^3)); a sample next to a state
    that is not finite (a failed step) is inf."""
    from rbo_jax.integrate.midpoint import hermite_samples, step_grid

    ts = np.linspace(0.0, 1.0, 97)[:-3] + 0.003  # samples off the grid, up to its ends
    ts[0], ts[-1] = 0.0, 1.0

    def grid_of(S):
        return step_grid(np.array([0.0, 1.0]), 1.0 / S)

    g = grid_of(8)
    quad = lambda t: np.stack([1.0 + 2.0 * t - 3.0 * t**2, t**2], -1)  # noqa: E731
    np.testing.assert_allclose(hermite_samples(quad(g), g, ts), quad(ts), atol=1e-13)
    np.testing.assert_allclose(hermite_samples(quad(g), g, g), quad(g), atol=1e-14)
    curve = lambda t: np.stack([np.sin(3.0 * t), np.exp(t)], -1)  # noqa: E731
    errors = [
        np.max(np.abs(hermite_samples(curve(grid_of(S)), grid_of(S), ts) - curve(ts)))
        for S in (8, 16, 32)
    ]
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert np.all((ratios > 6.5) & (ratios < 9.5)), (errors, ratios)
    bad = curve(g).copy()
    bad[5:] = np.inf
    out = np.asarray(hermite_samples(bad, g, ts))
    assert np.all(np.isfinite(out[ts < g[3]])) and np.all(np.isinf(out[ts > g[4]]))


def test_interpolated_turns_cross_the_pi_sphere_in_one_chart():
    """A body turning steadily about one axis through |θ| = π: the grid's turn-vectors are
    re-centred there (a jump of 2π in the chart), and the samples between them are the exact
    turns (in the chart within π), not an average across the jump."""
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    grid = np.linspace(0.0, 1.0, 41)
    ts = np.linspace(0.013, 0.987, 51)

    def turns(t):  # |θ| from 2 to 4.5 rad, recentred within π
        theta = (2.0 + 2.5 * t)[:, None, None] * axis
        size = np.linalg.norm(theta, axis=-1, keepdims=True)
        return np.where(size > np.pi, theta * (1.0 - 2.0 * np.pi / size), theta)

    def states(t):
        z = np.zeros((len(t), 1, 3))
        return lattice.RodState(jnp.asarray(turns(t)), z, z, z)

    out = _rod_midpoint._sampled(states(grid), jnp.asarray(grid), jnp.asarray(ts))
    np.testing.assert_allclose(out.theta, turns(ts), atol=1e-12)


@pytest.mark.slow  # a 21-body rod over four periods, two midpoint programs (~25 s compiled)
def test_released_cantilever_with_steps_longer_than_the_samples():
    """The stiff rod released from its static shape, four periods sampled 800 times, with
    ``dt`` four sample intervals: the steps lie on a grid of their own (every fourth sample a
    step's end, the rest interpolated). The first frequency is Euler–Bernoulli's within 1 %;
    the energy at the steps' ends is kept to the Newton tolerance (here tight: 1e-8 of it
    measured); the samples agree with the midpoint rule at its default step to the rule's own
    phase error, (ω dt)²/12 a radian of phase per radian, times the amplitude (up to 3x: the
    second mode's lag is 39 times the first's), and the interpolated samples no worse than the
    steps' ends (1.92x and 1.00x measured)."""
    rod = stiff_rod(20)
    s0 = released(rod)
    ts = jnp.linspace(0.0, 4 * 2 * np.pi / EULER_BERNOULLI_1, 801)
    dt = 4 * float(ts[1] - ts[0])
    tight = {"rtol": 1e-10, "atol": 1e-14}
    traj = lattice.simulate(rod, s0, ts, dt=dt, **tight)
    assert bool(traj.ok) and int(traj.num_steps) == 200
    x = np.asarray(traj.states.r[:, -1, 0])
    w = first_frequency(np.asarray(ts), x)
    assert abs(w / EULER_BERNOULLI_1 - 1.0) < 1e-2
    E = np.asarray(traj.energy)
    assert np.max(np.abs(E[::4] - E[0])) <= 1e-6 * abs(E[0])
    fine = np.asarray(lattice.simulate(rod, s0, ts, **tight).states.r[:, -1, 0])
    amplitude = np.max(np.abs(fine - fine.mean()))
    phase = 4 * 2 * np.pi * (w * dt) ** 2 / 12  # the coarse run's lag after four periods
    assert np.max(np.abs(x - fine)) <= 3.0 * phase * amplitude
    at_ends = np.max(np.abs(x[::4] - fine[::4]))
    assert np.max(np.abs(x[2::4] - fine[2::4])) <= 1.05 * at_ends


def test_undamped_field_of_a_stripped_rod_equals_the_full_field():
    """The midpoint rule's field of a rod without damping or velocity-reading loads, traced
    without the velocities' terms and with its zero attachment offsets left out
    (``_static_zeros``), equals the full field (the same equations of motion, (4.14), (4.55))."""
    from rbo_jax.lattice._rod_verlet import _static_zeros

    rod = stiff_rod(4).with_loads((lattice.TipForce((0.1, 0.0, -0.2), follower=True),))
    stripped, damped = _static_zeros(rod)
    assert not damped and stripped.attach_a is None
    rng = np.random.default_rng(3)
    x = _rod_midpoint._pack(rod.straight()) + 0.05 * rng.standard_normal((rod.n_bodies, 12))
    full = eqx.filter_jit(_rod_midpoint._field)(0.3, x, rod)
    undamped = eqx.filter_jit(_rod_midpoint._field_undamped)(0.3, x, stripped)
    np.testing.assert_allclose(undamped, full, atol=1e-12)
    damped_rod = lattice.rod(
        4, 1.0, bending=1.0, torsion=0.8, shear=1e4, stretch=1e4, mass=1.0, rotary=1e-4,
        damping=0.01,
    )  # fmt: skip
    assert _static_zeros(damped_rod)[1]


@pytest.mark.slow  # reverse mode through the midpoint rule's fixed loops (~30 s compiled)
def test_gradient_through_steps_longer_than_the_samples_matches_central_differences():
    """``jax.grad`` of a sample between two steps' ends (the Hermite interpolation of the
    grid's states, each step differentiated by the implicit rule) with respect to the bending
    stiffness equals central differences (3e-11 measured)."""

    def tip(EI):
        rod = lattice.rod(
            6, 1.0, bending=EI, torsion=0.8, shear=1e3, stretch=1e3, mass=1.0, rotary=1e-3,
            loads=(lattice.TipForce((0.05, 0.0, 0.0)),),
        )  # fmt: skip
        ts = jnp.linspace(0.0, 1.0, 41)  # dt two sample intervals: the samples interpolated
        traj = lattice.simulate(
            rod, rod.straight(), ts, method="midpoint", dt=0.05, rtol=1e-12, atol=1e-14
        )
        return traj.states.r[-2, -1, 0]  # t = 0.975, between the steps at 0.95 and 1

    g = float(jax.grad(tip)(1.0))
    fd = float((tip(1.0 + 1e-5) - tip(1.0 - 1e-5)) / 2e-5)
    assert abs(g - fd) <= 1e-7 * abs(fd), (g, fd)
