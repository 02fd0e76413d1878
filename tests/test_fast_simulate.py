"""The ensemble integrator :func:`rbo_jax.fast_simulate` (DOP853 as SciPy takes it).

Checked against SciPy's ``solve_ivp(method="DOP853")`` on the same vector field (the same steps,
the same states to rounding), against :func:`rbo_jax.simulate` at a tight tolerance, against the
integral of energy (4.78) of a conservative oscillator, against finite differences (forward-mode
derivatives), and for every failure status. The batched path (refilled lanes) must give every
trajectory exactly what it gets alone.
"""

import importlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
from scipy.integrate._ivp import dop853_coefficients as scipy_tableau

from rbo_jax import ensemble, fast_simulate
from rbo_jax.foundations import BarrierFoundation, QuadraticFoundation
from rbo_jax.inertia import transversely_isotropic_inertia
from rbo_jax.integrate import dop853 as _dop853
from rbo_jax.integrate import tableau as _tableau
from rbo_jax.loads import Friction, SemiTangentialMoment
from rbo_jax.model import RigidBodyOscillator
from rbo_jax.simulate import SolveStatus, simulate

K = jnp.array([0.0, 0.0, 1.0])
TS = jnp.linspace(0.0, 8.0, 17)
THETA0 = jnp.array([0.5, -0.4, 0.3])
OMEGA0 = jnp.array([0.3, 0.9, 0.6])
RUNTIME_ERRORS = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError)
# the module (``rbo_jax.ensemble._solve`` is also the name of a function in the package)
LANES_SOLVER = importlib.import_module("rbo_jax.ensemble._solve")
QUEUE = importlib.import_module("rbo_jax.ensemble._queue")


def make_model(c=1.0, d=2.0, alpha=2.0, beta=1.5, A1=1.0, A3=0.6, M=0.3, b=0.05):
    """Barrier foundation (4.49), semi-tangential moment (4.75), friction (4.84)."""
    return RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, K),
        BarrierFoundation(c, d, alpha, beta, K),
        [SemiTangentialMoment(M, K), Friction(b)],
    )


def conservative_model(c=1.0, d=2.0, A1=1.0, A3=0.6):
    return RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, K), QuadraticFoundation(c, d, K), []
    )


def scipy_dop853(model, y0, ts, rtol, atol, sample=True):
    """SciPy's DOP853 on the model's right form: at ``ts`` (``sample``) or at its own steps."""
    rhs = jax.jit(lambda y: jnp.concatenate(model.right_form()(0.0, (y[:3], y[3:]))))
    return scipy.integrate.solve_ivp(
        lambda t, y: np.asarray(rhs(jnp.asarray(y))),
        (float(ts[0]), float(ts[-1])),
        np.asarray(y0),
        method="DOP853",
        rtol=rtol,
        atol=atol,
        t_eval=np.asarray(ts) if sample else None,
    )


def test_tableau_is_scipys():
    """The literal tableau of ``integrate.tableau`` is SciPy's ``dop853_coefficients``."""
    np.testing.assert_array_equal(np.asarray(_tableau.C), scipy_tableau.C)
    for s in range(scipy_tableau.A.shape[0]):
        np.testing.assert_array_equal(np.asarray(_tableau.A[s]), scipy_tableau.A[s])
    np.testing.assert_array_equal(np.asarray(_tableau.B), scipy_tableau.B)
    np.testing.assert_array_equal(np.asarray(_tableau.E3), scipy_tableau.E3)
    np.testing.assert_array_equal(np.asarray(_tableau.E5), scipy_tableau.E5)
    np.testing.assert_array_equal(np.asarray(_tableau.D), scipy_tableau.D)


