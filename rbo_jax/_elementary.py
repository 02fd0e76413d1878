r"""Elementary functions as elementwise polynomial code: sin, cos, cot and atan2 in float64.

XLA's float64 ``sin``, ``cos`` and ``atan2`` are calls of the C library per element on CPU (~10 ns
each, and duplicated into every fusion that uses them); these polynomials vectorise. They are
fdlibm's kernels (``k_sin.c``, ``k_cos.c``, ``s_atan.c``) after a 3-part Cody-Waite reduction by
pi/2, within an ulp or so of the C library (the coefficient functions of
:mod:`rbo_jax.kinematics` are tested against mpmath). A lattice's DOP853 step is faster with
them (benchmarks/bench_lattice.py; figures: benchmarks/README.md, History).

**Derivatives** come from the functions' own rules (``jax.custom_jvp``), not by differentiating
the polynomials: $(\sin, \cos)' = (\cos, -\sin)$, $\cot' = -(1 + \cot^2)$,
$d\,\mathrm{atan2}(s, w) = (w\,ds - s\,dw)/(s^2 + w^2)$, each in terms of the function's
value, so that a derivative of any order evaluates the kernels once: a nested derivative (the
third-order jets of Lyapunov coefficients) is a smaller program, and an exact one. The
derivative of an approximation is not an approximation of the derivative (differentiated, the
kernels' third derivatives were within 2e-12 only); by the rules every derivative up to the
third is within 4e-15 of mpmath (``tests/test_kinematics_accuracy.py``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

__all__ = ["atan2_nonnegative", "cot", "horner", "sin_cos"]


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def horner(coeffs: tuple[float, ...], t):
    r"""$\sum_n c_n t^n$ by Horner's rule; its derivative $\sum_n n c_n t^{n-1}$ by the same rule
    (a polynomial of its own, not the derivative of the recurrence)."""
    out = jnp.full_like(t, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        out = out * t + c
    return out


@horner.defjvp
def _horner_jvp(coeffs, primals, tangents):
    (t,), (dt,) = primals, tangents
    slope = tuple(n * c for n, c in enumerate(coeffs))[1:] or (0.0,)
    return horner(coeffs, t), horner(slope, t) * dt


# fdlibm's kernels on |r| <= pi/4. cot(h): over h in [0.5, 3.12] within 61 ulp of mpmath, like
# libm's cos/sin quotient; the reduction is exact for h < 1e6 (|theta| < 2e6 rad).
_KSIN = (
    -1.66666666666666324348e-01,
    8.33333333332248946124e-03,
    -1.98412698298579493134e-04,
    2.75573137070700676789e-06,
    -2.50507602534068634195e-08,
    1.58969099521155010221e-10,
)
_KCOS = (
    4.16666666666666019037e-02,
    -1.38888888888741095749e-03,
    2.48015872894767294178e-05,
    -2.75573143513906633035e-07,
    2.08757232129817482790e-09,
    -1.13596475577881948265e-11,
)
_INVPIO2 = 6.36619772367581382433e-01
_PIO2 = (1.57079632673412561417e00, 6.07710050630396597660e-11, 2.02226624871116645580e-21)


def _reduce(h):
    """n = round(h/(pi/2)) and r = h - n pi/2 (3-part Cody-Waite, exact for h < 1e6)."""
    n = jnp.round(h * _INVPIO2)
    return n, ((h - n * _PIO2[0]) - n * _PIO2[1]) - n * _PIO2[2]


def _kernels(r):
    """fdlibm's __kernel_sin and __kernel_cos on |r| <= pi/4: (sin r, cos r)."""
    z = r * r
    s = r + (z * r) * horner(_KSIN, z)
    w = z * z
    cr = z * (_KCOS[0] + z * (_KCOS[1] + z * _KCOS[2])) + w * w * (
        _KCOS[3] + z * (_KCOS[4] + z * _KCOS[5])
    )
    hz = 0.5 * z
    w1 = 1.0 - hz
    return s, w1 + (((1.0 - w1) - hz) + z * cr)


