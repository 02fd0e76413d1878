"""One mechanics (issue 49): every analysis written once, for the rigid body, lattices and rods.

An open chain of three different bodies, each on its own foundation (4.50) under a follower
moment (4.57) and friction (4.84), coupled by the isotropic energy ½κ|φ|² of their relative
turns: its equilibrium, spectrum and flutter point against an independent computation in NumPy
(the equations of motion of three rotation matrices, SciPy's rotations, the paper's Z (4.11));
the critical loads and flutter loads in rescaled units; and a map whose classification agrees
with the critical load at every point.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
from scipy.spatial.transform import Rotation

import rbo_jax as rbo
from rbo_jax import lattice

K = np.array([0.0, 0.0, 1.0])
# three different bodies: transverse and axial inertias, foundation stiffnesses, the follower
# moment per unit load mu, friction
A_T = np.array([1.0, 1.4, 0.8])
A_3 = np.array([0.6, 0.9, 0.5])
C = np.array([1.0, 1.3, 0.9])
D = np.array([2.0, 2.5, 1.8])
M = np.array([1.0, 0.7, 1.2])
B = np.array([0.05, 0.08, 0.04])
KAPPA = 0.7


def chain(mu, scale_time=1.0, kappa=KAPPA):
    """The open chain at the load mu; ``scale_time``: the same chain in a time unit that many
    times longer (inertias times its square, friction times it); ``kappa``: the coupling."""

    def body(a, a3, c, d, m, b):
        k = jnp.asarray(K)
        inertia = rbo.transversely_isotropic_inertia(a * scale_time**2, a3 * scale_time**2, k)
        loads = [rbo.FollowerMoment(mu * m, k), rbo.Friction(b * scale_time)]
        return rbo.RigidBodyOscillator(inertia, rbo.QuadraticFoundation(c, d, k), loads)

    bodies = jax.vmap(body)(*(jnp.asarray(x) for x in (A_T, A_3, C, D, M, B)))
    coupling = rbo.IsotropicFoundation(lambda s: 0.5 * kappa * s)
    return lattice.chain(3, bodies, coupling, periodic=False)


# --------------------------------------------------------------------------------------------
# The independent reference: NumPy and SciPy's rotations, nothing of rbo_jax.
# --------------------------------------------------------------------------------------------


def skew(x):
    return np.array([[0, -x[2], x[1]], [x[2], 0, -x[0]], [-x[1], x[0], 0]])


def Z(theta):
    """(4.11) with the small-angle series of ERRATA item 3."""
    t = np.linalg.norm(theta)
    R = skew(theta)
    a = 1 / 12 + t**2 / 720 if t < 1e-4 else (1 - t * np.sin(t) / (2 * (1 - np.cos(t)))) / t**2
    return np.eye(3) - 0.5 * R + a * R @ R


def world_moments(mu, rotations, omegas, kappa=KAPPA):
    """The world-frame moment on every body: foundation -Z^T dU/dθ (4.23), couplings (the
    moment of ½κ|φ|² on body j is -κ Q_i φ_ij: Z^T(φ)φ = φ), follower and friction."""
    thetas = [Rotation.from_matrix(R).as_rotvec() for R in rotations]
    moments = []
    for i, (theta, R, w) in enumerate(zip(thetas, rotations, omegas)):
        kt = K @ theta
        grad = C[i] * (theta - kt * K) + D[i] * kt * K
        moments.append(-Z(theta).T @ grad + mu * M[i] * R @ K - B[i] * w)
    for i in range(2):  # the open chain's two couplings
        phi = Rotation.from_matrix(rotations[i].T @ rotations[i + 1]).as_rotvec()
        torque = kappa * rotations[i] @ phi
        moments[i] = moments[i] + torque
        moments[i + 1] = moments[i + 1] - torque
    return moments


def inertias():
    return [np.diag([a, a, a3]) for a, a3 in zip(A_T, A_3)]


def rates(mu, base, y, kappa=KAPPA):
    """(δφ̇, Ω̇) of the bodies at left increments δφ of the rotations ``base`` (δφ̇ = ω to
    first order about rest) and body-frame angular velocities Ω (4.55)."""
    phis, Omegas = y[:9].reshape(3, 3), y[9:].reshape(3, 3)
    rotations = [Rotation.from_rotvec(p).as_matrix() @ R for p, R in zip(phis, base)]
    omegas = [R @ W for R, W in zip(rotations, Omegas)]
    moments = world_moments(mu, rotations, omegas, kappa)
    dOmega = [np.linalg.solve(A, R.T @ m - np.cross(W, A @ W))
              for A, R, m, W in zip(inertias(), rotations, moments, Omegas)]  # fmt: skip
    return np.concatenate([np.concatenate(omegas), np.concatenate(dOmega)])


def reference_equilibrium(mu, kappa=KAPPA):
    """Turns x_i about k: d_i x_i + κ Σ (x_i - x_j) = μ m_i (a linear system)."""
    L = np.diag(D) + kappa * np.array([[1, -1, 0], [-1, 2, -1], [0, -1, 1]])
    return np.linalg.solve(L, mu * M)


def reference_spectrum(mu, kappa=KAPPA):
    """Eigenvalues of the central-difference Jacobian of :func:`rates` at the equilibrium."""
    base = [Rotation.from_rotvec(x * K).as_matrix() for x in reference_equilibrium(mu, kappa)]
    h, J = 1e-6, np.zeros((18, 18))
    for j in range(18):
        e = np.zeros(18)
        e[j] = h
        J[:, j] = (rates(mu, base, e, kappa) - rates(mu, base, -e, kappa)) / (2 * h)
    return np.linalg.eigvals(J)


def reference_flutter_load(kappa=KAPPA):
    """The load where the spectral abscissa of :func:`reference_spectrum` crosses zero."""
    return scipy.optimize.brentq(
        lambda mu: reference_spectrum(mu, kappa).real.max(), 0.01, 1.5, xtol=1e-12
    )


# --------------------------------------------------------------------------------------------
# The tests
# --------------------------------------------------------------------------------------------


def test_chain_equilibrium_and_spectrum_against_numpy():
    """The open chain's equilibrium (θ_i = x_i k, the linear torsion balance) and its 18
    eigenvalues (4.63)–(4.69) against the reference; the chain's linear algebra is
    block-tridiagonal."""
    mu = 0.3
    model = chain(mu)
    assert model.structure() == "tridiagonal"
    sol = rbo.solve_equilibrium(model)
    assert bool(sol.ok)
    np.testing.assert_allclose(sol.state, np.outer(reference_equilibrium(mu), K), atol=1e-12)
    p = np.sort_complex(np.asarray(rbo.spectrum(model, sol.state)))
    ref = np.sort_complex(reference_spectrum(mu))
    np.testing.assert_allclose(p, ref, atol=1e-7)


@pytest.mark.slow  # cost: ~14 s, the chain's Hopf program compiled
def test_chain_flutter_point_against_numpy():
    """The chain's Hopf point in the load (:func:`rbo_jax.hopf_point`, the solver every model
    shares) is where the reference's spectral abscissa crosses zero."""
    h = rbo.hopf_point(chain, {}, "mu", 0.3)
    assert bool(h.ok) and h.kind == "hopf"
    mu_ref = reference_flutter_load()
    assert float(h.value) == pytest.approx(mu_ref, rel=1e-7)
    p = reference_spectrum(float(h.value))
    critical = p[np.argmax(p.real)]
    assert float(h.frequency) == pytest.approx(abs(critical.imag), rel=1e-6)


