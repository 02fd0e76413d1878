"""The simulator: :func:`rbo_jax.simulate.simulate` and :func:`rbo_jax.simulate.solve_darboux`.

Checked against exact solutions (plane oscillation, the regular precession (4.113), a prescribed
turn-vector path for the Darboux problems (4.15)/(4.16)), finite differences, and the other form of
the equations (4.53)–(4.54). Failures must be reported with the right status, never as NaN.

Compilation dominates the run time (diffeqsolve compiles once per model structure, ``ts`` length
and static option), so almost every test uses the same model structure (:func:`make_model`) and
``N`` samples, and the solves are shared through module-scoped fixtures.
"""

import importlib.util
import os
import subprocess
import sys
import textwrap

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.stats
from jaxtyping import Array

from rbo_jax.foundations import BarrierFoundation, QuadraticFoundation
from rbo_jax.inertia import transversely_isotropic_inertia
from rbo_jax.loads import CallableLoad, Friction, SemiTangentialMoment
from rbo_jax.model import RigidBodyOscillator
from rbo_jax.simulate import SolveStatus, simulate, solve_darboux

K = jnp.array([0.0, 0.0, 1.0])
N = 21  # samples in every ts: one compilation per model structure
TIGHT = dict(rtol=1e-12, atol=1e-12)
THETA0 = jnp.array([0.5, -0.4, 0.3])
OMEGA0 = jnp.array([0.3, 0.9, 0.6])
TS = jnp.linspace(0.0, 10.0, N)
RUNTIME_ERRORS = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError)


class Forcing(eqx.Module):
    """A time-dependent world moment amp·(sin t, cos 2t, ½), NaN for t > t_blowup."""

    amp: Array
    t_blowup: Array

    def __call__(self, t, theta, omega):
        moment = self.amp * jnp.stack([jnp.sin(t), jnp.cos(2 * t), 0.5 * jnp.ones_like(t)])
        return jnp.where(t > self.t_blowup, jnp.nan, moment)


def make_model(
    c=1.0, d=2.0, alpha=2.0, beta=1.5, A1=1.0, A3=0.6, M=0.3, b=0.05, amp=0.1, t_blowup=jnp.inf
):
    """The model structure shared by the tests: transversely isotropic inertia (4.40), barrier
    foundation (4.49), semi-tangential moment (4.75), friction (4.84), a time-dependent
    CallableLoad. Zero loads and alpha = beta = inf give the quadratic foundation (4.50)."""
    forcing = Forcing(jnp.asarray(amp, dtype=float), jnp.asarray(t_blowup, dtype=float))
    return RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, K),
        BarrierFoundation(c, d, alpha, beta, K),
        [SemiTangentialMoment(M, K), Friction(b), CallableLoad(forcing)],
    )


def free_model(**kwargs):
    """make_model without loads and barriers: (4.50) with the given stiffnesses."""
    return make_model(alpha=jnp.inf, beta=jnp.inf, M=0.0, b=0.0, amp=0.0, **kwargs)


def np_Q(theta):
    """Turn-tensor (4.3)-(4.4) in NumPy (Rodrigues)."""
    theta = np.asarray(theta, dtype=float)
    th = np.linalg.norm(theta)
    R = np.array(
        [[0.0, -theta[2], theta[1]], [theta[2], 0.0, -theta[0]], [-theta[1], theta[0], 0.0]]
    )
    return np.eye(3) + np.sin(th) / th * R + (1 - np.cos(th)) / th**2 * R @ R


def np_barrier_energy(theta, c=1.0, d=2.0, alpha=2.0, beta=1.5):
    """U of (4.49) as printed, axis k = e3."""
    x, t = theta[2], theta @ theta
    return 0.5 * alpha**2 * c * t / (alpha**2 - t + x**2) + 0.5 * beta**2 * (d - c) * x**2 / (
        beta**2 - x**2
    )


_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
_COMPILES = [0]


def _count_compiles(event, duration, **kwargs):
    if event == _COMPILE_EVENT:
        _COMPILES[0] += 1


# registered once for the session: older JAX versions have no way to unregister a listener
jax.monitoring.register_event_duration_secs_listener(_count_compiles)


class CompileCounter:
    """Counts XLA compilations (jax.monitoring backend-compile events) inside a ``with``."""

    def __enter__(self):
        self._start, self._end = _COMPILES[0], None
        return self

    @property
    def count(self) -> int:
        """Compilations between entering and leaving the ``with`` (not those of later code)."""
        return (_COMPILES[0] if self._end is None else self._end) - self._start

    def __exit__(self, *exc):
        self._end = _COMPILES[0]


def _all_inf_or_finite(x):
    x = np.asarray(x)
    return not np.any(np.isnan(x))