@jax.custom_jvp
def sin_cos(h):
    """(sin h, cos h) for 0 <= h < 1e6 by the kernels above (see cot): elementwise code that
    vectorises, where XLA calls libm per element; within 1 ulp or so of libm there (tested
    against mpmath through the coefficient functions)."""
    n, r = _reduce(h)
    s, c = _kernels(r)
    q = jnp.remainder(n, 4.0)
    sin = jnp.where(q == 0.0, s, jnp.where(q == 1.0, c, jnp.where(q == 2.0, -s, -c)))
    cos = jnp.where(q == 0.0, c, jnp.where(q == 1.0, -s, jnp.where(q == 2.0, -c, s)))
    return sin, cos


@sin_cos.defjvp
def _sin_cos_jvp(primals, tangents):
    (h,), (dh,) = primals, tangents
    sin, cos = sin_cos(h)
    return (sin, cos), (cos * dh, -sin * dh)


@jax.custom_jvp
def cot(h):
    """cot(h) for 0 <= h < 1e6 (see above): n = round(h/(pi/2)), r = h - n pi/2;
    cot h = cos r / sin r for even n, -sin r / cos r for odd n."""
    n, r = _reduce(h)
    s, c = _kernels(r)
    odd = jnp.remainder(n, 2.0) == 1.0
    return jnp.where(odd, -s / c, c / s)


@cot.defjvp
def _cot_jvp(primals, tangents):
    (h,), (dh,) = primals, tangents
    c = cot(h)
    return c, -(1.0 + c * c) * dh


# atan by fdlibm's s_atan.c on [0, 1] (its first three reductions), for atan2_nonnegative
_ATAN_HI = (4.63647609000806093515e-01, 7.85398163397448278999e-01, 1.57079632679489655800e00)
_ATAN_LO = (2.26987774529616870924e-17, 3.06161699786838301793e-17, 6.12323399573676603587e-17)
_AT_ODD = (
    3.33333333333329318027e-01,
    1.42857142725034663711e-01,
    9.09088713343650656196e-02,
    6.66107313738753120669e-02,
    4.97687799461593236017e-02,
    1.62858201153657823623e-02,
)
_AT_EVEN = (
    -1.99999999998764832476e-01,
    -1.11111104054623557880e-01,
    -7.69187620504482999495e-02,
    -5.83357013379057348645e-02,
    -3.65315727442169155270e-02,
)


def _atan01(x):
    """atan(x) for 0 <= x <= 1 (fdlibm: reduced about 0.5 and 1, then its polynomial)."""
    mid = x >= 0.4375
    high = x >= 0.6875
    xr = jnp.where(high, (x - 1.0) / (x + 1.0), jnp.where(mid, (2.0 * x - 1.0) / (2.0 + x), x))
    z = xr * xr
    w = z * z
    s1 = z * horner(_AT_ODD, w)
    s2 = w * horner(_AT_EVEN, w)
    hi = jnp.where(high, _ATAN_HI[1], _ATAN_HI[0])
    lo = jnp.where(high, _ATAN_LO[1], _ATAN_LO[0])
    reduced = hi - ((xr * (s1 + s2) - lo) - xr)
    return jnp.where(mid, reduced, xr - xr * (s1 + s2))


@jax.custom_jvp
def atan2_nonnegative(s, w):
    """atan2(s, w) for s, w >= 0, not both 0: atan(s/w) or pi/2 - atan(w/s), the ratio in
    [0, 1] (vectorising code, as sin_cos; finite derivatives everywhere)."""
    swap = s > w
    x = jnp.where(swap, w, s) / jnp.where(swap, s, w)
    a = _atan01(x)
    return jnp.where(swap, (_ATAN_HI[2] - a) + _ATAN_LO[2], a)


@atan2_nonnegative.defjvp
def _atan2_jvp(primals, tangents):
    (s, w), (ds, dw) = primals, tangents
    return atan2_nonnegative(s, w), (w * ds - s * dw) / (s * s + w * w)
