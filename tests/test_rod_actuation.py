"""Rods in motion with actuation and a ground, and gradients through their motion (issue 50,
C and D): muscle torques as PyElastica defines them, a rest curvature that changes with time,
a plane with anisotropic friction, and ``jax.grad`` through the default integrator."""

from __future__ import annotations

import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.interpolate import BSpline

from rbo_jax import lattice
from rbo_jax.models.rod import Motion
from rbo_jax.models.rod._actuation import bspline_basis, coupling_fractions

B_COEFF = np.array([3.4e-3, 3.3e-3, 4.2e-3, 2.6e-3, 3.6e-3, 3.5e-3])  # PyElastica's snake


def pyelastica_spline(coeff):
    """The clamped cubic spline of PyElastica's ``_bspline`` (elastica/utils.py), built here
    with SciPy: knots 0,0,0, then the coefficients' count - 2 points on [0, 1], then 1,1,1."""
    inner = np.linspace(0.0, 1.0, len(coeff) - 2)
    knots = np.concatenate([[0.0] * 3, inner, [1.0] * 3])
    return BSpline(knots, coeff, 3, extrapolate=False)


def test_bspline_basis_is_pyelasticas_envelope():
    s = np.random.default_rng(0).uniform(0.0, 1.0, 200)
    ours = np.asarray(bspline_basis(jnp.asarray(s), len(B_COEFF)) @ B_COEFF)
    np.testing.assert_allclose(ours, pyelastica_spline(B_COEFF)(s), rtol=1e-13, atol=1e-18)


def straight_motion(rod, t, v=None):
    state = rod.straight()
    Q = jax.vmap(lambda th: jnp.eye(3))(state.theta)
    v = jnp.zeros_like(state.r) if v is None else v
    return Motion(Q, state.r, jnp.zeros_like(state.r), v, t)


def test_muscle_torques_are_the_travelling_wave_of_couples():
    """Gazzola et al. 2018 (4.6), as PyElastica's ``MuscleTorques``: the couple of coupling c is
    min(1, t/t_r) beta(s) sin(omega t - k s) about ``direction``, s counted from the tip; each
    couple acts + on the outer body, - on the inner one, so the moments sum to zero."""
    n, t, period, k = 12, 1.3, 2.0, 2 * np.pi / 0.97
    rod = lattice.rod(
        n, 0.35, bending=1.0, torsion=1.0, shear=10.0, stretch=10.0, mass=1.0, rotary=1e-3
    )
    muscle = lattice.MuscleTorques(B_COEFF, period, k, ramp_up_time=2.0, direction=(0, 1, 0))
    F, M = muscle.forces(rod, None, 1.0, straight_motion(rod, t))
    s = 1.0 - (np.arange(n) + 0.5) / n
    tau = min(1.0, t / 2.0) * pyelastica_spline(B_COEFF)(s) * np.sin(2 * np.pi / period * t - k * s)
    expected = np.zeros((n + 1, 3))
    expected[1:, 1] += tau
    expected[:-1, 1] -= tau
    np.testing.assert_allclose(np.asarray(M), expected, rtol=1e-12, atol=1e-18)
    np.testing.assert_array_equal(np.asarray(F), 0.0)
    np.testing.assert_allclose(np.asarray(coupling_fractions(rod)), 1.0 - s, rtol=1e-14)
    # zero in the statics (t = 0): the ramp
    _, M0 = muscle.forces(rod, None, 1.0, straight_motion(rod, 0.0))
    np.testing.assert_array_equal(np.asarray(M0), 0.0)


