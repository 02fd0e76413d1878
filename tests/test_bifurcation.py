"""Bifurcation analysis (issue 15): Hopf points of the Nikolai problem with friction (4.57),
(4.84) against the Routh-Hurwitz relation of its bending equation, derivatives by the implicit
function theorem against finite differences, the first Lyapunov coefficient against closed
forms, Floquet multipliers of regular precessions (4.110)-(4.118) against the rotating-frame
spectrum, and continuation (equilibria, limit cycles, the flutter boundary)."""

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import rbo_jax as rbo
from rbo_jax.bifurcation import first_lyapunov_coefficient

K_AXIS = (0.0, 0.0, 1.0)
A1, A3, C, D = 1.0, 0.6, 1.0, 2.0


def nikolai(M, b):
    return rbo.nikolai_model(M, C, D, A1=A1, A3=A3, k=K_AXIS, friction=b)


def nikolai_A3(M, b, A3):
    return rbo.nikolai_model(M, C, D, A1=A1, A3=A3, k=K_AXIS, friction=b)


def critical_moment(b):
    r"""The root of $M = 2b\sqrt{K(M)/A_1}$: Routh-Hurwitz for the damped bending equation
    $(A_1p^2 + bp + K)^2 + M^2/4 = 0$ (notebook 02), with $K$ of (4.69), by Brent's method on
    the closed form (no autodiff, no Newton of the package)."""

    def f(M):
        return M - 2 * b * np.sqrt(float(rbo.nikolai_bending_stiffness(C, D, M)) / A1)

    return scipy.optimize.brentq(f, 1e-9, 1.0, xtol=1e-15)


@pytest.fixture(scope="module")
def hopf():
    return rbo.hopf_point(nikolai, {"b": 0.1}, "M", 0.15)


# --------------------------------------------------------------------------------------------
# First Lyapunov coefficient on planar systems with known normal forms
# --------------------------------------------------------------------------------------------


def _planar_l1(f, g, omega):
    """l1 of x' = -omega y + f(x, y), y' = omega x + g(x, y) at 0, embedded in R^2."""

    def F(x):
        return jnp.stack([-omega * x[1] + f(x[0], x[1]), omega * x[0] + g(x[0], x[1])])

    q = jnp.asarray(np.array([1.0, -1.0j]) / np.sqrt(2.0))  # J q = i omega q, |q| = 1
    p = q  # J^T p = -i omega p and conj(p).q = 1
    return float(first_lyapunov_coefficient(F, jnp.zeros(2), omega, q, p))


def test_first_lyapunov_of_the_normal_form():
    """x' = -w y + s x r^2, y' = w x + s y r^2 is z' = iwz + s z|z|^2 (z = x + iy): with
    Kuznetsov's normalisation x = zq + conj(zq), |q| = 1, the coefficient is 2s/w."""
    for s, w in [(-0.3, 2.0), (0.7, 0.5)]:
        l1 = _planar_l1(
            lambda x, y, s=s: s * x * (x * x + y * y), lambda x, y, s=s: s * y * (x * x + y * y), w
        )
        assert l1 == pytest.approx(2 * s / w, rel=1e-12)


def test_first_lyapunov_against_guckenheimer_holmes():
    """With quadratic and cubic terms, l1 = 2a/w with a of Guckenheimer & Holmes (3.4.11):
    a = (f_xxx + f_xyy + g_xxy + g_yyy)/16
        + (f_xy (f_xx + f_yy) - g_xy (g_xx + g_yy) - f_xx g_xx + f_yy g_yy)/(16 w)."""
    w = 1.3
    a1, a2, a3, b1, b2, b3, c1, c2 = 0.4, -0.7, 0.25, 0.9, -0.3, 0.5, -0.6, 0.2

    def f(x, y):
        return a1 * x * x + a2 * x * y + a3 * y * y + c1 * x**3 + c2 * x * y * y

    def g(x, y):
        return b1 * x * x + b2 * x * y + b3 * y * y - 0.4 * x * x * y + 0.8 * y**3

    fxx, fxy, fyy, gxx, gxy, gyy = 2 * a1, a2, 2 * a3, 2 * b1, b2, 2 * b3
    fxxx, fxyy, gxxy, gyyy = 6 * c1, 2 * c2, -0.8, 4.8
    a = (fxxx + fxyy + gxxy + gyyy) / 16 + (
        fxy * (fxx + fyy) - gxy * (gxx + gyy) - fxx * gxx + fyy * gyy
    ) / (16 * w)
    assert _planar_l1(f, g, w) == pytest.approx(2 * a / w, rel=1e-12)


