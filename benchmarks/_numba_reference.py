"""A numba-compiled per-trajectory DOP853 solver of the Nikolai problem: the "performance-minded
user's own solver" baseline of the simulation benchmarks, independent of rbo_jax (no JAX).

* Right-hand side: the ODE of ``_numpy_reference.numpy_rhs`` ((4.55)-(4.56), quadratic
  foundation (4.50), follower moment (4.57)) in scalar code, no allocations; Z and Zᵀ are applied
  as ``v ∓ ½ θ×v + g (θ(θ·v) − |θ|² v)`` instead of being formed.
* Integrator: explicit Runge–Kutta of order 8 with scipy's DOP853 tableau and its combined 5th/3rd
  order error estimator, read from ``scipy.integrate._ivp.dop853_coefficients`` at import
  (nothing copied); the step-size controller, the initial-step selection (Hairer–Nørsett–Wanner
  II.4), the minimum step and the end-point clipping are those of ``scipy.integrate.solve_ivp``
  (``RungeKutta._step_impl``, ``select_initial_step``; in ``_numba_dop853.py``, shared with
  ``_numba_lattice.py``), so with the same rtol/atol it takes the
  same steps as ``solve_ivp(method="DOP853")`` (up to the rounding of the dot products) and
  ``nfev`` counts the same evaluations (2 + 12 per attempted step). Forward integration only,
  final state only (no dense output).
* Drivers: one compiled loop over the parameter points, compiled twice: serial (``njit``, one
  core) and ``njit(parallel=True)`` with ``prange`` over the points (all cores numba sees).

The K array (13×6) and the work vectors are allocated once per trajectory, not per step.
"""

from __future__ import annotations

import math
import os
import time

# numba's prange threads (GNU OpenMP here) wait for the next parallel region by spinning on
# every core after a region ends, which took ~2 us a trajectory (20 %) from the JAX call timed
# next to it in the same process; passive waiting left prange's own time unchanged (14.0-14.5 us
# a trajectory, 2 cores) and stops the interference (benchmarks/README.md, History). A user's
# own OMP_WAIT_POLICY is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import _numba_dop853 as dop  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402
from numba import njit, prange  # noqa: E402
from scipy.integrate._ivp import dop853_coefficients as _dc  # noqa: E402

__all__ = ["NUMBA_VERSION", "solve_points_serial", "solve_points_parallel", "timed_solve"]

NUMBA_VERSION = numba.__version__

# scipy's DOP853 tableau (12 stages; E3 and E5 act on the 13 rows of K, the last being f(t + h)),
# read from scipy at import. The njit functions see these module globals as compile-time
# constants (numba freezes global arrays), as are the sizes: the stage loops unroll and the zero
# coefficients fold away (40 → 37 µs per trajectory in a best-of-7 test against passing the arrays
# as arguments; bitwise the same results).
NS = dop.NS  # 12 stages
NY = 6
TABLEAU_A, TABLEAU_B, TABLEAU_E3, TABLEAU_E5 = (
    np.ascontiguousarray(x, dtype=np.float64) for x in (_dc.A[:NS, :NS], _dc.B, _dc.E3, _dc.E5)
)
assert TABLEAU_A.shape == (NS, NS) and TABLEAU_B.shape == (NS,) and TABLEAU_E5.shape == (NS + 1,)