def test_rest_curvature_gives_the_regular_polygon_of_its_turns():
    """A clamped rod whose rest curvature is kappa about e1 and that carries no load rests with
    every relative turn h kappa and no shear or stretch: its nodes are the vertices of a regular
    polygon of side h, on a circle of radius h / (2 sin(h kappa / 2)), exactly."""
    n, L, kappa = 16, 1.0, 2.0
    rod = lattice.rod(
        n, L, bending=1.0, torsion=0.8, shear=50.0, stretch=50.0, mass=1.0, rotary=1e-3
    )
    rod = rod.with_loads(lattice.RestCurvature((kappa, 0.0, 0.0)))
    r = np.asarray(lattice.equilibrium(rod).r)
    h = L / n
    radius = h / (2 * np.sin(h * kappa / 2))
    # the circle through the base, tangent to e3 there, in the plane x = 0: centre on the y axis
    centre = np.array([0.0, np.sign(r[-1, 1]) * radius, 0.0])
    np.testing.assert_allclose(np.linalg.norm(r - centre, axis=1), radius, rtol=1e-9)
    np.testing.assert_allclose(r[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(np.diff(r, axis=0), axis=1), h, rtol=1e-9)


def test_rest_curvature_of_time_enters_the_motion_and_the_energy():
    """A function of time: the energy at each sample is the strain energy against that
    sample's rest curvature (here zero at t = 0, so the straight rod starts at rest with no
    energy and is driven)."""
    rod = lattice.rod(
        6, 1.0, bending=1.0, torsion=0.8, shear=50.0, stretch=50.0, mass=1.0, rotary=1e-2
    )

    def curvature(t, xi, params):
        return jnp.stack([params * jnp.sin(t) * jnp.ones_like(xi), 0 * xi, 0 * xi], -1)

    driven = rod.with_loads(lattice.RestCurvature(curvature, jnp.asarray(0.5)))
    ts = jnp.linspace(0.0, 1.0, 11)
    traj = lattice.simulate(driven, driven.straight(), ts)
    assert traj.ok
    assert abs(float(traj.energy[0])) < 1e-25  # no strain, no motion
    assert float(jnp.max(jnp.abs(traj.centreline[:, -1, 1]))) > 1e-3  # it bends
    with pytest.raises(ValueError, match="must return"):
        rod.with_loads(lattice.RestCurvature(lambda t, xi, p: jnp.zeros((3,)), None))


def test_frictional_plane_is_anisotropic_coulomb_friction():
    """A body resting on the plane at its static penetration carries its weight; sliding at
    speeds far above the slip velocity it feels mu N against its motion: forward mu_f along
    its axis, backward mu_b, sideways mu_l; at rest (the statics) no friction."""
    n = 4
    rod = lattice.rod(
        n, 1.0, bending=1.0, torsion=1.0, shear=10.0, stretch=10.0, mass=2.0, rotary=1e-3
    )
    k, mu = 1e5, np.array([0.1, 0.3, 0.7])
    plane = lattice.FrictionalPlane(
        mu=mu, stiffness=k, origin=(0.0, 0.01, 0.0), normal=(0, 1, 0), slip_velocity=1e-6
    )  # the bodies (y = 0) 0.01 inside it
    share = np.asarray(rod.share)
    N = share * k * 0.01  # well inside the plane: softplus(x) = x to 1e-40
    for v_dir, coefficient in [((0, 0, 1), mu[0]), ((0, 0, -1), mu[1]), ((1, 0, 0), mu[2])]:
        v = jnp.broadcast_to(jnp.asarray(v_dir, float), (n + 1, 3))
        F, M = plane.forces(rod, None, 1.0, straight_motion(rod, 0.0, v))
        F = np.asarray(F)
        np.testing.assert_allclose(F[:, 1], N, rtol=1e-10)
        friction = F - F[:, 1:2] * np.array([0, 1, 0])
        np.testing.assert_allclose(friction, -coefficient * N[:, None] * np.array(v_dir), rtol=1e-6)
        np.testing.assert_array_equal(np.asarray(M), 0.0)
    F, _ = plane.forces(rod, None, 1.0, straight_motion(rod, 0.0)._replace(v=None))
    np.testing.assert_allclose(np.asarray(F)[:, [0, 2]], 0.0)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: lattice.MuscleTorques(B_COEFF, 0.0, 1.0), "period"),
        (lambda: lattice.MuscleTorques(B_COEFF[:3], 1.0, 1.0), "amplitude"),
        (lambda: lattice.MuscleTorques(B_COEFF, 1.0, 1.0, direction=(0, 0, 0)), "direction"),
        (lambda: lattice.FrictionalPlane(mu=(-0.1, 0.1, 0.1), stiffness=1.0), "mu"),
        (lambda: lattice.FrictionalPlane(mu=(0.1, 0.1, 0.1), stiffness=0.0), "stiffness"),
        (lambda: lattice.FrictionalPlane(mu=(0.1,) * 3, stiffness=1.0, slip_velocity=0), "slip"),
        (lambda: lattice.RestCurvature((1.0, 2.0)), "curvature"),
        (
            lambda: lattice.pendulum([1.0, 1.0], [1.0, 1.0], [1.0, 1.0]).with_loads(
                lattice.MuscleTorques(1.0, 1.0, 1.0)
            ),
            "rest length",
        ),
    ],
)
def test_bad_actuation_and_ground_name_the_argument(make, match):
    with pytest.raises(ValueError, match=match):
        make()


# ------------------------------------------------------------------------------------------
# Motion: the splitting and the midpoint rule agree on a driven rod; gradients.
# ------------------------------------------------------------------------------------------


