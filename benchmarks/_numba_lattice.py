"""A numba-compiled DOP853 for a periodic chain of N rigid body oscillators: the "performance-minded
user's own solver" baseline of ``bench_lattice.py``, independent of rbo_jax (no JAX).

* System: N bodies on a ring, body i coupled to i − 1 and i + 1; the state is 6N numbers,
  component-major like rbo_jax's lattice solver: ``y = (θx[0:N], θy, θz, Ωx, Ωy, Ωz)``.
* Right-hand side: every body obeys the right form (4.55)–(4.56),
  ``θ̇ = Zᵀ(θ)·Ω``, ``Ω̇ = A⁻¹(M − Ω × AΩ)``, with the body-frame moment
  ``M = −Z(θ)·(cθ + (d − c)(k·θ)k) + (couplings) + M_load k`` (quadratic foundation (4.50),
  follower moment (4.57)). A coupled pair (i, j = i + 1) has the relative turn
  ``φ = log(conj(q_i)·q_j)`` (unit quaternions, principal logarithm) and the energy
  ``W(φ) = ½κ_b(φ² − (k·φ)²) + ½κ_t(k·φ)²``; with ``u = ∇W(φ)`` body i takes ``Zᵀ(φ)·u`` and
  body j ``−Z(φ)·u``, each in its own frame (rbo_jax's ``lattice._field.coupling_moments``).
  Z and Zᵀ are applied as ``v ∓ ½ θ×v + g (θ(θ·v) − |θ|² v)``, ``g = (1 − (θ/2)cot(θ/2))/θ²``,
  never formed. One fused pass over the bodies (a stencil): each body's quaternion and Z
  coefficient are computed once per evaluation (its cos/sin serve both), each pair's relative
  turn once, the pair's moment on the next body carried to the next iteration; no temporaries.
  ``math`` functions (sqrt, cos, sin, atan2) with Taylor branches only for small arguments
  (|θ|² < 1e-4 and (|v|/w)² < 1e-4 in the logarithm), where they are exact to rounding.
* Integrator: scipy's DOP853 on the whole 6N system — the tableau and error-estimator
  coefficients read from ``scipy.integrate._ivp.dop853_coefficients`` at import, the error norm
  ``DOP853._estimate_error_norm`` (RMS over all 6N scalars), SciPy's step-size controller
  (safety 0.9, factors within [0.2, 10], exponent −1/8), ``select_initial_step``, the minimum
  step ``10 |nextafter(t) − t|`` and the end-point clipping (``RungeKutta._step_impl``; the
  step control in ``_numba_dop853.py``): the
  steps of ``solve_ivp(method="DOP853")`` on the flattened system, and of
  ``rbo_jax.lattice.simulate(method="dop853")``. The stages are summed through the non-zero
  tableau entries only, in column order (SciPy's order; the zeros it adds are exact). Forward
  integration, final state only (no dense output). Same style as ``_numba_reference.py`` (one
  body), with which it shares the step control (``_numba_dop853.py``).

Work arrays (the 13 slopes, 13 × 6N numbers) are allocated once per solve.
"""

from __future__ import annotations

import math
import time

import _numba_dop853 as dop
import numba
import numpy as np
from numba import njit
from scipy.integrate._ivp import dop853_coefficients as _dc

__all__ = ["NUMBA_VERSION", "dop853_chain", "chain_rhs", "solve_chain"]

NUMBA_VERSION = numba.__version__

NS = dop.NS  # 12 stages
NC = 6  # state components per body


def _sparse(rows):
    """Column indices, coefficients and counts of the non-zero entries of each row (column
    order), padded with zeros: three NumPy arrays (numba freezes them as constants)."""
    rows = np.atleast_2d(np.asarray(rows, dtype=np.float64))
    width = max(1, max(int(np.count_nonzero(r)) for r in rows))
    cols = np.zeros((rows.shape[0], width), np.int64)
    coefs = np.zeros((rows.shape[0], width))
    nnz = np.zeros(rows.shape[0], np.int64)
    for s, r in enumerate(rows):
        idx = np.flatnonzero(r)
        cols[s, : idx.size], coefs[s, : idx.size], nnz[s] = idx, r[idx], idx.size
    return cols, coefs, nnz