def test_mixed_derivatives_by_polarization_of_jets_along_one_direction():
    """jets_by_row's D F[t1], D^2 F[t1, t2], D^3 F[t1, t2, t3] (four jets along t1 ± t2 ± t3)
    against the closed forms of a cubic F(x) = A x + T2(x, x) + T3(x, x, x) (symmetric
    T2, T3): A t1 + 2 T2(x, t1) + 3 T3(x, x, t1), 2 T2(t1, t2) + 6 T3(x, t1, t2),
    6 T3(t1, t2, t3); with directions of lengths 1e-3 to 1e3, zero ones, and shifted points."""
    from rbo_jax.bifurcation._field import jets_by_row

    rng = np.random.default_rng(7)
    n = 4
    A = rng.normal(size=(n, n))
    T2 = rng.normal(size=(n, n, n))
    T2 = (T2 + T2.transpose(0, 2, 1)) / 2
    T3 = rng.normal(size=(n, n, n, n))
    T3 = sum(T3.transpose((0, *p)) for p in itertools.permutations((1, 2, 3))) / 6

    def F(x):
        return A @ x + jnp.einsum("ijk,j,k", T2, x, x) + jnp.einsum("ijkl,j,k,l", T3, x, x, x)

    y = rng.normal(size=n)
    rows = rng.normal(size=(5, 3, n)) * np.array([1.0, 1e-3, 1e3])[None, :, None]
    rows[3, 2] = 0.0  # a second-order row
    rows[4, 1:] = 0.0  # a first-order row
    shifts = rng.normal(size=(5, n)) * 0.1
    D1, D2, D3 = jets_by_row(F, jnp.asarray(y), jnp.asarray(rows), shifts=jnp.asarray(shifts))
    for i, (t1, t2, t3) in enumerate(rows):
        x = y + shifts[i]
        d1 = (
            A @ t1 + 2 * np.einsum("ijk,j,k", T2, x, t1) + 3 * np.einsum("ijkl,j,k,l", T3, x, x, t1)
        )
        d2 = 2 * np.einsum("ijk,j,k", T2, t1, t2) + 6 * np.einsum("ijkl,j,k,l", T3, x, t1, t2)
        d3 = 6 * np.einsum("ijkl,j,k,l", T3, t1, t2, t3)
        for got, want in ((D1[i], d1), (D2[i], d2), (D3[i], d3)):
            np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * (1 + np.abs(want).max()))


# --------------------------------------------------------------------------------------------
# Hopf points
# --------------------------------------------------------------------------------------------


