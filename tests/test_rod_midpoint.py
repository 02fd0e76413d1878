"""A rod's motion by the implicit midpoint rule (issue 50, A): the default for a stiff rod
(``method="auto"``), its order, its energy, and its checks."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rbo_jax import lattice
from rbo_jax.lattice import _rod_dynamics

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
    periods; a soft chain's (shear and stretch like its bending) is not."""
    ts = np.linspace(0.0, 4 * 2 * np.pi / EULER_BERNOULLI_1, 201)
    stiff = stiff_rod(20)
    assert _rod_dynamics._auto(stiff, stiff.straight(), ts, None, False) == "midpoint"
    soft = lattice.rod(
        4, 1.0, bending=1.0, torsion=1.0, shear=3.0, stretch=3.0, mass=1.0, rotary=0.1
    )
    assert _rod_dynamics._auto(soft, soft.straight(), ts, None, False) == "explicit"
    assert _rod_dynamics._auto(stiff, stiff.straight(), ts, object(), False) == "explicit"


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
    """Large swings of three pendulums at a step of a sixth of their period (one step per
    interval): the Newton iterations of a whole step do not converge."""
    from rbo_jax.integrate import midpoint as mp

    x0 = jnp.stack([jnp.array([2.5, 2.0, 1.5]), jnp.zeros(3)], -1)
    ts = jnp.linspace(0.0, 6.0, 7)
    counts, steps = jnp.ones(6, jnp.int32), jnp.ones(6)
    tol = dict(rtol=1e-12, atol=1e-14)
    return mp.midpoint(_pendulums, x0, ts, counts, steps, args=k, max_count=1, **tol)


def test_a_step_whose_newton_fails_is_split_into_substeps(monkeypatch):
    """Without substeps the solve fails; with them (``MAX_SUBSTEPS``) it completes."""
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