# ---------------------------------------------------------------------------------------------
# Left and right forms; derived quantities.
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def right_trajectory():
    return simulate(make_model(), THETA0, OMEGA0, TS, **TIGHT)


@pytest.fixture(scope="module")
def left_trajectory():
    return simulate(make_model(), THETA0, OMEGA0, TS, form="left", **TIGHT)


def test_left_and_right_forms_agree_4_53_4_56(right_trajectory, left_trajectory):
    """(4.53)–(4.54) in (θ, L) and (4.55)–(4.56) in (θ, Ω) give the same motion (barrier
    foundation, semi-tangential load, friction, time-dependent forcing) to 1e-9."""
    for traj in (right_trajectory, left_trajectory):
        assert bool(traj.ok) and traj.message == "successful"
    assert np.max(np.linalg.norm(np.asarray(right_trajectory.theta), axis=1)) > 0.5
    np.testing.assert_allclose(left_trajectory.theta, right_trajectory.theta, rtol=0, atol=1e-9)
    np.testing.assert_allclose(left_trajectory.Omega, right_trajectory.Omega, rtol=0, atol=1e-9)


def test_trajectory_derived_quantities(right_trajectory):
    """ω = P·Ω, P orthogonal with det 1, L = P·A·Ω (4.44), E = K + U with U of (4.49)."""
    traj = right_trajectory
    A = np.diag([1.0, 1.0, 0.6])
    P = np.asarray(traj.turn_tensor)
    omega, L, E = np.asarray(traj.omega), np.asarray(traj.kinetic_moment), np.asarray(traj.energy)
    K_, U_ = np.asarray(traj.kinetic_energy), np.asarray(traj.potential_energy)
    for i, (theta, Omega) in enumerate(zip(np.asarray(traj.theta), np.asarray(traj.Omega))):
        Q = np_Q(theta)
        np.testing.assert_allclose(P[i], Q, atol=1e-14)
        np.testing.assert_allclose(P[i] @ P[i].T, np.eye(3), atol=1e-14)
        assert abs(np.linalg.det(P[i]) - 1) < 1e-14
        np.testing.assert_allclose(omega[i], Q @ Omega, atol=1e-14)
        np.testing.assert_allclose(L[i], Q @ A @ Omega, atol=1e-14)
        kinetic = 0.5 * Omega @ A @ Omega
        potential = np_barrier_energy(theta)
        np.testing.assert_allclose(K_[i], kinetic, rtol=1e-13)
        np.testing.assert_allclose(U_[i], potential, rtol=1e-13)
        np.testing.assert_allclose(E[i], kinetic + potential, rtol=1e-13)


# ---------------------------------------------------------------------------------------------
# Exact solutions; convergence order.
# ---------------------------------------------------------------------------------------------


def test_plane_torsion_oscillation_through_2pi_is_exact():
    """Plane rotation about k (θ ∥ Ω ∥ k, A3 = 1, U = ½d(k·θ)²): |θ| obeys θ̈ = −dθ, so
    θ(t) = (θ0 cos√d t + θ̇0/√d sin√d t) k, through |θ| = 2π (θ×Ω = 0: no singular point), and
    P(t) = exp(θ(t)×E)."""
    d = 0.01
    model = free_model(c=d, d=d, A1=1.0, A3=1.0)
    traj = simulate(model, 6.0 * K, 1.0 * K, TS, **TIGHT)
    w = np.sqrt(d)
    t = np.asarray(TS)
    exact = 6.0 * np.cos(w * t) + 1.0 / w * np.sin(w * t)
    assert exact.max() > 2 * np.pi + 4 and exact[0] < 2 * np.pi  # crosses the sphere
    np.testing.assert_allclose(traj.theta[:, 2], exact, rtol=2e-9)
    np.testing.assert_array_equal(traj.theta[:, :2], 0.0)
    # |ΔQ| ≤ |Δθ| ≤ 2e-9·|θ|: the turn-tensor is as exact as the turn-vector
    atol = 2e-9 * np.max(np.abs(exact))
    for i in range(N):
        expm = scipy.linalg.expm(exact[i] * np.array([[0, -1, 0], [1, 0, 0], [0, 0, 0.0]]))
        np.testing.assert_allclose(traj.turn_tensor[i], expm, rtol=0, atol=atol)


def _precession(A1, A3, c, vartheta):
    """Regular precession θ = ϑ Q(ψk)·p, p = e1, ψ = ψ̇t, with ψ̇ from (4.113) (C = c, D = 0 on
    k·θ = 0 for (4.50)); returns ψ̇, θ(t) and Ω0 = P0ᵀ·ω0, ω0 of (4.112)."""
    psi_dot = np.sqrt(
        c * vartheta / (np.sin(vartheta) * (A3 * (1 - np.cos(vartheta)) + A1 * np.cos(vartheta)))
    )
    p, k = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    omega0 = psi_dot * ((1 - np.cos(vartheta)) * k + np.sin(vartheta) * np.cross(k, p))
    Omega0 = np_Q(vartheta * p).T @ omega0

    def theta(t):
        return vartheta * np.array([np.cos(psi_dot * t), np.sin(psi_dot * t), 0.0])

    return psi_dot, theta, Omega0