@pytest.mark.slow  # ~55 s alone: tracing the chain's equilibrium into the scan and bisection
def test_chain_critical_load_and_map_agree_with_the_flutter_point():
    """The batch engine's critical load of the chain (any model: its equilibrium, spectrum and
    one instability test) is its flutter point, and a stability map's classification agrees
    with the critical load at every point."""
    mu_h = float(rbo.hopf_point(chain, {}, "mu", 0.3).value)

    def scaled(mu, s):
        return chain(mu * s)

    crit = rbo.critical_load(scaled, {"s": [1.0, 2.0]}, "mu", 1.0, n_scan=8, n_bisect=40)
    # the test's threshold Re p > 1e-9 |p| lies rtol |p| / (d Re p / d mu) past the crossing
    np.testing.assert_allclose(crit.values, [mu_h, mu_h / 2], rtol=1e-6)
    assert np.all(crit.values >= [mu_h, mu_h / 2])
    grid = {"mu": np.linspace(0.05, 0.95, 7), "s": [1.0, 2.0]}
    ds = rbo.stability_map(scaled, grid)
    assert np.all(ds["equilibrium_status"].values == 0) and ds.sizes["mode"] == 18
    names = np.array(ds["kind"].attrs["flag_meanings"].split(), dtype=object)
    unstable = np.isin(names[ds["kind"].values], ["flutter", "divergence"])
    np.testing.assert_array_equal(unstable, grid["mu"][:, None] > crit.values[None, :])


