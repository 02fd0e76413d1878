"""Rods: lattices of rigid body oscillators that also translate (issue 32).

Checks against the continuum (Timoshenko's cantilever, the elastica, Euler's and Beck's columns,
the cantilever's frequencies), Ziegler's pendulum in closed form, the invariants of the motion
(energy, kinetic moment (4.44) summed over the bodies), the strains' objectivity and symmetry,
the forces as the gradient of the energy, and the implicit derivatives against finite
differences. Each tolerance is stated at its n (bodies past the base): the discretisation is
second order in 1/n (tested).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ziegler_pendulum as _ziegler

import rbo_jax
from rbo_jax import lattice
from rbo_jax.models.rod import _field as _rod_field
from rbo_jax.solvers import _linear as _banded

STIFF = 1e6  # shear and stretch stiffness: an inextensible, unshearable rod to ~1e-6


def cantilever(n, loads=(), *, bending=1.0, shear=STIFF, stretch=STIFF, rotary=1e-8, **kw):
    return lattice.rod(
        n,
        1.0,
        bending=bending,
        torsion=1.0,
        shear=shear,
        stretch=stretch,
        mass=1.0,
        rotary=rotary,
        loads=loads,
        **kw,
    )


# ------------------------------------------------------------------------------------------
# Construction and bad input (no compilation).
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"bending": -1.0}, "bending"),
        ({"shear": 0.0}, "shear"),
        ({"stretch": np.nan}, "stretch"),
        ({"mass": -2.0}, "mass"),
        ({"rotary": 0.0}, "rotary"),
        ({"damping": -0.1}, "damping"),
        ({"bending": np.ones(3)}, "bending"),
        ({"base": "welded"}, "base"),
    ],
)
def test_bad_parameters_are_named(kwargs, match):
    args = dict(bending=1.0, torsion=1.0, shear=1.0, stretch=1.0, mass=1.0, rotary=1.0)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        lattice.rod(5, 1.0, **args)


def test_too_few_bodies_and_missing_bodies_are_refused():
    with pytest.raises(ValueError, match="n must be >= 2"):
        cantilever(1)
    with pytest.raises(ValueError, match="body=7 does not exist"):
        cantilever(4, lattice.TipForce([1.0, 0, 0], body=7))
    with pytest.raises(ValueError, match="clamped base"):
        cantilever(4, lattice.TipForce([1.0, 0, 0], body=0))
    with pytest.raises(ValueError, match="length"):
        lattice.rod(4, -1.0, bending=1, torsion=1, shear=1, stretch=1, mass=1, rotary=1)


def test_a_force_on_a_body_without_position_is_refused():
    k = [0.0, 0.0, 1.0]
    with pytest.raises(TypeError, match="bodies that translate"):
        rbo_jax.RigidBodyOscillator(
            rbo_jax.transversely_isotropic_inertia(1.0, 1.0, k),
            rbo_jax.QuadraticFoundation(1.0, 1.0, k),
            lattice.TipForce([0.0, 0.0, -1.0], follower=True),
        )


def test_lumped_masses_and_the_straight_state():
    """Every body carries half of each of its segments; the tip half of one; the nodes at
    z_i = i L/n."""
    rod = cantilever(4)
    np.testing.assert_allclose(rod.mass, [0.125, 0.25, 0.25, 0.25, 0.125])
    s = rod.straight()
    np.testing.assert_allclose(s.centreline[:, 2], np.linspace(0.0, 1.0, 5), atol=1e-15)
    assert s.centreline.shape == (5, 3)


def test_circular_rod_conventions():
    """A = pi r^2, I = pi r^4/4, J = 2I, shear = 27/28 G A (PyElastica 1.0's alpha_c)."""
    r, E, G, rho = 0.01, 1e6, 4e5, 1000.0
    rod = lattice.circular_rod(4, 1.0, radius=r, density=rho, youngs_modulus=E, shear_modulus=G)
    A, I = math.pi * r**2, math.pi * r**4 / 4  # noqa: E741 - the second moment of area
    h = 0.25
    np.testing.assert_allclose(rod.turn_stiffness[0], [E * I / h, E * I / h, G * 2 * I / h])
    np.testing.assert_allclose(rod.gap_stiffness[0], [27 / 28 * G * A / h] * 2 + [E * A / h])
    np.testing.assert_allclose(rod.mass[1], rho * A * h)
    np.testing.assert_allclose(np.diag(rod.inertia[1]), [rho * I * h] * 2 + [rho * 2 * I * h])


# ------------------------------------------------------------------------------------------
# Strains and forces.
# ------------------------------------------------------------------------------------------


def _random_state(rod, seed, scale=0.3):
    rng = np.random.default_rng(seed)
    s = rod.straight()
    return lattice.RodState(
        s.theta + scale * rng.standard_normal(s.theta.shape),
        s.r + 0.1 * scale * rng.standard_normal(s.r.shape),
        rng.standard_normal(s.theta.shape),
        rng.standard_normal(s.r.shape),
    )


def test_strains_are_objective():
    """A rigid motion Q -> R Q, r -> R r + c leaves the relative turn and the mid-frame gap
    unchanged (Crisfield & Jelenic's objectivity)."""
    rod = cantilever(5)
    s = _random_state(rod, 0)
    Q = _rod_field.tensors(s.theta)
    R = rbo_jax.turn_tensor(jnp.array([0.4, -1.1, 0.7]))
    c = jnp.array([0.3, -2.0, 5.0])
    strains = jax.jit(lambda Q, r: _rod_field.strains(rod, Q, r))
    phi, gap = strains(Q, s.r)
    phi2, gap2 = strains(jnp.einsum("ij,bjk->bik", R, Q), s.r @ R.T + c[None, :])
    np.testing.assert_allclose(phi2, phi, atol=1e-13)
    np.testing.assert_allclose(gap2, gap, atol=1e-13)


def test_strains_of_the_reversed_pair():
    """Seen from the other body, phi -> -phi and the gap's strain -> -(gap + g0) - g0: the
    mid-frame is the same from either end."""
    rod = cantilever(2)
    s = _random_state(rod, 1)
    Q = _rod_field.tensors(s.theta)
    strains = jax.jit(lambda Q, r: _rod_field.strains(rod, Q, r))
    phi, gap = strains(Q, s.r)
    phi_r, gap_r = strains(Q[::-1], s.r[::-1])
    g0 = np.asarray(rod.rest_gap)
    np.testing.assert_allclose(phi_r[::-1], -phi, atol=1e-13)
    np.testing.assert_allclose(gap_r[::-1] + g0, -(gap + g0), atol=1e-13)


def test_forces_are_the_gradient_of_the_energy():
    """Without damping and loads, M_i = -dU/d(delta_i) at 0 and F_i = -dU/dr_i."""
    rod = cantilever(4, shear=30.0, stretch=80.0, base="free")
    s = _random_state(rod, 2)
    z = jnp.zeros_like(s.theta)

    def U(delta, d):
        Q = _rod_field.composed(s.theta, delta)
        return _rod_field.coupling_energy(rod, Q, s.r + d)

    @jax.jit
    def both(z):
        return _rod_field.body_forces(rod, s.theta, s.r, z, z), jax.grad(U, argnums=(0, 1))(z, z)

    (M, F), (gd, gr) = both(z)
    np.testing.assert_allclose(M, -gd, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(F, -gr, rtol=1e-12, atol=1e-12)


def test_tridiagonal_jacobian_differences_and_solve_match_dense():
    """The block-tridiagonal Jacobian from 3m JVPs is the dense one; from 3m forward differences
    (the midpoint rule's chord matrix) it is within the differences' O(sqrt(eps)) error, each
    block divided by its own step (one block of unknowns ~1e3: steps 1e3 times larger; divided
    by a neighbour's, its columns would be 1e3 times too large)."""
    rng = np.random.default_rng(3)
    N, m = 7, 6
    W = rng.standard_normal((3, m, m))

    def fn(x):
        left = jnp.concatenate([jnp.zeros((1, m)), x[:-1]])
        right = jnp.concatenate([x[1:], jnp.zeros((1, m))])
        return jnp.sin(x) @ W[1].T + left**2 @ W[0].T + right @ W[2].T

    x = jnp.asarray(rng.standard_normal((N, m)) * np.where(np.arange(N) == 3, 1e3, 1.0)[:, None])
    exact, by_differences = jax.jit(
        lambda x: (_banded.tridiagonal_jacobian(fn, x), _banded.tridiagonal_differences(fn, x))
    )(x)
    J = jax.jacfwd(lambda y: fn(y.reshape(N, m)).ravel())(x.ravel())

    def dense(blocks):
        L, D, U = blocks
        out = np.zeros((N * m, N * m))
        for i in range(N):
            out[i * m : (i + 1) * m, i * m : (i + 1) * m] = D[i]
            if i:
                out[i * m : (i + 1) * m, (i - 1) * m : i * m] = L[i]
            if i < N - 1:
                out[i * m : (i + 1) * m, (i + 1) * m : (i + 2) * m] = U[i]
        return out

    np.testing.assert_allclose(dense(exact), J, atol=1e-13)
    # the error of a forward difference with the step sqrt(eps) s_j, s_j = max(|x_j|, 1):
    # rounding eps |f_i| / (sqrt(eps) s_j) and truncation sqrt(eps) s_j |f''| / 2, |f''| < 6
    s = np.maximum(np.abs(np.asarray(x)).ravel(), 1.0)[None, :]
    f = np.abs(np.asarray(fn(x))).ravel()[:, None]
    bound = 1e-6 * (1.0 + f / s + s)
    assert np.all(np.abs(dense(by_differences) - J) <= bound)
    L, D, U = exact
    b = rng.standard_normal((N, m))
    xs = jax.jit(_banded.tridiagonal_solve)(L, D, U, jnp.asarray(b))
    np.testing.assert_allclose(np.asarray(xs).ravel(), np.linalg.solve(J, b.ravel()), rtol=1e-10)


# ------------------------------------------------------------------------------------------
# Statics against the continuum.
# ------------------------------------------------------------------------------------------


def test_timoshenko_cantilever_small_tip_force():
    """Tip deflection F L/(kGA) + F L^3/(3EI) to 1e-3 at n = 16 (shear flexible rod)."""
    F, kGA = 1e-6, 50.0
    sol = lattice.solve_equilibrium(cantilever(16, lattice.TipForce([F, 0, 0]), shear=kGA))
    assert bool(sol.ok)
    exact = F / kGA + F / 3.0
    assert abs(float(sol.state.tip[0]) / exact - 1) < 1e-3


@pytest.mark.slow  # two solves at two sizes (two programs)
def test_timoshenko_convergence_is_second_order():
    F, kGA = 1e-6, 50.0
    exact = F / kGA + F / 3.0
    errors = [
        abs(
            float(lattice.equilibrium(cantilever(n, lattice.TipForce([F, 0, 0]), shear=kGA)).tip[0])
            / exact
            - 1
        )
        for n in (10, 20)
    ]
    order = math.log2(errors[0] / errors[1])
    assert 1.9 < order < 2.1, errors


@pytest.mark.slow  # four large deflections, 40 bodies, load steps
@pytest.mark.parametrize(
    ("alpha", "deflection", "angle"),
    [
        (1.0, 0.30172, 0.46135),
        (2.0, 0.49346, 0.78175),
        (5.0, 0.71379, 1.21537),
        (10.0, 0.81061, 1.43029),
    ],
)
def test_elastica_large_deflection(alpha, deflection, angle):
    """Inextensible cantilever, dead perpendicular tip force F L^2/EI = alpha: tip deflection
    and tip angle of the elastica to 2e-4 at n = 40."""
    rod = cantilever(40, lattice.TipForce(jnp.array([alpha, 0.0, 0.0])))
    sol = lattice.solve_equilibrium(rod, steps=5)
    assert bool(sol.ok)
    assert abs(float(sol.state.tip[0]) - deflection) < 2e-4
    tip_angle = float(jnp.linalg.norm(sol.state.theta[-1]))
    assert abs(tip_angle - angle) < 2e-4 * 10


@pytest.mark.slow  # 20 load steps to a full circle
def test_tip_moment_rolls_a_full_circle():
    """A tip moment 2 pi EI/L bends the rod into a circle: every segment turns by 2 pi/n and
    keeps its length, so the nodes make a regular n-gon of side L/n closing on the base (the
    tip back at the origin with the base's turn: its principal turn-vector is zero), whose
    circumradius tends to L/(2 pi)."""
    n = 24
    rod = cantilever(n, lattice.TipMoment(jnp.array([0.0, 2 * math.pi, 0.0])))
    s = lattice.equilibrium(rod, steps=20)
    assert float(jnp.linalg.norm(s.tip)) < 1e-9
    assert float(jnp.linalg.norm(s.theta[-1])) < 1e-9
    nodes = np.asarray(s.centreline[:-1])
    radii = np.linalg.norm(nodes - nodes.mean(axis=0, keepdims=True), axis=1)
    np.testing.assert_allclose(radii, (1 / n) / (2 * math.sin(math.pi / n)), rtol=1e-9)
    assert abs(radii[0] * 2 * math.pi - 1) < 2 / n**2


@pytest.mark.slow  # implicit gradients of parameters the balance does not see, and of the base
def test_gradients_of_unseen_parameters_and_of_the_base():
    """The mass does not enter a static balance without gravity (gradient zero, no error); a
    clamped base moved by c moves the whole rod by c."""

    def tip(mass, z0):
        rod = lattice.rod(
            4,
            1.0,
            bending=1.0,
            torsion=1.0,
            shear=50.0,
            stretch=50.0,
            mass=mass,
            rotary=1e-3,
            loads=lattice.TipForce(jnp.array([0.1, 0.0, 0.0])),
        )
        rod = eqx.tree_at(lambda r: r.base_position, rod, jnp.stack([0.0, 0.0, z0]))
        return lattice.equilibrium(rod).tip[2]

    g_mass, g_z0 = jax.grad(tip, argnums=(0, 1))(1.0, 0.0)
    assert float(g_mass) == 0.0
    np.testing.assert_allclose(g_z0, 1.0, rtol=1e-10)


@pytest.mark.slow  # implicit gradients compile the Newton program with its derivative
def test_gradient_of_tip_deflection_by_implicit_function_theorem():
    """jax.grad of the tip deflection with respect to EI and kGA against central differences."""

    def tip(EI, kGA):
        rod = cantilever(8, lattice.TipForce(jnp.array([0.3, 0.0, 0.0])), bending=EI, shear=kGA)
        return lattice.equilibrium(rod, steps=2).tip[0]

    g = jax.grad(tip, argnums=(0, 1))(1.0, 40.0)
    h = 1e-6
    fd_EI = (tip(1.0 + h, 40.0) - tip(1.0 - h, 40.0)) / (2 * h)
    fd_GA = (tip(1.0, 40.0 + 1e-4) - tip(1.0, 40.0 - 1e-4)) / 2e-4
    np.testing.assert_allclose(g[0], fd_EI, rtol=1e-7)
    np.testing.assert_allclose(g[1], fd_GA, rtol=1e-6)


def test_a_failed_solve_reports_a_status():
    """One Newton step for a large deflection: not converged, reported, no NaN."""
    rod = cantilever(6, lattice.TipForce(jnp.array([10.0, 0.0, 0.0])))
    sol = lattice.solve_equilibrium(rod, max_steps=1)
    assert not bool(sol.ok)
    assert rbo_jax._enumeration.name(sol.status) == "not_converged"
    with pytest.raises(Exception, match="Newton"):
        jax.block_until_ready(lattice.equilibrium(rod, max_steps=1).theta)


# ------------------------------------------------------------------------------------------
# Stability.
# ------------------------------------------------------------------------------------------


@pytest.mark.slow  # a dense 240 x 240 eigenproblem
def test_cantilever_frequencies():
    """The first two bending frequencies 3.51602 and 22.0345 sqrt(EI/(rho A L^4)) to 0.1 % at
    n = 20 (each twice: two transverse planes)."""
    p = np.asarray(lattice.spectrum(cantilever(20)))
    w = np.sort(np.abs(p.imag[p.imag > 1e-6]))
    np.testing.assert_allclose(w[[0, 1]], 3.51602, rtol=1e-3)
    np.testing.assert_allclose(w[[2, 3]], 22.0345, rtol=1e-3)
    assert np.max(np.abs(p.real)) < 1e-8 * np.max(np.abs(p))  # undamped: on the axis


@pytest.mark.slow  # a scan and bisection of spectra
def test_euler_buckling_of_a_cantilever():
    """Dead compressive tip force: divergence at pi^2 EI/(4 L^2) to 0.2 % at n = 16."""
    Pc = lattice.critical_load(
        lambda P: cantilever(16, lattice.TipForce(jnp.stack([0.0, 0.0, -P]))), 5.0
    )
    np.testing.assert_allclose(float(Pc), math.pi**2 / 4, rtol=2e-3)


@pytest.mark.slow  # a scan and bisection of spectra
def test_beck_column_flutter():
    """Follower tip force: flutter at 20.0509 EI/L^2, to 1 % at n = 20."""
    Pc = lattice.critical_load(
        lambda P: cantilever(20, lattice.TipForce(jnp.stack([0.0, 0.0, -P]), follower=True)),
        30.0,
    )
    np.testing.assert_allclose(float(Pc), 20.0509, rtol=1e-2)
    # just below the flutter load the two lowest frequencies have nearly merged, near 11.0
    below = cantilever(20, lattice.TipForce(jnp.array([0.0, 0.0, -0.999 * float(Pc)]), True))
    p = np.asarray(lattice.spectrum(below))
    w = np.unique(np.round(np.sort(np.abs(p.imag[p.imag > 1e-6])), 5))
    assert 10.5 < w[0] < w[1] < 11.5


@pytest.mark.slow  # a scan and bisection of spectra (a vmapped Newton loop and eig)
def test_ziegler_pendulum_flutter():
    """Ziegler's double pendulum (masses 2m, m; hinge springs c; links l): undamped flutter at
    (7/2 - sqrt 2) c/l, to 1e-5 (the hinges' stiffness and the point masses' small rotary
    inertia are 1e6 and 1e-6 of the pendulum's)."""
    Pc = lattice.critical_load(_ziegler, 5.0)
    np.testing.assert_allclose(float(Pc), 3.5 - math.sqrt(2), rtol=1e-5)


def first_unstable(unstable, loads, n_bisect=60):
    """The smallest load of the grid ``loads`` past which ``unstable`` holds, refined by
    bisection on the first change (the references below, in NumPy)."""
    k = next(k for k, P in enumerate(loads) if unstable(P))
    lo, hi = loads[k - 1], loads[k]
    for _ in range(n_bisect):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if unstable(mid) else (mid, hi)
    return hi


def ziegler_reference(b):
    """The critical load of Ziegler's rigid double pendulum (masses 2m, m; links l; hinge springs c
    and dampers b; m = l = c = 1) from its own linear equations M q'' + B q' + (K - P N) q = 0 in
    the link angles (Ziegler 1952): scan and bisection of the spectral abscissa."""
    M = np.array([[3.0, 1.0], [1.0, 1.0]])
    B = b * np.array([[2.0, -1.0], [-1.0, 1.0]])
    K = np.array([[2.0, -1.0], [-1.0, 1.0]])
    N = np.array([[1.0, -1.0], [0.0, 0.0]])

    def unstable(P):
        A = np.block(
            [
                [np.zeros((2, 2)), np.eye(2)],
                [-np.linalg.solve(M, K - P * N), -np.linalg.solve(M, B)],
            ]
        )
        return np.linalg.eigvals(A).real.max() > 1e-13

    return first_unstable(unstable, np.linspace(0.01, 5.0, 2000), 60)


def test_ziegler_reference_has_the_paradox():
    """The rigid pendulum's own equations: (7/2 - sqrt 2) c/l undamped, 41/28 c/l as b -> 0."""
    assert abs(ziegler_reference(0.0) - (3.5 - math.sqrt(2))) < 1e-6
    assert abs(ziegler_reference(1e-4) - 41 / 28) < 1e-7


@pytest.mark.slow  # two scans and bisections with damping
@pytest.mark.parametrize("b", [1e-1, 1e-2])
def test_ziegler_paradox_with_hinge_dampers(b):
    """Equal hinge dampers b (Kelvin-Voigt time b/c): the pendulum built of two bodies that
    translate has the rigid pendulum's critical load to 1e-5, near 41/28 c/l, far below the
    undamped (7/2 - sqrt 2) c/l (Ziegler's paradox)."""
    Pc = float(lattice.critical_load(lambda P: _ziegler(P, b), 5.0, rtol=1e-14))
    np.testing.assert_allclose(Pc, ziegler_reference(b), rtol=1e-5)
    assert abs(Pc - 41 / 28) < 0.01


def pfluger_galerkin(mass_ratio, K=10):
    """Pflüger's column (Beck's column with a tip mass M = mass_ratio rho A L) by the Ritz-Galerkin
    method of our own: w = sum q_k x^(k+1) (clamped at 0), EI = rho A = L = 1,
    M q'' + (K - P G + P F) q = 0 with K = int w''w'', G = int w'w' (the axial force),
    F = w(1) w'(1) (the follower force's transverse part at the tip); flutter where two
    squared frequencies merge."""
    i = np.arange(1, K + 1)[:, None]
    j = i.T
    Kst = (i + 1) * i * (j + 1) * j / (i + j - 1.0)
    G = (i + 1) * (j + 1) / (i + j + 1.0)
    F = np.broadcast_to(j + 1.0, (K, K))
    M = 1.0 / (i + j + 3.0) + mass_ratio

    def unstable(P):
        w2 = np.linalg.eigvals(np.linalg.solve(M, Kst - P * G + P * F))
        return np.any(np.abs(w2.imag) > 1e-9 * np.abs(w2).max()) or np.any(w2.real < 0)

    return first_unstable(unstable, np.linspace(0.01, 40.0, 4001), 60)


def beck_kelvin_voigt_galerkin(eta, K=10):
    """Beck's column with Kelvin-Voigt damping in bending, EI (w + eta w_t), by the same
    Ritz-Galerkin basis as :func:`pfluger_galerkin`: M q'' + eta K q' + (K - P G + P F) q = 0."""
    i = np.arange(1, K + 1)[:, None]
    j = i.T
    Kst = (i + 1) * i * (j + 1) * j / (i + j - 1.0)
    G = (i + 1) * (j + 1) / (i + j + 1.0)
    F = np.broadcast_to(j + 1.0, (K, K))
    M = 1.0 / (i + j + 3.0)

    def unstable(P):
        A = np.block(
            [
                [np.zeros((K, K)), np.eye(K)],
                [-np.linalg.solve(M, Kst - P * G + P * F), -eta * np.linalg.solve(M, Kst)],
            ]
        )
        return np.linalg.eigvals(A).real.max() > 1e-12

    return first_unstable(unstable, np.linspace(0.5, 30.0, 600), 50)


def test_beck_galerkin_reference_has_the_paradox():
    """Vanishing Kelvin-Voigt damping in bending lowers Beck's load to 10.94 EI/L^2."""
    assert abs(beck_kelvin_voigt_galerkin(1e-5) - 10.94) < 5e-3


@pytest.mark.slow  # a scan and bisection of damped spectra
def test_beck_column_with_vanishing_internal_damping():
    """Beck's column of 20 bodies with Kelvin-Voigt damping 1e-3 in bending and twist: flutter
    near 10.94 EI/L^2 (the Galerkin reference at the same damping, to 2 %), half of the
    undamped 20.05 (the destabilising paradox of internal damping)."""
    Pc = lattice.critical_load(
        lambda P: cantilever(
            20,
            lattice.TipForce(jnp.stack([0.0, 0.0, -P]), follower=True),
            damping=1e-3,
            shear_damping=0.0,
        ),
        30.0,
        rtol=1e-12,
    )
    np.testing.assert_allclose(float(Pc), beck_kelvin_voigt_galerkin(1e-3), rtol=2e-2)


def test_pfluger_galerkin_reference_gives_beck():
    """Without a tip mass the Galerkin reference is Beck's 20.0509 EI/L^2."""
    assert abs(pfluger_galerkin(0.0) - 20.0509) < 1e-3


@pytest.mark.slow  # a scan and bisection of spectra
def test_pfluger_column_tip_mass():
    """Beck's column with a tip mass equal to the rod's (ratio 1): the flutter load of the
    rod of 20 bodies against the Galerkin reference, to 1 %."""
    Pc = lattice.critical_load(
        lambda P: cantilever(
            20, lattice.TipForce(jnp.stack([0.0, 0.0, -P]), follower=True), tip_mass=1.0
        ),
        30.0,
    )
    np.testing.assert_allclose(float(Pc), pfluger_galerkin(1.0), rtol=1e-2)


# ------------------------------------------------------------------------------------------
# Motion.
# ------------------------------------------------------------------------------------------


@pytest.mark.slow  # a diffrax solve of 60 coupled bodies
def test_free_rod_conserves_energy_and_kinetic_moment():
    """A free rod, no loads, no damping: energy and the total kinetic moment about the origin
    (orbital plus (4.44) of every body) stay to 1e-8 relative."""
    rod = cantilever(6, base="free", shear=40.0, stretch=60.0, rotary=1e-2)
    s0 = _random_state(rod, 4, scale=0.1)
    s0 = lattice.RodState(s0.theta, s0.r, 0.3 * s0.Omega, 0.3 * s0.v)
    traj = lattice.simulate(rod, s0, jnp.linspace(0.0, 2.0, 5), rtol=1e-11, atol=1e-12)
    assert bool(traj.ok)
    E = np.asarray(traj.energy)
    L = np.asarray(traj.kinetic_moment)
    np.testing.assert_allclose(E, E[0], rtol=1e-8)
    np.testing.assert_allclose(L, np.broadcast_to(L[0], L.shape), atol=1e-8 * np.abs(L[0]).max())


@pytest.mark.slow  # three diffrax solves: Kvaerno5 twice, Dopri8
def test_implicit_method_follows_diffrax_kvaerno5_and_dopri8():
    """method="implicit" (Kvaerno5 with the rod's matrix chord root finder) against diffrax's own
    Kvaerno5 (its linearised root finder: the same Newton matrix) and against method="explicit"
    (Dopri8), on a damped cantilever under a follower tip force released with random velocities:
    the sampled states agree to 1e-9 of their largest value (measured 1.5e-11 and 4.8e-11; 3909,
    3906 and 1082 steps)."""
    import diffrax

    tip = lattice.TipForce(jnp.array([0.0, 0.5, -1.0]), follower=True)
    rod = cantilever(3, (tip,), shear=400.0, stretch=600.0, rotary=1e-3, damping=0.01)
    rng = np.random.default_rng(7)
    s = rod.straight()
    s0 = lattice.RodState(
        s.theta, s.r, 0.3 * rng.standard_normal(s.theta.shape), 0.3 * rng.standard_normal(s.r.shape)
    )
    ts = jnp.linspace(0.0, 0.5, 6)
    kw = dict(rtol=1e-10, atol=1e-12)
    runs = [
        lattice.simulate(rod, s0, ts, method="implicit", **kw),
        lattice.simulate(rod, s0, ts, solver=diffrax.Kvaerno5(), **kw),
        lattice.simulate(rod, s0, ts, method="explicit", **kw),
    ]
    flat = [
        np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(t.states)]) for t in runs
    ]
    scale = np.max(np.abs(flat[2]))
    assert np.max(np.abs(flat[0] - flat[1])) < 1e-9 * scale
    assert np.max(np.abs(flat[0] - flat[2])) < 1e-9 * scale


