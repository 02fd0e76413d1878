r"""Kinematics of the turn-vector: section 4.2 of the paper.

A turn of the body is described by the turn-vector $\theta = \theta n$ ($|n| = 1$) and by the
turn-tensor $Q(\theta) = \exp(\theta\times E)$, eq. (4.3). The integrating tensor $Z(\theta)$,
eq. (4.11), maps the left angular velocity to the rate of the turn-vector,
$\dot\theta = Z\cdot\omega$ (4.10); its transpose maps the right angular velocity,
$\dot\theta = Z^T\cdot\Omega$ (4.14).

Conventions: every function takes a single, unbatched input (a ``(3,)`` vector or a ``(3, 3)``
tensor) and is jit-, vmap- and grad-compatible; batch with ``jax.vmap``. Tensors are stored as
matrices in an orthonormal basis, with ``(a \times E)`` the skew matrix of ``a`` (Appendix A).

Numerical care (cf. jaxlie ``_so3.py``): every coefficient that is singular-looking at $\theta = 0$
(``sin θ/θ``, ``(1 − cos θ)/θ²``, ...) is an analytic function of $t = \theta\cdot\theta$. It is
evaluated by its Taylor polynomial in ``t`` for ``t < 1`` and by the closed form otherwise, with
the *double-where* trick so that neither branch produces a NaN in the forward or the reverse pass.
The Taylor polynomials are carried to machine precision at the hand-over point ($t = 1$), so
values and derivatives of all orders are exact at $\theta = 0$ and values show no accuracy dip
anywhere (relative error ≤ 1.2e-15 against mpmath over $|\theta| \in [10^{-12}, 3]$). First and
second derivatives lose a little just above the hand-over, where the closed forms cancel (measured:
8e-14 and 6e-12 relative for $(1-g)/\theta^2$).
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from fractions import Fraction

import jax.numpy as jnp

from ._custom_types import Matrix, MatrixLike, Scalar, Vector, VectorLike
from ._elementary import atan2_nonnegative, cot, horner

__all__ = [
    "skew",
    "vector_invariant",
    "turn_tensor",
    "turn_vector",
    "compose",
    "composition_invariants",
    "integrating_tensor",
    "integrating_tensor_inv",
    "integrating_tensor_det",
    "distance_to_singularity",
    "Turn",
    "stored",
    "storing",
]

# --------------------------------------------------------------------------------------------
# Input checking (trace-time, on shapes).
# --------------------------------------------------------------------------------------------


def _as_float_array(x, shape: tuple[int, ...], name: str):
    x = jnp.asarray(x)
    if x.shape != shape:
        raise ValueError(
            f"{name} must have shape {shape}, got {x.shape}. rbo_jax functions take a single "
            "(unbatched) input: use jax.vmap for batches."
        )
    if not jnp.issubdtype(x.dtype, jnp.inexact):
        x = x.astype(jnp.result_type(float))
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise TypeError(f"{name} must be real, got dtype {x.dtype}.")
    return x


def as_vector(x, name: str = "theta") -> Vector:
    return _as_float_array(x, (3,), name)


def _as_matrix(x, name: str = "Q") -> Matrix:
    return _as_float_array(x, (3, 3), name)


# --------------------------------------------------------------------------------------------
# Safe coefficient functions of t = θ·θ.
# --------------------------------------------------------------------------------------------

# Hand-over point of the Taylor branches, in t = θ². Each series below is carried until its
# remainder at t = _T_SWITCH is below 1e-17 (relative), so both branches agree to rounding there.
_T_SWITCH = 1.0


def _bernoulli(n_max: int) -> list[Fraction]:
    """Bernoulli numbers B_0..B_{n_max} (B_1 = -1/2), exact."""
    b = [Fraction(1)]
    for m in range(1, n_max + 1):
        b.append(-sum(math.comb(m + 1, k) * b[k] for k in range(m)) / (m + 1))
    return b


def _coeffs(f, n: int) -> tuple[float, ...]:
    return tuple(float(f(i)) for i in range(n))


_B = _bernoulli(40)
# sin θ/θ = Σ (−t)^n/(2n+1)!
_SINC = _coeffs(lambda n: Fraction((-1) ** n, math.factorial(2 * n + 1)), 11)
# (1 − cos θ)/θ² = Σ (−t)^n/(2n+2)!
_COSC = _coeffs(lambda n: Fraction((-1) ** n, math.factorial(2 * n + 2)), 11)
# (θ − sin θ)/θ³ = Σ (−t)^n/(2n+3)!
_SINC3 = _coeffs(lambda n: Fraction((-1) ** n, math.factorial(2 * n + 3)), 11)
# cos θ = Σ (−t)^n/(2n)!
_COS = _coeffs(lambda n: Fraction((-1) ** n, math.factorial(2 * n)), 12)
# (1 − g)/θ², g = (θ/2)cot(θ/2) = Σ (−1)^n B_2n θ^2n/(2n)!  (reading R3: → 1/12 at θ = 0)
_GCOEF = _coeffs(lambda n: (-1) ** n * _B[2 * n + 2] / math.factorial(2 * n + 2), 16)
# atan(x)/x = Σ (−x²)^n/(2n+1), used by the logarithm with x² < X2_SWITCH
ATANC = _coeffs(lambda n: Fraction((-1) ** n, 2 * n + 1), 11)
X2_SWITCH = 1e-2


def _series_or_closed_form(t, coeffs, closed_form, switch=_T_SWITCH):
    """Taylor polynomial for ``t < switch``, ``closed_form(t)`` otherwise (double where).

    Both branches are fed inputs on which they are finite, so that the branch not taken
    cannot inject NaN into the gradient.
    """
    small = t < switch
    t_series = jnp.where(small, t, jnp.zeros_like(t))
    t_closed = jnp.where(small, jnp.full_like(t, switch), t)
    return jnp.where(small, horner(coeffs, t_series), closed_form(t_closed))


def sinc(t, sincos=None):
    """sin θ/θ as a function of t = θ² (``sincos``: a (sin, cos) function of θ for the closed
    form, default XLA's sin)."""

    def closed(t):
        th = jnp.sqrt(t)
        return (jnp.sin(th) if sincos is None else sincos(th)[0]) / th

    return _series_or_closed_form(t, _SINC, closed)


def cosc(t):
    """(1 − cos θ)/θ² as a function of t = θ² (closed form 2 sin²(θ/2)/θ², no cancellation)."""

    def closed(t):
        h = 0.5 * jnp.sqrt(t)
        return 0.5 * (jnp.sin(h) / h) ** 2

    return _series_or_closed_form(t, _COSC, closed)


def _sinc3(t):
    """(θ − sin θ)/θ³ as a function of t = θ²."""

    def closed(t):
        th = jnp.sqrt(t)
        return (th - jnp.sin(th)) / (th * t)

    return _series_or_closed_form(t, _SINC3, closed)


def _cos(t, sincos=None):
    """cos θ as a function of t = θ² (smooth at θ = 0, unlike cos(sqrt(t))); ``sincos`` as
    :func:`sinc`."""
    closed = (
        (lambda t: jnp.cos(jnp.sqrt(t))) if sincos is None else (lambda t: sincos(jnp.sqrt(t))[1])
    )
    return _series_or_closed_form(t, _COS, closed)


def gcoef(t):
    """(1 − g)/θ² with g = θ sin θ / (2(1 − cos θ)) = (θ/2)cot(θ/2), eq. (4.11).

    Singular at θ = 2πk, k ≥ 1, where 1 − cos θ = 0: Z itself is singular there.
    """

    def closed(t):
        h = 0.5 * jnp.sqrt(t)
        return (1.0 - h * cot(h)) / t

    return _series_or_closed_form(t, _GCOEF, closed)


def safe_norm(v):
    """|v| with a zero (not NaN) gradient at v = 0; NaN/inf in ``v`` give NaN/inf (the test is
    ``t == 0``, not ``t > 0``, which would map a NaN ``v`` to 0)."""
    t = jnp.dot(v, v)
    zero = t == 0
    return jnp.where(zero, jnp.zeros_like(t), jnp.sqrt(jnp.where(zero, jnp.ones_like(t), t)))


# --------------------------------------------------------------------------------------------
# Tensor helpers.
# --------------------------------------------------------------------------------------------


def skew(a: VectorLike) -> Matrix:
    r"""The skew tensor $a\times E$: $(a\times E)\cdot b = a\times b$ (Appendix A, eq. (4.4))."""
    a = as_vector(a, "a")
    z = jnp.zeros_like(a[0])
    return jnp.stack(
        [
            jnp.stack([z, -a[2], a[1]]),
            jnp.stack([a[2], z, -a[0]]),
            jnp.stack([-a[1], a[0], z]),
        ]
    )


def vector_invariant(T: MatrixLike) -> Vector:
    r"""The vector invariant $T_\times$ of a second-rank tensor, $(a\otimes b)_\times = a\times b$.

    With this convention $(a\times E)_\times = -2a$ and, for a turn-tensor,
    $-Q(\theta)_\times = 2\,\frac{\sin\theta}{\theta}\,\theta$ (left-hand side of (4.7)).
    """
    T = _as_matrix(T, "T")
    return jnp.stack([T[1, 2] - T[2, 1], T[2, 0] - T[0, 2], T[0, 1] - T[1, 0]])


def _r_squared(theta, t):
    """R² = θ⊗θ − θ² E, eq. (4.4)."""
    return jnp.outer(theta, theta) - t * jnp.eye(3, dtype=theta.dtype)


# --------------------------------------------------------------------------------------------
# Turn-tensor and turn-vector.
# --------------------------------------------------------------------------------------------


def turn_tensor(theta: VectorLike) -> Matrix:
    r"""Turn-tensor $Q(\theta) = E + \frac{\sin\theta}{\theta}R + \frac{1-\cos\theta}{\theta^2}R^2
    = \exp R$, $R = \theta\times E$, eqs. (4.1), (4.3), (4.4).

    Exact (values and all derivatives) at $\theta = 0$; valid for every $\theta$, the angle is
    not reduced.
    """
    theta = as_vector(theta)
    t = jnp.dot(theta, theta)
    eye = jnp.eye(3, dtype=theta.dtype)
    return eye + sinc(t) * skew(theta) + cosc(t) * _r_squared(theta, t)


def quaternion_of(theta, sincos=None):
    """Unit quaternion (w, v) = (cos(θ/2), sin(θ/2)/θ · θ) of the turn-vector θ (half-angle form
    of (4.3)). Component by component (:func:`dot3`), as all of the quaternion helpers: under
    ``vmap`` elementwise code, not batched ``dot_general`` calls. ``sincos``: as :func:`sinc`
    (the lattices pass :func:`rbo_jax._elementary.sin_cos`, which vectorises)."""
    t = dot3(theta, theta)
    return _cos(0.25 * t, sincos), 0.5 * sinc(0.25 * t, sincos) * theta


def log_quaternion(w, v):
    r"""Principal turn-vector ($|\theta| \le \pi$) of the unit quaternion $(w, v)$.

    $\theta = 2\,\mathrm{atan2}(|v|, w)/|v| \cdot v$ after choosing the sign with $w \ge 0$. The
    factor $\mathrm{atan2}(s, w)/s$ is evaluated by the series of $\arctan(x)/x$, $x = s/w$, near
    the identity and by its closed form elsewhere (double where); it stays well conditioned at
    $\theta = \pi$ ($w = 0$).
    """
    sign = jnp.where(w < 0, -jnp.ones_like(w), jnp.ones_like(w))
    w = sign * w
    v = sign * v
    s2 = dot3(v, v)
    small = s2 < X2_SWITCH * w * w
    w_safe = jnp.where(small, w, jnp.ones_like(w))
    x2 = jnp.where(small, s2, jnp.zeros_like(s2)) / (w_safe * w_safe)
    series = horner(ATANC, x2) / w_safe
    s_safe = jnp.sqrt(jnp.where(small, jnp.ones_like(s2), s2))
    closed = atan2_nonnegative(s_safe, w) / s_safe
    return 2.0 * jnp.where(small, series, closed) * v


def turn_vector(Q: MatrixLike) -> Vector:
    r"""The principal turn-vector $\theta$, $|\theta| \le \pi$, with $Q(\theta) = Q$: the inverse
    of :func:`turn_tensor` (4.3) on rotations.

    Goes through the unit quaternion, extracted with Shepperd's branch choice (the largest of
    $1 + \mathrm{tr}\,Q$ and $1 + 2Q_{ii} - \mathrm{tr}\,Q$ is the pivot), so it is accurate for
    every rotation, including angles at and near $\pi$, where the vector invariant $Q_\times$ of
    (4.7) loses the axis. At exactly $|\theta| = \pi$ either of $\pm\theta$ may be returned.
    ``Q`` is assumed orthogonal with determinant +1; small deviations are projected away by
    normalising the quaternion. Non-finite input gives non-finite output.
    """
    m = _as_matrix(Q, "Q")
    d0, d1, d2 = m[0, 0], m[1, 1], m[2, 2]
    a, b, c = m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]  # 4w(x, y, z)
    xy, xz, yz = m[1, 0] + m[0, 1], m[0, 2] + m[2, 0], m[2, 1] + m[1, 2]  # 4(xy, xz, yz)
    ts = jnp.stack([1 + d0 + d1 + d2, 1 + d0 - d1 - d2, 1 - d0 + d1 - d2, 1 - d0 - d1 + d2])
    qs = jnp.stack(
        [
            jnp.stack([ts[0], a, b, c]),
            jnp.stack([a, ts[1], xy, xz]),
            jnp.stack([b, xy, ts[2], yz]),
            jnp.stack([c, xz, yz, ts[3]]),
        ]
    )
    i = jnp.argmax(ts)
    q = qs[i]
    # Pivot ≥ 1 for a rotation (the four t's sum to 4), so this normalisation is safe.
    q = q / jnp.sqrt(jnp.dot(q, q))
    return log_quaternion(q[0], q[1:])