def reference_crossing(frequency, lo, hi):
    """The load in ``(lo, hi)`` where the reference's root nearest ``i frequency`` crosses the
    imaginary axis."""

    def re(mu):
        p = reference_spectrum(mu)
        return p[np.argmin(np.abs(p - 1j * frequency))].real

    return scipy.optimize.brentq(re, lo, hi, xtol=1e-12)


@pytest.mark.slow  # a branch of 18-dimensional spectra and three flutter solves (~40 s)
def test_chain_branch_of_equilibria_finds_its_hopf_points():
    """:func:`rbo_jax.continue_equilibria` follows the chain's equilibria in the load (Keller's
    method with the chain's block-tridiagonal solver): every point is the reference's linear
    torsion balance; the branch is stable up to the first of three Hopf points (three pairs
    cross the axis below 0.4, the first two between the same two points of the branch), each
    located by :func:`rbo_jax.hopf_point` where the reference's root of its frequency crosses."""
    ds = rbo.continue_equilibria(chain, {}, "mu", 0.0, 0.4, ds=0.05, ds_max=0.1)
    assert ds.attrs["stop_reason"] == "reached stop"
    assert ds["theta"].dims == ("point", "body", "component")
    mu = ds["mu"].values
    expected = np.stack([np.outer(reference_equilibrium(m), K) for m in mu])
    np.testing.assert_allclose(ds["theta"].values, expected, atol=1e-10)
    assert list(ds["special_type"].values) == ["hopf"] * 3
    values, frequencies = ds["special_value"].values, ds["special_frequency"].values
    assert np.all(np.diff(values) > 0)
    assert values[0] == pytest.approx(reference_flutter_load(), rel=1e-7)
    for value, frequency in zip(values, frequencies):
        assert value == pytest.approx(reference_crossing(frequency, 0.05, 0.35), rel=1e-6)
    np.testing.assert_array_equal(ds["stable"].values, mu < values[0])


@pytest.mark.slow  # the flutter program in a scan over the coupling (~30 s)
def test_chain_flutter_boundary_in_the_coupling_is_its_critical_load():
    """:func:`rbo_jax.continue_hopf` of the chain's flutter load against the coupling κ
    (natural continuation around the one flutter program) meets the reference's flutter load
    at every κ (the reference's Jacobian by central differences: 1e-6)."""
    kappas = np.array([0.7, 0.5, 0.35])
    ds = rbo.continue_hopf(chain, {}, "mu", 0.3, "kappa", kappas)
    assert np.all(ds["status"].values == 0)
    assert ds["theta"].dims == ("kappa", "body", "component")
    expected = [reference_flutter_load(kappa) for kappa in kappas]
    np.testing.assert_allclose(ds["mu"].values, expected, rtol=1e-6)
    assert np.all(np.diff(ds["mu"].values) < 0)  # a weaker coupling flutters sooner


@pytest.mark.slow  # the flutter program with the first Lyapunov coefficient of 12 unknowns
def test_first_lyapunov_coefficient_of_a_chain_of_identical_bodies():
    """Two identical bodies with an isotropic coupling of their relative turn: the in-phase
    motion (no relative turn, no coupling moment) is an invariant manifold holding the centre
    manifold, so the chain flutters at the single body's load and frequency, and with the
    eigenvector normalised over both bodies (|q| = 1: each body's share 1/√2) the cubic
    normal form's coefficient is the body's over the number of bodies, ℓ₁/2."""
    k = jnp.asarray(K)

    def body(load):
        inertia = rbo.transversely_isotropic_inertia(1.0, 0.6, k)
        foundation = rbo.BarrierFoundation(c=1.0, d=2.0, alpha=2.0, beta=1.5, k=k)
        loads = [rbo.FollowerMoment(load, k), rbo.Friction(0.05)]
        return rbo.RigidBodyOscillator(inertia, foundation, loads)

    def pair(load):
        bodies = jax.vmap(lambda _: body(load))(jnp.arange(2))
        coupling = rbo.IsotropicFoundation(lambda s: 0.5 * KAPPA * s)
        return lattice.chain(2, bodies, coupling, periodic=False)

    one = rbo.hopf_point(body, {}, "load", 0.5, lyapunov=True)
    two = rbo.hopf_point(pair, {}, "load", 0.5, lyapunov=True)
    assert bool(one.ok) and bool(two.ok) and float(one.first_lyapunov) < 0
    assert float(two.value) == pytest.approx(float(one.value), rel=1e-10)
    assert float(two.frequency) == pytest.approx(float(one.frequency), rel=1e-10)
    assert 2 * float(two.first_lyapunov) == pytest.approx(float(one.first_lyapunov), rel=1e-8)