@pytest.mark.slow  # Levenberg-Marquardt through the eigenvalue problem (forward mode)
def test_fit_bending_stiffness_and_damping_to_eigenvalues():
    """The four lowest eigenvalues (two planes, two modes; frequency and decay) of a damped rod
    give back its EI and Kelvin-Voigt time from a start 30 % and 2x off; with 1e-4 noise on
    the data the standard errors cover the error."""

    def make(EI, eta):
        return lattice.rod(
            8,
            1.0,
            bending=EI,
            torsion=1.0,
            shear=1e4,
            stretch=1e4,
            mass=1.0,
            rotary=1e-4,
            damping=eta,
        )

    p = np.asarray(lattice.spectrum(make(1.3, 2e-3), make(1.3, 2e-3).straight()))
    p = p[p.imag > 1e-6]
    measured = p[np.argsort(p.imag)][:4]
    fit = lattice.fit_spectrum(make, {"EI": 1.0, "eta": 1e-3}, measured)
    assert fit.converged
    np.testing.assert_allclose(fit.params["EI"], 1.3, rtol=1e-8)
    np.testing.assert_allclose(fit.params["eta"], 2e-3, rtol=1e-6)
    rng = np.random.default_rng(5)
    noisy = measured + 1e-4 * (rng.standard_normal(4) + 1j * rng.standard_normal(4))
    fit = lattice.fit_spectrum(make, {"EI": 1.0, "eta": 1e-3}, noisy)
    for name, true in (("EI", 1.3), ("eta", 2e-3)):
        assert 0 < fit.stderr[name] < 0.1 * true
        assert abs(fit.params[name] - true) < 4 * fit.stderr[name]