def test_hopf_point_is_the_damped_nikolai_critical_load(hopf):
    """The Hopf point of the Nikolai problem with friction b: M_cr = 2b sqrt(K(M_cr)/A1) with
    frequency sqrt(K/A1) (the bending roots p = ±i omega of (A1 p^2 + bp + K)^2 + M^2/4 = 0,
    K of (4.69)), at the equilibrium (4.62)."""
    assert bool(hopf.ok), hopf.status
    M_cr = critical_moment(0.1)
    assert float(hopf.value) == pytest.approx(M_cr, rel=1e-11)
    K = float(rbo.nikolai_bending_stiffness(C, D, M_cr))
    assert float(hopf.frequency) == pytest.approx(np.sqrt(K / A1), rel=1e-10)
    np.testing.assert_allclose(hopf.theta, rbo.nikolai_equilibrium(M_cr, D, K_AXIS), atol=1e-12)
    # the eigenvalue pair crosses the axis with positive speed; J q = i omega q
    assert float(hopf.transversality) > 0
    J = np.asarray(rbo.linearize(nikolai(hopf.value, 0.1), hopf.theta))
    q, p = np.asarray(hopf.eigenvector), np.asarray(hopf.adjoint)
    np.testing.assert_allclose(J @ q, 1j * float(hopf.frequency) * q, atol=1e-10)
    np.testing.assert_allclose(J.T @ p, -1j * float(hopf.frequency) * p, atol=1e-10)
    assert abs(np.vdot(p, q) - 1) < 1e-10


def test_transversality_is_the_speed_of_the_critical_root(hopf):
    """d Re(p)/dM at the Hopf point equals the finite difference of the spectral abscissa of
    the equilibria (4.62) on both sides."""

    def abscissa(M):
        p = rbo.spectrum(nikolai(M, 0.1), rbo.nikolai_equilibrium(M, D, K_AXIS))
        return float(jnp.max(jnp.real(p)))

    h = 1e-5
    fd = (abscissa(hopf.value + h) - abscissa(hopf.value - h)) / (2 * h)
    assert float(hopf.transversality) == pytest.approx(fd, rel=1e-6)


@pytest.mark.slow  # cost; the quick tier checks l1 by the normal-form amplitude test
def test_first_lyapunov_coefficient_is_the_decay_at_the_hopf_point(hopf):
    """At M = M_H exactly the normal form is z' = i omega z + c1 z|z|^2 with Re c1 = omega l1,
    so along a simulated motion 1/|z|^2 grows by -2 omega l1 per unit time; |z| is measured
    as |<p, x - x_H>| (the adjoint eigenvector), averaged over the first and the last period
    of a fast_simulate run of t = 3000 from |z| = 0.05."""
    q, p = np.asarray(hopf.eigenvector), np.asarray(hopf.adjoint)
    x_h = np.concatenate([np.asarray(hopf.theta), np.zeros(3)])
    x0 = x_h + 2 * 0.05 * np.real(q)
    T, t_end = float(hopf.period), 3000.0
    ts = np.concatenate([np.linspace(0, T, 101)[:-1], t_end + np.linspace(0, T, 101)[:-1]])
    traj = rbo.fast_simulate(
        nikolai(hopf.value, 0.1),
        jnp.asarray(x0[:3]),
        jnp.asarray(x0[3:]),
        jnp.asarray(ts),
        rtol=1e-11,
        atol=1e-12,
    )
    X = np.concatenate([np.asarray(traj.theta), np.asarray(traj.Omega)], axis=1)
    z = np.abs((X - x_h) @ np.conj(p))
    r_first, r_last = np.mean(z[:100]), np.mean(z[100:])
    re_c1 = (1 / r_first**2 - 1 / r_last**2) / (2 * t_end)
    assert re_c1 == pytest.approx(float(hopf.frequency) * float(hopf.first_lyapunov), rel=1e-3)


def test_hopf_point_from_a_guess_at_the_crossing_itself():
    """A guess on the crossing (a neighbour's Hopf point in a flutter map, where M_cr does not
    depend on A3): the follower moment moves the spectrum only through its equilibrium, so the
    start must move the equilibrium with the parameter to tell the crossing pair from the
    damped ones; it once picked a damped pair and failed or landed on -M_cr."""
    M_cr = critical_moment(0.1)
    for A3 in (0.5, 1.0, 2.0):
        h = rbo.hopf_point(nikolai_A3, {"b": 0.1, "A3": A3}, "M", M_cr)
        assert bool(h.ok), (A3, h.status)
        assert float(h.value) == pytest.approx(M_cr, rel=1e-12)