A_COLS, A_COEFS, A_NNZ = _sparse(_dc.A[:NS, :NS])
B_COLS, B_COEFS, B_NNZ = _sparse(_dc.B)
E5_COLS, E5_COEFS, E5_NNZ = _sparse(_dc.E5)
E3_COLS, E3_COEFS, E3_NNZ = _sparse(_dc.E3)

SMALL_T = 1e-4  # |θ|² below which the Taylor branches are used
SMALL_X2 = 1e-4  # (|v|/w)² below which atan(x)/x is its Taylor polynomial


# ---------------------------------------------------------------------------------------------
# Right-hand side.
# ---------------------------------------------------------------------------------------------


@njit(cache=False)
def _turn(t0, t1, t2):
    """(|θ|², w = cos(|θ|/2), s = sin(|θ|/2)/|θ|, g = (1 − (|θ|/2)cot(|θ|/2))/|θ|²): the
    quaternion (w, s θ) and Z's coefficient of θ, from one cos and one sin."""
    t = t0 * t0 + t1 * t1 + t2 * t2
    if t < SMALL_T:
        x = 0.25 * t  # (|θ|/2)²
        w = 1.0 - x * (0.5 - x * (1.0 / 24.0 - x * (1.0 / 720.0)))
        s = 0.5 * (1.0 - x * (1.0 / 6.0 - x * (1.0 / 120.0 - x * (1.0 / 5040.0))))
        g = 1.0 / 12.0 + t * (1.0 / 720.0 + t * (1.0 / 30240.0 + t * (1.0 / 1209600.0)))
        return t, w, s, g
    th = math.sqrt(t)
    h = 0.5 * th
    ch = math.cos(h)
    sh = math.sin(h)
    return t, ch, sh / th, (1.0 - h * ch / sh) / t


@njit(cache=False)
def _gcoef(t):
    """(1 − (θ/2)cot(θ/2))/θ² of t = θ²."""
    if t < SMALL_T:
        return 1.0 / 12.0 + t * (1.0 / 720.0 + t * (1.0 / 30240.0 + t * (1.0 / 1209600.0)))
    h = 0.5 * math.sqrt(t)
    return (1.0 - h / math.tan(h)) / t


@njit(cache=False)
def _pair(wi, a0, a1, a2, wj, b0, b1, b2, kb, kt, k0, k1, k2):
    """The coupling moments of the pair (i, j) with quaternions (wi, a), (wj, b): (on i in its
    frame, Zᵀ(φ)·∇W(φ); on j in its frame, −Z(φ)·∇W(φ)), φ = log(conj(q_i) q_j)."""
    # conj(q_i)·q_j = (wi wj + a·b, wi b − wj a − a×b)
    w = wi * wj + (a0 * b0 + a1 * b1 + a2 * b2)
    v0 = (wi * b0 - wj * a0) - (a1 * b2 - a2 * b1)
    v1 = (wi * b1 - wj * a1) - (a2 * b0 - a0 * b2)
    v2 = (wi * b2 - wj * a2) - (a0 * b1 - a1 * b0)
    # principal logarithm: φ = 2 atan2(|v|, w)/|v| v with w >= 0
    if w < 0.0:
        w, v0, v1, v2 = -w, -v0, -v1, -v2
    s2 = v0 * v0 + v1 * v1 + v2 * v2
    if s2 < SMALL_X2 * w * w:
        x2 = s2 / (w * w)
        f = (1.0 - x2 * (1.0 / 3.0 - x2 * (0.2 - x2 * (1.0 / 7.0 - x2 * (1.0 / 9.0))))) / w
    else:
        s = math.sqrt(s2)
        f = math.atan2(s, w) / s
    f *= 2.0
    p0, p1, p2 = f * v0, f * v1, f * v2
    # ∇W(φ) = κ_b φ + (κ_t − κ_b)(k·φ) k
    kp = (kt - kb) * (k0 * p0 + k1 * p1 + k2 * p2)
    u0, u1, u2 = kb * p0 + kp * k0, kb * p1 + kp * k1, kb * p2 + kp * k2
    tp = p0 * p0 + p1 * p1 + p2 * p2
    g = _gcoef(tp)
    pu = p0 * u0 + p1 * u1 + p2 * u2
    r0, r1, r2 = g * (p0 * pu - tp * u0), g * (p1 * pu - tp * u1), g * (p2 * pu - tp * u2)
    c0, c1, c2 = 0.5 * (p1 * u2 - p2 * u1), 0.5 * (p2 * u0 - p0 * u2), 0.5 * (p0 * u1 - p1 * u0)
    return (
        (u0 + c0) + r0,
        (u1 + c1) + r1,
        (u2 + c2) + r2,
        -((u0 - c0) + r0),
        -((u1 - c1) + r1),
        -((u2 - c2) + r2),
    )