def driven_rod(bending=1.0, damping=0.01, amplitude=0.05, wave_number=2.0, period=0.5, n=6):
    muscle = lattice.MuscleTorques(
        amplitude, period, wave_number, direction=(1.0, 0.0, 0.0), ramp_up_time=0.25
    )
    return lattice.rod(
        n, 1.0, bending=bending, torsion=0.8, shear=1e4, stretch=1e4, mass=1.0,
        rotary=1e-3, damping=damping, loads=(muscle,),
    )  # fmt: skip


@pytest.mark.slow  # two integrators' programs of a driven rod (~16 s)
def test_driven_rod_splitting_and_midpoint_agree():
    """Muscle torques act at each step's time in both fixed-step methods: the two second-order
    methods at small steps give the same motion (to their O(dt^2) errors)."""
    rod = driven_rod()
    ts = jnp.linspace(0.0, 0.5, 6)
    a = lattice.simulate(rod, rod.straight(), ts, method="splitting")  # its stable step
    b = lattice.simulate(rod, rod.straight(), ts, method="midpoint", dt=1e-3, rtol=1e-12)
    tip_a, tip_b = np.asarray(a.centreline[:, -1]), np.asarray(b.centreline[:, -1])
    assert np.max(np.abs(tip_a[:, 1])) > 1e-3  # the wave moves the tip
    np.testing.assert_allclose(tip_a, tip_b, atol=2e-5 * np.max(np.abs(tip_a)))


@pytest.mark.slow  # three programs (value, reverse and forward mode) of a driven rod: ~75 s
def test_gradient_through_the_default_integrator_matches_central_differences():
    """Issue 50, D: ``jax.grad`` of the tip's position at the end with respect to the bending
    stiffness, the damping and the muscle wave's amplitude, wave number and period, through
    ``lattice.simulate`` with no method (the midpoint rule: the rod is stiff), equals central
    differences to 1e-5 relative, and forward mode."""
    ts = jnp.linspace(0.0, 0.4, 9)
    tight = dict(rtol=1e-12, atol=1e-14)
    names = ("bending", "damping", "amplitude", "wave_number", "period")
    p0 = jnp.array([1.0, 0.01, 0.05, 2.0, 0.5])

    def tip(p):
        rod = driven_rod(**dict(zip(names, p)))
        traj = lattice.simulate(rod, rod.straight(), ts, **tight)
        return traj.centreline[-1, -1, 1]

    rod = driven_rod()
    from rbo_jax.lattice import _rod_midpoint

    assert _rod_midpoint.auto(rod, rod.straight(), np.asarray(ts), None, False) == "midpoint"
    grad = np.asarray(jax.grad(tip)(p0))
    fwd = np.asarray(jax.jacfwd(tip)(p0))
    eps = 1e-5 * np.maximum(np.abs(np.asarray(p0)), 1e-2)
    fd = np.array(
        [
            (float(tip(p0.at[i].add(e))) - float(tip(p0.at[i].add(-e)))) / (2 * e)
            for i, e in enumerate(eps)
        ]
    )
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-9 * np.max(np.abs(fd)))
    np.testing.assert_allclose(grad, fwd, rtol=1e-9, atol=1e-14)


@pytest.mark.slow  # PyElastica's snake (40,000 steps) and ours, n = 50, four periods: ~70 s
def test_continuum_snake_crawls_as_pyelasticas():
    """Issue 50, C: PyElastica's ContinuumSnakeCase (n = 50, its parameters, dt = 1e-4) and the
    same snake as a rod with MuscleTorques and a FrictionalPlane (the default method, dt = 0.01)
    over four periods: the centre of mass moves forward by the same distance within 3 %, and
    the average forward speed (PyElastica's own measure) agrees within 5 %."""
    pytest.importorskip("elastica")
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
    import bench_snake

    ts, com, v, *_ = bench_snake.rj_snake(50, 4.0, 0.01)
    pe_ts, pe_com, pe_v, _ = bench_snake.pe_snake(50, 4.0, 1e-4)
    ours, theirs = com[-1, 2] - com[0, 2], pe_com[-1, 2] - pe_com[0, 2]
    assert theirs > 0.05  # it crawls forward
    assert abs(ours / theirs - 1.0) < 0.03
    fwd, _ = bench_snake.forward_speed(ts, com, v, 2.0)
    pe_fwd, _ = bench_snake.forward_speed(pe_ts, pe_com, pe_v, 2.0)
    assert abs(fwd / pe_fwd - 1.0) < 0.05