def _hopf_value(b):
    return rbo.hopf_point(nikolai, {"b": b}, "M", 0.15).value


def _critical_moment_slope(b, e=1e-6):
    return (critical_moment(b + e) - critical_moment(b - e)) / (2 * e)


def test_hopf_value_gradient_matches_finite_differences(hopf):
    """jax.grad of the critical moment with respect to b (implicit function theorem at the
    converged Hopf system) against central differences of the closed form M = 2b sqrt(K(M)/A1)
    (Brent's method, no autodiff)."""
    g = float(jax.grad(_hopf_value)(0.1))
    assert g == pytest.approx(_critical_moment_slope(0.1), rel=1e-7)


@pytest.mark.slow  # cost: ~15 s, two Hopf programs and a forward-mode tangent compiled
def test_hopf_gradient_from_the_lyapunov_jet_equals_forward_mode():
    """The implicit derivative of a simple Hopf point takes the flutter system's Jacobian and its
    derivatives in the parameters from l1's third-order jet (D F[e_j], D^2 F[e_j, v], one
    program with the value); without l1 the tangent computes them by forward mode of the
    residual. The same gradients (in b and in A3, which moves the equilibrium and the pair),
    and the same value and frequency."""

    def value(params, lyapunov):
        h = rbo.hopf_point(nikolai_A3, params, "M", 0.15, lyapunov=lyapunov)
        return h.value + 0.1 * h.frequency

    params = {"b": 0.1, "A3": 0.6}
    with_jet = jax.grad(value)(params, True)
    forward = jax.grad(value)(params, False)
    for name in params:
        assert float(with_jet[name]) == pytest.approx(float(forward[name]), rel=1e-10), name
    assert float(value(params, True)) == float(value(params, False))


@pytest.mark.slow  # cost: ~12 s, the forward-mode and the jitted reverse-mode programs compiled
def test_hopf_value_gradient_in_forward_mode_and_under_jit():
    """jax.jacfwd and jax.jit(jax.grad) of the critical moment: the same derivative, which
    matches central differences of the closed form."""
    g = float(jax.jacfwd(_hopf_value)(0.1))
    assert g == pytest.approx(_critical_moment_slope(0.1), rel=1e-7)
    assert float(jax.jit(jax.grad(_hopf_value))(0.1)) == pytest.approx(g, rel=1e-12)


class TraceCounter:
    """Counts JAX's traces of functions named ``name`` inside a ``with`` (jax.monitoring)."""

    def __init__(self, *names):
        self.names, self.count = names, 0

    def _listen(self, event, duration, **kwargs):
        if (
            event == "/jax/core/compile/jaxpr_trace_duration"
            and kwargs.get("fun_name") in self.names
        ):
            self.count += 1

    def __enter__(self):
        jax.monitoring.register_event_duration_secs_listener(self._listen)
        return self

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self._listen)


def test_hopf_programs_are_traced_once_per_model_structure(hopf):
    """A new but identical model function (a notebook cell run again), other parameter values,
    other frequencies of the pair to follow and the gradient reuse the compiled Hopf program: no
    trace. A model function that computes
    something else is a new program."""

    def cell():  # the same source run again: a new function object with the same code
        return lambda M, b: nikolai(M, b)

    with TraceCounter("hopf_program") as first:
        rbo.hopf_point(cell(), {"b": 0.1}, "M", 0.15)
    with TraceCounter("hopf_program") as again:
        h = rbo.hopf_point(cell(), {"b": 0.12}, "M", 0.15)
    with TraceCounter("hopf_program") as gradient:
        jax.grad(lambda b: rbo.hopf_point(cell(), {"b": b}, "M", 0.15).value)(0.08)
    assert (first.count, again.count, gradient.count) == (1, 0, 0)
    assert float(h.value) == pytest.approx(critical_moment(0.12), rel=1e-11)
    # the pair to follow given by its frequency (continue_equilibria's Hopf points): one program
    # for every frequency (the two bending pairs share theirs at M = 0.15: either crossing, at
    # -M_cr or M_cr, is the answer)
    with TraceCounter("hopf_program") as by_frequency:
        near = [rbo.hopf_point(cell(), {"b": 0.1}, "M", 0.15, frequency=w) for w in (0.9, 1.1)]
    assert by_frequency.count == 1
    for point in near:
        assert abs(float(point.value)) == pytest.approx(critical_moment(0.1), rel=1e-11)
    with TraceCounter("hopf_program") as other:
        rbo.hopf_point(lambda M, b: nikolai(M, 2 * b), {"b": 0.05}, "M", 0.15)
    assert other.count == 1


