"""``lattice.simulate`` of a rod inside ``jax.vmap``, ``jax.jit`` and ``jax.grad`` (issue 32).

Checks: the splitting vmapped over the bending stiffness gives every member the samples and the
step count of its own eager call (each member its own default step, so its own number of steps:
the loop of each interval masks the members that are done); ``jax.jit`` of one call with traced
``ts`` gives the eager samples, and traced times that do not increase the status
``invalid_times``; ``jax.grad`` of the tip's position through the splitting (a fixed ``dt``)
against central finite differences; the failures under a transformation (more steps than
``max_steps``, a step that is not finite and > 0) as statuses with ``throw=False`` and as
errors naming ``max_steps`` or ``dt`` with ``throw=True``; traced invalid rod parameters as
the status ``invalid_parameters`` or an error naming the parameter; Dopri8 and Kvaerno5
vmapped over the bending stiffness against their eager calls; the same parameter checks in the
statics (``solve_equilibrium``'s status, ``equilibrium`` and ``spectrum`` raising, a NaN
``critical_load``). The small clamped rod of
``tests/test_rod_verlet.py`` (N = 4, shear 50, stretch 80: ~0.1 s of motion in ~10-50 steps).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rbo_jax import SolveStatus, lattice
from rbo_jax import _enumeration as enum

RUNTIME_ERRORS = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError)
EIS = (1.0, 3.0, 9.0)  # the stiffest mode moves from shear to bending: three default steps
TS = jnp.linspace(0.0, 0.5, 6)


def rod_of(EI):
    return lattice.rod(
        4, 1.0, bending=EI, torsion=0.7, shear=50.0, stretch=80.0, mass=1.0, rotary=2e-2
    )  # fmt: skip


def moving(rod):
    """The straight rod with velocities and angular velocities about every axis, zero on the
    clamped base (as in tests/test_rod_verlet.py)."""
    s = rod.straight()
    z = np.asarray(s.r)[:, 2]
    v = np.stack([np.sin(np.pi * z), 0.3 * np.cos(2 * z), 0.1 * z], 1)
    Om = np.stack([0.5 + z, -0.4 * z, 2.0 - z], 1)
    v[0], Om[0] = 0.0, 0.0
    return lattice.RodState(s.theta, s.r, jnp.asarray(Om), jnp.asarray(v))


STATE0 = moving(rod_of(1.0))  # the straight rod does not depend on EI


def assert_same_states(a, b, rtol=1e-12):
    """Every field of two RodStates equal to ``rtol`` of its largest entry."""
    for name in ("theta", "r", "Omega", "v"):
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        np.testing.assert_allclose(x, y, rtol=rtol, atol=rtol * np.abs(y).max(), err_msg=name)


def splitting(EI, ts=TS, **kw):
    return lattice.simulate(rod_of(EI), STATE0, ts, method="splitting", **kw)


@pytest.mark.slow  # cost: ~15-20 s, the splitting compiled under vmap and for the eager calls
def test_vmap_of_the_splitting_is_the_eager_calls():
    r"""vmap over EI: every member's default step is its own call's (the same Gershgorin bound
    from the same rod, batched), so the same counts per interval (``num_steps`` equal and
    different across the members: the while loop of a batch masks the members that are done)
    and the same arithmetic step by step: the samples agree to 1e-12 of each field's scale.
    The energy of these conservative runs (no loads, no damping), taken on the batch, keeps
    the splitting's bounded O(h^2) error at ~0.9 of the stability limit (< 0.1 relative, as
    tests/test_rod_verlet.py)."""
    batch = jax.vmap(lambda EI: splitting(EI, throw=False))(jnp.asarray(EIS))
    assert np.all(batch.ok)
    steps = np.asarray(batch.num_steps)
    assert len(set(steps.tolist())) == 3, steps
    for i, EI in enumerate(EIS):
        one = splitting(EI)
        assert int(one.num_steps) == steps[i]
        member = jax.tree_util.tree_map(lambda x, i=i: x[i], batch.states)
        assert_same_states(member, one.states)
    E = np.asarray(jax.vmap(lambda t: t.energy)(batch))
    assert E.shape == (3, len(TS))
    dE = np.abs(E - E[:, :1]) / E[:, :1]
    assert 0 < dE.max() < 0.1, dE


@pytest.mark.slow  # cost: ~16 s, the midpoint rule compiled under vmap and for the eager calls
def test_vmap_of_the_midpoint_rule_is_the_eager_calls():
    """vmap over EI of ``method="midpoint"`` (the implicit midpoint rule, its step 0.02): every
    member's samples are those of its own eager call to the Newton tolerance (a batched loop
    runs until every member is done, each member's attempts, new matrices and factors its
    own: integrate/midpoint.py, "Batches"), and the members differ (EI from 1 to 9)."""
    kw = dict(method="midpoint", dt=0.02, rtol=1e-10, atol=1e-12)
    batch = jax.vmap(lambda EI: lattice.simulate(rod_of(EI), STATE0, TS, throw=False, **kw))(
        jnp.asarray(EIS)
    )
    assert np.all(batch.ok)
    tips = []
    for i, EI in enumerate(EIS):
        one = lattice.simulate(rod_of(EI), STATE0, TS, **kw)
        member = jax.tree_util.tree_map(lambda x, i=i: x[i], batch.states)
        assert_same_states(member, one.states, rtol=1e-8)
        tips.append(np.asarray(one.states.r)[-1, -1])
    assert np.abs(tips[0] - tips[2]).max() > 1e-2  # the stiffness changes the motion


def test_jit_of_one_call_and_traced_times():
    """jit with EI and ts traced, and jit of a call with concrete inputs (every operation
    staged): the eager samples and step count (1e-12); the first program with times that do
    not increase reports ``invalid_times`` and NaN samples (throw=False)."""
    run = jax.jit(lambda EI, ts: splitting(EI, ts, throw=False))
    got = run(3.0, TS)
    ref = splitting(3.0)
    assert bool(got.ok) and int(got.num_steps) == int(ref.num_steps)
    assert_same_states(got.states, ref.states)
    # every input concrete (a closure's constants): staged all the same, the same samples
    const = jax.jit(lambda: splitting(3.0, throw=False))()
    assert int(const.num_steps) == int(ref.num_steps)
    assert_same_states(const.states, ref.states)
    bad = run(3.0, TS[::-1])
    assert enum.name(bad.status) == "invalid_times" and not bool(bad.ok)
    assert np.all(np.isnan(np.asarray(bad.states.r)))


@pytest.mark.slow  # compiles the reverse pass of the splitting's loops (~15 s)
def test_grad_of_the_tip_through_the_splitting():
    r"""d x_tip(t = 0.5)/d EI through 100 steps of dt = 0.005 (given: the counts do not depend
    on EI, and the loops have a fixed length, which reverse mode transposes) against the
    central difference of the eager calls with the step 1e-4 (relative 3e-5 at EI = 3):
    truncation ~(3e-5)^2 (measured 1.1e-9; 1.1e-7 at the step 1e-3), rounding
    ~1e-16 |x| / 1e-4 ~ 1e-12: 1e-8 relative; both differentiate the same discrete map (the
    same steps)."""

    def tip_x(EI):
        return splitting(EI, dt=0.005, throw=False).centreline[-1, -1, 0]

    g = float(jax.grad(tip_x)(3.0))
    d = 1e-4
    fd = (float(tip_x(3.0 + d)) - float(tip_x(3.0 - d))) / (2 * d)
    assert abs(g) > 1e-3
    np.testing.assert_allclose(g, fd, rtol=1e-8)


def test_failures_under_a_transformation_are_statuses_or_errors():
    """A traced dt: too many steps for max_steps = 1000 (dt = 1e-5: 50,000 steps) and a step
    that is not finite and > 0 are the statuses max_steps_reached and invalid_parameters
    (nothing run, the samples after the first inf) in one vmap, throw=False; jit with
    throw=True raises naming max_steps, or dt."""
    dts = jnp.array([0.005, 1e-5, -1.0, jnp.nan])
    batch = jax.vmap(lambda dt: splitting(3.0, dt=dt, max_steps=1000, throw=False))(dts)
    names = enum.names(SolveStatus)
    got = [names[int(c)] for c in np.asarray(enum.code(batch.status))]
    assert got == ["successful", "max_steps_reached", "invalid_parameters", "invalid_parameters"]
    assert np.asarray(batch.num_steps).tolist() == [100, 0, 0, 0]
    r = np.asarray(batch.centreline)
    assert np.all(np.isfinite(r[0])) and np.all(np.isfinite(r[1:, 0]))
    assert np.all(np.isinf(r[1:, 1:]))

    # equinox's jit: its errors raise as EquinoxRuntimeError (jax.jit's as a ValueError
    # wrapping the callback's failure)
    run = eqx.filter_jit(lambda dt: splitting(3.0, dt=dt, max_steps=1000).centreline)
    assert np.all(np.isfinite(np.asarray(run(dts[0]))))
    with pytest.raises(RUNTIME_ERRORS, match="max_steps = 1000"):
        jax.block_until_ready(run(dts[1]))
    with pytest.raises(RUNTIME_ERRORS, match="dt must be finite and > 0"):
        jax.block_until_ready(run(dts[2]))


def test_traced_rod_parameters_are_checked_by_simulate():
    """Parameters traced at construction are not checked by ``lattice.rod`` (it cannot): a
    negative or NaN bending stiffness in a vmap is the status invalid_parameters with NaN
    states (``Rod.parameter_checks``), the other members run as alone; with throw=True the
    error names the parameter."""
    EIs = jnp.array([3.0, -1.0, jnp.nan])
    batch = jax.vmap(lambda EI: splitting(EI, dt=0.005, throw=False))(EIs)
    names = enum.names(SolveStatus)
    got = [names[int(c)] for c in np.asarray(enum.code(batch.status))]
    assert got == ["successful", "invalid_parameters", "invalid_parameters"]
    r = np.asarray(batch.centreline)
    np.testing.assert_array_equal(r[0], np.asarray(splitting(3.0, dt=0.005).centreline))
    assert np.all(np.isnan(r[1:]))

    run = eqx.filter_jit(lambda EI: splitting(EI, dt=0.005).centreline)
    with pytest.raises(RUNTIME_ERRORS, match="bending and torsion must be > 0"):
        jax.block_until_ready(run(EIs[1]))
    with pytest.raises(RUNTIME_ERRORS, match="a parameter is NaN or infinite"):
        jax.block_until_ready(run(EIs[2]))


@pytest.mark.slow  # compiles each method twice (eager, vmapped): Kvaerno5 ~11 s a program
@pytest.mark.parametrize("method", ["explicit", "implicit"])
def test_vmap_of_the_diffrax_methods_is_the_eager_calls(method):
    """Dopri8 (method="explicit") and Kvaerno5 (method="implicit") vmapped over EI: each
    member's adaptive steps are its own call's (diffrax's loop masks the members that are
    done), so the samples agree with the eager calls far below the solver's tolerance
    rtol = 1e-8 (asserted to 1e-10)."""
    ts = jnp.linspace(0.0, 0.2, 3)
    batch = jax.vmap(
        lambda EI: lattice.simulate(rod_of(EI), STATE0, ts, method=method, throw=False)
    )(jnp.asarray(EIS))
    assert np.all(batch.ok)
    for i, EI in enumerate(EIS):
        one = lattice.simulate(rod_of(EI), STATE0, ts, method=method)
        assert int(one.num_steps) == int(batch.num_steps[i])
        assert_same_states(
            jax.tree_util.tree_map(lambda x, i=i: x[i], batch.states), one.states, 1e-10
        )


def past_the_constructor(EI):
    """``rod_of(3.0)`` with the bending stiffness ``EI`` set past the constructor's checks, as a
    value traced at construction (``jax.vmap`` over EI) reaches the solvers."""
    rod = rod_of(3.0)
    k = np.array(rod.turn_stiffness)
    k[..., :2] *= EI / 3.0  # EI / h per coupling
    return eqx.tree_at(lambda r: r.turn_stiffness, rod, jnp.asarray(k))


def test_traced_rod_parameters_are_checked_by_the_statics_and_spectra():
    """The checks of ``Rod.parameter_checks`` in the statics: ``solve_equilibrium`` of a rod
    with a negative or NaN bending stiffness has the status ``invalid_parameters`` and a NaN
    state (one compiled program for the three rods, a valid one as before); ``equilibrium``
    and ``spectrum`` (at a given state, and at the equilibrium it solves) raise naming the
    parameter."""
    load = (lattice.TipForce(jnp.array([0.2, 0.0, -0.1])),)
    rods = [past_the_constructor(EI).with_loads(load) for EI in (3.0, -1.0, np.nan)]
    assert (
        np.asarray(rods[0].turn_stiffness).tolist()
        == np.asarray(rod_of(3.0).turn_stiffness).tolist()
    )
    sols = [lattice.solve_equilibrium(rod) for rod in rods]
    names = enum.names(lattice.RodEquilibriumStatus)
    got = [names[int(enum.code(s.status))] for s in sols]
    assert got == ["successful", "invalid_parameters", "invalid_parameters"]
    assert np.abs(np.asarray(sols[0].state.tip)[0]) > 1e-3  # bent by the load
    assert all(np.all(np.isnan(np.asarray(s.state.r))) for s in sols[1:])
    for fn, caller in (
        (lattice.equilibrium, "lattice.equilibrium"),
        (lambda rod: lattice.spectrum(rod, rod.straight()), "lattice.spectrum"),
        (lattice.spectrum, "lattice.spectrum"),  # at the equilibrium it solves
    ):
        with pytest.raises(RUNTIME_ERRORS, match=f"{caller}: rod: bending and torsion must be"):
            jax.block_until_ready(fn(rods[1]))
        with pytest.raises(RUNTIME_ERRORS, match=f"{caller}: rod: a parameter is NaN"):
            jax.block_until_ready(fn(rods[2]))


@pytest.mark.slow  # a critical load's scan of spectra vmapped: ~15-25 s of compilation
def test_traced_rod_parameters_give_a_nan_critical_load():
    """``lattice.critical_load`` vmapped over the bending stiffness of Beck's column: a negative
    or NaN EI gives NaN, a valid one its own flutter load (the other members unaffected)."""

    def beck(EI):
        def rod_at(P):
            return rod_of(EI).with_loads((lattice.TipForce(jnp.array([0, 0, -P]), follower=True),))

        return rod_at

    crit = jax.vmap(lambda EI: lattice.critical_load(beck(EI), 200.0, n_scan=8, n_bisect=20))
    found = np.asarray(crit(jnp.array([3.0, -1.0, jnp.nan])))
    alone = float(lattice.critical_load(beck(3.0), 200.0, n_scan=8, n_bisect=20))
    assert np.isfinite(alone) and np.all(np.isnan(found[1:]))
    np.testing.assert_allclose(found[0], alone, rtol=1e-12)
