r"""Independent references for the rods' section (:mod:`._rods`), in NumPy: nothing of
:mod:`rbo_jax.lattice` enters them.

**Beck's and Pflüger's columns** (EI = ρA = L = 1) by a Galerkin method of our own on the
cantilever's modes. The continuum $w'''' + \eta\,\dot w'''' + P w'' + \ddot w = 0$ (Kelvin–Voigt
damping $EI\,(w + \eta\dot w)$), clamped at $x = 0$, with a compressive follower force $P$ and a
tip mass $\mu$ at $x = 1$, and $w = \sum_{k=1}^{K} q_k(t)\,\phi_k(x)$ give

$$M\ddot q + \eta S\dot q + (S - P G + P F)\,q = 0,\quad
S_{ij} = \int_0^1 \phi_i''\phi_j''\,dx,\ G_{ij} = \int_0^1 \phi_i'\phi_j'\,dx,\
F_{ij} = \phi_i(1)\,\phi_j'(1),\ M_{ij} = \int_0^1 \phi_i\phi_j\,dx + \mu\,\phi_i(1)\phi_j(1),$$

with the cantilever's modes
$\phi_k = \cosh\beta_k x - \cos\beta_k x - \sigma_k(\sinh\beta_k x - \sin\beta_k x)$,
$\cos\beta_k\cosh\beta_k = -1$,
$\sigma_k = (\sinh\beta_k - \sin\beta_k)/(\cosh\beta_k + \cos\beta_k)$
($S = \mathrm{diag}\,\beta_k^4$ and $\int_0^1\phi_i\phi_j\,dx = \delta_{ij}$: a well-conditioned
basis, unlike the monomials $x^{k+1}$), the integrals by Gauss–Legendre quadrature. The column
loses stability where the spectral abscissa of the first-order system turns positive: Beck's
$20.0509$ at $\mu = \eta = 0$ (20.0507 at K = 12); as $\eta \to 0$ the critical load tends to
$10.94$, about half of it (the destabilisation paradox of Bolotin and Zhinzher).

**Ziegler's pendulum** (masses 2m and m, links l, hinge springs c and dampers b; m = l = c = 1),
whose linear equations in the link angles are $M\ddot q + B\dot q + (K - P N)\,q = 0$
(Ziegler 1952). Undamped it flutters at $7/2 - \sqrt2$; with equal dampers $b$ at
$41/28 + b^2/2$ (the Routh–Hurwitz condition), which tends to $41/28$, not to $7/2 - \sqrt2$,
as $b \to 0$.
"""

from __future__ import annotations

import math

import numpy as np

BECK = 20.0509  # Beck's column, EI/L^2 (Beck 1952)
BECK_KV_LIMIT = 10.94  # Beck's column as the Kelvin-Voigt damping vanishes, EI/L^2
ZIEGLER = 3.5 - math.sqrt(2.0)  # Ziegler's double pendulum, c/l
ZIEGLER_DAMPED_LIMIT = 41.0 / 28.0  # its limit under vanishing equal hinge dampers, c/l
MODES = 12  # Galerkin modes of the columns' reference


def ziegler_damped(b):
    r"""The critical load $41/28 + b^2/2$ (c/l; m = l = c = 1) of Ziegler's pendulum with equal
    hinge dampers $b$."""
    return ZIEGLER_DAMPED_LIMIT + 0.5 * np.square(b)


def first_unstable(unstable, loads, n_bisect: int = 50) -> float:
    """The smallest load of the grid ``loads`` past which ``unstable`` holds, refined by bisection
    on the first change."""
    k = next(k for k, P in enumerate(loads) if unstable(P))
    lo, hi = loads[max(k - 1, 0)], loads[k]
    for _ in range(n_bisect):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if unstable(mid) else (mid, hi)
    return float(hi)


def cantilever_betas(K: int) -> np.ndarray:
    r"""The roots $\beta_k$ of $\cos\beta\cosh\beta = -1$ (as $\cos\beta + 1/\cosh\beta = 0$),
    by Newton's method from $(k - 1/2)\pi$: 1.8751, 4.6941, 7.8548, ..."""
    b = (np.arange(1, K + 1) - 0.5) * np.pi
    for _ in range(30):
        b = b - (np.cos(b) + 1 / np.cosh(b)) / (-np.sin(b) - np.tanh(b) / np.cosh(b))
    return b


def cantilever_modes(K: int, x):
    r"""$\phi_k$, $\phi_k'$, $\phi_k''$ at the points ``x``, each (K, len(x)); the growing
    exponentials are combined first, $\cosh\beta x - \sigma\sinh\beta x =
    \frac12[(1 - \sigma)e^{\beta x} + (1 + \sigma)e^{-\beta x}]$, with
    $1 - \sigma = (e^{-\beta} + \cos\beta + \sin\beta)/(\cosh\beta + \cos\beta)$."""
    b = cantilever_betas(K)[:, None]
    x = np.asarray(x, dtype=float)[None, :]
    e = np.exp(-b)
    c, s = np.cos(b), np.sin(b)
    grow = (e + c + s) * 2 * np.exp(b * (x - 1)) / (1 + e * e + 2 * c * e)  # (1 - σ) e^{βx}
    sigma = 1 - (e + c + s) / (np.cosh(b) + c)
    decay = (1 + sigma) * np.exp(-b * x)
    cx, sx = np.cos(b * x), np.sin(b * x)
    phi = 0.5 * (grow + decay) - cx + sigma * sx
    d1 = b * (0.5 * (grow - decay) + sx + sigma * cx)
    d2 = b * b * (0.5 * (grow + decay) + cx - sigma * sx)
    return phi, d1, d2


def _column_matrices(mass_ratio: float, K: int):
    x, w = np.polynomial.legendre.leggauss(200)
    x, w = 0.5 * (x + 1), 0.5 * w
    phi, d1, d2 = cantilever_modes(K, x)
    tip, tip_slope, _ = cantilever_modes(K, [1.0])
    S = (d2 * w) @ d2.T
    G = (d1 * w) @ d1.T
    F = tip @ tip_slope.T
    M = (phi * w) @ phi.T + mass_ratio * tip @ tip.T
    return S, G, F, M


def column_galerkin(mass_ratio: float = 0.0, eta: float = 0.0, K: int = MODES) -> float:
    r"""The critical load (EI/L²) of Beck's column with a tip mass ``mass_ratio`` ρAL (Pflüger's
    column) and Kelvin–Voigt damping ``eta`` in bending, by the Galerkin method of the module
    docstring with ``K`` modes: a scan of $P \in [0.5, 30]$ in steps of 0.05 and 50 bisections
    of the sign of the spectral abscissa (beyond $10^{-13}$ of the largest $|p|$)."""
    S, G, F, M = _column_matrices(mass_ratio, K)
    Minv = np.linalg.inv(M)
    zero, one, damping = np.zeros((K, K)), np.eye(K), eta * Minv @ S

    def unstable(P):
        p = np.linalg.eigvals(np.block([[zero, one], [-Minv @ (S - P * G + P * F), -damping]]))
        return p.real.max() > 1e-13 * np.abs(p).max()

    return first_unstable(unstable, np.linspace(0.5, 30.0, 591), 50)