@njit(cache=False)
def rhs(y, out, row, c, d, M, Am, Ai, k):
    """``numpy_rhs`` in scalar form: y = (θ, Ω) → out[row] = (Zᵀ Ω, A⁻¹(M k − Z ∇U − Ω × AΩ))
    (a row index rather than a row view: no array struct built per call; 49 → 40 µs per
    trajectory in a best-of-7 test)."""
    t0, t1, t2 = y[0], y[1], y[2]
    w0, w1, w2 = y[3], y[4], y[5]
    # Z's coefficient g as numpy_rhs has it, in scalar math (the NumPy baseline needs no numba)
    th2 = t0 * t0 + t1 * t1 + t2 * t2
    th = math.sqrt(th2)
    if th < 1e-4:
        g = 1.0 / 12.0 + th2 / 720.0
    else:
        gg = th * math.sin(th) / (2.0 * (1.0 - math.cos(th)))
        g = (1.0 - gg) / th2
    # θ̇ = Zᵀ Ω = Ω + ½ θ×Ω + g (θ (θ·Ω) − |θ|² Ω)
    tw = t0 * w0 + t1 * w1 + t2 * w2
    out[row, 0] = w0 + 0.5 * (t1 * w2 - t2 * w1) + g * (t0 * tw - th2 * w0)
    out[row, 1] = w1 + 0.5 * (t2 * w0 - t0 * w2) + g * (t1 * tw - th2 * w1)
    out[row, 2] = w2 + 0.5 * (t0 * w1 - t1 * w0) + g * (t2 * tw - th2 * w2)
    # ∇U of (4.50): c θ + (d − c)(k·θ) k; Z ∇U = u − ½ θ×u + g (θ (θ·u) − |θ|² u)
    k0, k1, k2 = k[0], k[1], k[2]
    kt = (d - c) * (k0 * t0 + k1 * t1 + k2 * t2)
    u0, u1, u2 = c * t0 + kt * k0, c * t1 + kt * k1, c * t2 + kt * k2
    tu = t0 * u0 + t1 * u1 + t2 * u2
    z0 = u0 - 0.5 * (t1 * u2 - t2 * u1) + g * (t0 * tu - th2 * u0)
    z1 = u1 - 0.5 * (t2 * u0 - t0 * u2) + g * (t1 * tu - th2 * u1)
    z2 = u2 - 0.5 * (t0 * u1 - t1 * u0) + g * (t2 * tu - th2 * u2)
    # A Ω and Ω × AΩ
    a0 = Am[0, 0] * w0 + Am[0, 1] * w1 + Am[0, 2] * w2
    a1 = Am[1, 0] * w0 + Am[1, 1] * w1 + Am[1, 2] * w2
    a2 = Am[2, 0] * w0 + Am[2, 1] * w1 + Am[2, 2] * w2
    r0 = M * k0 - z0 - (w1 * a2 - w2 * a1)
    r1 = M * k1 - z1 - (w2 * a0 - w0 * a2)
    r2 = M * k2 - z2 - (w0 * a1 - w1 * a0)
    out[row, 3] = Ai[0, 0] * r0 + Ai[0, 1] * r1 + Ai[0, 2] * r2
    out[row, 4] = Ai[1, 0] * r0 + Ai[1, 1] * r1 + Ai[1, 2] * r2
    out[row, 5] = Ai[2, 0] * r0 + Ai[2, 1] * r1 + Ai[2, 2] * r2


@njit(cache=False)
def dop853_final(y0, t0, t_bound, rtol, atol, c, d, M, Am, Ai, k):
    """Integrate from t0 to t_bound > t0 as ``solve_ivp(method="DOP853")``; returns
    (final y, accepted steps, rejected steps, nfev, status: 0 ok, -1 step size too small).

    K[0] holds f(t, y) between steps (scipy's ``self.f``), K[ns] the f of the new point."""
    n = NY
    ns = NS
    A = TABLEAU_A
    B = TABLEAU_B
    E3 = TABLEAU_E3
    E5 = TABLEAU_E5
    K = np.empty((ns + 1, n))
    y = y0.copy()
    y_new = np.empty(n)
    ytmp = np.empty(n)
    rhs(y, K, 0, c, d, M, Am, Ai, k)
    nfev = 1

    # Initial step: scipy.integrate._ivp.common.select_initial_step (RMS norms).
    interval = abs(t_bound - t0)
    h0, d1 = dop.first_guess(y, K, n, rtol, atol, interval)
    for i in range(n):
        ytmp[i] = y[i] + h0 * K[0, i]
    rhs(ytmp, K, 1, c, d, M, Am, Ai, k)  # f1, in K[1] as scratch
    nfev += 1
    h_abs = dop.initial_step(y, K, n, rtol, atol, interval, h0, d1)

    t = t0
    accepted = 0
    rejected = 0
    status = 0
    # RungeKutta._step_impl's loop, as in _numba_lattice.py around its own stages and norm; the
    # step control is shared (_numba_dop853), a shared loop would take the stages as a function
    while t < t_bound:
        h_min = dop.min_step(t)
        if h_abs < h_min:
            h_abs = h_min
        step_rejected = False
        while True:
            if h_abs < h_min:
                status = -1
                break
            t_new, h, h_abs = dop.clipped_step(t, h_abs, t_bound)
            # stages (scipy.integrate._ivp.rk.rk_step; the RHS is autonomous, C is not needed)
            for s in range(1, ns):
                for i in range(n):
                    acc = 0.0
                    for j in range(s):
                        acc += K[j, i] * A[s, j]
                    ytmp[i] = y[i] + acc * h
                rhs(ytmp, K, s, c, d, M, Am, Ai, k)
            for i in range(n):
                acc = 0.0
                for j in range(ns):
                    acc += K[j, i] * B[j]
                y_new[i] = y[i] + h * acc
            rhs(y_new, K, ns, c, d, M, Am, Ai, k)
            nfev += ns
            # error norm (DOP853._estimate_error_norm)
            e5 = 0.0
            e3 = 0.0
            for i in range(n):
                sc = atol + max(abs(y[i]), abs(y_new[i])) * rtol
                s5 = 0.0
                s3 = 0.0
                for j in range(ns + 1):
                    s5 += K[j, i] * E5[j]
                    s3 += K[j, i] * E3[j]
                e5 += (s5 / sc) ** 2
                e3 += (s3 / sc) ** 2
            err = dop.step_error(e5, e3, h_abs, n)
            accepted_step, h_abs = dop.step_factor(err, h_abs, step_rejected)
            if accepted_step:
                break
            step_rejected = True
            rejected += 1
        if status != 0:
            break
        accepted += 1
        t = t_new
        for i in range(n):
            y[i] = y_new[i]
            K[0, i] = K[ns, i]
    return y, accepted, rejected, nfev, status