@njit(cache=False)
def chain_rhs(y, out, n, c, d, M, kb, kt, Am, Ai, k):
    """out = f(y) for the periodic chain (module docstring), y and out flat, component-major
    (6n,). One pass over the bodies; pair (i, i+1) is evaluated at body i, and its moment on
    body i+1 carried to the next iteration (the wrapped pair (n−1, 0) first, for body 0)."""
    k0, k1, k2 = k[0], k[1], k[2]
    # body 0's turn, and the wrapped pair (n-1, 0): its moment on body 0
    t_0, w_0, s_0, g_0 = _turn(y[0], y[n], y[2 * n])
    j = n - 1
    _, w_l, s_l, _ = _turn(y[j], y[n + j], y[2 * n + j])
    _, _, _, m0, m1, m2 = _pair(
        w_l,
        s_l * y[j],
        s_l * y[n + j],
        s_l * y[2 * n + j],
        w_0,
        s_0 * y[0],
        s_0 * y[n],
        s_0 * y[2 * n],
        kb,
        kt,
        k0,
        k1,
        k2,
    )
    ti, wi, si, gi = t_0, w_0, s_0, g_0
    for i in range(n):
        j = i + 1 if i + 1 < n else 0
        th0, th1, th2 = y[i], y[n + i], y[2 * n + i]
        om0, om1, om2 = y[3 * n + i], y[4 * n + i], y[5 * n + i]
        if j == 0:
            tj, wj, sj, gj = t_0, w_0, s_0, g_0
        else:
            tj, wj, sj, gj = _turn(y[j], y[n + j], y[2 * n + j])
        a0, a1, a2, b0, b1, b2 = _pair(
            wi,
            si * th0,
            si * th1,
            si * th2,
            wj,
            sj * y[j],
            sj * y[n + j],
            sj * y[2 * n + j],
            kb,
            kt,
            k0,
            k1,
            k2,
        )
        # couplings on body i: pair (i, i+1) and the carried pair (i-1, i)
        q0, q1, q2 = a0 + m0, a1 + m1, a2 + m2
        m0, m1, m2 = b0, b1, b2
        # foundation: u = c θ + (d − c)(k·θ) k; moment −Z(θ)·u
        kt_ = (d - c) * (k0 * th0 + k1 * th1 + k2 * th2)
        u0, u1, u2 = c * th0 + kt_ * k0, c * th1 + kt_ * k1, c * th2 + kt_ * k2
        tu = th0 * u0 + th1 * u1 + th2 * u2
        z0 = (u0 - 0.5 * (th1 * u2 - th2 * u1)) + gi * (th0 * tu - ti * u0)
        z1 = (u1 - 0.5 * (th2 * u0 - th0 * u2)) + gi * (th1 * tu - ti * u1)
        z2 = (u2 - 0.5 * (th0 * u1 - th1 * u0)) + gi * (th2 * tu - ti * u2)
        e0, e1, e2 = (-z0 + q0) + M * k0, (-z1 + q1) + M * k1, (-z2 + q2) + M * k2
        # Ω̇ = A⁻¹(M − Ω × AΩ)
        x0 = Am[0, 0] * om0 + Am[0, 1] * om1 + Am[0, 2] * om2
        x1 = Am[1, 0] * om0 + Am[1, 1] * om1 + Am[1, 2] * om2
        x2 = Am[2, 0] * om0 + Am[2, 1] * om1 + Am[2, 2] * om2
        r0 = e0 - (om1 * x2 - om2 * x1)
        r1 = e1 - (om2 * x0 - om0 * x2)
        r2 = e2 - (om0 * x1 - om1 * x0)
        out[3 * n + i] = Ai[0, 0] * r0 + Ai[0, 1] * r1 + Ai[0, 2] * r2
        out[4 * n + i] = Ai[1, 0] * r0 + Ai[1, 1] * r1 + Ai[1, 2] * r2
        out[5 * n + i] = Ai[2, 0] * r0 + Ai[2, 1] * r1 + Ai[2, 2] * r2
        # θ̇ = Zᵀ(θ)·Ω
        tw = th0 * om0 + th1 * om1 + th2 * om2
        out[i] = (om0 + 0.5 * (th1 * om2 - th2 * om1)) + gi * (th0 * tw - ti * om0)
        out[n + i] = (om1 + 0.5 * (th2 * om0 - th0 * om2)) + gi * (th1 * tw - ti * om1)
        out[2 * n + i] = (om2 + 0.5 * (th0 * om1 - th1 * om0)) + gi * (th2 * tw - ti * om2)
        ti, wi, si, gi = tj, wj, sj, gj