def composition_invariants(phi: VectorLike, psi: VectorLike) -> tuple[Scalar, Vector]:
    r"""The invariants of the composed turn $Q(\theta) = Q(\varphi)\cdot Q(\psi)$, eqs. (4.6)–(4.7).

    Returns $(\cos\theta,\ \frac{\sin\theta}{\theta}\theta)$ with, as corrected in readings
    R1–R2 (docs/readings.md),

    $1 + 2\cos\theta = \cos\varphi + \cos\psi + \cos\varphi\cos\psi
      - 2\frac{\sin\varphi\sin\psi}{\varphi\psi}\,\varphi\cdot\psi
      + \frac{1-\cos\varphi}{\varphi^2}\frac{1-\cos\psi}{\psi^2}(\varphi\cdot\psi)^2$  (4.6)

    $2\frac{\sin\theta}{\theta}\theta
      = \big[\tfrac{\sin\varphi}{\varphi}(1+\cos\psi)
             - \tfrac{1-\cos\varphi}{\varphi^2}\tfrac{\sin\psi}{\psi}\varphi\cdot\psi\big]\varphi
      + \big[\tfrac{\sin\psi}{\psi}(1+\cos\varphi)
             - \tfrac{1-\cos\psi}{\psi^2}\tfrac{\sin\varphi}{\varphi}\varphi\cdot\psi\big]\psi
      + \big[\tfrac{\sin\varphi\sin\psi}{\varphi\psi}
             - \tfrac{1-\cos\varphi}{\varphi^2}\tfrac{1-\cos\psi}{\psi^2}\varphi\cdot\psi\big]
        \varphi\times\psi$  (4.7)

    These determine $\theta$ up to the branch, but lose the axis near $\theta = \pi$ (where
    $\sin\theta \to 0$); :func:`compose` therefore uses their half-angle form.
    """
    phi = as_vector(phi, "phi")
    psi = as_vector(psi, "psi")
    tp, tq = jnp.dot(phi, phi), jnp.dot(psi, psi)
    sp, sq = sinc(tp), sinc(tq)
    cp, cq = cosc(tp), cosc(tq)
    cos_p, cos_q = _cos(tp), _cos(tq)
    pq = jnp.dot(phi, psi)
    cos_theta = 0.5 * (cos_p + cos_q + cos_p * cos_q - 2.0 * sp * sq * pq + cp * cq * pq**2 - 1.0)
    vec = (
        (sp * (1.0 + cos_q) - cp * sq * pq) * phi
        + (sq * (1.0 + cos_p) - cq * sp * pq) * psi
        + (sp * sq - cp * cq * pq) * jnp.cross(phi, psi)
    )
    return cos_theta, 0.5 * vec