def test_equilibrium_continuation_is_traced_once_per_model_structure():
    def run():  # a new but identical lambda each time
        return rbo.continue_equilibria(
            lambda M, b: nikolai(M, b), {"b": 0.1}, "M", 0.0, 0.1, ds=0.05, locate_hopf=False
        )

    run()
    with TraceCounter("_step") as again:
        branch = run()
    assert again.count == 0
    np.testing.assert_allclose(branch["theta"].values[:, 2], branch["M"].values / D, atol=1e-10)


def test_hopf_point_failures_are_statuses():
    """A guess where the equilibrium cannot be computed gives a status and NaN, not an error;
    arguments of the wrong kind raise at the call."""
    bad = rbo.hopf_point(nikolai, {"b": 0.1}, "M", jnp.nan)
    assert not bool(bad.ok)
    assert np.isnan(float(bad.value))
    with pytest.raises(TypeError, match="parameter must be the name"):
        rbo.hopf_point(nikolai, {"b": 0.1}, 3, 0.15)
    with pytest.raises(ValueError, match="guess must be a scalar"):
        rbo.hopf_point(nikolai, {"b": 0.1}, "M", [0.1, 0.2])


@pytest.mark.slow  # cost; notebook 05 (complete tier too) checks the same
def test_flutter_boundary_matches_the_stability_map_and_the_closed_form():
    """continue_hopf over b, vmapped over A3 (which does not enter the bending roots): every
    point satisfies M = 2b sqrt(K/A1), tends to the small-damping asymptote 2b sqrt(c/A1) with
    an error O(b^2), and lies between the grid points of a stability map where the spectral
    abscissa changes sign."""
    bs = np.array([0.1, 0.05, 0.02, 0.01])
    curve = rbo.continue_hopf(nikolai_A3, {"A3": np.array([0.6, 1.4])}, "M", 0.15, "b", bs)
    assert curve["M"].dims == ("A3", "b")
    assert np.all(curve["status"].values == 0)
    expected = np.array([critical_moment(b) for b in bs])
    np.testing.assert_allclose(curve["M"].values, np.stack([expected, expected]), rtol=1e-10)
    error = curve["M"].values[0] / (2 * bs * np.sqrt(C / A1)) - 1
    assert np.all(np.abs(error) < 0.2 * bs**2)
    assert np.all(np.abs(error[1:]) < np.abs(error[:-1]))
    Ms = np.linspace(0.0, 0.3, 61) + 1.3e-3  # no grid point on a critical value
    smap = rbo.stability_map(
        lambda M, b: nikolai(M, b),
        {"b": bs, "M": Ms},
        theta_eq_fn=lambda M, b: rbo.nikolai_equilibrium(M, D, K_AXIS),
    )
    for i, b in enumerate(bs):
        a = smap["spectral_abscissa"].sel(b=b).values
        j = int(np.argmax(a > 0))
        assert a[j - 1] < 0 < a[j]
        assert Ms[j - 1] < float(curve["M"].values[0, i]) < Ms[j]