PRECESSION = dict(A1=1.0, A3=0.6, c=1.0, vartheta=0.8)
FIXED_MAX_STEPS = 4096


def _fixed_step_simulate(model, theta0, Omega0, ts, dt, **kwargs):
    return simulate(
        model,
        theta0,
        Omega0,
        ts,
        dt0=jnp.asarray(np.float64(dt)),  # strongly typed: one compilation for all dt
        stepsize_controller=diffrax.ConstantStepSize(),
        max_steps=FIXED_MAX_STEPS,
        **kwargs,
    )


def test_dopri8_convergence_order_on_regular_precession_4_113():
    """Fixed steps of the default solver (Dopri8) on the exact regular precession (4.113),
    A1 ≠ A3: the error at t = T (one revolution) falls as dt^p with p ≈ 8."""
    psi_dot, theta_exact, Omega0 = _precession(**PRECESSION)
    model = free_model(c=PRECESSION["c"], d=2.0, A1=PRECESSION["A1"], A3=PRECESSION["A3"])
    T = 2 * np.pi / psi_dot
    ts = jnp.linspace(0.0, T, N)
    theta0 = jnp.asarray(theta_exact(0.0))
    steps = np.array([8, 10, 12, 16, 20, 24, 32])  # errors ~1e-7 ... 1e-12
    errors = []
    for n in steps:
        traj = _fixed_step_simulate(model, theta0, jnp.asarray(Omega0), ts, T / n)
        assert int(traj.num_steps) == n
        errors.append(np.linalg.norm(np.asarray(traj.theta[-1]) - theta_exact(T)))
    errors = np.array(errors)
    assert np.all(errors > 1e-13), errors  # above roundoff (~1e-15 here)
    assert np.all(np.diff(errors) < 0), errors
    fit = scipy.stats.linregress(np.log(T / steps), np.log(errors))
    assert 7.0 <= fit.slope <= 9.5, (fit.slope, errors)


# ---------------------------------------------------------------------------------------------
# Gradients.
# ---------------------------------------------------------------------------------------------

P0 = jnp.concatenate([jnp.array([1.0, 2.0, 1.0]), THETA0])  # (c, d, A1, θ0)
WEIGHTS = jnp.array([0.7, -1.3, 0.4, 1.1, 0.5, -0.9])
TS_GRAD = jnp.linspace(0.0, 3.0, N)


def _end_state(p, adjoint=None):
    """w·(θ(T), Ω(T)) as a function of (c, d) of (4.49), A1 of (4.40) and θ0."""
    model = make_model(c=p[0], d=p[1], A1=p[2])
    traj = simulate(model, p[3:6], OMEGA0, TS_GRAD, adjoint=adjoint, **TIGHT)
    return jnp.concatenate([traj.theta[-1], traj.Omega[-1]]) @ WEIGHTS


@pytest.fixture(scope="module")
def finite_difference_gradient():
    """Central differences, h = 1e-4 relative (truncation ~1e-8, solver noise ~1e-8)."""
    grads = []
    for i in range(P0.size):
        h = 1e-4 * max(1.0, abs(float(P0[i])))
        e = jnp.zeros_like(P0).at[i].set(h)
        grads.append((float(_end_state(P0 + e)) - float(_end_state(P0 - e))) / (2 * h))
    return np.array(grads)


@pytest.mark.slow  # cost: ~20 s, reverse mode through diffrax compiled
def test_reverse_mode_gradient_matches_finite_differences(finite_difference_gradient):
    """jax.grad (RecursiveCheckpointAdjoint, the default), under jit, w.r.t. c, d, A1 and θ0."""
    grad = np.asarray(jax.jit(jax.grad(_end_state))(P0))
    assert np.all(np.abs(finite_difference_gradient) > 1e-3)  # every parameter matters
    np.testing.assert_allclose(grad, finite_difference_gradient, rtol=1e-5)


def test_forward_mode_gradient_matches_finite_differences(finite_difference_gradient):
    """jax.jacfwd with adjoint=diffrax.ForwardMode(), under jit."""
    grad = np.asarray(jax.jit(jax.jacfwd(lambda p: _end_state(p, diffrax.ForwardMode())))(P0))
    np.testing.assert_allclose(grad, finite_difference_gradient, rtol=1e-5)