# ---------------------------------------------------------------------------------------------
# DOP853 on the whole chain.
# ---------------------------------------------------------------------------------------------


@njit(cache=False)
def _combine(K, s, y, h, out):
    """out = y + h Σ_m A[s, cols[m]] K[cols[m]] (row s of the tableau, non-zeros in order)."""
    nnz = A_NNZ[s]
    for idx in range(y.shape[0]):
        acc = 0.0
        for m in range(nnz):
            acc += K[A_COLS[s, m], idx] * A_COEFS[s, m]
        out[idx] = y[idx] + acc * h


@njit(cache=False)
def dop853_chain(y0, t0, t_bound, rtol, atol, n, c, d, M, kb, kt, Am, Ai, k):
    """Integrate the chain from t0 to t_bound > t0 as ``solve_ivp(method="DOP853")`` on the 6n
    system; returns (final y, accepted steps, rejected steps, nfev, status: 0 ok, -1 step size
    too small). K[0] holds f(t, y) between steps, K[NS] the f of the new point."""
    size = y0.shape[0]
    ns = NS
    K = np.empty((ns + 1, size))
    y = y0.copy()
    y_new = np.empty(size)
    ytmp = np.empty(size)
    chain_rhs(y, K[0], n, c, d, M, kb, kt, Am, Ai, k)
    nfev = 1

    # Initial step: scipy.integrate._ivp.common.select_initial_step (RMS norms over 6n).
    interval = abs(t_bound - t0)
    h0, d1 = dop.first_guess(y, K, size, rtol, atol, interval)
    for i in range(size):
        ytmp[i] = y[i] + h0 * K[0, i]
    chain_rhs(ytmp, K[1], n, c, d, M, kb, kt, Am, Ai, k)  # f1, in K[1] as scratch
    nfev += 1
    h_abs = dop.initial_step(y, K, size, rtol, atol, interval, h0, d1)

    t = t0
    accepted = 0
    rejected = 0
    status = 0
    t_new = t
    # RungeKutta._step_impl's loop, as in _numba_reference.py around its own stages and norm
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
            # stages 1 … 11 (the field is autonomous: no c_s), then y_new and f(y_new)
            for s in range(1, ns):
                _combine(K, s, y, h, ytmp)
                chain_rhs(ytmp, K[s], n, c, d, M, kb, kt, Am, Ai, k)
            for i in range(size):
                acc = 0.0
                for m in range(B_NNZ[0]):
                    acc += K[B_COLS[0, m], i] * B_COEFS[0, m]
                y_new[i] = y[i] + h * acc
            chain_rhs(y_new, K[ns], n, c, d, M, kb, kt, Am, Ai, k)
            nfev += ns
            # error norm (DOP853._estimate_error_norm): per body over its 6 components, then
            # over the bodies; the squared norms as sqrt(.)**2, as SciPy's norm(.)**2
            e5 = 0.0
            e3 = 0.0
            for b in range(n):
                b5 = 0.0
                b3 = 0.0
                for comp in range(NC):
                    i = comp * n + b
                    sc = atol + max(abs(y[i]), abs(y_new[i])) * rtol
                    s5 = 0.0
                    for m in range(E5_NNZ[0]):
                        s5 += K[E5_COLS[0, m], i] * E5_COEFS[0, m]
                    s3 = 0.0
                    for m in range(E3_NNZ[0]):
                        s3 += K[E3_COLS[0, m], i] * E3_COEFS[0, m]
                    s5 /= sc
                    s3 /= sc
                    b5 += s5 * s5
                    b3 += s3 * s3
                e5 += b5
                e3 += b3
            e5 = math.sqrt(e5) ** 2
            e3 = math.sqrt(e3) ** 2
            err = dop.step_error(e5, e3, h_abs, size)
            accepted_step, h_abs = dop.step_factor(err, h_abs, step_rejected)
            if accepted_step:
                break
            step_rejected = True
            rejected += 1
        if status != 0:
            break
        accepted += 1
        t = t_new
        for i in range(size):
            y[i] = y_new[i]
            K[0, i] = K[ns, i]
    return y, accepted, rejected, nfev, status