def compose(phi: VectorLike, psi: VectorLike) -> Vector:
    r"""The principal turn-vector $\theta$ ($|\theta| \le \pi$) with
    $Q(\theta) = Q(\varphi)\cdot Q(\psi)$, eq. (4.5).

    Computed from (4.6)–(4.7) in their half-angle form: dividing (4.7) by $4\cos(\theta/2)$ and
    writing (4.6) for $\cos(\theta/2)$ gives the Euler–Rodrigues (quaternion) product

    $\cos\frac\theta2 = \cos\frac\varphi2\cos\frac\psi2 - \sin\frac\varphi2\sin\frac\psi2\,
      n_\varphi\cdot n_\psi$,
    $\sin\frac\theta2\,n_\theta = \cos\frac\psi2\sin\frac\varphi2\,n_\varphi
      + \cos\frac\varphi2\sin\frac\psi2\,n_\psi + \sin\frac\varphi2\sin\frac\psi2\,
      n_\varphi\times n_\psi$,

    which, unlike (4.6)–(4.7) themselves (:func:`composition_invariants`), stays well
    conditioned when the composed angle is near $\pi$. Agrees with
    ``turn_vector(turn_tensor(phi) @ turn_tensor(psi))``.
    """
    phi = as_vector(phi, "phi")
    psi = as_vector(psi, "psi")
    return log_quaternion(*quaternion_product(quaternion_of(phi), quaternion_of(psi)))