# ---------------------------------------------------------------------------------------------
# jit, vmap, recompilation.
# ---------------------------------------------------------------------------------------------

TRACES = []


def _run(c, theta0):
    TRACES.append(None)  # Python side effect: runs once per trace
    return simulate(make_model(c=c), theta0, OMEGA0, TS, throw=False, **TIGHT)


run_batch = jax.jit(jax.vmap(_run))
CS = jnp.array([0.8, 1.0, 1.4])
THETAS = jnp.stack([THETA0, 0.5 * THETA0, jnp.array([0.1, 0.6, -0.4])])


@pytest.fixture(scope="module")
def batch():
    return run_batch(CS, THETAS)


def test_vmap_matches_loop_of_single_calls(batch):
    """jax.vmap over (c, θ0), model built inside the vmap, equals separate simulate calls."""
    assert np.all(np.asarray(batch.ok))
    for i in range(CS.size):
        single = simulate(make_model(c=float(CS[i])), THETAS[i], OMEGA0, TS, **TIGHT)
        # same equations and tolerances (1e-12); batched arithmetic may round differently, and
        # a different rounding takes other steps: agreement to ~100x the tolerance
        np.testing.assert_allclose(batch.theta[i], single.theta, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(batch.Omega[i], single.Omega, rtol=1e-9, atol=1e-10)


def test_jit_does_not_recompile_for_new_parameter_values(batch):
    n_traces, n_cache = len(TRACES), run_batch._cache_size()
    again = run_batch(1.1 * CS, THETAS[::-1])
    assert np.all(np.asarray(again.ok))
    assert not np.allclose(again.theta, batch.theta)
    assert len(TRACES) == n_traces == 1
    assert run_batch._cache_size() == n_cache == 1


def test_eager_simulate_does_not_recompile_for_new_values(right_trajectory):
    """Calling simulate again with new parameter values and initial state compiles nothing
    (the event and conversion functions must not be fresh closures per call)."""
    theta0, Omega0 = 0.9 * THETA0, OMEGA0[::-1]
    with CompileCounter() as counter:
        traj = simulate(make_model(c=1.2, b=0.1), theta0, Omega0, TS, **TIGHT)
        jax.block_until_ready(traj.theta)
    assert bool(traj.ok)
    assert not np.allclose(traj.theta, right_trajectory.theta)
    assert counter.count == 0
    # the counter does count: a new tolerance is a new program
    with CompileCounter() as control:
        jax.block_until_ready(
            simulate(make_model(c=1.2, b=0.1), theta0, Omega0, TS, rtol=1e-11, atol=1e-11).theta
        )
    assert control.count >= 1


def test_vmap_without_throw_flags_only_the_bad_points(batch):
    """One non-finite θ0 and one θ0 beyond the bending barrier: those points get their status,
    the others are successful and unchanged."""
    thetas = THETAS.at[1, 0].set(jnp.nan).at[2].set(jnp.array([2.5, 0.0, 0.0]))
    traj = run_batch(CS, thetas)
    expected = [SolveStatus.successful, SolveStatus.nonfinite_input, SolveStatus.domain_error]
    for i, status in enumerate(expected):
        assert bool((traj.status == status)[i]), i
    np.testing.assert_array_equal(traj.theta[0], batch.theta[0])
    assert np.all(np.isinf(np.asarray(traj.theta[1:])))


# ---------------------------------------------------------------------------------------------
# Failures.
# ---------------------------------------------------------------------------------------------


def _assert_failed_after(traj, status, t_fail):
    """Status, message, finite samples before t_fail and inf samples (never NaN) after."""
    assert not bool(traj.ok)
    assert bool(traj.status == status)
    assert traj.message == SolveStatus[status]
    ts = np.asarray(traj.ts)
    for x in (np.asarray(traj.theta), np.asarray(traj.Omega)):
        assert _all_inf_or_finite(x)
        assert np.all(np.isfinite(x[ts < t_fail]))
        assert np.all(np.isinf(x[ts > t_fail]))


def test_max_steps_reached():
    """Too few steps: status max_steps_reached, samples after the last step inf; throw=True
    raises with the message."""
    _, theta_exact, Omega0 = _precession(**PRECESSION)
    model = free_model(A1=PRECESSION["A1"], A3=PRECESSION["A3"])
    args = (model, jnp.asarray(theta_exact(0.0)), jnp.asarray(Omega0), TS, 1e-3)
    traj = _fixed_step_simulate(*args, throw=False)
    assert int(traj.num_steps) == FIXED_MAX_STEPS
    _assert_failed_after(traj, SolveStatus.max_steps_reached, FIXED_MAX_STEPS * 1e-3)
    assert "max_steps" in traj.message
    with pytest.raises(RUNTIME_ERRORS, match="maximum number of solver steps"):
        jax.block_until_ready(_fixed_step_simulate(*args).theta)


@pytest.mark.parametrize("where", ["theta0", "Omega0", "parameter"])
def test_nonfinite_input(where):
    theta0, Omega0, model = THETA0, OMEGA0, make_model()
    if where == "theta0":
        theta0 = theta0.at[1].set(jnp.inf)
    elif where == "Omega0":
        Omega0 = Omega0.at[0].set(jnp.nan)
    else:  # bypasses the constructor's validation: the solve's parameter check catches it
        model = eqx.tree_at(lambda m: m.foundation.c, model, model.foundation.c * np.nan)
        traj = simulate(model, theta0, Omega0, TS, throw=False, **TIGHT)
        assert traj.status_name == "invalid_parameters"
        assert np.all(np.isnan(np.asarray(traj.theta))) and np.all(np.isnan(np.asarray(traj.Omega)))
        with pytest.raises(RUNTIME_ERRORS, match="a model parameter is NaN"):
            jax.block_until_ready(simulate(model, theta0, Omega0, TS, **TIGHT).theta)
        return
    traj = simulate(model, theta0, Omega0, TS, throw=False, **TIGHT)
    assert bool(traj.status == SolveStatus.nonfinite_input)
    assert np.all(np.isinf(np.asarray(traj.theta))) and np.all(np.isinf(np.asarray(traj.Omega)))
    with pytest.raises(RUNTIME_ERRORS, match="not finite"):
        jax.block_until_ready(simulate(model, theta0, Omega0, TS, **TIGHT).theta)


def test_infinite_barrier_parameters_are_not_nonfinite_input():
    """alpha = beta = inf is a valid BarrierFoundation ((4.50)): the solve succeeds."""
    traj = simulate(free_model(), THETA0, OMEGA0, TS, **TIGHT)
    assert bool(traj.ok) and np.all(np.isfinite(np.asarray(traj.theta)))
    assert traj.status_name == "successful"


def test_nan_load_gives_step_size_collapse():
    """A load that turns NaN at t > 1.2 makes the step size collapse (steps are rejected until
    dt < dtmin): reported as step_size_collapse, samples before 1.2 finite, later ones inf."""
    model = make_model(t_blowup=1.2)
    traj = simulate(model, THETA0, OMEGA0, TS, throw=False, **TIGHT)
    _assert_failed_after(traj, SolveStatus.step_size_collapse, 1.2)
    with pytest.raises(RUNTIME_ERRORS, match="step size collapsed"):
        jax.block_until_ready(simulate(model, THETA0, OMEGA0, TS, **TIGHT).theta)


def test_nearly_plane_rotation_stops_at_singular_point_4_11():
    """As the plane test, with a 1e-5 transverse component of Ω0: θ×Ω ≠ 0 when |θ| reaches 2π,
    where det Z = ∞ (4.11): status singular_point (not NaN, not a wrong answer)."""
    d = 0.01
    model = free_model(c=d, d=d, A1=1.0, A3=1.0)
    Omega0 = jnp.array([1e-5, 0.0, 1.0])
    traj = simulate(model, 6.0 * K, Omega0, TS, throw=False, **TIGHT)
    # the plane motion 6 cos wt + (1/w) sin wt = R cos(wt − φ) reaches 2π at t_cross ≈ 0.28
    w = np.sqrt(d)
    R, phi = np.hypot(6.0, 1.0 / w), np.arctan2(1.0 / w, 6.0)
    t_cross = (phi - np.arccos(2 * np.pi / R)) / w
    assert 0.0 < t_cross < float(TS[1])
    _assert_failed_after(traj, SolveStatus.singular_point, t_cross)
    assert "singular point" in traj.message and traj.status_name == "singular_point"
    with pytest.raises(RUNTIME_ERRORS, match="singular point"):
        jax.block_until_ready(simulate(model, 6.0 * K, Omega0, TS, **TIGHT).theta)


def test_initial_state_beyond_barrier_is_domain_error_4_49():
    """θ0 beyond the bending barrier θ_⊥ = α of (4.49): domain_error at once, all samples inf."""
    traj = simulate(make_model(), jnp.array([0.0, 2.1, 0.0]), OMEGA0, TS, throw=False, **TIGHT)
    assert bool(traj.status == SolveStatus.domain_error)
    assert np.all(np.isinf(np.asarray(traj.theta)))
    with pytest.raises(RUNTIME_ERRORS, match="left the domain"):
        theta0 = jnp.array([0.0, 2.1, 0.0])
        jax.block_until_ready(simulate(make_model(), theta0, OMEGA0, TS, **TIGHT).theta)


def test_step_across_barrier_is_domain_error_4_49():
    """A step that jumps over the bending barrier (small alpha, fast motion, fixed steps) is
    reported as domain_error, with inf (not NaN) afterwards."""
    model = make_model(alpha=0.3)
    traj = _fixed_step_simulate(
        model, jnp.array([0.1, 0.0, 0.0]), jnp.array([0.0, 50.0, 0.0]), TS, 0.05, throw=False
    )
    _assert_failed_after(traj, SolveStatus.domain_error, 0.05 + 1e-12)


def test_adaptive_solve_stays_inside_barrier_4_49():
    """With the adaptive default the infinite barrier is never crossed: the fast motion that a
    fixed step carries across it stays inside, and energy is conserved (no loads)."""
    model = make_model(alpha=0.3, M=0.0, b=0.0, amp=0.0)
    ts = jnp.linspace(0.0, 0.5, N)
    traj = simulate(model, jnp.array([0.1, 0.0, 0.0]), jnp.array([0.0, 50.0, 0.0]), ts, **TIGHT)
    margins = jax.vmap(model.domain_margin)(traj.theta)
    assert np.all(np.asarray(margins) > 0)
    theta_perp = np.linalg.norm(np.asarray(traj.theta)[:, :2], axis=1)
    assert theta_perp.max() > 0.25  # it does run into the barrier
    E = np.asarray(traj.energy)
    np.testing.assert_allclose(E, E[0], rtol=1e-8)


# ---------------------------------------------------------------------------------------------
# Arguments.
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "ts, match",
    [
        (jnp.array([0.0, 2.0, 1.0]), "strictly increasing"),
        (jnp.array([0.0, 1.0, 1.0]), "strictly increasing"),
        (jnp.zeros((2, 3)), "1-D"),
        (jnp.zeros((0,)), "non-empty"),
        (jnp.array([0.0, jnp.nan]), "finite"),
    ],
    ids=["unsorted", "repeated", "2d", "empty", "nan"],
)
def test_bad_times_are_refused(ts, match):
    with pytest.raises(ValueError, match=match):
        simulate(make_model(), THETA0, OMEGA0, ts)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="form"):
        simulate(make_model(), THETA0, OMEGA0, TS, form="middle")
    with pytest.raises(TypeError, match="RigidBodyOscillator"):
        simulate(make_model().foundation, THETA0, OMEGA0, TS)
    with pytest.raises(ValueError, match="theta0"):
        simulate(make_model(), jnp.zeros(2), OMEGA0, TS)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(t0=0.5), "t0 must not be after"),
        (dict(t0=np.nan), "t0 must be a finite"),
        (dict(t0=np.zeros(2)), "t0 must be a finite scalar"),
        (dict(dt0=-0.1), "dt0 must be"),
        (dict(dt0=0.0), "dt0 must be"),
        (dict(dt0=np.inf), "dt0 must be"),
    ],
)
def test_bad_start_time_and_first_step_are_refused_on_the_host(kwargs, match):
    """diffrax's own checks of t0, dt0 and the sample times are host callbacks, which the
    compiled solve leaves out (so that JAX's cache and the program store keep it): simulate
    refuses a bad concrete t0 or dt0 itself, with a ValueError naming it."""
    with pytest.raises(ValueError, match=match):
        simulate(make_model(), THETA0, OMEGA0, TS + 0.25, **kwargs)


