r"""Initial states of nonlinear waves on a chain: the sine-Gordon kink and breather, and the
spinning twisted state of Kelvin's medium.

**Sine-Gordon.** Plane rotations $\theta_n = \varphi_n k$ of bodies with the foundation
$U = c(1 - \cos|\theta|)$ (:class:`rbo_jax.CosineFoundation`), coupled by a quadratic foundation
of the relative turn with torsional stiffness $\kappa$, obey exactly the discrete sine-Gordon
(Frenkel–Kontorova) chain

$$A_3\ddot\varphi_n = \kappa(\varphi_{n+1} - 2\varphi_n + \varphi_{n-1}) - c\sin\varphi_n,$$

whose continuum limit for $\lambda = \sqrt{\kappa/c} \gg 1$ (lengths in sites) has the kink
$\varphi = 4\arctan\exp\big((n - x_0 - vt)/(\lambda\sqrt{1 - v^2/s^2})\big)$, $s =
\sqrt{\kappa/A_3}$, of energy $8\sqrt{c\kappa}/\sqrt{1 - v^2/s^2}$, and the breather
$\varphi = 4\arctan\big(\tan\mu\,\sin(\omega t)/\cosh((n - x_0)\sin\mu/\lambda)\big)$ with
$\omega = \sqrt{c/A_3}\cos\mu$, of energy $16\sqrt{c\kappa}\sin\mu$.

**Kelvin's medium** (no foundation): the uniform twist with uniform spin,
$\theta_n = (nq + \Omega t)k$ with $q = 2\pi m/N$ on a periodic chain, is an exact solution: every
relative turn is $qk$, whose moments on a body from its two neighbours cancel.
"""

from __future__ import annotations

import numpy as np

__all__ = ["breather", "kink", "twist"]


def _states(phi, dphi, k):
    k = np.asarray(k, dtype=float)
    k = k / np.linalg.norm(k)
    return np.asarray(phi)[:, None] * k, np.asarray(dphi)[:, None] * k


def kink(
    n: int,
    c: float,
    kappa: float,
    A3: float,
    *,
    x0: float,
    v: float = 0.0,
    k=(0.0, 0.0, 1.0),
    anti: bool = False,
):
    r"""``(theta0 (n, 3), Omega0 (n, 3))`` of the sine-Gordon kink (module docstring) centred at
    site ``x0`` moving at ``v`` sites per unit time ($|v| < s = \sqrt{\kappa/A_3}$): the turn
    rises by $2\pi$ along the chain (falls, with ``anti``). For plane rotations about ``k``,
    $\Omega = \dot\varphi\,k$."""
    s = np.sqrt(kappa / A3)
    if not abs(v) < s:
        raise ValueError(
            f"lattice.kink: |v| must be below the speed of sound s = "
            f"sqrt(kappa/A3) = {s:g}, got {v!r}."
        )
    width = np.sqrt(kappa / c) * np.sqrt(1.0 - (v / s) ** 2)
    xi = (np.arange(n) - x0) / width
    sign = -1.0 if anti else 1.0
    phi = 4.0 * np.arctan(np.exp(sign * xi))
    dphi = -sign * 2.0 / np.cosh(xi) * v / width
    return _states(phi, dphi, k)


def breather(n: int, c: float, kappa: float, A3: float, *, x0: float, mu: float, k=(0.0, 0.0, 1.0)):
    r"""``(theta0, Omega0)`` of the sine-Gordon breather (module docstring) at rest at site
    ``x0``, at $t = 0$ (all turns zero, the velocities at their largest), $0 < \mu < \pi/2$:
    frequency $\sqrt{c/A_3}\cos\mu$, amplitude $4\arctan(\tan\mu)$ = $4\mu$ at the centre."""
    if not 0.0 < mu < np.pi / 2:
        raise ValueError(f"lattice.breather: mu must lie in (0, pi/2), got {mu!r}.")
    lam = np.sqrt(kappa / c)
    omega = np.sqrt(c / A3) * np.cos(mu)
    envelope = np.tan(mu) / np.cosh((np.arange(n) - x0) * np.sin(mu) / lam)
    return _states(np.zeros(n), 4.0 * envelope * omega, k)


def twist(n: int, m: int, Omega: float, *, k=(0.0, 0.0, 1.0)):
    r"""``(theta0, Omega0)`` of Kelvin's spinning twisted state on a periodic chain of ``n``
    bodies: $\theta_j = \varphi_j k$ with $\varphi_j = 2\pi m j/n$ taken in $(-\pi, \pi]$, and
    $\Omega_j = \Omega k$; the exact solution is $\varphi_j(t) = \varphi_j + \Omega t$."""
    phi = np.angle(np.exp(2j * np.pi * m * np.arange(n) / n))
    return _states(phi, np.full(n, float(Omega)), k)
