"""SciPy's DOP853 step control in numba, shared by the two hand-written baselines,
``_numba_reference.py`` (one body) and ``_numba_lattice.py`` (a chain of bodies); independent of
rbo_jax (no JAX).

The constants of ``scipy.integrate._ivp.rk`` (safety 0.9, factors within [0.2, 10], exponent
−1/8 from DOP853's error-estimator order 7), ``select_initial_step`` (Hairer–Nørsett–Wanner
II.4, RMS norms), the minimum step ``10 |nextafter(t) − t|`` and the end-point clipping of
``RungeKutta._step_impl``, the error of ``DOP853._estimate_error_norm`` from its two squared
norms, and the step-size factor. Each baseline keeps its own stages and norms (the right-hand
sides and the layouts of the state differ). Slopes are rows of ``K`` read by index (no row
views built per call). Small functions that numba inlines into its callers: the same
arithmetic in the same order as written out there, hence the same bits.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy.integrate._ivp import dop853_coefficients as _dc

__all__ = [
    "ERROR_EXPONENT",
    "MAX_FACTOR",
    "MIN_FACTOR",
    "NS",
    "ORDER_INITIAL_STEP",
    "SAFETY",
    "clipped_step",
    "first_guess",
    "initial_step",
    "min_step",
    "step_error",
    "step_factor",
]

# scipy.integrate._ivp.rk constants and DOP853's error-estimator order (7): exponent -1/(7 + 1).
SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 10.0
ERROR_EXPONENT = -1.0 / 8.0
ORDER_INITIAL_STEP = 7.0
NS = int(_dc.N_STAGES)  # 12


@njit(cache=False)
def first_guess(y, K, n, rtol, atol, interval):
    """``select_initial_step``'s first guess h0 from y and f0 = K[0] (n scalars): (h0, d1)."""
    d0 = 0.0
    d1 = 0.0
    for i in range(n):
        sc = atol + abs(y[i]) * rtol
        d0 += (y[i] / sc) ** 2
        d1 += (K[0, i] / sc) ** 2
    d0 = math.sqrt(d0 / n)
    d1 = math.sqrt(d1 / n)
    h0 = 1e-6 if (d0 < 1e-5 or d1 < 1e-5) else 0.01 * d0 / d1
    return min(h0, interval), d1


@njit(cache=False)
def initial_step(y, K, n, rtol, atol, interval, h0, d1):
    """``select_initial_step``'s first |h| from f0 = K[0] and f1 = K[1] = f(y + h0 f0)."""
    d2 = 0.0
    for i in range(n):
        sc = atol + abs(y[i]) * rtol
        d2 += ((K[1, i] - K[0, i]) / sc) ** 2
    d2 = math.sqrt(d2 / n) / h0
    if d1 <= 1e-15 and d2 <= 1e-15:
        h1 = max(1e-6, h0 * 1e-3)
    else:
        h1 = (0.01 / max(d1, d2)) ** (1.0 / (ORDER_INITIAL_STEP + 1.0))
    return min(100.0 * h0, h1, interval)


@njit(cache=False)
def min_step(t):
    """The smallest step from t: 10 |nextafter(t) − t|."""
    return 10.0 * abs(np.nextafter(t, np.inf) - t)


@njit(cache=False)
def clipped_step(t, h_abs, t_bound):
    """The step of |h| = h_abs from t, its end clipped at t_bound: (t_new, h, |h|)."""
    t_new = t + h_abs
    if t_new > t_bound:
        t_new = t_bound
    h = t_new - t
    return t_new, h, abs(h)


@njit(cache=False)
def step_error(e5, e3, h_abs, n):
    """The error of a step of |h| = h_abs over n scalars from the squared norms e5, e3 of the
    5th- and 3rd-order estimates (``DOP853._estimate_error_norm``)."""
    if e5 == 0.0 and e3 == 0.0:
        return 0.0
    return h_abs * e5 / math.sqrt((e5 + 0.01 * e3) * n)


@njit(cache=False)
def step_factor(err, h_abs, step_rejected):
    """(accepted, the next |h|) of ``RungeKutta._step_impl`` for the error ``err`` of a step of
    |h| = h_abs (``step_rejected``: an attempt from this point was rejected already)."""
    if err < 1.0:
        if err == 0.0:
            factor = MAX_FACTOR
        else:
            factor = min(MAX_FACTOR, SAFETY * err**ERROR_EXPONENT)
        if step_rejected:
            factor = min(1.0, factor)
        return True, h_abs * factor
    return False, h_abs * max(MIN_FACTOR, SAFETY * err**ERROR_EXPONENT)
