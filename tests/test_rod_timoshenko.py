r"""The natural frequencies of a stocky cantilever against Timoshenko's beam.

Timoshenko's beam (Timoshenko 1921; the cantilever's frequency equation: Huang, J. Appl. Mech.
28, 1961) couples the deflection $w$ and the section's turn $\psi$:

$$ EI\,\psi'' + \kappa GA\,(w' - \psi) + \rho I\,\omega^2\psi = 0, \qquad
   \kappa GA\,(w'' - \psi') + \rho A\,\omega^2 w = 0, $$

clamped at $x = 0$ ($w = \psi = 0$), free at $x = L$ (moment $EI\psi' = 0$, shear force
$\kappa GA(w' - \psi) = 0$). With $y = (w, \psi, \psi', w' - \psi)$ it is $y' = A(\omega)\,y$,
$A$ constant, so $y(L) = e^{AL}y(0)$ and the frequencies are the roots of the $2\times2$ minor of
$e^{AL}$ that maps $(\psi'(0), (w'-\psi)(0))$ to the free end's $(\psi'(L), (w'-\psi)(L))$.
Here SciPy's ``expm`` and ``brentq`` solve it, independent of the package. The rod of
:func:`rbo_jax.lattice.rod` is a discrete Cosserat rod whose strains are Timoshenko's (shear
$\kappa GA$, rotary inertia $\rho I$ per length): its lowest bending frequencies from
:func:`rbo_jax.lattice.spectrum` converge to these at second order in $h = L/N$.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.optimize import brentq

from rbo_jax import lattice

# a stocky beam: slenderness L/r = 20 (r^2 = I/A), E/(kappa G) = 3
EI, RHO_A, RHO_I, LENGTH = 1.0, 1.0, 0.0025, 1.0
KGA = EI / (3.0 * RHO_I / RHO_A)  # kappa G A = EI / (3 r^2)
EULER_BERNOULLI = np.array([1.8751040687, 4.6940911330, 7.8547574382]) ** 2


def timoshenko_cantilever(EI, kGA, rhoA, rhoI, L, count, w_max=80.0):
    """The lowest ``count`` circular frequencies of the clamped-free Timoshenko beam
    (module docstring), by a scan of the frequency determinant and bisection."""

    def minor(w):
        A = np.array(
            [
                [0.0, 1.0, 0.0, 1.0],
                [0.0, 0.0, 1.0, 0.0],
                [0.0, -rhoI * w * w / EI, 0.0, -kGA / EI],
                [-rhoA * w * w / kGA, 0.0, 0.0, 0.0],
            ]
        )
        return np.linalg.det(expm(A * L)[2:, 2:])

    grid = np.linspace(1e-3, w_max, 4000)
    d = np.array([minor(w) for w in grid])
    changes = np.flatnonzero(np.sign(d[:-1]) != np.sign(d[1:]))
    return np.array([brentq(minor, grid[i], grid[i + 1], xtol=1e-14) for i in changes[:count]])


def test_reference_has_the_euler_bernoulli_limit():
    """The reference's own check: with a stiff shear and no rotary inertia it gives the
    Euler–Bernoulli cantilever, $\\omega_k = (\\beta_k L)^2\\sqrt{EI/(\\rho A L^4)}$ with
    $\\beta_k L$ = 1.8751, 4.6941, 7.8548, to 1e-7; the stocky beam's are lower, by shear and
    rotary inertia, more so for the higher modes."""
    slender = timoshenko_cantilever(1.0, 1e9, 1.0, 1e-12, 1.0, 3)
    np.testing.assert_allclose(slender, EULER_BERNOULLI, rtol=1e-7)
    stocky = timoshenko_cantilever(EI, KGA, RHO_A, RHO_I, LENGTH, 3)
    drop = 1 - stocky / EULER_BERNOULLI
    assert 0.01 < drop[0] < drop[1] < drop[2] < 0.5


def bending_frequencies(n, count=3):
    """The lowest ``count`` bending frequencies of the rod of ``n`` bodies, each a pair (the
    two planes of bending); the single torsion and stretch frequencies between them skipped."""
    beam = lattice.rod(
        n, LENGTH, bending=EI, torsion=EI, shear=KGA, stretch=1e4, mass=RHO_A, rotary=RHO_I
    )
    p = np.asarray(lattice.spectrum(beam, beam.straight()))
    w = np.sort(p.imag[p.imag > 0])
    pairs, i = [], 0
    while len(pairs) < count:
        if abs(w[i + 1] / w[i] - 1) < 1e-6:
            pairs.append(w[i : i + 2])
            i += 2
        else:
            i += 1
    return np.array(pairs)


@pytest.mark.slow  # three dense spectra (96, 192 and 384 unknowns), three programs
def test_stocky_cantilever_frequencies_converge_to_timoshenko_at_second_order():
    """The lowest three bending frequencies at N = 8, 16, 32 bodies: each comes as a pair (the
    two planes) equal to 1e-9; the errors against Timoshenko's beam fall by 4 when N doubles
    (measured orders 1.99–2.00 for the first two modes, 1.83 and 1.98 for the third; asserted
    2 to within 0.2) and at N = 32 are below 0.1 % (measured -2.5e-4, -3.5e-4, -5.2e-4)."""
    reference = timoshenko_cantilever(EI, KGA, RHO_A, RHO_I, LENGTH, 3)
    errors = []
    for n in (8, 16, 32):
        pairs = bending_frequencies(n)
        np.testing.assert_allclose(pairs[:, 0], pairs[:, 1], rtol=1e-9)
        errors.append(pairs[:, 0] / reference - 1)
    errors = np.array(errors)
    order = np.log2(np.abs(errors[:-1]) / np.abs(errors[1:]))
    np.testing.assert_allclose(order, 2.0, atol=0.2)
    assert np.all(np.abs(errors[-1]) < 1e-3)
