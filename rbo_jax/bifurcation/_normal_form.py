r"""The second Lyapunov coefficient $\ell_2$: the quintic coefficient of the normal form at a
generalized Hopf (Bautin) point, from directional derivatives of the vector field up to fifth
order.

On the centre manifold of a Hopf point, with $x = x_0 + 2\,\mathrm{Re}(wq) + \dots$,
$Jq = i\omega q$, $|q| = 1$, $J^Tp = -i\omega p$, $\langle p, q\rangle = \bar p^Tq = 1$, the
Poincaré normal form is (Kuznetsov, *Numerical normalization techniques for all codim 2
bifurcations of equilibria in ODEs*, SIAM J. Numer. Anal. 36 (1999) 1104–1124, section 7)

$$\dot w = i\omega w + \tfrac12 G_{21}\,w|w|^2 + \tfrac1{12}G_{32}\,w|w|^4 + O(|w|^6),$$

and we normalise both coefficients by the frequency, as the first Lyapunov coefficient of
:mod:`._lyapunov` (Kuznetsov's *Elements*, eq. (3.20)):

$$\ell_1 = \frac{\mathrm{Re}\,G_{21}}{2\omega},\qquad
  \ell_2 = \frac{\mathrm{Re}\,G_{32}}{12\omega},$$

so that in the time $\omega t$ the amplitude obeys $\rho' = \rho(\beta + \ell_1\rho^2 +
\ell_2\rho^4)$. (The 1999 paper's $\ell_2 = \mathrm{Re}\,G_{32}/12$ is $\omega\ell_2$.) With the
multilinear forms $B = D^2F$, $C = D^3F$, $D = D^4F$, $E = D^5F$ at $x_0$ (complex arguments by
multilinearity) and $L = J$, the coefficients follow from the solves (the paper's (7.2)–(7.7)
and the formulas after them)

$$\begin{aligned}
H_{20} &= (2i\omega - L)^{-1}B(q, q), \qquad H_{11} = -L^{-1}B(q, \bar q),\\
H_{30} &= (3i\omega - L)^{-1}\big[C(q, q, q) + 3B(q, H_{20})\big],\\
h_{21} &= C(q, q, \bar q) + B(\bar q, H_{20}) + 2B(q, H_{11}),\qquad
  G_{21} = \langle p, h_{21}\rangle,\\
(i\omega - L)H_{21} &= h_{21} - G_{21}q,\quad \langle p, H_{21}\rangle = 0,\\
H_{31} &= (2i\omega - L)^{-1}\big[D(q, q, q, \bar q) + 3C(q, q, H_{11}) + 3C(q, \bar q, H_{20})
  + 3B(H_{20}, H_{11}) + B(\bar q, H_{30}) + 3B(q, H_{21}) - 3G_{21}H_{20}\big],\\
H_{22} &= -L^{-1}\big[D(q, q, \bar q, \bar q) + 4C(q, \bar q, H_{11}) + C(\bar q, \bar q, H_{20})
  + C(q, q, \bar H_{20}) + 2B(H_{11}, H_{11}) + 2B(q, \bar H_{21}) + 2B(\bar q, H_{21})\\
  &\qquad + B(\bar H_{20}, H_{20}) - 4\,\mathrm{Re}(G_{21})H_{11}\big],\\
G_{32} &= \big\langle p,\ E(q, q, q, \bar q, \bar q) + D(q, q, q, \bar H_{20})
  + 3D(q, \bar q, \bar q, H_{20}) + 6D(q, q, \bar q, H_{11}) + C(\bar q, \bar q, H_{30})
  + 3C(q, q, \bar H_{21}) + 6C(q, \bar q, H_{21})\\
  &\qquad + 3C(q, \bar H_{20}, H_{20}) + 6C(q, H_{11}, H_{11}) + 6C(\bar q, H_{20}, H_{11})
  + 2B(\bar q, H_{31}) + 3B(q, H_{22}) + B(\bar H_{20}, H_{30}) + 3B(\bar H_{21}, H_{20})
  + 6B(H_{11}, H_{21})\big\rangle.
\end{aligned}$$

A $k$-linear form of complex arguments is the sum, over the choices of real or imaginary part of
each argument, of real directional derivatives $D^kF[t_1, \dots, t_k]$ times $i^m$ ($m$ the
number of imaginary parts chosen). Every such derivative is one row of a fifth-order nested
forward-mode jet (:func:`jet5`), and the four stages above (each needing the previous one's
solves) run in one ``lax.fori_loop`` around a single vmapped copy of it: one traced fifth
derivative of the vector field, not one per form.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np

from ._field import jet

__all__ = ["second_lyapunov_coefficient", "jet5"]

ORDER = 5


# Richardson's central stencil for a first derivative, error O(h^4): f'(0) ≈ Σ w f(sh)/h
# (also the Bautin solve's derivative of l1 along the Hopf curve)
STENCIL = np.array([-2.0, -1.0, 1.0, 2.0])
WEIGHTS = np.array([1.0, -8.0, 8.0, -1.0]) / 12.0
STEP = 2e-3  # h: truncation ~h^4 ~ 1e-11, rounding ~1e-16/h^2 ~ 1e-11 for the fifth derivative


def jet5(F, y, t):
    r"""$(D^1F(y)[t_1], \dots, D^5F(y)[t_1, \dots, t_5])$, shape ``(5, n)``, for the rows of
    ``t`` (shape ``(5, m)``). The first three are exact (:func:`._field.jet`, nested forward
    mode); the fourth and fifth are central differences of the exact third derivative along
    $t_4$, $t_5$ (unit steps of $h$ = ``STEP``, Richardson's fourth-order stencil in each, so
    $O(h^4)$ truncation and $O(\epsilon/h^2)$ rounding, ~1e-11 relative): a traced fifth
    derivative would make the program's compilation minutes long."""
    n4, n5 = jnp.linalg.norm(t[3]), jnp.linalg.norm(t[4])
    u4 = t[3] / jnp.where(n4 > 0, n4, 1.0)
    u5 = t[4] / jnp.where(n5 > 0, n5, 1.0)
    h = jnp.asarray(STEP, y.dtype)
    s = jnp.asarray(STENCIL, y.dtype)
    w = jnp.asarray(WEIGHTS, y.dtype)
    one = jnp.concatenate([s[:, None] * u4[None, :], jnp.zeros((1, y.shape[0]), y.dtype)]) * h
    two = (s[:, None, None] * u4[None, None] + s[None, :, None] * u5[None, None]).reshape(
        -1, y.shape[0]
    ) * h
    shifts = jnp.concatenate([one, two])  # 4 + 1 (the base point) + 16 shifted points

    def third(shift):
        return jet(F, y + shift, t[0], t[1], t[2])

    f0, d1, d2, d3 = jax.vmap(third)(shifts)
    d4 = jnp.tensordot(w, d3[:4], 1) / h * n4
    d5 = jnp.tensordot(jnp.outer(w, w).reshape(-1), d3[5:], 1) / h**2 * n4 * n5
    return jnp.stack([d1[4], d2[4], d3[4], d4, d5])