def quaternion_product(p, q):
    r"""The product of unit quaternions ``p = (w1, v1)``, ``q = (w2, v2)``: the quaternion of
    $Q(\varphi)\cdot Q(\psi)$ (Euler–Rodrigues), component by component."""
    (w1, v1), (w2, v2) = p, q
    return w1 * w2 - dot3(v1, v2), w1 * v2 + w2 * v1 + cross3(v1, v2)


# --------------------------------------------------------------------------------------------
# Integrating tensor.
# --------------------------------------------------------------------------------------------


def integrating_tensor(theta: VectorLike) -> Matrix:
    r"""Integrating tensor $Z(\theta) = E - \frac12 R + \frac{1-g}{\theta^2}R^2$,
    $g = \frac{\theta\sin\theta}{2(1-\cos\theta)}$, eq. (4.11).

    $\dot\theta = Z\cdot\omega$ (4.10), $\dot\theta = Z^T\cdot\Omega$ (4.14). Near $\theta = 0$,
    $(1-g)/\theta^2 = 1/12 + \theta^2/720 + \dots$ (reading R3). Singular at $|\theta| = 2\pi k$,
    $k \ge 1$ (see :func:`distance_to_singularity`), where the result is non-finite.
    """
    theta = as_vector(theta)
    t = jnp.dot(theta, theta)
    eye = jnp.eye(3, dtype=theta.dtype)
    return eye - 0.5 * skew(theta) + gcoef(t) * _r_squared(theta, t)


