"""The rods' explicit Lie-group Verlet, ``lattice.simulate(rod, ..., method="splitting")``.

Checks: second order in the step against diffrax's Dopri8 at tight tolerances (an independent
integrator of the same equations), with a full (non-diagonal, non-axisymmetric) inertia tensor,
a follower force and Kelvin-Voigt damping; the invariants of a free rod (kinetic moment (4.44)
to rounding, energy bounded without drift: a symplectic integrator); the cantilever's bending
frequencies from a run against the eigenvalues of ``lattice.spectrum``; Beck's column past its
flutter load growing at the rate of the spectral abscissa (Lyapunov's first method, as (4.69)
for one body) and staying bounded below it; the default step against Verlet's stability limit
omega * dt < 2 on the stiffest eigenvalue; the failures (a step past the limit, bad ``dt``,
``max_steps``).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rbo_jax import lattice
from rbo_jax.kinematics import turn_tensor
from rbo_jax.lattice import _rod_verlet


def free_rod():
    """A free rod whose bodies have a full inertia tensor: principal moments 1, 1.7, 2.3 times
    the rod's about axes turned by a fixed rotation (every free rotation of the splitting
    acts)."""
    rod = lattice.rod(
        4, 1.0, bending=1.0, torsion=0.7, shear=50.0, stretch=80.0, mass=1.0, rotary=2e-2,
        base="free",
    )  # fmt: skip
    R = np.asarray(turn_tensor(jnp.array([0.3, -0.5, 0.2])))
    A = np.stack([R @ np.diag(np.diag(a) * [1.0, 1.7, 2.3]) @ R.T for a in np.asarray(rod.inertia)])
    return eqx.tree_at(lambda r: r.inertia, rod, A)


def moving(rod, scale=1.0):
    """The straight rod with velocities and angular velocities about every axis (zero on the
    held base)."""
    s = rod.straight()
    z = np.asarray(s.r)[:, 2]
    v = np.stack([np.sin(np.pi * z), 0.3 * np.cos(2 * z), 0.1 * z], 1) * scale
    Om = np.stack([0.5 + z, -0.4 * z, 2.0 - z], 1) * scale
    if rod.base != "free":
        v[0], Om[0] = 0.0, 0.0
    return lattice.RodState(s.theta, s.r, jnp.asarray(Om), jnp.asarray(v))


def damped_follower():
    """A clamped rod with Kelvin-Voigt damping under a follower force (not conservative)."""
    return lattice.rod(
        4, 1.0, bending=1.0, torsion=0.7, shear=50.0, stretch=80.0, mass=1.0, rotary=2e-2,
        damping=0.02, loads=lattice.TipForce(jnp.array([0.5, 0.0, -3.0]), follower=True),
    )  # fmt: skip


def max_error(a, b):
    return max(
        float(jnp.max(jnp.abs(getattr(a, k) - getattr(b, k)))) for k in "theta r Omega v".split()
    )


def measured_orders(rod, dts):
    state0 = moving(rod)
    ts = jnp.linspace(0.0, 1.0, 5)
    ref = lattice.simulate(rod, state0, ts, rtol=1e-12, atol=1e-14, max_steps=10**6)
    errors = [
        max_error(lattice.simulate(rod, state0, ts, method="splitting", dt=dt).states, ref.states)
        for dt in dts
    ]
    return np.log2(np.array(errors[:-1]) / np.array(errors[1:])), errors


# ------------------------------------------------------------------------------------------
# Bad input (no compilation).
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dt", [0.0, -1e-3, np.inf, np.nan])
def test_bad_dt_is_refused_by_name(dt):
    rod = free_rod()
    with pytest.raises(ValueError, match="dt must be finite and > 0"):
        lattice.simulate(rod, rod.straight(), jnp.linspace(0.0, 1.0, 3), method="splitting", dt=dt)


def test_max_steps_is_checked_before_the_run():
    rod = free_rod()
    with pytest.raises(ValueError, match="needs 1000 steps .* max_steps = 999"):
        lattice.simulate(
            rod, rod.straight(), jnp.array([0.0, 1.0]), method="splitting", dt=1e-3, max_steps=999
        )
    # 10^15 steps: counted in float64 (no int32 overflow slipping past the check)
    with pytest.raises(ValueError, match="needs 1000000000000000 steps"):
        lattice.simulate(rod, rod.straight(), jnp.array([0.0, 1e3]), method="splitting", dt=1e-12)
    # a max_steps past int32: one interval of 3e9 steps would overflow the program's count
    with pytest.raises(ValueError, match="3000000000 steps .* between two samples"):
        lattice.simulate(
            rod,
            rod.straight(),
            jnp.array([0.0, 3.0]),
            method="splitting",
            dt=1e-9,
            max_steps=10**10,
        )


def test_unknown_method_names_splitting():
    rod = free_rod()
    with pytest.raises(ValueError, match="'splitting'"):
        lattice.simulate(rod, rod.straight(), jnp.array([0.0, 1.0]), method="verlett")


# ------------------------------------------------------------------------------------------
# Invariants of a free rod (one program).
# ------------------------------------------------------------------------------------------


def test_free_rod_keeps_kinetic_moment_and_bounded_energy():
    r"""A free rod without loads: the couplings are internal and objective, so every flow of the
    splitting keeps $\sum_i r_i\times m_i v_i + Q_i A_i\Omega_i$ (4.44) exactly (kick: internal
    forces; drift; free rotations about the body's own axes); measured to rounding over ~9,000
    steps. The energy error of a symplectic integrator oscillates at O(dt^2) without drift: its
    mean over the last fifth of the run is within 1.5x of its mean over the first fifth, and
    halving the step divides its largest value by 4 (3.5-4.5)."""
    rod = free_rod()
    state0 = moving(rod)
    ts = jnp.linspace(0.0, 100.0, 501)
    dt = float(_rod_verlet.stable_step(rod, state0))
    traj = lattice.simulate(rod, state0, ts, method="splitting", dt=dt)
    assert traj.ok and int(traj.num_steps) > 4000
    K = np.asarray(traj.kinetic_moment)
    assert np.max(np.abs(K - K[0])) < 1e-12 * np.max(np.abs(K[0]))
    E = np.asarray(traj.energy)
    dE = np.abs(E - E[0]) / E[0]
    assert dE.max() < 0.1  # 0.046 at 0.9 of the stability limit, the stiff modes excited
    first, last = dE[1:101].mean(), dE[-100:].mean()
    assert last < 1.5 * first and first < 1.5 * last, (first, last)
    # O(dt^2) below the limit (near it the stiff modes add higher orders: 4.9 from dt to dt/2)
    E2, E4 = (
        np.asarray(lattice.simulate(rod, state0, ts, method="splitting", dt=dt / k).energy)
        for k in (2, 4)
    )
    ratio = np.abs(E2 - E2[0]).max() / np.abs(E4 - E4[0]).max()
    assert 3.5 < ratio < 4.5, ratio


def test_step_past_the_stability_limit_is_reported_not_silent():
    """Three times the default step: Verlet is unstable (omega dt > 2 on the stiff modes), the
    state overflows; ``throw=True`` raises naming ``dt``, ``throw=False`` returns the status
    with the samples after the failure ``inf``."""
    rod = free_rod()
    state0 = moving(rod)
    dt = 3.0 * float(_rod_verlet.stable_step(rod, state0))
    ts = jnp.linspace(0.0, 100.0, 501)  # as above: the same program
    with pytest.raises(RuntimeError, match="non-finite .* smaller dt"):
        lattice.simulate(rod, state0, ts, method="splitting", dt=dt)
    traj = lattice.simulate(rod, state0, ts, method="splitting", dt=dt, throw=False)
    assert not traj.ok
    r = np.asarray(traj.states.r)
    assert np.all(np.isfinite(r[0])) and np.all(np.isinf(r[-1]))


# ------------------------------------------------------------------------------------------
# Order against Dopri8.
# ------------------------------------------------------------------------------------------


@pytest.mark.slow  # compiles Dopri8 at rtol 1e-12 and the splitting for the free rod
def test_second_order_free_rod_full_inertia():
    """Strang splitting of kick, drift and free rotations (Cayley maps): global error O(dt^2)
    against Dopri8 at rtol 1e-12; measured orders 1.968, 1.999."""
    orders, errors = measured_orders(free_rod(), [0.004, 0.002, 0.001])
    assert np.all((orders > 1.9) & (orders < 2.1)), (orders, errors)


@pytest.mark.slow  # compiles Dopri8 at rtol 1e-12 and the splitting for the damped rod
def test_second_order_with_follower_force_and_damping():
    """Kelvin-Voigt damping with the velocities predicted by the first kick and a follower force
    in the kick: still second order (measured 1.996, 2.011). At the default step (0.9 of the
    stability limit, the stiff modes excited by this start) the run agrees with Dopri8 to
    5.4e-3 of a motion of order 1."""
    rod = damped_follower()
    orders, errors = measured_orders(rod, [0.004, 0.002, 0.001])
    assert np.all((orders > 1.9) & (orders < 2.1)), (orders, errors)
    state0 = moving(rod)
    ts = jnp.linspace(0.0, 1.0, 5)
    ref = lattice.simulate(rod, state0, ts, rtol=1e-12, atol=1e-14, max_steps=10**6)
    default = lattice.simulate(rod, state0, ts, method="splitting")
    assert max_error(default.states, ref.states) < 1e-2


# ------------------------------------------------------------------------------------------
# Physics: frequencies, stability limit, flutter.
# ------------------------------------------------------------------------------------------


def matrix_pencil(y, dt, order):
    """Complex exponents and amplitudes of ``order`` exponentials fitted to samples ``y``
    (Hua & Sarkar 1990)."""
    n = len(y)
    p = n // 3
    H = np.array([y[i : i + p + 1] for i in range(n - p)])
    V = np.linalg.svd(H, full_matrices=False)[2][:order].conj().T
    lam = np.log(np.linalg.eigvals(np.linalg.pinv(V[:-1]) @ V[1:]).astype(complex)) / dt
    amp = np.linalg.lstsq(np.exp(np.outer(np.arange(n) * dt, lam)), y.astype(complex), rcond=None)
    return lam, amp[0]


@pytest.mark.slow  # compiles the spectrum and a 5,600-step run
def test_cantilever_frequencies_are_the_spectrum_with_verlets_phase_error():
    r"""A cantilever (n = 6) set swinging in its lowest bending modes: the two frequencies of
    the tip's motion (matrix pencil) are those of ``lattice.spectrum`` shifted by position
    Verlet's phase error, $\sin(\tilde\omega h/2) = \omega h/2$ on every linear mode
    ($\tilde\omega/\omega - 1 \approx (\omega h)^2/24$: 1.0e-6 and 3.8e-5 at the default step),
    to 1e-7 (12 exponentials fitted). The default step's bound $\bar\omega$ lies above the
    largest |p| (Gershgorin: stable) and within 30 % of it."""
    rod = lattice.rod(
        6, 1.0, bending=1.0, torsion=1.0, shear=1e3, stretch=1e3, mass=1.0, rotary=1e-3
    )  # fmt: skip
    p = np.asarray(lattice.spectrum(rod, rod.straight()))
    w = np.sort(p.imag[p.imag > 0])
    w12 = np.array([w[0], w[2]])  # every bending frequency twice (two planes)
    s = rod.straight()
    z = np.asarray(s.r)[:, 2]
    v = np.zeros((7, 3))
    v[1:, 0] = 1e-3 * (z[1:] ** 2 + 2.0 * z[1:] ** 3)
    state0 = lattice.RodState(s.theta, s.r, s.Omega, jnp.asarray(v))
    bound = float(_rod_verlet._omega_bound(rod, state0))
    assert np.abs(p).max() < bound < 1.3 * np.abs(p).max()
    dt_s, T = 0.01, 8.0
    traj = lattice.simulate(rod, state0, np.arange(801) * dt_s, method="splitting")
    h = T / int(traj.num_steps)
    lam, amp = matrix_pencil(np.asarray(traj.states.r[:, -1, 0]), dt_s, 12)
    keep = lam.imag > 0
    top = np.sort(lam[keep][np.argsort(-np.abs(amp[keep]))[:2]].imag)
    discrete = 2.0 / h * np.arcsin(w12 * h / 2.0)
    assert np.all(discrete / w12 - 1.0 > 5e-7)  # the shift is measurable
    np.testing.assert_allclose(top, discrete, rtol=1e-7)


def beck(P):
    """Beck's column (a cantilever under a compressive follower force at its tip), n = 6, a
    shear and stretch of 1e3 EI/L^2 (a stable step of ~1.5e-3)."""
    return lattice.rod(
        6, 1.0, bending=1.0, torsion=1.0, shear=1e3, stretch=1e3, mass=1.0, rotary=1e-3,
        loads=lattice.TipForce(jnp.stack([0.0, 0.0, -P]), follower=True),
    )  # fmt: skip


@pytest.mark.slow  # two equilibria, two spectra and two 2,000-step runs of one program
def test_beck_column_flutters_at_the_spectral_abscissa():
    r"""Below Beck's flutter load (P = 15 EI/L^2; 20.05 for the continuum) a small kick of the
    straight column stays small; above it (P = 22) it grows as $e^{\alpha t}$ with $\alpha$ the
    spectral abscissa of ``lattice.spectrum`` at that load (Lyapunov's first method): the rate
    fitted to the tip's envelope agrees to 3 %."""
    rates = {}
    for P in (15.0, 22.0):
        rod = beck(P)
        eq = lattice.equilibrium(rod)
        p = np.asarray(lattice.spectrum(rod, eq))
        kick = np.zeros((7, 3))
        kick[1:, 0] = 1e-9 * np.arange(1, 7) / 6
        state0 = lattice.RodState(eq.theta, eq.r, eq.Omega, jnp.asarray(kick))
        traj = lattice.simulate(rod, state0, jnp.linspace(0.0, 3.0, 601), method="splitting")
        x = np.abs(np.asarray(traj.states.r[:, -1, 0]))
        rates[P] = (p.real.max(), p[np.argmax(p.real)].imag, x)
    alpha, _, x = rates[15.0]
    assert alpha < 1e-9 and x.max() < 1e-8  # stable: bounded by the kick's scale
    alpha, w, x = rates[22.0]
    assert alpha > 0.1
    window = int(round(2 * np.pi / abs(w) / 0.005))  # one period of the flutter mode
    env = np.array([x[i : i + window].max() for i in range(0, len(x) - window, window)])
    t = np.arange(len(env)) * window * 0.005
    half = len(env) // 2  # after the stable modes' transient
    rate = np.polyfit(t[half:], np.log(env[half:]), 1)[0]
    assert abs(rate / alpha - 1.0) < 0.03, (rate, alpha)


# ------------------------------------------------------------------------------------------
# The step's force path.
# ------------------------------------------------------------------------------------------


@pytest.mark.slow  # compiles two force programs (a foundation, damping, three loads)
def test_tangent_forces_equal_the_autodiff_forces():
    r"""``forces_tangent`` (increments entering as $Q(E + \delta\times)$, the integrator's
    path) against ``forces_at`` (increments through $Q\cdot Q(\delta)$ and $Z(\delta)$) at a
    bent, stretched, moving state of a damped rod on a foundation under a follower force,
    gravity and a dead moment: equal to 1e-12 of the largest force and moment; and
    ``body_forces`` (``forces_tangent`` at the composed turns) against ``forces_at`` at nonzero
    increments, with their derivatives along the increments (1e-10)."""
    from rbo_jax import QuadraticFoundation
    from rbo_jax.models.rod import _field as _rod_field

    rod = lattice.rod(
        5, 1.0, bending=1.3, torsion=0.8, shear=40.0, stretch=90.0, mass=1.0, rotary=2e-2,
        damping=0.05, foundation=QuadraticFoundation(0.7, 0.4, jnp.array([0.0, 0.0, 1.0])),
        loads=(
            lattice.TipForce(jnp.array([0.4, 0.1, -2.0]), follower=True),
            lattice.Gravity(jnp.array([0.0, -9.81, 0.0])),
            lattice.TipMoment(jnp.array([0.0, 0.3, 0.2])),
        ),
    )  # fmt: skip
    rng = np.random.default_rng(3)
    s = rod.straight()
    theta = jnp.asarray(0.4 * rng.standard_normal((6, 3)))
    r = s.r + jnp.asarray(0.05 * rng.standard_normal((6, 3)))
    Om, v = (jnp.asarray(rng.standard_normal((6, 3))) for _ in range(2))
    Q = _rod_field.tensors(theta)
    z = jnp.zeros_like(r)
    for args in ((), (Om, v)):
        M0, F0 = eqx.filter_jit(_rod_field.forces_at)(rod, Q, r, z, z, *args)
        M1, F1 = eqx.filter_jit(_rod_field.forces_tangent)(rod, Q, r, *args)
        scale = max(float(jnp.max(jnp.abs(M0))), float(jnp.max(jnp.abs(F0))))
        assert scale > 1.0
        assert float(jnp.max(jnp.abs(M1 - M0))) < 1e-12 * scale
        assert float(jnp.max(jnp.abs(F1 - F0))) < 1e-12 * scale
    # at nonzero increments: body_forces (forces_tangent at Q(θ)Q(δ), r + d) against the
    # definition through Z(δ) (forces_at), also their derivatives along the increments
    delta = jnp.asarray(0.5 * rng.standard_normal((6, 3)))
    d = jnp.asarray(0.02 * rng.standard_normal((6, 3)))
    for args in ((), (Om, v)):
        M0, F0 = eqx.filter_jit(_rod_field.forces_at)(rod, Q, r, delta, d, *args)
        M1, F1 = eqx.filter_jit(_rod_field.body_forces)(rod, theta, r, delta, d, *args)
        scale = max(float(jnp.max(jnp.abs(M0))), float(jnp.max(jnp.abs(F0))))
        assert float(jnp.max(jnp.abs(M1 - M0))) < 1e-12 * scale
        assert float(jnp.max(jnp.abs(F1 - F0))) < 1e-12 * scale
    tangent = (jnp.asarray(rng.standard_normal((6, 3))), jnp.asarray(rng.standard_normal((6, 3))))
    _, dM0 = jax.jvp(lambda a, b: _rod_field.forces_at(rod, Q, r, a, b), (delta, d), tangent)
    _, dM1 = jax.jvp(lambda a, b: _rod_field.body_forces(rod, theta, r, a, b), (delta, d), tangent)
    for x, y in zip(dM1, dM0):
        assert float(jnp.max(jnp.abs(x - y))) < 1e-10 * float(jnp.max(jnp.abs(y)))