class _Forms:
    """A list of complex multilinear forms (each a tuple of 1 to 5 arguments; an argument is a
    complex or a real vector) expanded into rows of real directions for :func:`jet5`, and
    their values assembled from the rows' derivatives (module docstring). The structure (which
    arguments are real, the orders) is static; the arguments are traced."""

    def __init__(self, forms, n, dtype):
        rows, orders, coeffs, owners = [], [], [], []
        for f, args in enumerate(forms):
            parts = [
                ((jnp.real(a), 0), (jnp.imag(a), 1)) if jnp.iscomplexobj(a) else ((a, 0),)
                for a in args
            ]
            for choice in itertools.product(*parts):
                t = [c[0] for c in choice] + [jnp.zeros(n, dtype)] * (ORDER - len(args))
                rows.append(jnp.stack(t))
                orders.append(len(args) - 1)
                coeffs.append(1j ** sum(c[1] for c in choice))
                owners.append(f)
        self.rows = jnp.stack(rows)
        self.orders, self.coeffs = np.array(orders), np.array(coeffs, np.complex128)
        self.owners, self.count = np.array(owners), len(forms)

    def padded(self, size, n):
        pad = jnp.zeros((size - self.rows.shape[0], ORDER, n), self.rows.dtype)
        return jnp.concatenate([self.rows, pad])

    def values(self, D):
        """The forms' complex values, shape ``(count, n)``, from the derivatives ``D`` of
        :func:`jet5` along the (padded) rows, shape ``(R, 5, n)``."""
        cdtype = np.result_type(D.dtype, np.complex64)
        picked = D[np.arange(len(self.orders)), self.orders].astype(cdtype)  # (rows, n)
        terms = jnp.asarray(self.coeffs, cdtype)[:, None] * picked
        return jax.ops.segment_sum(terms, self.owners, num_segments=self.count)


def _solve(L, frequency, rhs):
    r"""$(i\,\text{frequency}\,E - L)^{-1}\,\text{rhs}$ (complex)."""
    n = L.shape[0]
    return jnp.linalg.solve(jax.lax.complex(-L, frequency * jnp.eye(n, dtype=L.dtype)), rhs)


def _bordered(L, omega, q, p, rhs):
    r"""$H$ with $(i\omega - L)H = \text{rhs}$, $\langle p, H\rangle = 0$ (rhs in the range of
    $i\omega - L$): the bordered system $\begin{pmatrix}i\omega - L & q\\ p^H & 0\end{pmatrix}$."""
    n = L.shape[0]
    A = jax.lax.complex(-L, omega * jnp.eye(n, dtype=L.dtype))
    top = jnp.concatenate([A, q[:, None]], axis=1)
    bottom = jnp.concatenate([jnp.conj(p), jnp.zeros(1, q.dtype)])[None, :]
    rhs = jnp.concatenate([rhs, jnp.zeros(1, q.dtype)])
    return jnp.linalg.solve(jnp.concatenate([top, bottom]), rhs)[:n]