# --------------------------------------------------------------------------------------------
# Floquet multipliers and periodic orbits
# --------------------------------------------------------------------------------------------


def test_floquet_multipliers_of_a_regular_precession():
    """(4.110)-(4.118): in the precessing frame the perturbations are exp(lambda t) with the
    exponents of precession_spectrum; the frame turns by 2 pi in T = 2 pi/psi_dot, so the
    multipliers are exp(lambda T). The double zero exponent (a Jordan block: energy and phase)
    makes the two multipliers 1 split by O(sqrt(tolerance))."""
    k = jnp.asarray(K_AXIS)
    model = rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(A1, A3, k), rbo.QuadraticFoundation(C, D, k)
    )
    pr = rbo.regular_precession(model, 0.5)
    T = 2 * np.pi / float(pr.rate)
    mu = np.asarray(rbo.floquet_multipliers(model, pr.theta0, pr.Omega0, T))
    lam = np.asarray(rbo.precession_spectrum(model, pr))
    expected = np.exp(lam * T)
    nontrivial = expected[np.abs(expected - 1) > 1e-3]
    assert nontrivial.size == 4
    for e in nontrivial:
        assert np.min(np.abs(mu - e)) < 1e-7
    near_one = mu[np.abs(mu - 1) < 1e-3]
    assert near_one.size == 2
    assert np.all(np.abs(near_one - 1) < 1e-4)
    assert np.all(np.abs(mu) < 1 + 1e-4)


@pytest.fixture(scope="module")
def cycles(hopf):
    return rbo.continue_limit_cycles(nikolai, {"b": 0.1}, "M", hopf, amplitude=0.02, max_points=9)


@pytest.mark.slow  # cost; notebook 05 (complete tier too) checks the same
def test_limit_cycles_follow_the_normal_form(hopf, cycles):
    """Near a supercritical Hopf point (l1 < 0) the cycles exist beyond it, are stable, and
    their amplitude follows the normal form: |z|^2 = -transversality (M - M_H)/(omega l1),
    theta - theta_H = 2 Re(z e^{i omega t} q_theta). The trivial multiplier is 1."""
    assert float(hopf.first_lyapunov) < 0 and bool(hopf.supercritical)
    M = cycles["M"].values[1:]
    assert np.all(M > float(hopf.value))
    assert np.all(cycles["stable"].values[1:])
    assert np.all(cycles["trivial_multiplier_error"].values[1:] < 1e-8)
    q = np.asarray(hopf.eigenvector)[:3]
    phases = np.exp(1j * np.linspace(0, 2 * np.pi, 721))
    shape = np.max(np.linalg.norm(np.real(phases[:, None] * q[None, :]), axis=1))
    z2 = (
        -float(hopf.transversality)
        * (M[0] - float(hopf.value))
        / (float(hopf.frequency) * float(hopf.first_lyapunov))
    )
    predicted = 2 * np.sqrt(z2) * shape
    assert cycles["amplitude"].values[1] == pytest.approx(predicted, rel=1e-3)
    # amplitude^2 grows linearly with the distance to the Hopf point at first
    slope = cycles["amplitude"].values[1:4] ** 2 / (M[:3] - float(hopf.value))
    assert np.ptp(slope) < 0.05 * slope[0]