def test_undefined_moment_direction_still_raises_in_the_compiled_solve():
    """The compiled solve leaves out diffrax's checks of the inputs, not rbo_jax's checks in the
    equations of motion: started where the direction of the semi-tangential moment (4.75) is
    undefined (a half turn about an axis ⊥ k, l1 = l2), throw=True raises its message, and
    throw=False stops with a status."""
    k = np.array([0.0, 0.0, 1.0])
    model = RigidBodyOscillator(
        np.eye(3), QuadraticFoundation(1.0, 2.0, k), [SemiTangentialMoment(1.0, k)]
    )
    half_turn = np.array([0.0, np.pi, 0.0])
    with pytest.raises(Exception, match="direction of the moment"):
        jax.block_until_ready(simulate(model, half_turn, np.zeros(3), TS).theta)
    traj = simulate(model, half_turn, np.zeros(3), TS, throw=False)
    assert traj.status_name != "successful"


def test_integer_and_float32_inputs_give_float64_results(right_trajectory):
    """Integer times/initial values and float32 initial values with the (float64) model are
    integrated in float64, with no precision warning."""
    ts_int = np.arange(N)  # 0, 1, ..., 20
    traj = simulate(make_model(), [0, 1, 0], [1, 0, 0], ts_int, **TIGHT)
    ref = simulate(
        make_model(), jnp.array([0.0, 1.0, 0.0]), jnp.array([1.0, 0, 0]), 1.0 * ts_int, **TIGHT
    )
    assert traj.theta.dtype == jnp.float64 and traj.ts.dtype == jnp.float64
    np.testing.assert_array_equal(traj.theta, ref.theta)
    theta32, Omega32 = THETA0.astype(jnp.float32), OMEGA0.astype(jnp.float32)
    traj32 = simulate(make_model(), theta32, Omega32, TS.astype(jnp.float32), **TIGHT)
    ref32 = simulate(
        make_model(),
        theta32.astype(float),
        Omega32.astype(float),
        TS.astype(jnp.float32).astype(float),
        **TIGHT,
    )
    assert traj32.theta.dtype == jnp.float64
    np.testing.assert_array_equal(traj32.theta, ref32.theta)