def integrating_tensor_inv(theta: VectorLike) -> Matrix:
    r"""Inverse integrating tensor
    $Z^{-1}(\theta) = E + \frac{1-\cos\theta}{\theta^2}R + \frac{\theta-\sin\theta}{\theta^3}R^2$,
    eq. (4.20) (Appendix B, (4.123)).

    $\omega = Z^{-1}\cdot\dot\theta$, $\Omega = Z^{-T}\cdot\dot\theta$ (4.19). Finite everywhere;
    singular (not invertible) at $|\theta| = 2\pi k$, $k \ge 1$.
    """
    theta = as_vector(theta)
    t = jnp.dot(theta, theta)
    eye = jnp.eye(3, dtype=theta.dtype)
    return eye + cosc(t) * skew(theta) + _sinc3(t) * _r_squared(theta, t)


def integrating_tensor_det(theta: VectorLike) -> Scalar:
    r"""$\det Z(\theta) = \frac{\theta^2}{2(1-\cos\theta)}$ (after (4.11); reading R3).

    Equal to 1 at $\theta = 0$ and infinite at $|\theta| = 2\pi k$, $k \ge 1$.
    """
    theta = as_vector(theta)
    return 0.5 / cosc(jnp.dot(theta, theta))


def distance_to_singularity(theta: VectorLike) -> Scalar:
    r"""Distance $\min_{k\ge1} \big|\,|\theta| - 2\pi k\,\big|$ from $\theta$ to the nearest
    singular sphere of $Z(\theta)$ (4.11).

    The equations of motion (4.54)/(4.56) break down there unless $\theta\times\omega = 0$; the
    simulator uses this to stop cleanly.
    """
    theta = as_vector(theta)
    n = safe_norm(theta)
    two_pi = 2.0 * jnp.pi
    k = jnp.maximum(jnp.round(n / two_pi), 1.0)
    return jnp.abs(n - two_pi * k)