def _solve_points(points, t1, rtol, atol, perturbation, Am, Ai, k):
    """Final states of the benchmark problem at each (c, d, M) row of ``points``: start
    θ = (M/d)k + perturbation, Ω = 0, t ∈ [0, t1]; inertia ``Am`` (3×3), its inverse ``Ai``, axis
    ``k``. Returns (y (n, 6), accepted steps, nfev, status) per point."""
    n = points.shape[0]
    out = np.empty((n, 6))
    nfev = np.empty(n, dtype=np.int64)
    steps = np.empty(n, dtype=np.int64)
    status = np.empty(n, dtype=np.int64)
    for p in prange(n):
        c, d, M = points[p, 0], points[p, 1], points[p, 2]
        y0 = np.zeros(6)
        for i in range(3):
            y0[i] = (M / d) * k[i] + perturbation[i]
        y, acc, rej, nf, st = dop853_final(y0, 0.0, t1, rtol, atol, c, d, M, Am, Ai, k)
        for i in range(6):
            out[p, i] = y[i]
        nfev[p] = nf
        steps[p] = acc
        status[p] = st
    return out, steps, nfev, status


# One source, two compilations: in a serial njit function prange is range.
solve_points_serial = njit(cache=False)(_solve_points)
solve_points_parallel = njit(cache=False, parallel=True)(_solve_points)


def timed_solve(points, parallel, t1, rtol, atol, perturbation, Am, Ai, k):
    """Compile (a first call on one point, timed alone: JIT of the driver and, on the first
    driver compiled, of the shared rhs/dop853_final), then solve every point (timed).
    Returns a dict: y, steps (accepted), nfev, status, seconds, compile_s, threads, and
    already_compiled (the driver was compiled by an earlier call in this process: compile_s is
    then only the dispatch of the first call)."""
    fn = solve_points_parallel if parallel else solve_points_serial
    already_compiled = bool(fn.signatures)
    args = (
        float(t1),
        float(rtol),
        float(atol),
        np.ascontiguousarray(perturbation, dtype=float),
        np.ascontiguousarray(Am, dtype=float),
        np.ascontiguousarray(Ai, dtype=float),
        np.ascontiguousarray(k, dtype=float),
    )
    points = np.ascontiguousarray(points, dtype=float)
    t0 = time.perf_counter()
    fn(points[:1], *args)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    y, steps, nfev, status = fn(points, *args)
    seconds = time.perf_counter() - t0
    return {
        "y": y,
        "steps": steps,
        "nfev": nfev,
        "status": status,
        "seconds": seconds,
        "compile_s": compile_s,
        "already_compiled": already_compiled,
        "threads": numba.get_num_threads() if parallel else 1,
    }
