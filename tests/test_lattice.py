"""Lattices of rigid body oscillators (rbo_jax.lattice), tested against closed forms: the Bloch
branches at rest, the single body's spectrum (4.69) at q = 0, the discrete sine-Gordon kink,
the spinning twisted state of Kelvin's medium, the conservation of energy ((4.78) summed) and of
the total kinetic moment, and the bounded energy error of the symplectic splitting."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rbo_jax
from rbo_jax import lattice as L

K = np.array([0.0, 0.0, 1.0])
A1, A3, C, D, KB, KT = 1.0, 0.6, 1.0, 2.0, 0.7, 0.3
# one set of tolerances and sample counts where it can be shared: every distinct lattice
# structure, sample count or setting is a program compiled of its own
TOL = dict(rtol=1e-11, atol=1e-12)
TS = np.linspace(0.0, 5.0, 11)


def body(c=C, d=D, A3=A3, loads=()):
    return rbo_jax.RigidBodyOscillator(
        rbo_jax.transversely_isotropic_inertia(A1, A3, K),
        rbo_jax.QuadraticFoundation(c, d, K),
        loads,
    )


def coupling(kb=KB, kt=KT):
    return rbo_jax.QuadraticFoundation(kb, kt, K)


def relative(theta_i, theta_j):
    """The relative turn-vector by matrices: turn_vector(Q_i^T Q_j)."""
    return rbo_jax.turn_vector(rbo_jax.turn_tensor(theta_i).T @ rbo_jax.turn_tensor(theta_j))


# ---------------------------------------------------------------------------------------------
# The energy, against a loop over the edges with turn-tensor matrices.
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["chain", "grid_mixed", "edges"])
def test_coupling_energy_is_the_sum_of_W_of_the_relative_turns(kind):
    """U_coupling = sum over the coupled pairs (each once) of W(turn_vector(Q_i^T Q_j)); a free
    end drops the pair that wraps around; an edge list couples exactly its pairs."""
    rng = np.random.default_rng(1)
    W = coupling()
    if kind == "chain":
        lat, pairs = L.chain(5, body(), W), [(i, (i + 1) % 5) for i in range(5)]
    elif kind == "grid_mixed":
        lat = L.grid((3, 4), body(), W, periodic=(True, False))
        pairs = [(a * 4 + b, ((a + 1) % 3) * 4 + b) for a in range(3) for b in range(4)]
        pairs += [(a * 4 + b, a * 4 + b + 1) for a in range(3) for b in range(3)]
    else:
        pairs = [(0, 1), (1, 2), (0, 2), (3, 1)]
        lat = L.Lattice.from_edges(body(), np.array(pairs), W)
    theta = rng.normal(size=(lat.size, 3)) * 0.6
    expected = sum(float(W.energy(relative(theta[i], theta[j]))) for i, j in pairs)
    got = float(L.coupling_energy(lat, jnp.asarray(theta.T)))
    np.testing.assert_allclose(got, expected, rtol=1e-13)


def test_energy_gradient_against_finite_differences():
    """dU/dtheta of the total energy (foundations by their closed forms, couplings by reverse
    mode) against central differences of U."""
    from tests.helpers import finite_difference_jacobian

    rng = np.random.default_rng(2)
    lat = L.grid((3, 3), body(), coupling(), periodic=(False, True))
    theta = jnp.asarray(rng.normal(size=(3, 9)) * 0.5)

    @jax.jit
    def U(x):
        th = jnp.reshape(x, (3, 9))
        return jnp.atleast_1d(L.total_energy(lat, th, jnp.zeros_like(th)))

    fd = finite_difference_jacobian(U, jnp.ravel(theta))[0]
    got = jnp.ravel(jax.jit(L.energy_gradient)(lat, theta))
    np.testing.assert_allclose(got, fd, rtol=1e-8, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# Linear waves.
# ---------------------------------------------------------------------------------------------


def test_chain_branches_at_rest_are_the_closed_forms():
    """At rest with (4.50) and a quadratic coupling: omega^2 = (c + 4 kb sin^2(q/2))/A1 twice
    (bending) and (d + 4 kt sin^2(q/2))/A3 (torsion), no growth; group velocities are the
    derivatives of these."""
    lat = L.chain(8, body(), coupling())
    blocks = L.bloch_blocks(lat)
    qs = np.linspace(-np.pi, np.pi, 13)
    lam = np.asarray(jax.vmap(lambda q: L.dispersion(lat, q, blocks=blocks))(qs))
    wb = np.sqrt((C + 4 * KB * np.sin(qs / 2) ** 2) / A1)
    wt = np.sqrt((D + 4 * KT * np.sin(qs / 2) ** 2) / A3)
    expected = np.sort(np.stack([wb, wb, wt], 1), 1)
    np.testing.assert_allclose(np.sort(lam.imag[:, 3:], 1), expected, rtol=1e-13)
    np.testing.assert_allclose(np.sort(lam.imag[:, :3], 1), -expected[:, ::-1], rtol=1e-13)
    assert np.abs(lam.real).max() < 1e-12
    q = 0.7
    v = np.asarray(L.group_velocity(lat, q, blocks=blocks))
    vb = KB * np.sin(q) / (A1 * np.sqrt((C + 4 * KB * np.sin(q / 2) ** 2) / A1))
    vt = KT * np.sin(q) / (A3 * np.sqrt((D + 4 * KT * np.sin(q / 2) ** 2) / A3))
    np.testing.assert_allclose(np.sort(v[3:]), np.sort([vb, vb, vt]), rtol=1e-10)


def test_grid_branches_sum_the_directions():
    """On a 2-D grid: omega^2 = (c + 4 kb (sin^2(qx/2) + sin^2(qy/2)))/A1 and the torsion
    branch likewise."""
    lat = L.grid((4, 4), body(), coupling())
    blocks = L.bloch_blocks(lat)
    for q in ([0.3, -1.1], [np.pi, 0.5], [0.0, 0.0]):
        s = np.sum(np.sin(np.asarray(q) / 2) ** 2)
        wb, wt = np.sqrt((C + 4 * KB * s) / A1), np.sqrt((D + 4 * KT * s) / A3)
        lam = np.asarray(jax.jit(L.dispersion)(lat, jnp.asarray(q), blocks=blocks))
        np.testing.assert_allclose(np.sort(lam.imag[3:]), np.sort([wb, wb, wt]), rtol=1e-13)


def nikolai_body(M, b=None):
    return rbo_jax.nikolai_model(M, C, D, A1=A1, A3=A3, k=K, friction=b)


def test_q0_spectrum_is_the_single_body_spectrum_4_69():
    """At q = 0 the Bloch matrix of a chain of Nikolai bodies is one body's linearization: its
    eigenvalues are the roots of (4.69) at theta = (M/d) k (rbo_jax.nikolai_spectrum), whatever
    the coupling."""
    M = 0.4
    lat = L.chain(6, nikolai_body(M), coupling(2.0, 0.5))
    theta_eq = L.uniform_equilibrium(lat)
    np.testing.assert_allclose(theta_eq, [0.0, 0.0, M / D], atol=1e-14)
    lam = np.asarray(L.dispersion(lat, 0.0))
    expected = np.asarray(rbo_jax.nikolai_spectrum(A1, A3, C, D, M))
    key = lambda z: (round(z.imag, 8), round(z.real, 8))  # noqa: E731
    np.testing.assert_allclose(sorted(lam, key=key), sorted(expected, key=key), atol=1e-12)


@pytest.mark.slow  # cost: ~15 s of compilation
def test_friction_gives_flutter_bands_of_wavenumbers():
    """Nikolai bodies with friction b flutter above the single body's Hopf load (q = 0: the
    uniform motion, growth = the body's spectral abscissa); the couplings stiffen the shorter
    waves, so a band of long waves 0 <= q < q* flutters, widening with M. Through the batch
    engine: a (q, M) map with sweep."""
    b = 0.1
    qs = np.linspace(0.0, np.pi, 13)

    def growth(q, M):
        lat = L.chain(6, nikolai_body(M, b), coupling(0.8, 0.5))
        return {"growth": jnp.max(jnp.real(L.dispersion(lat, q)))}

    ds = rbo_jax.sweep(growth, {"q": qs, "M": np.array([0.0, 0.15, 0.25, 0.35])}, progress=False)
    g = ds["growth"].values  # (q, M)
    assert np.all(g[:, :2] < 0)  # no load, or below the Hopf load: every wave decays
    edges = []
    for j in (2, 3):
        unstable = g[:, j] > 0
        assert unstable[0] and not unstable[-1]
        edge = int(np.argmin(unstable))
        assert np.all(unstable[:edge]) and not np.any(unstable[edge:])  # one band from q = 0
        edges.append(edge)
    assert edges[1] > edges[0]  # wider with the load
    single = rbo_jax.spectral_abscissa(
        rbo_jax.spectrum(nikolai_body(0.25, b), jnp.array([0.0, 0.0, 0.25 / D]))
    )
    np.testing.assert_allclose(g[0, 2], single, rtol=1e-10)


# ---------------------------------------------------------------------------------------------
# Nonlinear waves and invariants.
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow  # cost: ~10 s, a long run of a large chain
def test_sine_gordon_kink_keeps_its_speed_width_and_energy():
    """Plane rotations about k with U = c(1 - cos|theta|) (CosineFoundation) and a quadratic
    coupling are the discrete sine-Gordon chain A3 phi_n'' = kappa (phi_{n+1} - 2 phi_n +
    phi_{n-1}) - c sin phi_n. For lambda = sqrt(kappa/c) = 5 the kink 4 arctan exp((n - vt) /
    (lambda sqrt(1 - v^2/s^2))), s = sqrt(kappa/A3), v = s/2, keeps its speed and contracted
    width, with energy 8 sqrt(c kappa)/sqrt(1 - v^2/s^2); the motion stays plane; the bodies
    ahead of it sit near |theta| = 2 pi."""
    c, kappa, A3k = 1.0, 25.0, 1.0
    lam, s = np.sqrt(kappa / c), np.sqrt(kappa / A3k)
    v = 0.5 * s
    gamma = 1.0 / np.sqrt(1.0 - (v / s) ** 2)
    n_sites, x0 = 120, 30.0
    site = rbo_jax.RigidBodyOscillator(
        rbo_jax.transversely_isotropic_inertia(1.0, A3k, K), rbo_jax.CosineFoundation(c)
    )
    lat = L.chain(n_sites, site, rbo_jax.QuadraticFoundation(kappa, kappa, K), periodic=False)
    xi = gamma * (np.arange(n_sites) - x0) / lam
    phi, dphi = 4 * np.arctan(np.exp(xi)), -2 / np.cosh(xi) * gamma * v / lam
    ts = np.linspace(0.0, 8.0, 5)  # the kink moves 20 sites
    traj = L.simulate(lat, phi[:, None] * K, dphi[:, None] * K, ts, rtol=1e-10, atol=1e-12)
    theta = np.asarray(traj.theta)
    assert traj.status_name == "successful" and np.abs(theta[..., :2]).max() == 0.0
    assert theta[0, -1, 2] > 2 * np.pi - 1e-4
    for k, t in enumerate(ts):
        p = theta[k, :, 2]
        i = int(np.argmax(p > np.pi))
        centre = i - 1 + (np.pi - p[i - 1]) / (p[i] - p[i - 1])
        assert abs(centre - (x0 + v * t)) < 0.1, (t, centre)
        slope = p[i] - p[i - 1]  # 2 gamma/lambda at the centre of the continuum kink
        np.testing.assert_allclose(slope, 2 * gamma / lam, rtol=0.02)
    energy = np.asarray(traj.energy)
    np.testing.assert_allclose(energy, 8 * np.sqrt(c * kappa) * gamma, rtol=2e-3)
    np.testing.assert_allclose(energy, energy[0], rtol=1e-10)


def test_sine_gordon_breather_oscillates_at_its_frequency_with_its_energy():
    """The breather of the same chain (lattice.breather, mu = 0.6: amplitude 4 arctan(tan mu) =
    4 mu at the centre, frequency sqrt(c/A3) cos mu, energy 16 sqrt(c kappa) sin mu) keeps
    its amplitude and frequency over a period; lattice.kink gives the kink of the test above."""
    c, kappa, A3k, mu = 1.0, 25.0, 1.0, 0.6
    n_sites, x0 = 120, 60.0
    site = rbo_jax.RigidBodyOscillator(
        rbo_jax.transversely_isotropic_inertia(1.0, A3k, K), rbo_jax.CosineFoundation(c)
    )
    lat = L.chain(n_sites, site, rbo_jax.QuadraticFoundation(kappa, kappa, K), periodic=False)
    th0, Om0 = L.breather(n_sites, c, kappa, A3k, x0=x0, mu=mu)
    period = 2 * np.pi / (np.sqrt(c / A3k) * np.cos(mu))
    ts = np.linspace(0.0, period, 5)  # 0, P/4, P/2, 3P/4, P (the kink test's program)
    traj = L.simulate(lat, th0, Om0, ts, rtol=1e-10, atol=1e-12)
    centre = np.asarray(traj.theta)[:, int(x0), 2]
    # measured 6e-3 (discreteness)
    np.testing.assert_allclose(centre, [0.0, 4 * mu, 0.0, -4 * mu, 0.0], atol=0.015)
    energy = np.asarray(traj.energy)
    np.testing.assert_allclose(energy, 16 * np.sqrt(c * kappa) * np.sin(mu), rtol=1e-4)  # 2.6e-6
    np.testing.assert_allclose(energy, energy[0], rtol=1e-10)
    lam = np.sqrt(kappa / c)
    xi = (np.arange(40) - 10.0) / lam
    np.testing.assert_allclose(
        L.kink(40, c, kappa, A3k, x0=10.0)[0][:, 2], 4 * np.arctan(np.exp(xi)), rtol=1e-14
    )


def kelvin_chain(n=12, kb=0.9, kt=0.4):
    site = rbo_jax.RigidBodyOscillator(
        rbo_jax.transversely_isotropic_inertia(A1, A3, K), rbo_jax.ZeroFoundation()
    )
    return L.chain(n, site, rbo_jax.QuadraticFoundation(kb, kt, K))


def test_kelvin_medium_spinning_twist_is_exact():
    """Kelvin's medium (no foundation): the uniform twist with uniform spin theta_n = (n q +
    Omega t) k, q = 2 pi m/N, is an exact solution; the bodies pass |theta| = 2 pi in plane
    motion and go on (no re-centring, no stop)."""
    n, Om = 12, 1.7
    lat = kelvin_chain(n)
    phi0 = np.angle(np.exp(1j * np.arange(n) * 2 * np.pi * 2 / n))  # m = 2, in (-pi, pi]
    ts = np.linspace(0.0, 10.0, 11)
    traj = L.simulate(lat, phi0[:, None] * K, np.tile(Om * K, (n, 1)), ts, rtol=1e-11, atol=1e-12)
    assert traj.status_name == "successful" and int(traj.num_recentred) == 0
    theta = np.asarray(traj.theta)
    np.testing.assert_allclose(theta[..., 2], phi0[None] + Om * ts[:, None], atol=1e-8)
    assert np.abs(theta[..., :2]).max() == 0.0 and theta[-1, :, 2].max() > 4 * np.pi
    np.testing.assert_allclose(traj.Omega, np.broadcast_to(Om * K, theta.shape), atol=1e-8)


def test_energy_and_kinetic_moment_are_conserved():
    """Energy ((4.78) summed) is conserved without friction and follower loads; in Kelvin's
    medium the coupling is invariant under a common rotation, so the total kinetic moment
    sum Q_i A_i Omega_i is conserved too (not with a foundation)."""
    rng = np.random.default_rng(5)
    ts = 4 * TS
    for n, lat in ((12, kelvin_chain(12)), (8, L.chain(8, body(), coupling()))):
        th0, Om0 = rng.normal(size=(n, 3)) * 0.4, rng.normal(size=(n, 3)) * 0.6
        traj = L.simulate(lat, th0, Om0, ts, **TOL)
        assert traj.ok
        e = np.asarray(traj.energy)
        np.testing.assert_allclose(e, e[0], rtol=1e-8)
        moment = np.asarray(traj.kinetic_moment)
        drift = np.abs(moment - moment[0]).max()
        if isinstance(lat.body.foundation, rbo_jax.ZeroFoundation):
            assert drift < 1e-8
        else:
            assert drift > 1e-3  # the foundations take it up


def test_jax_array_input_stays_on_its_device_and_gives_the_numpy_result():
    """A JAX array (a GPU's, or here the CPU's) is laid out where it lives, not copied through
    NumPy: the same trajectory as from NumPy input, bit for bit, and the same checks (a NaN is
    refused by name)."""
    rng = np.random.default_rng(5)
    n, lat = 8, L.chain(8, body(), coupling())
    th0, Om0 = rng.normal(size=(n, 3)) * 0.4, rng.normal(size=(n, 3)) * 0.6
    ts = 4 * TS
    ref = L.simulate(lat, th0, Om0, ts, **TOL)
    got = L.simulate(lat, jnp.asarray(th0), jnp.asarray(Om0), ts, **TOL)
    np.testing.assert_array_equal(np.asarray(got.theta), np.asarray(ref.theta))
    np.testing.assert_array_equal(np.asarray(got.Omega), np.asarray(ref.Omega))
    with pytest.raises(ValueError, match="theta0 must be finite"):
        L.simulate(lat, jnp.asarray(th0).at[3, 1].set(jnp.nan), Om0, ts, **TOL)


def test_off_plane_turns_are_recentred_through_the_singular_sphere():
    """A uniform spin about a principal axis transverse to theta (every body alike: the
    couplings are idle) is the free rotation Q(theta_0) Q(w t e_x); its turn-vector comes
    within |theta_0| = 2e-4 of |theta| = 2 pi off the plane. With re-centring the solve goes on
    and the turn-tensors stay exact; without, it stops with singular_point."""
    n, w = 12, 2.0
    lat = kelvin_chain(n)
    th0 = np.tile([0.0, 2e-4, 0.0], (n, 1))
    Om0 = np.tile([w, 0.0, 0.0], (n, 1))
    ts = np.linspace(0.0, 6.0, 11)
    traj = L.simulate(lat, th0, Om0, ts, rtol=1e-11, atol=1e-12)
    assert traj.ok and int(traj.num_recentred) > 0 and np.asarray(traj.turns)[-1].min() >= 1
    for k, t in enumerate(ts):
        exact = np.asarray(rbo_jax.turn_tensor(th0[0]) @ rbo_jax.turn_tensor(w * t * np.eye(3)[0]))
        for i in (0, n - 1):
            np.testing.assert_allclose(rbo_jax.turn_tensor(traj.theta[k, i]), exact, atol=1e-8)
    stopped = L.simulate(lat, th0, Om0, ts, rtol=1e-11, atol=1e-12, recenter=False, throw=False)
    assert stopped.status_name == "singular_point"
    assert not np.all(np.isfinite(np.asarray(stopped.theta)[-1]))


@pytest.mark.slow  # large size: 1e5 steps
def test_splitting_energy_error_stays_bounded_over_1e5_steps():
    """The Lie-group splitting is symplectic: over 1e5 steps (dt = 0.01, t = 1000) the energy
    error of a conservative chain oscillates within O(dt^2) and does not drift (its largest
    value in the last tenth is no larger than twice that in the first), and in Kelvin's medium
    the total kinetic moment is kept to rounding. The samples converge to DOP853's at second
    order (one program for every step size: dt is traced)."""
    rng = np.random.default_rng(7)
    lat = L.chain(6, body(), coupling())
    th0, Om0 = rng.normal(size=(6, 3)) * 0.3, rng.normal(size=(6, 3)) * 0.5
    ts = np.linspace(0.0, 1000.0, 101)
    traj = L.simulate(lat, th0, Om0, ts, method="splitting", dt=0.01)
    assert traj.ok and int(traj.num_steps) == 100_000
    e = np.asarray(traj.energy)
    err = np.abs(e - e[0]) / e[0]
    assert err.max() < 1e-4
    assert err[-10:].max() < 2 * err[:11].max()
    short = np.linspace(0.0, 2.0, 101)
    ref = np.asarray(L.simulate(lat, th0, Om0, short, rtol=1e-12, atol=1e-13).theta[-1])
    errs = [
        np.abs(
            np.asarray(L.simulate(lat, th0, Om0, short, method="splitting", dt=dt).theta[-1]) - ref
        ).max()
        for dt in (0.02, 0.01)
    ]
    np.testing.assert_allclose(errs[0] / errs[1], 4.0, rtol=0.1)  # second order
    traj = L.simulate(
        kelvin_chain(6), th0, Om0, np.linspace(0.0, 50.0, 101), method="splitting", dt=0.01
    )
    moment = np.asarray(traj.kinetic_moment)
    assert np.abs(moment - moment[0]).max() < 1e-11


@pytest.mark.slow  # cost: ~13 s of compilation
def test_per_site_bodies_and_edge_lists():
    """Per-site parameters (bodies built with jax.vmap, each its own foundation stiffness) give
    the same motion on a chain and on the edge list of the same chain, with energy conserved;
    Bloch waves need one body on every site and a chain or grid."""
    rng = np.random.default_rng(3)
    n = 5
    cs = np.linspace(0.8, 1.6, n)
    per_site = jax.vmap(lambda c: body(c=c))(jnp.asarray(cs))
    chain = L.chain(n, per_site, coupling())
    edges = np.array([[i, (i + 1) % n] for i in range(n)])
    listed = L.Lattice.from_edges(per_site, edges, coupling())
    assert chain.per_site and listed.size == n
    th0, Om0 = rng.normal(size=(n, 3)) * 0.3, rng.normal(size=(n, 3)) * 0.5
    ts = TS
    a = L.simulate(chain, th0, Om0, ts, **TOL)
    b = L.simulate(listed, th0, Om0, ts, **TOL)
    np.testing.assert_allclose(a.theta, b.theta, atol=1e-9)
    np.testing.assert_allclose(a.energy, a.energy[0], rtol=1e-8)  # each body's own c
    with pytest.raises(ValueError, match="same body on every site"):
        L.dispersion(chain, 0.3)
    with pytest.raises(ValueError, match="edge list"):
        L.dispersion(listed, 0.3)


@pytest.mark.slow  # cost: ~40 s of compilation
def test_ensembles_of_lattices_and_forward_derivatives():
    """vmap over lattices (the coupling stiffness) under jit, the same one by one, and
    forward-mode derivatives of the final state with respect to it (jvp of the batch) against
    central differences."""
    rng = np.random.default_rng(4)
    th0, Om0 = rng.normal(size=(4, 3)) * 0.3, rng.normal(size=(4, 3)) * 0.5
    ts = jnp.array([0.0, 2.0])

    def final(kb):
        lat = L.chain(4, body(), coupling(kb=kb))
        return L.simulate(lat, th0, Om0, ts, rtol=1e-11, atol=1e-12, throw=False).theta[-1]

    h = 1e-5
    kbs = jnp.array([0.7 - h, 0.7, 0.7 + h])
    batch, d = jax.jit(lambda k: jax.jvp(jax.vmap(final), (k,), (jnp.ones(3),)))(kbs)
    fd = (batch[2] - batch[0]) / (2 * h)
    np.testing.assert_allclose(d[1], fd, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(batch[1], final(0.7), atol=1e-12)  # the batch, one by one


def test_float32_option_and_diffrax_path():
    """dtype=float32 runs in single precision (a warning at tolerances below its resolution)
    and agrees with float64 to 1e-3 over t = 20 (benchmarks/README.md documents its accuracy);
    the diffrax path agrees with DOP853."""
    rng = np.random.default_rng(6)
    lat = L.chain(8, body(), coupling())
    th0, Om0 = rng.normal(size=(8, 3)) * 0.3, rng.normal(size=(8, 3)) * 0.5
    ts = 4 * TS
    ref = L.simulate(lat, th0, Om0, ts, **TOL)
    with pytest.warns(RuntimeWarning, match="float32"):  # rtol 1e-8 is below its resolution
        single = L.simulate(lat, th0, Om0, ts, dtype=jnp.float32)
    assert single.theta.dtype == jnp.float32 and single.ok
    assert np.abs(np.asarray(single.theta, np.float64) - np.asarray(ref.theta)).max() < 1e-3
    other = L.simulate(lat, th0, Om0, ts, method="diffrax", **TOL)
    np.testing.assert_allclose(other.theta, ref.theta, atol=1e-8)


def test_bad_input_is_refused_with_the_name_of_the_argument():
    lat = L.chain(4, body(), coupling())
    th, ts = np.zeros((4, 3)), np.linspace(0.0, 1.0, 3)
    with pytest.raises(ValueError, match="theta0 must have shape"):
        L.simulate(lat, np.zeros((3, 3)), th, ts)
    with pytest.raises(ValueError, match="Omega0 must be finite"):
        L.simulate(lat, th, np.full((4, 3), np.nan), ts)
    with pytest.raises(ValueError, match="method"):
        L.simulate(lat, th, th, ts, method="rk4")
    with pytest.raises(ValueError, match="needs a step dt"):
        L.simulate(lat, th, th, ts, method="splitting")
    with pytest.raises(ValueError, match="no loads"):
        L.simulate(
            L.chain(4, nikolai_body(0.2), coupling()), th, th, ts, method="splitting", dt=0.1
        )
    with pytest.raises(ValueError, match="strictly increasing"):
        L.simulate(lat, th, th, ts[::-1])
    with pytest.raises(ValueError, match="n must be >= 2"):
        L.chain(1, body(), coupling())
    with pytest.raises(TypeError, match="coupling must be"):
        L.chain(4, body(), 0.5)
    with pytest.raises(ValueError, match="body.inertia must have shape"):
        L.chain(4, jax.vmap(lambda c: body(c=c))(jnp.ones(3)), coupling())
    with pytest.raises(ValueError, match="edges must index"):
        L.Lattice.from_edges(jax.vmap(lambda c: body(c=c))(jnp.ones(3)), [[0, 3]], coupling())
    with pytest.raises(ValueError, match="to itself"):
        L.Lattice.from_edges(body(), [[1, 1]], coupling())
    with pytest.raises(ValueError, match="periodic needs one flag per axis"):
        L.grid((3, 3), body(), coupling(), periodic=(True,))
    with pytest.raises(ValueError, match="one wavenumber per axis"):
        L.dispersion(L.grid((3, 3), body(), coupling()), 0.3)


def test_coupling_moments_are_the_potential_moments_of_the_total_energy():
    """The couplings' body-frame moments, -Z(phi) dW/dphi on body j and Z^T(phi) dW/dphi on
    body i (the potential moment (4.46) of the relative turn, with Q^T Z^T = Z (4.13)), equal
    -Z(theta_i) dU_W/dtheta_i of the coupling energy by reverse-mode differentiation, on a
    chain, a grid with a free end and an edge list, with quadratic and barrier (4.49)
    couplings."""
    from rbo_jax.kinematics import Turn

    rng = np.random.default_rng(8)
    barrier = rbo_jax.BarrierFoundation(0.7, 0.3, 2.0, 1.5, K)
    for lat in (
        L.chain(5, body(), coupling()),
        L.grid((3, 4), body(), barrier, periodic=(True, False)),
        L.Lattice.from_edges(body(), np.array([[0, 1], [1, 2], [0, 2], [3, 1]]), coupling()),
    ):
        theta = jnp.asarray(rng.normal(size=(3, lat.size)) * 0.6)

        @jax.jit
        def both(lat, theta):
            G = jax.grad(L.coupling_energy, argnums=1)(lat, theta)
            by_gradient = jax.vmap(lambda t, g: -Turn(t).Z(g), in_axes=(1, 1), out_axes=1)(theta, G)
            return L.coupling_moments(lat, theta), by_gradient

        got, expected = both(lat, theta)
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12 * np.abs(got).max())


@pytest.mark.slow  # cost: ~30 s, two fits compiled
def test_fits_recover_the_stiffnesses_from_a_dispersion_curve_and_a_field():
    """Least squares by gradients: the foundation's and the coupling's stiffnesses from the
    closed-form branches (the torsion branch measured at every other wavenumber, NaN
    elsewhere), and the coupling's from a recorded space-time field of a simulated chain."""

    def lattice(c, kb, kt):
        return L.chain(8, body(c=c), coupling(kb, kt))

    qs = np.linspace(0.0, np.pi, 9)
    wb = np.sqrt((C + 4 * KB * np.sin(qs / 2) ** 2) / A1)
    wt = np.sqrt((D + 4 * KT * np.sin(qs / 2) ** 2) / A3)
    omega = np.stack([wb, np.where(np.arange(9) % 2 == 0, wt, np.nan)], 1)
    fit = L.fit_dispersion(
        lattice, {"c": 1.5, "kb": 0.3, "kt": 1.0}, qs, omega, branches=[0, 2], theta_eq=np.zeros(3)
    )  # at rest for every c, kb, kt
    assert fit.converged and float(fit.rms) < 1e-12
    np.testing.assert_allclose([fit.params[k] for k in ("c", "kb", "kt")], [C, KB, KT], rtol=1e-10)

    def branches(c, kb, kt):
        s2 = np.sin(qs / 2) ** 2
        return np.stack([np.sqrt((c + 4 * kb * s2) / A1), np.sqrt((D + 4 * kt * s2) / A3)], 1)

    # the standard errors, against sigma (J^T J)^-1/2 of the closed form's Jacobian J
    sigma, truth = 1e-3, np.array([C, KB, KT])
    noisy = branches(*truth) + sigma * np.random.default_rng(4).normal(size=(9, 2))
    fit = L.fit_dispersion(
        lattice, {"c": 1.5, "kb": 0.3, "kt": 1.0}, qs, noisy, branches=[0, 2], theta_eq=np.zeros(3)
    )
    h = 1e-6 * np.eye(3)
    J = np.stack([(branches(*(truth + e)) - branches(*(truth - e))).ravel() / 2e-6 for e in h], 1)
    expected = sigma * np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    stderr = np.array([fit.stderr[k] for k in ("c", "kb", "kt")])
    assert fit.converged and np.all((stderr > expected / 1.5) & (stderr < 1.5 * expected))
    assert np.all(np.abs(np.array([fit.params[k] for k in ("c", "kb", "kt")]) - truth) < 4 * stderr)

    rng = np.random.default_rng(9)
    th0, Om0 = rng.normal(size=(8, 3)) * 0.3, rng.normal(size=(8, 3)) * 0.5
    ts = 0.6 * TS
    field = np.asarray(L.simulate(lattice(C, KB, KT), th0, Om0, ts, **TOL).theta)
    fit = L.fit_field(
        lambda kb, kt: lattice(C, kb, kt),
        {"kb": 0.5, "kt": 0.5},
        ts,
        field,
        th0,
        Om0,
        rtol=1e-11,
        atol=1e-12,
    )
    assert fit.converged
    np.testing.assert_allclose([fit.params["kb"], fit.params["kt"]], [KB, KT], rtol=1e-8)
    with pytest.raises(ValueError, match="starting values must be finite numbers > 0"):
        L.fit_dispersion(lattice, {"c": -1.0, "kb": 0.3, "kt": 1.0}, qs, omega)