@pytest.mark.slow  # cost; notebook 05 (complete tier too) checks the same
def test_simulation_beyond_the_hopf_point_settles_on_the_continued_cycle(hopf, cycles):
    """Long fast_simulate runs at the last parameter of the branch, started inside and outside
    the continued cycle (its initial state pulled towards and pushed away from the equilibrium
    (4.62)), both end on a cycle with the branch's amplitude: the cycle is stable, the flutter
    soft."""
    M = float(cycles["M"].values[-1])
    assert M - float(hopf.value) > 3e-3
    model = nikolai(M, 0.1)
    theta_eq = rbo.nikolai_equilibrium(M, D, K_AXIS)
    th0 = jnp.asarray(cycles["theta0"].values[-1])
    Om0 = jnp.asarray(cycles["Omega0"].values[-1])
    T = float(cycles["period"].values[-1])
    ts = jnp.concatenate([jnp.zeros(1), 6000.0 + jnp.linspace(0.0, T, 65)[:-1]])
    for scale in (0.5, 1.5):
        traj = rbo.fast_simulate(
            model, theta_eq + scale * (th0 - theta_eq), scale * Om0, ts, rtol=1e-9, atol=1e-9
        )
        th = np.asarray(traj.theta[1:])
        amplitude = np.max(np.linalg.norm(th - th.mean(axis=0), axis=1))
        assert amplitude == pytest.approx(float(cycles["amplitude"].values[-1]), rel=2e-3)


@pytest.mark.slow
def test_periodic_orbit_corrects_a_perturbed_limit_cycle(cycles):
    """Shooting from a perturbed state and period returns to the continued cycle; its
    multipliers match those of the branch. (Close to the Hopf point the radial multiplier
    tends to 1 and shooting becomes ill-conditioned: the last, farthest cycle is used.)"""
    j = cycles.sizes["point"] - 1
    model = nikolai(float(cycles["M"].values[j]), 0.1)
    th0 = cycles["theta0"].values[j]
    Om0 = cycles["Omega0"].values[j]
    T = float(cycles["period"].values[j])
    orbit = rbo.periodic_orbit(model, th0 * 1.005, Om0 * 0.995, T * 1.005)
    assert bool(orbit.ok), orbit.status
    assert float(orbit.period) == pytest.approx(T, rel=1e-8)
    assert abs(complex(orbit.trivial_multiplier) - 1) < 1e-8
    np.testing.assert_allclose(
        np.abs(orbit.multipliers), np.abs(cycles["multipliers"].values[j]), atol=1e-6
    )


# --------------------------------------------------------------------------------------------
# Continuation of equilibria
# --------------------------------------------------------------------------------------------


def test_equilibrium_branch_detects_the_hopf_point(hopf):
    branch = rbo.continue_equilibria(nikolai, {"b": 0.1}, "M", 0.0, 0.4, ds=0.05)
    assert list(branch["special_type"].values) == ["hopf"]
    assert float(branch["special_value"][0]) == pytest.approx(float(hopf.value), rel=1e-10)
    M = branch["M"].values
    np.testing.assert_array_equal(branch["stable"].values, M < float(hopf.value))
    np.testing.assert_allclose(branch["theta"].values[:, 2], M / D, atol=1e-10)  # (4.62)


def softening(M):
    """A dead moment M k (4.75) on the isotropic foundation U = F(theta^2), F(s) = s/2 - s^2/4,
    with friction (4.84): along k the balance is (1 - theta^2) theta = M (Z^T theta = theta),
    with a fold at theta = 1/sqrt(3), M = 2/(3 sqrt(3))."""
    k = jnp.asarray(K_AXIS)
    return rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(A1, A3, k),
        rbo.IsotropicFoundation(lambda s: 0.5 * s - 0.25 * s * s),
        [rbo.DeadMoment(M, k), rbo.Friction(0.05)],
    )


@pytest.mark.slow
def test_equilibrium_branch_passes_a_fold():
    branch = rbo.continue_equilibria(
        softening, {}, "M", 0.0, 0.5, theta_guess=(0, 0, 0.0), ds=0.05, max_points=40
    )
    types = list(branch["special_type"].values)
    assert "fold" in types
    fold = float(branch["special_value"].values[types.index("fold")])
    assert fold == pytest.approx(2 / (3 * np.sqrt(3)), abs=2e-3)
    # past the fold the branch turns back
    M = branch["M"].values
    i = int(np.argmax(M))
    assert M[-1] < M[i] and i < M.size - 1
    th = branch["theta"].values[:, 2]
    np.testing.assert_allclose((1 - th**2) * th, M, atol=1e-9)
    assert np.all(branch["stable"].values[:2])
    # past the fold the torsional root is real and positive (divergence): the fold is where
    # the torsional stiffness d((1 - theta^2) theta)/d theta = 1 - 3 theta^2 changes sign
    p = branch["eigenvalues"].values
    divergent = np.any((p.real > 1e-9) & (np.abs(p.imag) < 1e-9), axis=1)
    assert np.all(divergent[th > 0.6]) and not np.any(divergent[th < 0.55])


