r"""Pseudo-arclength continuation of rod equilibria through a limit point
(:func:`rbo_jax.lattice.continue_equilibrium`).

The problem: a cantilever on a pendulum foundation, :class:`rbo_jax.CosineFoundation`
$c\,(1 - \cos\varphi)$ per length, bent in its plane by a tip moment $M$ about $e_1$. No force
acts, so the gap strains vanish and the bending angle $\varphi(s)$ obeys the static sine-Gordon
equation

$$ EI\,\varphi'' = c\,\sin\varphi, \qquad \varphi(0) = 0, \qquad EI\,\varphi'(L) = M, $$

softening: past a tip angle of about $\pi$ the foundation gives way and $M$ has a maximum, a
limit point (fold). Its first integral $\tfrac{EI}{2}\varphi'^2 - c(1 - \cos\varphi) =
\tfrac{EI}{2}\varphi'(0)^2$ gives $L = \int_0^{\varphi_L} d\varphi/\sqrt{s^2 + a^2(1 -
\cos\varphi)}$, $a^2 = 2c/EI$, $s = \varphi'(0)$, and $M^2/EI^2 = s^2 + a^2(1 - \cos\varphi_L)$:
the continuum's limit moment by an elliptic integral. The rod of $N$ bodies is the discrete chain
$k(\varphi_{i+1} - 2\varphi_i + \varphi_{i-1}) = c\,h\,\sin\varphi_i$, $k = EI/h$, with the tip
balance $M = k(\varphi_N - \varphi_{N-1}) + \tfrac{c h}{2}\sin\varphi_N$ (the tip body carries
half a segment): shooting from $\varphi_1$ gives its limit moment exactly. Both references are
NumPy/SciPy, independent of the package.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq, minimize_scalar
from scipy.special import ellipkinc

from rbo_jax import CosineFoundation, lattice

EI, C, LENGTH = 1.0, 8.0, 1.0


def chain_moment(phi1, n, c=C):
    """The tip moment and tip angle of the discrete chain whose first body turns by ``phi1``."""
    h = LENGTH / n
    k = EI / h
    phi = [0.0, phi1]
    for i in range(1, n):
        phi.append(2 * phi[i] - phi[i - 1] + c * h / k * np.sin(phi[i]))
    return k * (phi[n] - phi[n - 1]) + 0.5 * c * h * np.sin(phi[n]), phi[n]


def chain_limit(n, c=C):
    """The first maximum of the chain's tip moment along its branch: (moment, tip angle)."""
    grid = np.linspace(1e-4, 1.0, 20001)
    M = np.array([chain_moment(p, n, c)[0] for p in grid])
    i = int(np.argmax(np.diff(M) < 0))
    assert i > 0, "no limit point in the scanned range"
    res = minimize_scalar(
        lambda p: -chain_moment(p, n, c)[0],
        bounds=(grid[i - 1], grid[i + 1]),
        method="bounded",
        options={"xatol": 1e-13},
    )
    return -res.fun, chain_moment(res.x, n, c)[1]


def continuum_limit(c=C):
    r"""The continuum's limit moment (module docstring). With $1 - \cos\varphi =
    2\sin^2(\varphi/2)$ the length is an incomplete elliptic integral of the first kind,
    $L = \frac{2}{s}\,F(\varphi_L/2 \mid -2a^2/s^2)$ (SciPy's ``ellipkinc``)."""
    a2 = 2 * c / EI

    def moment(phi_L):
        def length(s):
            return 2 / s * ellipkinc(phi_L / 2, -2 * a2 / s**2)

        s = brentq(lambda s: length(s) - LENGTH, 1e-6, 100.0, xtol=1e-15)
        return EI * np.sqrt(s * s + a2 * (1 - np.cos(phi_L)))

    res = minimize_scalar(lambda p: -moment(p), bounds=(2.0, 4.5), method="bounded",
                          options={"xatol": 1e-12})  # fmt: skip
    return -res.fun, res.x


