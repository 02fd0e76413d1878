r"""Special points along a curve, from test functions at consecutive points.

- A **sign change** of a test function between two points (:func:`sign_changes`): the
  parameter component of the tangent at a fold (a limit point of equilibria, a turning point
  of the Hopf boundary, a fold of cycles), the bordered determinant at a branch point, the
  first Lyapunov coefficient at a Bautin point.
- Its **crossing** by linear interpolation along the chord (:func:`crossing`, error $O(s^2)$),
  or, for a fold, the **vertex of the parabola** through three points around it
  (:func:`parabola_vertex`, the arclength $\sigma$ measured along the chords: error $O(s^3)$).
"""

from __future__ import annotations

import numpy as np

__all__ = ["crossing", "parabola_vertex", "sign_changes"]


def sign_changes(values) -> list[int]:
    """The indices ``i`` where ``values[i]`` and ``values[i + 1]`` have opposite signs."""
    v = np.asarray(values, dtype=float)
    return [i for i in range(len(v) - 1) if v[i] * v[i + 1] < 0]


def crossing(f0: float, f1: float, x0, x1):
    """Where the line through ``(0, f0)``, ``(1, f1)`` vanishes, applied to ``x0 → x1``: the
    interpolated value and the weight (0 at ``x0``, 1 at ``x1``)."""
    w = float(f0 / (f0 - f1)) if f0 != f1 else 1.0
    return np.asarray(x0) + w * (np.asarray(x1) - np.asarray(x0)), w


def parabola_vertex(sigma, values, others=()):
    """The vertex of the parabola through ``(sigma, values)`` (three points) and the other
    quantities ``others`` (each three values) on their parabolas there; ``None`` where the
    vertex is not between the first and last points (or the three are on a line)."""
    sigma = np.asarray(sigma, dtype=float)
    a, b, c = np.polyfit(sigma, np.asarray(values, dtype=float), 2)
    if a == 0:
        return None
    at = -b / (2 * a)
    if not sigma[0] <= at <= sigma[-1]:
        return None
    fitted = [float(np.polyval(np.polyfit(sigma, np.asarray(o, float), 2), at)) for o in others]
    return float(c - b * b / (4 * a)), fitted