def _nikolai(M, s, m):
    """The damped Nikolai problem (4.57), (4.84) with its inertia m s² times larger (a time
    unit s times longer, masses m times larger at the same stiffness and loads): friction
    times s √m keeps the damping ratio b/(2√(cA)), and every eigenvalue scales by 1/(s √m)."""
    return rbo.nikolai_model(
        M, 1.0, 2.0, A1=m * s**2, A3=0.6 * m * s**2, friction=0.1 * s * jnp.sqrt(m)
    )


UNITS = [(1.0, 1.0), (1e3, 1.0), (1e-3, 1.0), (1.0, 1e6)]


def _rigid_flutter_loads():
    return [float(rbo.hopf_point(_nikolai, {"s": s, "m": m}, "M", 0.15).value) for s, m in UNITS]


def test_flutter_load_does_not_depend_on_the_units_of_a_rigid_body():
    """Time ×1e3 and ×1e-3, masses ×1e6: every eigenvalue scales by one factor, and the Hopf
    point stays. (The critical load's scan in the same units: the complete tier.)"""
    h = _rigid_flutter_loads()
    np.testing.assert_allclose(h, h[0], rtol=1e-9)
    assert np.isfinite(h[0]) and h[0] > 0.0


@pytest.mark.slow  # cost: ~15 s, the critical-load scan and bisection compiled for 4 unit systems
def test_critical_and_flutter_loads_do_not_depend_on_the_units_of_a_rigid_body():
    """Time ×1e3 and ×1e-3, masses ×1e6: every eigenvalue scales by one factor, and the
    critical follower moment (the scan of classify's test) and the Hopf point stay."""
    h = _rigid_flutter_loads()
    np.testing.assert_allclose(h, h[0], rtol=1e-9)
    s, m = (np.array(x) for x in zip(*UNITS))
    axes = {"i": np.arange(len(UNITS), dtype=float)}
    crit = rbo.critical_load(lambda M, i: _nikolai(M, jnp.asarray(s)[i.astype(int)],
                                                   jnp.asarray(m)[i.astype(int)]),
                             axes, "M", 0.5, n_scan=8, n_bisect=44)  # fmt: skip
    np.testing.assert_allclose(crit.values, crit.values[0], rtol=1e-12)  # bisection's bits
    np.testing.assert_allclose(crit.values, h[0], rtol=1e-6)


def _beck(P, s, m, eta=1e-3):
    """Beck's column (a cantilever, EI = ρA = L = 1, a follower force P at its tip), lightly
    damped in bending and twist (Kelvin–Voigt time eta), its masses and rotary inertias m s²
    times larger and eta s √m: every eigenvalue scales by 1/(s √m)."""
    scale = m * s**2
    return lattice.rod(
        8, 1.0, bending=1.0, torsion=1.0, shear=1e4, stretch=1e4, mass=scale,
        rotary=1e-4 * scale, damping=eta * s * jnp.sqrt(m), shear_damping=0.0,
        loads=lattice.TipForce(jnp.stack([0.0, 0.0, -P]), follower=True),
    )  # fmt: skip


@pytest.mark.slow  # a rod's flutter program and a batch of four critical-load searches (~60 s)
def test_critical_and_flutter_loads_do_not_depend_on_the_units_of_a_rod():
    """The lightly damped Beck column in four systems of units: the same flutter load
    (:func:`rbo_jax.hopf_point`), and its critical load (the scan of classify's test, each root
    against its own modulus, under shear modes ~100 times faster) is that flutter load: a test
    scaled by the largest |p| lost the slow flutter mode's onset under the stiff modes'
    threshold and landed several percent above it."""
    h = [float(rbo.hopf_point(_beck, {"s": s, "m": m}, "P", 15.0).value) for s, m in UNITS]
    assert np.isfinite(h[0]) and 10.0 < h[0] < 20.2
    np.testing.assert_allclose(h, h[0], rtol=1e-8)
    s, m = (np.array(x) for x in zip(*UNITS))

    def indexed(P, i):
        j = i.astype(int)
        return _beck(P, jnp.asarray(s)[j], jnp.asarray(m)[j])

    axes = {"i": np.arange(len(UNITS), dtype=float)}
    crit = rbo.critical_load(indexed, axes, "P", 30.0, n_scan=16, n_bisect=44)
    np.testing.assert_allclose(crit.values, h[0], rtol=1e-6)
