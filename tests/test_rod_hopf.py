"""Rods through hopf_point, continue_hopf, stability_map and critical_load (issue 32 D).

Flutter of follower-loaded columns: Ziegler's double pendulum (undamped: the collision of two
frequencies at (7/2 - sqrt 2) c/l, Ziegler 1952; with hinge dampers: a Hopf point near
41/28 c/l), Beck's column (20.0509 EI/L^2 in the continuum, Beck 1952) and Pflüger's column
with a tip mass. References are closed forms, our own NumPy models of the rigid pendulum, and
the rods' own scan-and-bisect critical loads (lattice.critical_load), an independent search on
the spectral abscissa. Derivatives against central finite differences.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ziegler_pendulum as ziegler

import rbo_jax
from rbo_jax import lattice
from rbo_jax.bifurcation import _hopf, _hopf_start, _hopf_system

STIFF = 1e6  # shear and stretch stiffness: an inextensible, unshearable rod to ~1e-6


def column(P, n, *, tip_mass=0.0, damping=0.0):
    """Beck's column (Pflüger's with a tip mass): a cantilever, EI = rho A = L = 1, under a
    compressive follower force P at its tip; Kelvin-Voigt damping in bending and twist."""
    return lattice.rod(
        n,
        1.0,
        bending=1.0,
        torsion=1.0,
        shear=STIFF,
        stretch=STIFF,
        mass=1.0,
        rotary=1e-8,
        tip_mass=tip_mass,
        damping=damping,
        shear_damping=0.0,
        loads=lattice.TipForce(jnp.stack([0.0, 0.0, -P]), follower=True),
    )


# The rigid pendulum's own linear equations M q'' + B q' + (K - P N) q = 0 in the link angles
# (Ziegler 1952), independent of the rod's code.
M_Z = np.array([[3.0, 1.0], [1.0, 1.0]])
K_Z = np.array([[2.0, -1.0], [-1.0, 1.0]])
N_Z = np.array([[1.0, -1.0], [0.0, 0.0]])
B_Z = np.array([[2.0, -1.0], [-1.0, 1.0]])


def ziegler_collision_frequency(P):
    """The double root w = omega^2 of det(K - P N - w M) = 0 (a quadratic in w) at the
    collision load: w = -b / (2 a)."""
    a = np.linalg.det(M_Z)
    w1, w2 = 1.0, 2.0  # the quadratic from three values of det
    d = [np.linalg.det(K_Z - P * N_Z - w * M_Z) for w in (0.0, w1, w2)]
    b = (4 * d[1] - d[2] - 3 * d[0]) / 2  # d(w) = d0 + b w + a w^2
    assert abs(d[0] + b * w2 + a * w2**2 - d[2]) < 1e-12
    assert abs(b**2 - 4 * a * d[0]) < 1e-9  # a double root: P is the collision load
    return math.sqrt(-b / (2 * a))


def ziegler_damped_reference(b):
    """The critical load of the rigid pendulum with equal hinge dampers b: scan and bisection of
    the spectral abscissa of its 4 x 4 first-order matrix (NumPy)."""

    def unstable(P):
        A = np.block(
            [
                [np.zeros((2, 2)), np.eye(2)],
                [-np.linalg.solve(M_Z, K_Z - P * N_Z), -b * np.linalg.solve(M_Z, B_Z)],
            ]
        )
        return np.linalg.eigvals(A).real.max() > 1e-13

    loads = np.linspace(0.01, 5.0, 2000)
    k = next(k for k, P in enumerate(loads) if unstable(P))
    lo, hi = loads[k - 1], loads[k]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if unstable(mid) else (mid, hi)
    return hi


# ------------------------------------------------------------------------------------------
# Arguments and the protocol (no compilation of a solve).
# ------------------------------------------------------------------------------------------


def test_a_rod_and_a_rigid_body_share_one_flutter_solver():
    """The rods' names are the one solver's (issue 49: one mechanics)."""
    assert lattice.rod_hopf_point is rbo_jax.hopf_point
    assert lattice.rod_continue_hopf is rbo_jax.continue_hopf
    assert lattice.RodHopfPoint is rbo_jax.HopfPoint


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="kind"):
        rbo_jax.hopf_point(lambda P: ziegler(P), {}, "P", 2.0, kind="double")
    with pytest.raises(ValueError, match="theta_guess"):
        rbo_jax.hopf_point(lambda P: ziegler(P), {}, "P", 2.0, theta_guess=[0.1, 0, 0])
    with pytest.raises(ValueError, match="cluster"):
        rbo_jax.hopf_point(lambda P: ziegler(P), {}, "P", 2.0, cluster=0.0)
    with pytest.raises(ValueError, match="natural"):
        rbo_jax.continue_hopf(lambda P, b: ziegler(P, b), {}, "P", 1.4, "b", [0.1, 0.2],
                              method="secant")  # fmt: skip
    with pytest.raises(ValueError, match="one curve"):  # arclength: no batch axes
        rbo_jax.continue_hopf(lambda P, b, s: ziegler(P * s, b), {"s": [1.0, 2.0]}, "P", 1.4,
                              "b", [0.1, 0.2], method="arclength")  # fmt: skip
    with pytest.raises(ValueError, match="two distinct"):
        rbo_jax.continue_hopf(lambda P, b: ziegler(P, b), {}, "P", 1.4, "b", [0.1],
                              method="arclength")  # fmt: skip


def test_the_flutter_systems_row_count_is_its_equations_length():
    """``Layout.rows`` (the programs' carries shaped without tracing the residual) is the
    length of the real system :func:`_hopf_system.equations` builds, for a Hopf point and a
    collision (with its Jordan chain), a basis of one and of two columns."""
    rng = np.random.default_rng(4)
    m = 5
    n = 2 * m

    def cplx(*shape):
        return jnp.asarray(rng.standard_normal(shape) + 1j * rng.standard_normal(shape))

    for kind in ("hopf", "collision"):
        layout = _hopf_system.Layout(m, kind)
        for k in (1, 2):
            chain = cplx(n) if kind == "collision" else None
            products = jnp.asarray(rng.standard_normal((4 if chain is not None else 2, n)))
            r = _hopf_system.equations(layout, jnp.asarray(rng.standard_normal(n)), products,
                                       jnp.asarray(1.3), cplx(n), chain, cplx(n, k))  # fmt: skip
            assert r.shape == (layout.rows(k),), (kind, k)


def test_auto_kind_follows_the_damping():
    assert _hopf.resolve_kind("auto", ziegler(1.0)) == "collision"
    assert _hopf.resolve_kind("auto", ziegler(1.0, 0.1)) == "hopf"
    assert _hopf.resolve_kind("collision", ziegler(1.0, 0.1)) == "collision"
    friction = rbo_jax.nikolai_model(0.1, friction=0.1)  # a rigid body: the same rule
    assert _hopf.resolve_kind("auto", friction) == "hopf"
    assert _hopf.resolve_kind("auto", rbo_jax.nikolai_model(0.1)) == "collision"


def _spec(multiplicity):
    return _hopf_system.Spec(None, None, "P", (), (), "collision", 1e-10, 1e-10, 64, 1e-6, False,
                             multiplicity, 1)  # fmt: skip


def test_start_of_the_jordan_chain_solves_it_to_second_order():
    """From two eigenpairs (lam_j, v_j) of a matrix, the start of the collision's Jordan chain
    has (A - i w) u = v exactly and (A - i w) v = (lam1 - lam2)^2 / 4 u."""
    rng = np.random.default_rng(3)
    lams = np.array([1.0j, 1.1j, -1.0j, -1.1j, -0.5, -2.0])
    X = rng.normal(size=(6, 6)) + 1j * rng.normal(size=(6, 6))
    A = X @ np.diag(lams) @ np.linalg.inv(X)
    p, V = (jnp.asarray(x) for x in np.linalg.eig(A))
    start = _hopf_start._start_collision(_spec(2), p, V)
    w, v, u, C, found, count = (np.asarray(x) for x in start)
    assert found and count <= 2 and C.shape == (6, 2) and np.all(C[:, 1] == 0)  # simple ones
    # a followed eigenvalue of multiplicity 2 (both upper ones at 1j): more than one allows
    double = jnp.where(p.imag > 0.5, 1j, p)
    assert int(_hopf_start._start_hopf(_spec(1), double, V)[-1]) == 2
    np.testing.assert_allclose(w, 1.05, rtol=1e-12)
    np.testing.assert_allclose((A - 1j * w * np.eye(6)) @ u, v, atol=1e-10)
    np.testing.assert_allclose((A - 1j * w * np.eye(6)) @ v, (0.1j) ** 2 / 4 * u, atol=1e-10)
    np.testing.assert_allclose(C.conj().T @ v, [1.0, 0.0], atol=1e-12)  # the unused column: 0


# ------------------------------------------------------------------------------------------
# Ziegler's pendulum.
# ------------------------------------------------------------------------------------------


@pytest.mark.slow  # compiles the eigenproblem and the Newton step of a 24 x 24 system (~50 s)
def test_ziegler_pendulum_collision_is_the_closed_form():
    """Undamped: the Krein collision at (7/2 - sqrt 2) c/l (the pendulum of two bodies that
    translate approaches the rigid one to O(1e-6)), at the double root omega^2 of the rigid
    pendulum's frequency equation."""
    h = rbo_jax.hopf_point(lambda P: ziegler(P), {}, "P", 2.0)
    assert bool(h.ok) and h.kind == "collision"
    np.testing.assert_allclose(float(h.value), 3.5 - math.sqrt(2), rtol=2e-6)
    np.testing.assert_allclose(
        float(h.frequency), ziegler_collision_frequency(3.5 - math.sqrt(2)), rtol=2e-6
    )
    assert int(h.num_steps) <= 8


@pytest.mark.slow  # the damped pendulum's Hopf solve and a scan-and-bisect (two programs)
def test_ziegler_pendulum_with_hinge_dampers_is_a_hopf_point():
    """Hinge dampers b = 0.1 c s: a Hopf point at the rigid pendulum's critical load (NumPy, to
    1e-5), far below the undamped 2.0858 (Ziegler's paradox); lattice.critical_load's
    independent scan and bisection agrees."""
    h = rbo_jax.hopf_point(lambda P, b: ziegler(P, b), {"b": 0.1}, "P", 1.4)
    assert bool(h.ok) and h.kind == "hopf"
    np.testing.assert_allclose(float(h.value), ziegler_damped_reference(0.1), rtol=1e-5)
    Pc = lattice.critical_load(lambda P: ziegler(P, 0.1), 5.0, rtol=1e-14)
    np.testing.assert_allclose(float(h.value), float(Pc), rtol=1e-6)

    # the growth rate of the mode at the flutter frequency changes sign across the point (the
    # undamped twist and hinge modes keep real parts of rounding, ~1e-12)
    def growth(P):
        p = np.asarray(lattice.spectrum(ziegler(P, 0.1)))
        return p[np.argmin(np.abs(p - 1j * float(h.frequency)))].real

    assert growth(float(h.value) - 1e-3) < -1e-6 and growth(float(h.value) + 1e-3) > 1e-6


@pytest.mark.slow  # the vmapped solve and its vmapped sensitivities: two programs
def test_hopf_point_of_a_rod_under_vmap_with_its_gradient():
    """jax.vmap of hopf_point over the hinge damping b of Ziegler's pendulum (the solve is one
    traced program): each flutter load is the rigid pendulum's (NumPy scan and bisection,
    1e-5), and jax.vmap(jax.grad) of it, by the implicit function theorem, matches central
    differences of the vmapped solve (2e-6: the step 1e-2 is wide, as Newton leaves the load
    to ~1e-9) and of the NumPy reference (1e-3)."""
    bs = jnp.asarray([0.1, 0.2])

    def value(b):
        return rbo_jax.hopf_point(lambda P, b: ziegler(P, b), {"b": b}, "P", 1.4).value

    values = np.asarray(jax.vmap(value)(bs))
    reference = [ziegler_damped_reference(float(b)) for b in bs]
    np.testing.assert_allclose(values, reference, rtol=1e-5)
    grads = np.asarray(jax.vmap(jax.grad(value))(bs))
    e = 1e-2
    fd = (np.asarray(jax.vmap(value)(bs + e)) - np.asarray(jax.vmap(value)(bs - e))) / (2 * e)
    np.testing.assert_allclose(grads, fd, rtol=2e-6)
    ref = [(ziegler_damped_reference(b + 1e-3) - ziegler_damped_reference(b - 1e-3)) / 2e-3
           for b in (0.1, 0.2)]  # fmt: skip
    np.testing.assert_allclose(grads, ref, rtol=1e-3)


@pytest.mark.slow  # the continuation's scan, vmapped over a batch axis
def test_continue_hopf_of_a_rod_over_the_damping_with_a_batch_axis():
    """Natural continuation of the damped pendulum's flutter load over b, with a batch axis s
    that scales the follower force (the model at (P, s) is the pendulum at P s): every point
    is the NumPy reference over s, for both curves."""
    bs, ss = [0.1, 0.15, 0.2], [1.0, 1.1]
    ds = rbo_jax.continue_hopf(lambda P, b, s: ziegler(P * s, b), {"s": ss}, "P", 1.4, "b", bs)
    assert ds["P"].dims == ("s", "b") and ds.attrs["batch"] == "s" and ds.attrs["kind"] == "hopf"
    assert np.all(ds["status"].values == 0)
    reference = np.array([[ziegler_damped_reference(b) / s for b in bs] for s in ss])
    np.testing.assert_allclose(ds["P"].values, reference, rtol=1e-5)


# ------------------------------------------------------------------------------------------
# Beck's and Pflüger's columns.
# ------------------------------------------------------------------------------------------


@pytest.mark.slow  # a 240 x 240 eigenproblem and Newton on 962 unknowns, and a critical_load
def test_beck_column_flutter_is_a_collision():
    """n = 20: the collision of the two lowest frequencies agrees with the scan-and-bisect
    critical load (20.196, to 5e-6) and with Beck's 20.0509 EI/L^2 to 1 %, at a frequency
    between the two that merge (10.76 and 11.38 just below it: near 11.0 in the continuum)."""
    h = rbo_jax.hopf_point(lambda P: column(P, 20), {}, "P", 19.0)
    assert bool(h.ok) and h.kind == "collision"
    Pc = float(lattice.critical_load(lambda P: column(P, 20), 30.0))
    # The search stops where classify's test first sees an unstable root: past the collision
    # (Re p ~ sqrt(P - P_cr)) or, within the double root's conditioning (its computed eigenvalues
    # split by ~sqrt(eps |J|) beside a stiff shear scale), just before it: both ends are 5e-6 wide.
    assert abs(Pc - float(h.value)) < 5e-6 * Pc
    np.testing.assert_allclose(float(h.value), 20.0509, rtol=1e-2)
    assert 10.76 < float(h.frequency) < 11.38


def pfluger(P, mu):
    """Pflüger's column of 8 bodies: Beck's with a tip mass mu rho A L."""
    return column(P, 8, tip_mass=mu)


@pytest.mark.slow  # the implicit derivative, two more solves and two critical loads at n = 8
def test_gradient_of_pfluger_flutter_load_with_respect_to_the_tip_mass():
    """d P_cr / d mu of Pflüger's column (n = 8, mu = 0.2, where the load falls steeply with
    the tip mass) by jax.grad through the implicit function theorem, against central
    differences of hopf_point (Richardson-extrapolated, 2e-6) and of the scan-and-bisect
    critical load (1e-3)."""

    def value(mu):
        return rbo_jax.hopf_point(pfluger, {"mu": mu}, "P", 17.0).value

    g = float(jax.grad(value)(0.2))
    assert g < 0  # a tip mass lowers the flutter load (Pflüger)

    def central(e):
        return (float(value(0.2 + e)) - float(value(0.2 - e))) / (2 * e)

    e = 1e-3
    fd = (4 * central(e) - central(2 * e)) / 3  # Richardson: the curvature of P_cr(mu) is large
    np.testing.assert_allclose(g, fd, rtol=2e-6)
    crit = [float(lattice.critical_load(lambda P: pfluger(P, m), 30.0)) for m in (0.2 - e, 0.2 + e)]
    np.testing.assert_allclose(g, (crit[1] - crit[0]) / (2 * e), rtol=1e-3)


@pytest.mark.slow  # three flutter points of n = 8 and three critical loads
def test_continue_hopf_follows_pfluger_column_over_the_tip_mass():
    """Natural continuation in the tip mass: each point is the critical load of the
    scan-and-bisect search (5e-6, which stops just past it), falling from Beck's load as the
    tip mass grows."""
    mus = np.array([0.0, 0.1, 0.2])
    ds = rbo_jax.continue_hopf(pfluger, {}, "P", 20.0, "mu", mus)
    assert ds.attrs["kind"] == "collision" and np.all(ds["status"].values == 0)
    values = ds["P"].values
    for mu, value in zip(mus, values):
        Pc = float(lattice.critical_load(lambda P, mu=mu: pfluger(P, mu), 30.0))
        # the search stops just past the collision: 1e-8 is the collision solve's and the
        # nearly defective pair's rounding (its eigenvalues split like sqrt(eps) there)
        assert -1e-8 * Pc < Pc - value < 5e-6 * Pc
    assert np.all(np.diff(values) < 0)
    # Beck's 20.0509 at n = 8: the error is second order in 1/n, 0.145 at n = 20 (above)
    np.testing.assert_allclose(values[0], 20.0509, rtol=5e-2)


def ziegler_base_hinge(P, c1):
    """Ziegler's pendulum (masses 2m, m, links l, m = l = 1) with the base hinge's spring c1
    and the middle one's c = 1, a follower force P at the tip."""
    load = lattice.TipForce(jnp.stack([0.0, 0.0, -P]), follower=True)
    return lattice.pendulum([2.0, 1.0], [1.0, 1.0], jnp.stack([c1, 1.0]), loads=load)


@pytest.mark.slow  # the corrector's program (equilibria, a 99 x 97 QR) and ~100 points, ~20 s
def test_continue_hopf_of_a_rod_by_arclength_passes_the_turning_point():
    """The rigid pendulum's frequency equation with hinge springs c1 (base), c (middle), masses
    a m (middle joint), m (tip): a l^4 m^2 w^4 + (2P l - c1 - (a + 4)c) m l^2 w^2 + c1 c = 0
    (det(K - w^2 M), K = [[c1 + c - Pl, Pl - c], [-c, c]], M = m l^2 [[a + 1, 1], [1, 1]]).
    Its double root, the collision, for a = 2 and m = l = c = 1: 2P = c1 + 6 - 2 sqrt(2 c1),
    w^2 = sqrt(2 c1)/2. Solved for c1 as P varies, the boundary turns back in P at P = 2
    (c1 = 2), where natural continuation in P must stop: arclength from P = 2.5
    (c1 = 3 - 2 sqrt 2) downward passes it and comes back to P = 2.5 at c1 = 3 + 2 sqrt 2."""
    ds = rbo_jax.continue_hopf(ziegler_base_hinge, {}, "c1", 0.17, "P", [2.5, 1.9],
                               method="arclength", ds=0.05)  # fmt: skip
    assert ds.attrs["kind"] == "collision" and ds.attrs["method"] == "arclength"
    assert ds.attrs["stop_reason"] == "P left [1.9, 2.5]"
    P, c1 = ds["P"].values, ds["c1"].values
    assert np.all(ds["status"].values == 0) and len(P) > 10
    # the pendulum of two bodies that translate is the rigid one to O(1e-6)
    np.testing.assert_allclose(P, (c1 + 6 - 2 * np.sqrt(2 * c1)) / 2, rtol=1e-5)
    np.testing.assert_allclose(ds["frequency"].values, (2 * c1) ** 0.25 / math.sqrt(2), rtol=1e-5)
    assert c1[0] == pytest.approx(3 - 2 * math.sqrt(2), abs=2e-5) and c1[-1] > 3 + 2 * math.sqrt(2)
    assert list(ds["special_type"].values) == ["turning_point"]
    assert float(ds["special_value"][0]) == pytest.approx(2.0, abs=1e-4)
    assert float(ds["special_parameter"][0]) == pytest.approx(2.0, abs=5e-3)
    i = int(ds["special_index"][0])  # the point before the turn: P falls to it, rises after
    assert np.all(np.diff(P[: i + 1]) < 0) and np.all(np.diff(P[i + 1 :]) > 0)
    assert np.all(np.diff(c1) > 0)  # c1 is the curve's regular coordinate here


# ------------------------------------------------------------------------------------------
# Maps.
# ------------------------------------------------------------------------------------------


def beck_damped(P, eta):
    return column(P, 8, damping=eta)


@pytest.mark.slow  # a map of 6 spectra of 96 x 96 matrices with their equilibria
def test_stability_map_of_beck_column_over_load_and_damping():
    """Beck's column (n = 8) over P in {5, 15, 30} and the Kelvin-Voigt time eta in {0, 1e-3}:
    stable below its flutter load, flutter past it; with damping the load drops near 11
    (Bolotin's destabilisation, tests/test_rods.py), so P = 15 flutters only when damped.
    All 12 N eigenvalues per point, equal to lattice.spectrum's."""
    # the damped growth near the boundary is slow: rtol 1e-12, as lattice.critical_load needs
    axes = {"P": [5.0, 15.0, 30.0], "eta": [0.0, 1e-3]}
    ds = rbo_jax.stability_map(beck_damped, axes, rtol=1e-12)
    assert ds.sizes["mode"] == 12 * 8
    assert np.all(ds["equilibrium_status"].values == 0)
    names = ds["kind"].attrs["flag_meanings"].split()
    kind = np.array(names, dtype=object)[ds["kind"].values]
    stable = ("marginally_stable", "asymptotically_stable")
    expected_flutter = np.array([[False, False], [False, True], [True, True]])
    for i, j in np.ndindex(3, 2):
        assert (kind[i, j] == "flutter") == expected_flutter[i, j], (i, j, kind[i, j])
        assert kind[i, j] == "flutter" or kind[i, j] in stable
    p = np.asarray(lattice.spectrum(beck_damped(15.0, 1e-3)))
    scale = np.abs(p).max()
    np.testing.assert_allclose(
        ds["eigenvalues"].values[1, 1], np.sort_complex(p), atol=1e-9 * scale
    )


@pytest.mark.slow  # two scan-and-bisect searches in the sweep and two in lattice.critical_load
def test_critical_load_of_a_rod_matches_lattice_critical_load():
    """rbo_jax.critical_load over the tip mass equals lattice.critical_load at each value."""
    da = rbo_jax.critical_load(pfluger, {"mu": [0.0, 0.5]}, "P", 30.0, n_scan=32, n_bisect=40)
    for mu, value in zip([0.0, 0.5], da.values):
        Pc = float(lattice.critical_load(lambda P, mu=mu: pfluger(P, mu), 30.0))
        np.testing.assert_allclose(value, Pc, rtol=1e-9)