class CubicAntiDamping(eqx.Module):
    """The moment e|omega|^2 omega; a Module, so that e is a leaf (a closure over a traced e
    would be a compile-time constant of fast_simulate's program)."""

    e: jax.Array

    def __call__(self, t, theta, omega):
        return self.e * jnp.dot(omega, omega) * omega


def anti_damped(M, b, e):
    """The damped Nikolai problem with a cubic anti-damping moment e|omega|^2 omega (a
    CallableLoad): the linearization, hence the Hopf point, is that of e = 0."""
    model = nikolai(M, b)
    return rbo.RigidBodyOscillator(
        model.inertia, model.foundation, list(model.loads) + [rbo.CallableLoad(CubicAntiDamping(e))]
    )


@pytest.mark.slow
def test_subcritical_hopf_point_has_unstable_cycles_on_the_stable_side():
    """With cubic anti-damping the first Lyapunov coefficient changes sign (linearly in e: the
    cubic term enters l1 through C only); the cycles then exist below M_H, are unstable, and
    separate decaying from growing motions: a simulation started inside the continued cycle
    returns towards the equilibrium, one started just outside leaves it (hard flutter)."""
    e1, e2 = 0.05, 0.2
    h0 = rbo.hopf_point(anti_damped, {"b": 0.1, "e": 0.0}, "M", 0.15)
    h1 = rbo.hopf_point(anti_damped, {"b": 0.1, "e": e1}, "M", 0.15)
    h2 = rbo.hopf_point(anti_damped, {"b": 0.1, "e": e2}, "M", 0.15)
    assert float(h1.value) == pytest.approx(float(h0.value), rel=1e-13)
    l1 = [float(h.first_lyapunov) for h in (h0, h1, h2)]
    assert l1[0] < 0 < l1[1]
    assert (l1[2] - l1[0]) / e2 == pytest.approx((l1[1] - l1[0]) / e1, rel=1e-8)
    cycles = rbo.continue_limit_cycles(
        anti_damped, {"b": 0.1, "e": e1}, "M", h1, amplitude=0.02, max_points=6
    )
    M = cycles["M"].values[1:]
    assert np.all(M < float(h1.value))
    assert not np.any(cycles["stable"].values[1:])
    j = cycles.sizes["point"] - 1
    model = anti_damped(float(cycles["M"].values[j]), 0.1, e1)
    theta_eq = rbo.nikolai_equilibrium(float(cycles["M"].values[j]), D, K_AXIS)
    th0 = jnp.asarray(cycles["theta0"].values[j])
    Om0 = jnp.asarray(cycles["Omega0"].values[j])
    ts = jnp.linspace(0.0, 4000.0, 5)
    amplitude0 = float(jnp.linalg.norm(th0 - theta_eq))
    for scale, grows in ((0.5, False), (1.1, True)):
        traj = rbo.fast_simulate(
            model,
            theta_eq + scale * (th0 - theta_eq),
            scale * Om0,
            ts,
            rtol=1e-9,
            atol=1e-9,
            throw=False,
        )
        last = np.asarray(traj.theta[-1])
        finite = bool(np.all(np.isfinite(last)))
        distance = np.linalg.norm(last - np.asarray(theta_eq)) if finite else np.inf
        if grows:
            assert distance > 2 * amplitude0
        else:
            assert distance < 0.5 * scale * amplitude0
