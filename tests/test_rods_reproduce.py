"""The references of the rods' section of ``rbo-jax reproduce`` (rbo_jax/app/reproduce/
_rod_references.py) against published values and closed forms, and its fit of a growing
oscillation. The section itself runs in tests/test_cli.py (``reproduce --quick``, slow tier):
every one of its checks must pass there."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rbo_jax.app.reproduce import _rod_references as ref
from rbo_jax.app.reproduce._rods import _peaks


def test_cantilever_betas_are_the_published_roots():
    """cos(beta) cosh(beta) = -1: 1.875104, 4.694091, 7.854757, 10.995541 (Blevins' table),
    then (k - 1/2) pi to within e^{-beta}."""
    b = ref.cantilever_betas(8)
    np.testing.assert_allclose(b[:4], [1.875104, 4.694091, 7.854757, 10.995541], atol=1e-6)
    np.testing.assert_allclose(b[4:], (np.arange(5, 9) - 0.5) * np.pi, atol=1e-6)
    assert np.abs(np.cos(b) * np.cosh(b) + 1).max() < 1e-8 * np.cosh(b).max()


def test_cantilever_modes_are_orthonormal_and_clamped():
    """int phi_i phi_j = delta_ij, int phi_i'' phi_j'' = beta_i^4 delta_ij (the modes of
    w'''' = beta^4 w), phi(0) = phi'(0) = 0, and the free end's phi''(1) = 0; the quadrature of
    12 modes stays well conditioned (the monomials' mass matrix does not)."""
    S, G, F, M = ref._column_matrices(0.0, 12)
    b = ref.cantilever_betas(12)
    np.testing.assert_allclose(M, np.eye(12), atol=1e-12)
    np.testing.assert_allclose(S / b[:, None] ** 2 / b[None, :] ** 2, np.eye(12), atol=1e-12)
    phi, d1, d2 = ref.cantilever_modes(12, [0.0, 1.0])
    assert np.abs(phi[:, 0]).max() < 1e-12 and np.abs(d1[:, 0]).max() < 1e-12
    assert np.abs(d2[:, 1]).max() < 1e-9 * b.max() ** 2
    np.testing.assert_allclose(np.abs(phi[:, 1]), 2.0, rtol=1e-12)  # |phi(1)| = 2, every mode


def test_galerkin_gives_beck_and_the_damping_paradox():
    """Beck's column 20.0509 EI/L^2 (Beck 1952) to 1e-5; with vanishing Kelvin-Voigt damping
    10.94 (Bolotin and Zhinzher), rising with the damping."""
    assert abs(ref.column_galerkin() - 20.0509) < 2e-4
    low = ref.column_galerkin(0.0, 1e-5)
    assert abs(low - 10.94) < 2e-3
    assert low < ref.column_galerkin(0.0, 1e-2) < ref.column_galerkin(0.0, 3e-2)


def test_galerkin_pfluger_converges_with_the_modes():
    """Pflüger's column with a tip mass rho A L: 12 and 16 modes agree to 1e-3, and the tip mass
    lowers the flutter load below Beck's."""
    a, b = ref.column_galerkin(1.0, K=12), ref.column_galerkin(1.0, K=16)
    assert abs(a / b - 1) < 1e-3
    assert 15.5 < b < 17.0


@pytest.mark.parametrize("b", [0.0, 1e-3, 0.1, 0.5])
def test_ziegler_closed_form_against_its_linear_equations(b):
    """41/28 + b^2/2 (b > 0) and 7/2 - sqrt 2 (b = 0) against the spectral abscissa of the rigid
    pendulum's M q'' + B q' + (K - P N) q = 0 (masses 2, 1; links, springs 1; Ziegler 1952)."""
    M = np.array([[3.0, 1.0], [1.0, 1.0]])
    B = b * np.array([[2.0, -1.0], [-1.0, 1.0]])
    K = np.array([[2.0, -1.0], [-1.0, 1.0]])
    N = np.array([[1.0, -1.0], [0.0, 0.0]])

    def growth(P):
        A = np.block(
            [
                [np.zeros((2, 2)), np.eye(2)],
                [-np.linalg.solve(M, K - P * N), -np.linalg.solve(M, B)],
            ]
        )
        return np.linalg.eigvals(A).real.max()

    Pc = ref.ziegler_damped(b) if b > 0 else ref.ZIEGLER
    assert growth(Pc * (1 - 1e-6)) < 1e-13 < growth(Pc * (1 + 1e-6))
    assert b > 0 or abs(Pc - (3.5 - math.sqrt(2))) < 1e-15


def test_peaks_recover_growth_and_frequency():
    """The peaks of |e^{st} cos(wt)| sampled at 100 per unit time: ln(height) is linear in t
    with slope s, and they are pi/w apart."""
    s, w = 2.1, 10.9
    ts = np.linspace(0.0, 5.0, 501)
    tp, hp = _peaks(ts, np.exp(s * ts) * np.cos(w * ts + 0.3))
    assert abs(np.polyfit(tp, np.log(hp), 1)[0] / s - 1) < 2e-3
    assert abs(np.pi / np.mean(np.diff(tp)) / w - 1) < 1e-3