def test_chain_reference_converges_to_the_sine_gordon_limit_moment():
    """The references agree with each other: the chain's limit moment tends to the continuum's
    at second order in h (the errors fall by 4 when N doubles)."""
    M_inf, phi_inf = continuum_limit()
    errors = [M_inf - chain_limit(n)[0] for n in (10, 20, 40, 80)]
    assert 5.8 < M_inf < 5.82 and np.pi < phi_inf < 3.3
    assert all(e > 0 for e in errors)
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    np.testing.assert_allclose(ratios, 4.0, rtol=0.05)


def shaft(M, n=10):
    z = 0.0 * M
    return lattice.rod(
        n, LENGTH, bending=EI, torsion=EI, shear=1e3, stretch=1e3, mass=1.0, rotary=1e-2,
        foundation=CosineFoundation(C), loads=lattice.TipMoment(jnp.stack([M, z, z])),
    )  # fmt: skip


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"ds": -0.1}, "ds"),
        ({"ds": 0.5, "ds_max": 0.1}, "ds"),
        ({"load_scale": 0.0}, "load_scale"),
        ({"max_points": 1}, "max_points"),
    ],
)
def test_bad_arguments_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        lattice.continue_equilibrium(shaft, 0.0, 1.0, **kwargs)


def test_start_equal_to_stop_and_a_rod_fn_without_a_rod_are_refused():
    with pytest.raises(ValueError, match="start and stop"):
        lattice.continue_equilibrium(shaft, 1.0, 1.0)
    with pytest.raises(TypeError, match="must return a Rod"):
        lattice.continue_equilibrium(lambda M: M, 0.0, 1.0)


def real_unstable(p, rtol=1e-9):
    """The eigenvalues with Re p > 0 and Im p = 0 (divergence), to rtol of max |p|."""
    tol = rtol * np.max(np.abs(p))
    return int(np.sum((p.real > tol) & (np.abs(p.imag) <= tol)))


@pytest.mark.slow  # the continuation program (Newton on the bordered system and the spectrum)
def test_branch_passes_the_limit_point_of_the_sine_gordon_cantilever():
    """The branch goes round the fold: the tip angle keeps growing while M rises to its maximum
    and falls again; the fold's moment is the discrete chain's limit moment (shooting, module
    docstring) to 1e-4 (measured 2.2e-5: the error of the parabola through three points,
    O(s^3), at the arclength step 0.3), within 1.0 % of the continuum's at N = 10
    (second-order error 0.038). One real eigenvalue crosses into Re p > 0 there (divergence),
    none before it. A point past the fold is an equilibrium: Newton started there stops at once."""
    M_chain, phi_chain = chain_limit(10)
    M_inf, _ = continuum_limit()
    branch = lattice.continue_equilibrium(shaft, 0.0, 10.0, load_scale=6.0, ds=0.1, ds_max=0.3,
                                          max_points=30)  # fmt: skip
    loads = branch.loads
    tip_angle = np.unwrap(np.asarray(branch.states.theta[:, -1, 0]))  # past pi: wrapped
    folds = branch.folds
    assert folds.shape == (1,)
    np.testing.assert_allclose(folds[0], M_chain, rtol=1e-4)
    assert M_chain * (1 - 1e-3) < loads.max() <= M_chain * (1 + 1e-12)  # points on the branch
    assert abs(folds[0] / M_inf - 1) < 0.01
    i = int(np.argmax(loads))
    assert 0 < i < len(loads) - 3  # the branch goes on past the fold
    assert np.all(np.diff(tip_angle) > 0)  # the tip angle rises through the fold
    assert tip_angle[i] == pytest.approx(phi_chain, abs=0.2)
    assert np.all(np.diff(loads[: i + 1]) > 0) and np.all(np.diff(loads[i:]) < 0)
    counts = [real_unstable(p) for p in branch.eigenvalues]
    assert counts[:i] == [0] * i and counts[i + 1 :] == [1] * (len(loads) - i - 1)
    j = len(loads) - 1
    state = lattice.RodState.at_rest(branch.states.theta[j], branch.states.r[j])
    sol = lattice.solve_equilibrium(shaft(jnp.asarray(loads[j])), state)
    assert bool(sol.ok) and int(sol.iterations) <= 2