def _stage_forms(s, q, c):
    """The forms of stage ``s`` (0: H20, H11; 1: H30, G21, H21; 2: H31, H22; 3: G32) from the
    carry ``c`` of the earlier stages."""
    qb = jnp.conj(q)
    if s == 0:
        return [(q, q), (q, qb)]
    H20, H11 = c["H20"], c["H11"]
    if s == 1:
        return [(q, q, q), (q, H20), (q, q, qb), (qb, H20), (q, H11)]
    H30, H21 = c["H30"], c["H21"]
    H20b, H21b = jnp.conj(H20), jnp.conj(H21)
    if s == 2:
        return [
            *[(q, q, q, qb), (q, q, H11), (q, qb, H20), (H20, H11), (qb, H30), (q, H21)],
            *[(q, q, qb, qb), (q, qb, H11), (qb, qb, H20), (q, q, H20b), (H11, H11)],
            *[(q, H21b), (qb, H21), (H20b, H20)],
        ]
    H31, H22 = c["H31"], c["H22"]
    return [
        *[(q, q, q, qb, qb), (q, q, q, H20b), (q, qb, qb, H20), (q, q, qb, H11)],
        *[(qb, qb, H30), (q, q, H21b), (q, qb, H21), (q, H20b, H20), (q, H11, H11)],
        *[(qb, H20, H11), (qb, H31), (q, H22), (H20b, H30), (H21b, H20), (H11, H21)],
    ]


_G32_WEIGHTS = np.array([1, 1, 3, 6, 1, 3, 6, 3, 6, 6, 2, 3, 1, 3, 6])  # of G32's forms


def _stage_update(s, L, omega, q, p, c, v):
    """The carry after stage ``s`` from its forms' values ``v`` (module docstring)."""
    if s == 0:
        return {**c, "H20": _solve(L, 2 * omega, v[0]), "H11": -jnp.linalg.solve(L, v[1].real)}
    if s == 1:
        H30 = _solve(L, 3 * omega, v[0] + 3 * v[1])
        h21 = v[2] + v[3] + 2 * v[4]
        G21 = jnp.vdot(p, h21)
        return {**c, "H30": H30, "G21": G21, "H21": _bordered(L, omega, q, p, h21 - G21 * q)}
    G21 = c["G21"]
    if s == 2:
        h31 = v[0] + 3 * (v[1] + v[2] + v[3]) + v[4] + 3 * v[5] - 3 * G21 * c["H20"]
        h22 = v[6] + 4 * v[7] + v[8] + v[9] + 2 * (v[10] + v[11] + v[12]) + v[13]
        h22 = h22.real - 4 * G21.real * c["H11"]  # real: every term has its conjugate
        return {**c, "H31": _solve(L, 2 * omega, h31), "H22": -jnp.linalg.solve(L, h22)}
    return {**c, "G32": jnp.vdot(p, jnp.tensordot(jnp.asarray(_G32_WEIGHTS, v.dtype), v, 1))}


def second_lyapunov_coefficient(F, x0, omega, q, p):
    r"""Kuznetsov's second Lyapunov coefficient $\ell_2 = \mathrm{Re}\,G_{32}/(12\omega)$ (module
    docstring) of the vector field ``F`` at the Hopf point ``x0``, with $Jq = i\omega q$,
    $|q| = 1$, $J^Tp = -i\omega p$, $\bar p^Tq = 1$. Meaningful where $\ell_1 = 0$ (a Bautin
    point): there $\ell_2 < 0$ means the cycles born on the hard side ($\ell_1 > 0$) turn back
    at a fold of cycles and a large stable cycle exists. Fifth derivatives of ``F`` along
    directions only (:func:`jet5`), one traced copy."""
    x0 = jnp.asarray(x0)
    n = x0.shape[0]
    cdtype = np.result_type(x0.dtype, np.complex64)
    q, p = jnp.asarray(q, cdtype), jnp.asarray(p, cdtype)
    L = jax.jacfwd(F)(x0)
    zc, zr = jnp.zeros(n, cdtype), jnp.zeros(n, x0.dtype)
    carry = {"H20": zc, "H11": zr, "H30": zc, "G21": zc[0], "H21": zc}
    carry = {**carry, "H31": zc, "H22": zr, "G32": zc[0]}
    stages = [_Forms(_stage_forms(s, q, carry), n, x0.dtype) for s in range(4)]
    size = max(f.rows.shape[0] for f in stages)

    def body(s, c):
        def rows_of(k):
            return lambda c: _Forms(_stage_forms(k, q, c), n, x0.dtype).padded(size, n)

        rows = jax.lax.switch(s, [rows_of(k) for k in range(4)], c)
        D = jax.vmap(lambda t: jet5(F, x0, t))(rows)

        def update(k):
            def f(c, D):
                forms = _Forms(_stage_forms(k, q, c), n, x0.dtype)
                return _stage_update(k, L, omega, q, p, c, forms.values(D))

            return f

        return jax.lax.switch(s, [update(k) for k in range(4)], c, D)

    carry = jax.lax.fori_loop(0, 4, body, carry)
    return jnp.real(carry["G32"]) / (12 * omega)