@pytest.mark.parametrize("last", [_dop853.NS + 1, _dop853.N_EXT, "traced"])
@pytest.mark.parametrize("first", [0, 1, "traced"])
def test_unrolled_stages_are_the_loop_of_stages(monkeypatch, first, last):
    """The stages of a DOP853 step unrolled (``_dop853.UNROLL``, an option for GPUs) are the
    loop's: the same 16 slopes and new state on a nonlinear field of six components and eight
    lanes, the dense output's extra rows and a first slope made again included, with ``first``
    and ``last`` static or traced."""
    rng = np.random.default_rng(3)
    y = tuple(jnp.asarray(rng.normal(size=8)) for _ in range(6))

    def f(t, y):
        return tuple(jnp.sin(y[(i + 1) % 6]) * y[i] + t * jnp.cos(y[(i + 2) % 6]) for i in range(6))

    f0 = f(0.3, y)
    store = _dop853.Store(1.0)

    def run(unroll):
        monkeypatch.setattr(_dop853, "UNROLL", unroll)
        fi = jnp.asarray(0) if first == "traced" else first
        la = jnp.asarray(_dop853.N_EXT) if last == "traced" else last
        return _dop853.stages(f, 0.3, y, f0, 0.05, store, la, first=fi)

    (y_loop, K_loop), (y_unr, K_unr) = run(False), run(True)
    for a, b in zip(y_loop + K_loop, y_unr + K_unr):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("tol", [pytest.param(1e-6, marks=pytest.mark.slow), 1e-10])
def test_same_steps_and_states_as_scipy_dop853(tol):
    """(4.55)–(4.56) of a loaded, damped oscillator on a barrier foundation: the accepted steps
    and the samples (dense output between steps) are SciPy's."""
    model = make_model()
    tr = fast_simulate(model, THETA0, OMEGA0, TS, rtol=tol, atol=tol)
    ref = scipy_dop853(model, jnp.concatenate([THETA0, OMEGA0]), TS, tol, tol)
    assert ref.success
    n_steps = (ref.nfev - 2) // 12  # 2 evaluations for the initial step, 12 per step attempt
    assert int(tr.num_steps) <= n_steps
    steps = scipy_dop853(model, jnp.concatenate([THETA0, OMEGA0]), TS, tol, tol, sample=False)
    assert int(tr.num_steps) == steps.t.size - 1  # the same accepted steps
    got = np.concatenate([np.asarray(tr.theta), np.asarray(tr.Omega)], axis=1)
    np.testing.assert_allclose(got, ref.y.T, rtol=1e-11, atol=1e-11)


def test_accuracy_against_a_tight_diffrax_solve():
    """At rtol = atol = 1e-10 the samples agree with :func:`simulate` at 1e-13 to ~1e-8."""
    model = make_model()
    tr = fast_simulate(model, THETA0, OMEGA0, TS)
    ref = simulate(model, THETA0, OMEGA0, TS, rtol=1e-13, atol=1e-13)
    assert tr.status == SolveStatus.successful
    np.testing.assert_allclose(tr.theta, ref.theta, atol=1e-8)
    np.testing.assert_allclose(tr.Omega, ref.Omega, atol=1e-8)


def test_energy_is_conserved_4_78():
    """Without loads the total energy (4.78) is an integral of motion: conserved to the
    tolerance over a long run."""
    ts = jnp.linspace(0.0, 50.0, 101)
    tr = fast_simulate(conservative_model(), THETA0, OMEGA0, ts, rtol=1e-11, atol=1e-11)
    E = np.asarray(tr.energy)
    assert np.ptp(E) < 1e-8 * abs(E[0])


@pytest.mark.slow
def test_error_follows_the_tolerance():
    """Tolerance proportionality: the global error against a tight solve falls by more than 100
    when the tolerance falls by 1000 (rtol = atol = 1e-6 → 1e-9), and is below 1e-4 at 1e-6."""
    model = conservative_model()
    ts = jnp.array([0.0, 5.0])
    ref = simulate(model, THETA0, OMEGA0, ts, rtol=1e-14, atol=1e-14).theta[-1]
    errs = [
        float(
            jnp.max(
                jnp.abs(
                    fast_simulate(model, THETA0, OMEGA0, ts, rtol=tol, atol=tol).theta[-1] - ref
                )
            )
        )
        for tol in (1e-6, 1e-9)
    ]
    assert errs[1] < errs[0] / 100  # tolerance proportionality over three decades
    assert errs[0] < 1e-4