def _flat(theta, Omega):
    """(N, 3), (N, 3) -> the component-major state (6N,)."""
    theta = np.asarray(theta, dtype=np.float64)
    Omega = np.asarray(Omega, dtype=np.float64)
    return np.ascontiguousarray(np.concatenate([theta.T, Omega.T]).ravel())


def _arguments(params) -> tuple:
    """``params`` as the trailing arguments of :func:`chain_rhs` and :func:`dop853_chain`:
    c, d, M, kb, kt (floats), A, A⁻¹ and k (contiguous float64 arrays)."""
    A = np.ascontiguousarray(params["A"], dtype=np.float64)
    return (
        float(params["c"]),
        float(params["d"]),
        float(params["M"]),
        float(params["kb"]),
        float(params["kt"]),
        A,
        np.ascontiguousarray(np.linalg.inv(A)),
        np.ascontiguousarray(params["k"], dtype=np.float64),
    )


def solve_chain(theta0, Omega0, t1, rtol, atol, params) -> dict:
    """Integrate the chain from (theta0, Omega0) (each ``(N, 3)``) over [0, t1]. ``params``: a
    dict with c, d, M, kb, kt (floats), A (3×3 inertia) and k (the axis). Returns a dict: theta,
    Omega ``(N, 3)`` at t1, steps (accepted), rejected, nfev, status, seconds (the call)."""
    n = int(np.shape(theta0)[0])
    y0 = _flat(theta0, Omega0)
    args = _arguments(params)
    start = time.perf_counter()
    y, acc, rej, nfev, status = dop853_chain(y0, 0.0, float(t1), float(rtol), float(atol), n, *args)
    seconds = time.perf_counter() - start
    y = y.reshape(NC, n).T
    return {
        "theta": y[:, :3],
        "Omega": y[:, 3:],
        "steps": int(acc),
        "rejected": int(rej),
        "nfev": int(nfev),
        "status": int(status),
        "seconds": seconds,
    }


def rhs(theta, Omega, params) -> np.ndarray:
    """The right-hand side at one state, ``(6, N)`` component-major (θ̇x, θ̇y, θ̇z, Ω̇x, ...)."""
    n = int(np.shape(theta)[0])
    out = np.empty(NC * n)
    chain_rhs(_flat(theta, Omega), out, n, *_arguments(params))
    return out.reshape(NC, n)