@pytest.mark.slow
def test_float32_with_tight_tolerance_warns_in_subprocess():
    """With JAX_ENABLE_X64=0 the computation is float32, and rtol = 1e-10 is below its
    resolution: simulate warns (RuntimeWarning) and still integrates."""
    code = textwrap.dedent(
        """
        import jax.numpy as jnp
        from rbo_jax.foundations import QuadraticFoundation
        from rbo_jax.model import RigidBodyOscillator
        from rbo_jax.simulate import simulate
        model = RigidBodyOscillator(jnp.eye(3), QuadraticFoundation(1.0, 2.0, [0.0, 0.0, 1.0]))
        traj = simulate(model, [0.3, 0.0, 0.1], [0.0, 0.5, 0.0], jnp.linspace(0.0, 1.0, 3),
                        rtol=1e-10, atol=1e-10)
        print("DTYPE", traj.theta.dtype, bool(jnp.all(jnp.isfinite(traj.theta))))
        """
    )
    env = {**os.environ, "JAX_ENABLE_X64": "0", "JAX_PLATFORMS": "cpu"}
    out = subprocess.run(
        [sys.executable, "-W", "always::RuntimeWarning", "-c", code],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert "DTYPE float32 True" in out.stdout
    assert "RuntimeWarning" in out.stderr
    assert "integrating in float32 with tolerance 1e-10" in out.stderr


@pytest.mark.slow
def test_progress_bar():
    """progress=True shows a tqdm bar (same result); without tqdm installed it is refused with
    a message naming tqdm. (tqdm is not a dependency of rbo_jax.)"""
    if importlib.util.find_spec("tqdm") is None:
        with pytest.raises(ValueError, match="tqdm"):
            simulate(make_model(), THETA0, OMEGA0, TS, progress=True, **TIGHT)
    else:
        traj = simulate(make_model(), THETA0, OMEGA0, TS, progress=True, **TIGHT)
        ref = simulate(make_model(), THETA0, OMEGA0, TS, **TIGHT)
        np.testing.assert_array_equal(traj.theta, ref.theta)


# ---------------------------------------------------------------------------------------------
# Darboux problems (4.15), (4.16).
# ---------------------------------------------------------------------------------------------

PATH_A = jnp.array([0.3, -0.2, 0.5])
PATH_B = jnp.array([0.8, 0.4, -0.3])
PATH_C = jnp.array([-0.3, 0.5, 0.6])
TS_DARBOUX = jnp.linspace(0.0, 1.5, N)


def _path(t):
    """The prescribed turn-vector θ(t) = a + bt + ct² and its rate."""
    return PATH_A + PATH_B * t + PATH_C * t**2, PATH_B + 2 * PATH_C * t


def _skew(a):
    z = jnp.zeros_like(a[0])
    return jnp.stack(
        [jnp.stack([z, -a[2], a[1]]), jnp.stack([a[2], z, -a[0]]), jnp.stack([-a[1], a[0], z])]
    )


def _left_angular_velocity(t):
    """ω = Z⁻¹(θ)·θ̇ (4.19) with Z⁻¹ = E + (1−cosθ)/θ² R + (θ−sinθ)/θ³ R² (4.20), by hand."""
    theta, theta_dot = _path(t)
    th = jnp.linalg.norm(theta)
    R = _skew(theta)
    Z_inv = jnp.eye(3) + (1 - jnp.cos(th)) / th**2 * R + (th - jnp.sin(th)) / th**3 * R @ R
    return Z_inv @ theta_dot


def _right_angular_velocity(t):
    """Ω = Pᵀ·ω with P = Q(θ(t)) by Rodrigues."""
    theta, _ = _path(t)
    th = jnp.linalg.norm(theta)
    R = _skew(theta)
    Q = jnp.eye(3) + jnp.sin(th) / th * R + (1 - jnp.cos(th)) / th**2 * R @ R
    return Q.T @ _left_angular_velocity(t)


def _exact_path():
    theta = np.asarray(jax.vmap(lambda t: _path(t)[0])(TS_DARBOUX))
    norms = np.linalg.norm(theta, axis=1)
    assert norms.min() > 0.3 and norms.max() < 2.5  # away from θ = 0 and from 2π
    return theta


def test_darboux_left_4_15_recovers_prescribed_path():
    sol = solve_darboux(_left_angular_velocity, PATH_A, TS_DARBOUX, frame="left", **TIGHT)
    assert bool(sol.status == SolveStatus.successful)
    np.testing.assert_allclose(sol.theta, _exact_path(), rtol=0, atol=1e-9)
    # a float32 θ0 with the float64 angular velocity is integrated in float64 (no warning)
    theta0_32 = PATH_A.astype(jnp.float32)
    sol32 = solve_darboux(_left_angular_velocity, theta0_32, TS_DARBOUX, **TIGHT)
    ref = solve_darboux(_left_angular_velocity, theta0_32.astype(float), TS_DARBOUX, **TIGHT)
    assert sol32.theta.dtype == jnp.float64
    np.testing.assert_array_equal(sol32.theta, ref.theta)


def test_darboux_right_4_16_recovers_prescribed_path():
    sol = solve_darboux(_right_angular_velocity, PATH_A, TS_DARBOUX, frame="right", **TIGHT)
    exact = _exact_path()
    np.testing.assert_allclose(sol.theta, exact, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        sol.turn_tensor, np.stack([np_Q(th) for th in exact]), rtol=0, atol=1e-9
    )


def test_darboux_with_sampled_angular_velocity():
    """Dense samples of ω interpolated by cubic Hermite splines: the path to ~1e-6."""
    t_s = jnp.linspace(0.0, 1.5, 201)
    w_s = jax.jit(jax.vmap(_left_angular_velocity))(t_s)
    sol = solve_darboux((t_s, w_s), PATH_A, TS_DARBOUX, frame="left", **TIGHT)
    error = np.max(np.abs(np.asarray(sol.theta) - _exact_path()))
    assert error < 1e-6
    assert np.max(np.abs(_exact_path() - np.asarray(PATH_A))) > 0.5  # the path does move


def test_darboux_bad_arguments():
    t_s = jnp.linspace(0.0, 1.0, 5)
    with pytest.raises(ValueError, match="frame"):
        solve_darboux(_left_angular_velocity, PATH_A, TS_DARBOUX, frame="body")
    with pytest.raises(ValueError, match="shape"):
        solve_darboux((t_s, jnp.zeros((5, 2))), PATH_A, TS_DARBOUX)
    with pytest.raises(ValueError, match="shape"):
        solve_darboux((t_s, jnp.zeros((4, 3))), PATH_A, TS_DARBOUX)
    with pytest.raises(ValueError, match="strictly increasing"):
        solve_darboux((t_s[::-1], jnp.zeros((5, 3))), PATH_A, TS_DARBOUX)
    with pytest.raises(TypeError, match="angular_velocity"):
        solve_darboux(jnp.zeros((5, 3)), PATH_A, TS_DARBOUX)


@pytest.mark.slow  # two reverse-mode programs through diffrax (~30 s of compilation)
def test_dense_samples_equal_saved_samples_and_their_gradient():
    """``dense=True`` samples ``ts`` from the solve's dense output after the solve: the same
    values as saving inside the loop (the same interpolant), the same reverse-mode gradient with
    respect to a foundation constant; a step budget too small gives max_steps_reached with inf
    after the time reached, as the saved samples do."""
    model = make_model()
    theta0, Omega0 = jnp.array([0.3, -0.2, 0.1]), jnp.array([0.2, 0.5, -0.4])
    ts = jnp.linspace(0.0, 3.0, 301)

    def loss(c, dense):
        m = eqx.tree_at(lambda m: m.foundation.c, model, c)
        traj = simulate(m, theta0, Omega0, ts, rtol=1e-9, atol=1e-9, dense=dense, throw=False)
        return jnp.sum(traj.theta**2) + jnp.sum(jnp.sin(traj.Omega))

    c = jnp.asarray(1.0)
    saved, g_saved = jax.value_and_grad(loss)(c, False)
    dense, g_dense = jax.value_and_grad(loss)(c, True)
    assert np.isfinite(float(g_saved)) and abs(float(g_saved)) > 1e-3
    np.testing.assert_allclose(float(dense), float(saved), rtol=1e-13)
    np.testing.assert_allclose(float(g_dense), float(g_saved), rtol=1e-10)
    short = simulate(model, theta0, Omega0, ts, max_steps=4, dense=True, throw=False)
    assert bool(short.status == SolveStatus.max_steps_reached)
    x = np.asarray(short.theta)
    assert np.all(np.isinf(x[-1])) and np.all(np.isfinite(x[0]))
    assert _all_inf_or_finite(x)