def _batch(model_of, ps, y0s, ts, **kw):
    def one(p, y0):
        tr = fast_simulate(model_of(p), y0[:3], y0[3:], ts, throw=False, **kw)
        return tr.theta, tr.Omega, tr.status, tr.num_steps

    return jax.jit(jax.vmap(one))(ps, y0s)


def _model_of(p):
    return make_model(c=p[0], M=p[1])


@pytest.mark.slow  # cost: ~12 s of compilation
def test_vmap_without_jit_takes_numpy_batches():
    """``jax.vmap`` without ``jit`` hands batched NumPy parameters to the lanes as they are
    (they once failed with a TracerArrayConversionError): the results of ``jit(vmap)``, to
    rounding (eager and compiled programs fuse differently)."""

    def final(p):
        return fast_simulate(_model_of(p), THETA0, OMEGA0, TS, throw=False).theta[-1]

    ps = np.array([[0.8, 0.1], [1.2, 0.3], [1.6, 0.5]])
    eager = jax.vmap(final)(ps)
    np.testing.assert_allclose(
        eager, jax.jit(jax.vmap(final))(jnp.asarray(ps)), rtol=1e-12, atol=1e-14
    )
    assert np.all(np.isfinite(eager))


@pytest.mark.parametrize("lanes", [pytest.param(1000, marks=pytest.mark.slow), 5])
def test_batch_equals_single_trajectories(monkeypatch, lanes):
    """vmap runs the batch on refilled lanes (5 lanes for 16 trajectories: refills); every
    trajectory gets exactly its own solve, in its own place."""
    monkeypatch.setattr(ensemble, "LANES", lanes)
    rng = np.random.default_rng(lanes)
    n = 16  # as the sharded batch below on 2 devices: the same one-device program
    ps = jnp.asarray(np.stack([rng.uniform(0.5, 2.0, n), rng.uniform(0.0, 0.6, n)], 1))
    y0s = jnp.asarray(rng.uniform(-0.6, 0.6, (n, 6)))
    theta, Omega, status, steps = _batch(_model_of, ps, y0s, TS)
    for i in (0, 6, 15):
        tr = fast_simulate(_model_of(ps[i]), y0s[i, :3], y0s[i, 3:], TS)
        np.testing.assert_allclose(theta[i], tr.theta, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(Omega[i], tr.Omega, rtol=1e-13, atol=1e-13)
        assert int(steps[i]) == int(tr.num_steps)
    assert np.all(np.asarray(status == SolveStatus.successful))


def test_jit_vmap_on_a_named_sharding_keeps_the_one_device_bits(monkeypatch):
    """Issue 49 G, in this process (a worker has one CPU device per core of its affinity):
    ``jax.jit(jax.vmap(fast_simulate))`` of a batch placed with a ``NamedSharding`` over the
    local devices runs each device's share on its own lanes (5 lanes: refills), returns outputs
    on every device, and gives every trajectory the bits of the same batch on one device. (The
    complete tier's tests/test_devices.py checks 1, 2 and 4 devices in fresh processes, the
    padded replicated batch and the loops' collectives.)"""
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    monkeypatch.setattr(ensemble, "LANES", 5)
    devices = jax.devices()
    n = 8 * len(devices)
    rng = np.random.default_rng(5)
    ps = np.stack([rng.uniform(0.5, 2.0, n), rng.uniform(0.0, 0.6, n)], 1)
    y0s = rng.uniform(-0.6, 0.6, (n, 6))
    one = _batch(_model_of, jnp.asarray(ps), jnp.asarray(y0s), TS)
    spread = NamedSharding(Mesh(np.array(devices), ("batch",)), P("batch"))
    got = _batch(_model_of, jax.device_put(ps, spread), jax.device_put(y0s, spread), TS)
    for i in (0, 1, 3):  # theta, Omega, steps
        assert len(got[i].sharding.device_set) == len(devices)
        np.testing.assert_array_equal(np.asarray(got[i]), np.asarray(one[i]))
    assert bool(jnp.all(got[2] == one[2])) and bool(jnp.all(one[2] == SolveStatus.successful))


def test_final_state_only_takes_the_same_steps_without_dense_output():
    """With only the two ends of the interval sampled the program holds no dense output (the
    final sample is the last step's own state): the same steps and final state as a run that
    also samples inside the interval."""
    model = make_model()
    full = fast_simulate(model, THETA0, OMEGA0, TS)
    final = fast_simulate(model, THETA0, OMEGA0, TS[jnp.array([0, -1])])
    assert int(final.num_steps) == int(full.num_steps)
    np.testing.assert_allclose(final.theta[-1], full.theta[-1], rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(final.Omega[-1], full.Omega[-1], rtol=1e-13, atol=1e-14)


def test_lane_count_cuts_a_batch_into_waves():
    """A batch runs on at most ``LANES`` lanes and on no more than a quarter of its trajectories
    (but 256), so that the queue refills the lanes several times and the longest trajectories do
    not hold every lane (issue 31); always a multiple of the vector width, never more lanes than
    the batch needs. On an accelerator one wave, as wide as the batch allows."""
    count, V = LANES_SOLVER.lane_count, LANES_SOLVER.VECTOR
    assert count(13, 1000) == 16  # one wave, rounded up to the vector width
    assert count(200, 1000) == 208
    assert count(989, 1000) == 256  # the floor: four waves would be 256 - 8 lanes
    assert count(1483, 1000) == 384  # a quarter, rounded up
    assert count(2965, 1000) == 752
    assert count(5929, 1000) == 1008  # the cap, as before this rule
    assert count(5, 3) == 16  # a cap below the floor wins (tests use tiny caps)
    assert count(10**6, 2**18, waves=1) == 2**18
    assert count(1000, 2**18, waves=1) == 1008
    for n in (1, 17, 255, 257, 1023, 4001, 10**5):
        b = count(n, 1000)
        assert b % V == 0 and b <= LANES_SOLVER._round_up(n, V) and b <= 1008


@pytest.mark.slow  # cost: ~15-25 s, each batch compiled with and without compaction
@pytest.mark.parametrize("lanes, divisors", [(48, None), (256, (2, 8, 32))])
def test_tail_compaction_keeps_every_trajectory_bit_for_bit(monkeypatch, lanes, divisors):
    """Once the queue is empty, the running lanes are gathered into narrower loops (issue 31:
    the tail of a batch no longer costs every lane; the default one loop of a quarter of the
    lanes, or several): every trajectory's samples, status and accepted steps are those of the
    run without compaction, bit for bit, bad points included (a NaN start, invalid parameters,
    a barrier crossing)."""
    monkeypatch.setattr(ensemble, "LANES", lanes)
    if divisors is not None:
        monkeypatch.setattr(LANES_SOLVER, "COMPACT_DIVISORS", divisors)
    n = 3 * lanes + 5
    rng = np.random.default_rng(lanes)
    ps = np.stack([rng.uniform(0.5, 2.0, n), rng.uniform(0.0, 0.6, n)], 1)
    y0s = rng.uniform(-0.6, 0.6, (n, 6)) * rng.uniform(0.1, 1.0, (n, 1))  # unequal lengths
    y0s[7, 2], ps[11, 0], y0s[13] = np.nan, -1.0, [0.0, 2.1, 0.0, 0.0, 0.2, 0.0]
    ps, y0s = jnp.asarray(ps), jnp.asarray(y0s)
    monkeypatch.setattr(LANES_SOLVER, "COMPACT_FROM", 10**9)
    ref = _batch(_model_of, ps, y0s, TS)
    monkeypatch.setattr(LANES_SOLVER, "COMPACT_FROM", 0)
    widths = LANES_SOLVER.tail_widths(LANES_SOLVER._round_up(lanes, LANES_SOLVER.VECTOR), n)
    assert len(widths) == (1 if divisors is None else 3)
    got = _batch(_model_of, ps, y0s, TS)
    for i in (0, 1, 3):  # theta, Omega, steps
        np.testing.assert_array_equal(np.asarray(got[i]), np.asarray(ref[i]))
    assert bool(jnp.all(got[2] == ref[2]))  # the statuses
    assert len(set(np.asarray(ref[3]).tolist())) > 10  # the trajectories' lengths differ
    assert bool((ref[2] == SolveStatus.nonfinite_input)[7])
    assert bool((ref[2] == SolveStatus.invalid_parameters)[11])
    assert bool((ref[2] == SolveStatus.domain_error)[13])


@pytest.mark.slow  # cost: ~12-17 s, the batch compiled with and without its parking
def test_longest_first_keeps_every_trajectory_bit_for_bit(monkeypatch):
    """The queue run twice (issue 31, ``_queue.PROBE``): every trajectory first makes at most a
    few step attempts, the unfinished ones are parked (their lanes' states saved) and resumed
    later, longest first, from their saved states. Every trajectory's samples inside the
    interval, status and accepted steps are those of one run in the batch's order, bit for bit,
    bad points included, and most trajectories were parked and resumed (the order is for large
    batches, ``_queue.ORDER_FROM``; here a small one, so that it compiles fast)."""
    monkeypatch.setattr(ensemble, "LANES", 32)
    monkeypatch.setattr(QUEUE, "ORDER_FROM", 0)  # a small batch ordered too
    n = 3 * 32 + 7
    rng = np.random.default_rng(3)
    ps = np.stack([rng.uniform(0.5, 2.0, n), rng.uniform(0.0, 0.6, n)], 1)
    y0s = rng.uniform(-0.6, 0.6, (n, 6)) * rng.uniform(0.1, 1.0, (n, 1))  # unequal lengths
    y0s[5, 0], ps[9, 0], y0s[12] = np.nan, -1.0, [0.0, 2.1, 0.0, 0.0, 0.2, 0.0]
    ps, y0s = jnp.asarray(ps), jnp.asarray(y0s)
    monkeypatch.setattr(QUEUE, "PROBE", 2**30)  # never parked: the batch's order
    ref = _batch(_model_of, ps, y0s, TS)
    monkeypatch.setattr(QUEUE, "PROBE", 12)
    got = _batch(_model_of, ps, y0s, TS)
    for i in (0, 1, 3):  # theta, Omega (17 samples each), steps
        np.testing.assert_array_equal(np.asarray(got[i]), np.asarray(ref[i]))
    assert bool(jnp.all(got[2] == ref[2]))  # the statuses
    steps = np.asarray(ref[3])
    assert np.sum(steps > 12) > n // 2 and len(set(steps.tolist())) > 10  # parked, unequal
    assert bool((ref[2] == SolveStatus.nonfinite_input)[5])
    assert bool((ref[2] == SolveStatus.invalid_parameters)[9])
    assert bool((ref[2] == SolveStatus.domain_error)[12])
    assert int(jnp.sum(ref[2] == SolveStatus.successful)) == n - 3


def test_bad_points_are_flagged_and_the_rest_solved(monkeypatch):
    """In one batch: a NaN initial state, invalid parameters, a barrier crossing (domain of
    (4.49)), a step budget too small; the other trajectories are unaffected."""
    monkeypatch.setattr(ensemble, "LANES", 3)
    ps = jnp.array([[1.0, 0.3], [1.0, 0.3], [-1.0, 0.3], [1.0, 0.3], [1.5, 0.1]])
    y0s = jnp.array(
        [
            [0.1, 0.0, 0.1, 0.0, 0.2, 0.0],
            [jnp.nan, 0.0, 0.1, 0.0, 0.2, 0.0],
            [0.1, 0.0, 0.1, 0.0, 0.2, 0.0],
            [0.0, 2.1, 0.0, 0.0, 0.2, 0.0],  # beyond the bending barrier
            [0.2, 0.1, 0.0, 0.1, 0.0, 0.3],
        ]
    )
    theta, Omega, status, _ = _batch(_model_of, ps, y0s, TS)
    expect = [
        SolveStatus.successful,
        SolveStatus.nonfinite_input,
        SolveStatus.invalid_parameters,
        SolveStatus.domain_error,
        SolveStatus.successful,
    ]
    for i, e in enumerate(expect):
        assert bool((status == e)[i]), i
    assert np.all(np.isinf(np.asarray(theta[1]))) and np.all(np.isnan(np.asarray(theta[2])))
    assert np.all(np.isinf(np.asarray(theta[3])))
    for i in (0, 4):
        tr = fast_simulate(_model_of(ps[i]), y0s[i, :3], y0s[i, 3:], TS)
        np.testing.assert_allclose(theta[i], tr.theta, rtol=1e-13, atol=1e-13)


def test_max_steps_and_throw():
    model = make_model()
    tr = fast_simulate(model, THETA0, OMEGA0, TS, max_steps=5, throw=False)
    assert tr.status == SolveStatus.max_steps_reached
    assert np.all(np.isinf(np.asarray(tr.theta[-1])))
    with pytest.raises(RUNTIME_ERRORS, match="max"):
        fast_simulate(model, THETA0, OMEGA0, TS, max_steps=5)
    with pytest.raises(ValueError, match="rtol"):
        fast_simulate(model, THETA0, OMEGA0, TS, rtol=-1.0)


def test_singular_point_is_reported_not_nan():
    """Nearly plane rotation (Ω0 with a 1e-5 transverse part) from |θ| = 6: |θ| reaches 2π at
    t ≈ 0.28 with θ×Ω ≠ 0, where det Z = ∞ (4.11): status ``singular_point``, no NaN."""
    model = conservative_model(c=0.01, d=0.01, A1=1.0, A3=1.0)
    tr = fast_simulate(model, 6.0 * K, jnp.array([1e-5, 0.0, 1.0]), TS, throw=False)
    assert tr.status == SolveStatus.singular_point
    assert not np.any(np.isnan(np.asarray(tr.theta)))
    np.testing.assert_array_equal(np.isinf(np.asarray(tr.theta[1:, 0])), True)
    with pytest.raises(RUNTIME_ERRORS, match="singular point"):
        jax.block_until_ready(fast_simulate(model, 6.0 * K, jnp.array([1e-5, 0.0, 1.0]), TS).theta)


def test_plane_motion_passes_through_2pi():
    """Rotation about a fixed axis (θ ∥ Ω) crosses |θ| = 2π harmlessly: no singular status, and
    the rotation angle grows as for a free spin about k at rate Ω (4.14)."""
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(1.0, 0.6, K), QuadraticFoundation(1.0, 1e-12, K), []
    )
    ts = jnp.linspace(0.0, 10.0, 11)
    tr = fast_simulate(model, jnp.zeros(3), jnp.array([0.0, 0.0, 1.0]), ts)
    np.testing.assert_allclose(tr.theta[:, 2], ts, rtol=1e-8, atol=1e-8)


@pytest.mark.slow  # cost: ~12 s of compilation
def test_forward_derivatives_match_finite_differences():
    """jacfwd of the final state w.r.t. the foundation stiffness c and the initial state
    against central differences of tight solves."""
    ts = jnp.array([0.0, 3.0])

    def final(c, y0):
        tr = fast_simulate(make_model(c=c), y0[:3], y0[3:], ts, rtol=1e-12, atol=1e-12)
        return jnp.concatenate([tr.theta[-1], tr.Omega[-1]])

    y0 = jnp.concatenate([THETA0, OMEGA0])
    dc, dy = jax.jacfwd(final, argnums=(0, 1))(1.0, y0)
    eps = 1e-5
    fd_c = (final(1.0 + eps, y0) - final(1.0 - eps, y0)) / (2 * eps)
    np.testing.assert_allclose(dc, fd_c, rtol=1e-6, atol=1e-7)
    e = jnp.eye(6)[2] * eps
    fd_y = (final(1.0, y0 + e) - final(1.0, y0 - e)) / (2 * eps)
    np.testing.assert_allclose(dy[:, 2], fd_y, rtol=1e-6, atol=1e-7)


def test_jacfwd_traces_the_loop_of_its_directions_only(monkeypatch):
    """jax.jacfwd runs its K directions in one loop (the batching rule of the tangent solver);
    the loop for one direction, which its program does not hold, is not traced first (~0.25 s
    of tracing in a fit's fresh process). A single jax.jvp traces that one; vmap over
    trajectories of jacfwd and jacfwd over trajectories run the loop of K directions per
    trajectory. The probe that tells them apart: True only where a vmap batches an argument."""
    import rbo_jax.ensemble as ens

    directions = []
    real = ens.solve_one_tangents
    monkeypatch.setattr(
        ens, "solve_one_tangents", lambda *a: directions.append(a[-1].shape[0]) or real(*a)
    )
    ts = jnp.array([0.0, 1.0])

    def final(c, y0):
        return fast_simulate(make_model(c=c), y0[:3], y0[3:], ts, throw=False).theta[-1]

    y0 = jnp.concatenate([THETA0, OMEGA0])
    jax.jit(jax.jacfwd(final, argnums=(0, 1))).lower(1.0, y0)
    assert directions == [7]  # c and the six components of the state, in one trace
    directions.clear()
    jax.jit(lambda c: jax.jvp(lambda c: final(c, y0), (c,), (1.0,))).lower(1.0)
    assert directions == [1]
    directions.clear()
    jax.jit(jax.vmap(jax.jacfwd(final), (0, None))).lower(jnp.ones(3), y0)
    assert directions == [1]  # vmap of the loop of one direction over the 3 trajectories
    x, seen = jnp.ones(3), []
    for f in (
        lambda x: ens._batched((x,)),  # eager: False
        jax.jit(lambda x: seen.append(ens._batched((x,))) or x),  # inside jit alone: False
        jax.vmap(lambda x: seen.append(ens._batched((x, y0))) or x),  # batched by the vmap
        jax.vmap(lambda x: seen.append(ens._batched((y0,))) or x),  # not batched by it
    ):
        out = f(x)
        if isinstance(out, bool):
            seen.append(out)
    assert seen == [False, False, True, False]


@pytest.mark.slow
def test_batched_forward_derivatives():
    """vmap of jacfwd (lockstep per-trajectory loops) equals the per-point derivatives."""
    ts = jnp.array([0.0, 3.0])
    y0 = jnp.concatenate([THETA0, OMEGA0])

    def final(c):
        tr = fast_simulate(make_model(c=c), y0[:3], y0[3:], ts, rtol=1e-12, atol=1e-12)
        return jnp.concatenate([tr.theta[-1], tr.Omega[-1]])

    cs = jnp.array([1.0, 1.3])
    dcs = jax.jit(jax.vmap(jax.jacfwd(final)))(cs)
    for i in range(2):
        np.testing.assert_allclose(dcs[i], jax.jacfwd(final)(cs[i]), rtol=1e-12, atol=1e-14)


def test_throw_false_programs_hold_no_host_callback():
    """JAX's persistent compilation cache keeps no program with a host callback. With
    throw=False every check of fast_simulate (traced times, parameters, initial state, the
    solve) is in the status; with throw=True the checks raise, through callbacks."""

    def run(throw):
        return jax.jit(
            lambda c, ts: fast_simulate(make_model(c=c), THETA0, OMEGA0, ts, throw=throw).theta
        )

    assert "callback" not in run(False).lower(1.0, TS).as_text()
    assert "callback" in run(True).lower(1.0, TS).as_text()


@pytest.mark.parametrize("integrator", [fast_simulate, simulate], ids=lambda f: f.__name__)
def test_traced_bad_times_give_a_status_without_throw(integrator):
    """Traced times that are not strictly increasing and finite: status invalid_times and NaN
    samples with throw=False (the times are reported as given); good times solve normally."""
    run = jax.jit(lambda ts: integrator(conservative_model(), THETA0, OMEGA0, ts, throw=False))
    for ts in ([0.0, 2.0, 1.0], [0.0, 1.0, 1.0], [0.0, np.nan, 1.0], [0.0, 0.5, 1.0]):
        tr = run(jnp.asarray(ts))
        good = ts == [0.0, 0.5, 1.0]
        assert tr.status_name == ("successful" if good else "invalid_times"), ts
        assert bool(jnp.all(jnp.isnan(tr.theta))) != good
        np.testing.assert_array_equal(tr.ts, np.asarray(ts))
    if integrator is fast_simulate:
        with pytest.raises(RUNTIME_ERRORS, match="strictly increasing"):
            jax.block_until_ready(
                jax.jit(lambda ts: integrator(conservative_model(), THETA0, OMEGA0, ts).theta)(
                    jnp.array([0.0, 2.0, 1.0])
                )
            )


@pytest.mark.slow
def test_forward_derivatives_in_one_loop_equal_jvp_of_the_loop():
    """jacfwd with respect to parameters and the initial state runs all directions in one loop
    (ensemble._tangents); with respect to the times too it is JAX's JVP of the per-trajectory
    loop. Both give the same derivatives, a single jvp the same as jacfwd, and the primal of the
    derivative path the primal of fast_simulate."""
    ts = jnp.linspace(0.0, 4.0, 9)

    def samples(c, y0, ts):
        tr = fast_simulate(make_model(c=c), y0[:3], y0[3:], ts, rtol=1e-12, atol=1e-12)
        return jnp.concatenate([tr.theta, tr.Omega], axis=1)

    y0 = jnp.concatenate([THETA0, OMEGA0])
    dc, dy = jax.jit(jax.jacfwd(samples, argnums=(0, 1)))(1.0, y0, ts)
    dc2, dy2, _ = jax.jit(jax.jacfwd(samples, argnums=(0, 1, 2)))(1.0, y0, ts)
    np.testing.assert_allclose(dc, dc2, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(dy, dy2, rtol=1e-12, atol=1e-13)
    primal, tangent = jax.jvp(lambda c: samples(c, y0, ts), (1.0,), (1.0,))
    np.testing.assert_allclose(tangent, dc, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(primal, samples(1.0, y0, ts), rtol=1e-13, atol=1e-14)


def test_undefined_moment_direction_is_a_status_without_throw():
    """Started where l1 k + l2 P·k = 0 (a half turn about an axis ⊥ k, l1 = l2), the direction
    of the semi-tangential moment (4.75) is undefined: throw=True raises its message; with
    throw=False the vector field gives NaN instead of a host callback and the solve stops with
    nonfinite_state."""
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(1.0, 0.6, K),
        QuadraticFoundation(1.0, 2.0, K),
        [SemiTangentialMoment(1.0, K)],
    )
    half_turn = jnp.array([0.0, np.pi, 0.0])
    ts = jnp.linspace(0.0, 1.0, 5)
    run = jax.jit(lambda th: fast_simulate(model, th, OMEGA0 * 0, ts, throw=False))
    assert "callback" not in run.lower(half_turn).as_text()
    tr = run(half_turn)
    assert tr.status_name == "nonfinite_state"
    assert not np.any(np.isfinite(tr.theta[1:]))
    assert run(half_turn * 0.9).status_name == "successful"
    with pytest.raises(RUNTIME_ERRORS, match="direction of the moment"):
        jax.block_until_ready(fast_simulate(model, half_turn, OMEGA0 * 0, ts).theta)
