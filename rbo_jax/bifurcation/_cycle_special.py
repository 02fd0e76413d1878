r"""Special points along a branch of limit cycles: folds, period doubling and Neimark–Sacker.

Between two consecutive cycles $u_i$, $u_{i+1}$ of the branch (:mod:`._cycles`):

- **fold** (saddle-node of cycles): the parameter component of the branch's unit tangent (the
  null vector of the shooting Jacobian $G_y$, oriented along the branch) changes sign; located
  exactly by :func:`._cycle_fold.fold_of_cycles` from the linear interpolation of the two cycles
  at the zero of that component;
- **period doubling**: a real negative multiplier leaves or enters the unit circle (through
  $-1$);
- **Neimark–Sacker**: a complex pair crosses $|\mu| = 1$.

The last two compare the nontrivial multipliers of the two cycles (:func:`multiplier_crossings`:
the number of multipliers outside the unit circle in each class; a pair that collides outside
the circle and moves between the classes is no crossing) and are located by linear
interpolation of $\log|\mu|$ of the crossing multiplier, the one of its class nearest the unit
circle, in the arclength (hence in the parameter along the chord).
"""

from __future__ import annotations

import numpy as np

from ..continuation import crossing, sign_changes

__all__ = ["multiplier_crossings", "detect", "fold_guess"]

IMAG_TOL = 1e-7  # a multiplier with |Im mu| <= IMAG_TOL max(1, |mu|) is real


def _classes(mu, imag_tol):
    mu = np.asarray(mu, dtype=complex)
    real = np.abs(mu.imag) <= imag_tol * np.maximum(1.0, np.abs(mu))
    return {"period_doubling": mu[real & (mu.real < 0)], "neimark_sacker": mu[~real]}


def _outside(mu):
    return int(np.sum(np.abs(mu) > 1.0))


def _nearest_log_modulus(mu):
    logs = np.log(np.abs(mu))
    return float(logs[np.argmin(np.abs(logs))])


def multiplier_crossings(mu0, mu1, *, imag_tol: float = IMAG_TOL) -> list[tuple[str, float]]:
    r"""The crossings of the unit circle between two sets of nontrivial Floquet multipliers
    (the trivial multiplier 1 left out), as ``[(kind, w)]``: ``kind`` ``"period_doubling"`` (a
    real negative multiplier through $-1$) or ``"neimark_sacker"`` (a complex pair through
    $|\mu| = 1$), ``w`` in $[0, 1]$ the fraction of the way from the first set to the second at
    which $\log|\mu|$ of the crossing multiplier, interpolated linearly, vanishes. Real
    positive multipliers (folds, branch points) are not reported. Empty if either set holds a
    non-finite value. A pure function of its arguments."""
    mu0, mu1 = np.asarray(mu0, dtype=complex), np.asarray(mu1, dtype=complex)
    if not (np.all(np.isfinite(mu0)) and np.all(np.isfinite(mu1))):
        return []
    c0, c1 = _classes(mu0, imag_tol), _classes(mu1, imag_tol)
    change = {k: _outside(c1[k]) - _outside(c0[k]) for k in c0}
    collision = sum(change.values()) == 0  # moved between the classes outside the circle
    out = []
    for kind, d in change.items():
        if d == 0 or collision:
            continue
        w = 0.5
        if c0[kind].size and c1[kind].size:
            l0, l1 = _nearest_log_modulus(c0[kind]), _nearest_log_modulus(c1[kind])
            if l0 * l1 <= 0 and l0 != l1:
                w = l0 / (l0 - l1)
        out.append((kind, float(np.clip(w, 0.0, 1.0))))
    return out


def detect(rows, parameter_index: int = 7) -> list[tuple[str, float, int]]:
    """``[(kind, value, index)]`` along the branch ``rows`` (``(u, tangent, nontrivial
    multipliers)`` per cycle; the Hopf point, row 0, is skipped): folds from the tangent's
    parameter component (value: its linear zero, refined by the caller), period doubling and
    Neimark–Sacker from :func:`multiplier_crossings`; ``index`` the cycle before the point."""
    alpha = [float(u[parameter_index]) for u, _, _ in rows]
    slope = [float(t[parameter_index]) for _, t, _ in rows]
    special = [("fold", float(crossing(slope[i], slope[i + 1], alpha[i], alpha[i + 1])[0]), i)
               for i in sign_changes(slope) if i >= 1]  # fmt: skip
    for i in range(1, len(rows) - 1):
        for kind, w in multiplier_crossings(rows[i][2], rows[i + 1][2]):
            special.append((kind, alpha[i] + w * (alpha[i + 1] - alpha[i]), i))
    return sorted(special, key=lambda s: s[2])


def fold_guess(rows, index: int, parameter_index: int = 7):
    """The linear interpolation of cycles ``index`` and ``index + 1`` at the zero of the
    tangent's parameter component (the starting point of the fold's Newton solve)."""
    (u0, t0, _), (u1, t1, _) = rows[index], rows[index + 1]
    return crossing(float(t0[parameter_index]), float(t1[parameter_index]), u0, u1)[0]