# --------------------------------------------------------------------------------------------
# Component-wise operators: Q·v, Qᵀ·v, Z·v, Zᵀ·v without forming 3×3 matrices.
# --------------------------------------------------------------------------------------------


_STORE: contextvars.ContextVar = contextvars.ContextVar("rbo_jax_store", default=None)


def stored(x):
    """``x``, marked for XLA to compute once and keep (inside :func:`storing`; otherwise ``x``
    itself). The equations of motion mark their intermediates shared by several outputs (θ·θ, the
    coefficients of Z, dot products, the body moment), so that an integrator's unrolled stages do
    not make XLA recompute them in every consumer (see :mod:`rbo_jax.ensemble`)."""
    store = _STORE.get()
    return x if store is None else store.one_value(x)


@contextlib.contextmanager
def storing(store):
    """While tracing inside this context, :func:`stored` divides by ``store``'s run-time 1.0."""
    token = _STORE.set(store)
    try:
        yield
    finally:
        _STORE.reset(token)


def dot3(a, b):
    """a·b written out component by component (under ``vmap`` an elementwise expression, not a
    batched ``dot_general``)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross3(a, b):
    """a×b written out component by component."""
    return jnp.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def matvec3(A, v):
    """A·v for a 3×3 ``A``, written out component by component."""
    return jnp.stack([A[i, 0] * v[0] + A[i, 1] * v[1] + A[i, 2] * v[2] for i in range(3)])


def solve3(A, b):
    r"""$A^{-1}\cdot b$ for 3×3 matrices ``A`` ``(..., 3, 3)`` and vectors ``b`` ``(..., 3)``
    by Cramer's rule, $x_j = \det A_j/\det A$ ($A_j$: column $j$ replaced by $b$), written out
    component by component: a few elementwise operations, where ``jnp.linalg.solve`` is a
    LAPACK factorisation and two triangular solves per matrix (and as many again in each
    derivative). For the well-conditioned matrices it serves (a body's inertia tensor) its error
    is that of the factorisation, a few ulps times the condition number."""
    a0, a1, a2 = A[..., :, 0], A[..., :, 1], A[..., :, 2]  # the columns

    def det(c0, c1, c2):
        return dot3(
            jnp.moveaxis(c0, -1, 0), cross3(jnp.moveaxis(c1, -1, 0), jnp.moveaxis(c2, -1, 0))
        )

    d = det(a0, a1, a2)
    return jnp.stack([det(b, a1, a2), det(a0, b, a2), det(a0, a1, b)], -1) / d[..., None]


class Turn:
    r"""The tensors of a turn $\theta$ applied to vectors without forming them: the hot path of
    the equations of motion.

    With $R = \theta\times E$ and $R^2\cdot v = \theta(\theta\cdot v) - \theta^2 v$ (4.4):

    - :meth:`rotate` $Q\cdot v = v + \frac{\sin\theta}{\theta}\,\theta\times v +
      \frac{1-\cos\theta}{\theta^2} R^2\cdot v$ (4.3); :meth:`rotate_back` $Q^T\cdot v$ (the
      sign of the middle term flips);
    - :meth:`Z` $Z\cdot v = v - \frac12\theta\times v + \frac{1-g}{\theta^2} R^2\cdot v$ (4.11);
      :meth:`ZT` $Z^T\cdot v$.

    Each is a handful of elementwise operations on the three components, which XLA fuses into one
    kernel under ``vmap`` (a batched 3×3 product becomes a ``dot_general`` that runs poorly on
    CPU). The scalar coefficients are the same safe functions of $t = \theta\cdot\theta$ as in
    :func:`turn_tensor` and :func:`integrating_tensor` (exact at $\theta = 0$), computed once
    per turn and only if used. ``P @ v`` and ``P.T @ v`` work too, so code written for the
    turn-tensor matrix $P$ keeps working with a :class:`Turn`.
    """

    def __init__(self, theta: VectorLike):
        self.theta = as_vector(theta)
        self.t = stored(dot3(self.theta, self.theta))
        self._coefficients = {}

    def _coef(self, name, fn):
        if name not in self._coefficients:
            self._coefficients[name] = stored(fn(self.t))
        return self._coefficients[name]

    def _r2(self, v):
        th = self.theta
        return th * stored(dot3(th, v)) - self.t * v

    def rotate(self, v) -> Vector:
        """$Q(\\theta)\\cdot v$, eq. (4.3)."""
        return (
            v
            + self._coef("sinc", sinc) * cross3(self.theta, v)
            + self._coef("cosc", cosc) * self._r2(v)
        )

    def rotate_back(self, v) -> Vector:
        """$Q^T(\\theta)\\cdot v$."""
        return (
            v
            - self._coef("sinc", sinc) * cross3(self.theta, v)
            + self._coef("cosc", cosc) * self._r2(v)
        )

    def Z(self, v) -> Vector:
        """$Z(\\theta)\\cdot v$, eq. (4.11)."""
        return v - 0.5 * cross3(self.theta, v) + self._coef("gcoef", gcoef) * self._r2(v)

    def ZT(self, v) -> Vector:
        """$Z^T(\\theta)\\cdot v$: the rate $\\dot\\theta = Z^T\\cdot\\Omega$ (4.14)."""
        return v + 0.5 * cross3(self.theta, v) + self._coef("gcoef", gcoef) * self._r2(v)

    @property
    def matrix(self) -> Matrix:
        """The turn-tensor $Q(\\theta)$ as a matrix (:func:`turn_tensor`)."""
        return turn_tensor(self.theta)

    def __matmul__(self, v):
        return self.rotate(v)

    @property
    def T(self) -> _TransposedTurn:
        return _TransposedTurn(self)


class _TransposedTurn:
    """``turn.T @ v`` is ``turn.rotate_back(v)``."""

    def __init__(self, turn: Turn):
        self._turn = turn

    def __matmul__(self, v):
        return self._turn.rotate_back(v)
