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
number of imaginary parts chosen). The first three orders are exact (nested forward mode along
one direction and the polarization identities, :func:`._field.jets_by_row`); the fourth and fifth
are central differences of the exact third derivative along $t_4$ and $t_5$ (Richardson's
fourth-order stencil in each, steps of $h$ = ``STEP`` along the unit vectors: $O(h^4)$
truncation, $O(\epsilon/h^2)$ rounding; on the normal form of ``tests/test_bautin.py`` 8e-10
relative; a traced fifth derivative made the program's compilation minutes long). So every
term is one evaluation of the third-order jet at a shifted point, and :class:`Schedule` lists
them all, stage by stage (each stage needs the previous one's solves): 943 evaluations (four
jets along one direction each), one per iteration of a loop around ONE traced jet, the same copy
that gives $\ell_1$ in :func:`rbo_jax.bautin_point`.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np

from ._field import jets_by_row

__all__ = ["Schedule", "second_lyapunov_coefficient"]


# Richardson's central stencil for a first derivative, error O(h^4): f'(0) ≈ Σ w f(sh)/h
# (also the Bautin solve's derivative of l1 along the Hopf curve)
STENCIL = np.array([-2.0, -1.0, 1.0, 2.0])
WEIGHTS = np.array([1.0, -8.0, 8.0, -1.0]) / 12.0
STEP = 2e-3  # h: truncation ~h^4 ~ 1e-11, rounding ~1e-16/h^2 ~ 1e-11 for the fifth derivative

# The vectors the forms take (module docstring); H11 and H22 are real
_COMPLEX = ("q", "qb", "H20", "H20b", "H30", "H21", "H21b", "H31")
_REAL = ("H11", "H22")
# The forms of each stage: 0 gives H20, H11; 1: H30, G21, H21; 2: H31, H22; 3: G32
_STAGES = (
    (("q", "q"), ("q", "qb")),
    (("q", "q", "q"), ("q", "H20"), ("q", "q", "qb"), ("qb", "H20"), ("q", "H11")),
    (
        *[("q", "q", "q", "qb"), ("q", "q", "H11"), ("q", "qb", "H20"), ("H20", "H11")],
        *[("qb", "H30"), ("q", "H21"), ("q", "q", "qb", "qb"), ("q", "qb", "H11")],
        *[("qb", "qb", "H20"), ("q", "q", "H20b"), ("H11", "H11"), ("q", "H21b")],
        *[("qb", "H21"), ("H20b", "H20")],
    ),
    (
        *[("q", "q", "q", "qb", "qb"), ("q", "q", "q", "H20b"), ("q", "qb", "qb", "H20")],
        *[("q", "q", "qb", "H11"), ("qb", "qb", "H30"), ("q", "q", "H21b"), ("q", "qb", "H21")],
        *[("q", "H20b", "H20"), ("q", "H11", "H11"), ("qb", "H20", "H11"), ("qb", "H31")],
        *[("q", "H22"), ("H20b", "H30"), ("H21b", "H20"), ("H11", "H21")],
    ),
)
_G32_WEIGHTS = np.array([1, 1, 3, 6, 1, 3, 6, 3, 6, 6, 2, 3, 1, 3, 6])  # of G32's forms
# the rows of the basis of directions: real and imaginary parts of the complex vectors, the
# real ones, and a zero row (unused directions)
_BASIS = {(a, part): i for i, (a, part) in enumerate([(a, k) for a in _COMPLEX for k in (0, 1)])}
_BASIS.update({(a, 0): len(_BASIS) + i for i, a in enumerate(_REAL)})
_ZERO = len(_BASIS)


def _tables():
    """The static schedule: for every evaluation of the third-order jet, its stage, its five
    directions (rows of the basis), its shift along the unit fourth and fifth directions (in
    steps $h$), its weight, the derivative it contributes (order 1 to 3), the form's order $k$
    and index, and $i^m$."""
    cols = {k: [] for k in ("stage", "rows", "a4", "a5", "weight", "pick", "order", "form")}
    cols["coeff"], forms, first = [], 0, []
    for stage, stage_forms in enumerate(_STAGES):
        first.append(forms)
        for args in stage_forms:
            parts = [((a, 0), (a, 1)) if a in _COMPLEX else ((a, 0),) for a in args]
            k = len(args)
            if k <= 3:
                shifts = [(0.0, 0.0, 1.0)]
            elif k == 4:
                shifts = [(a, 0.0, w) for a, w in zip(STENCIL, WEIGHTS)]
            else:
                shifts = [
                    (a, b, wa * wb)
                    for a, wa in zip(STENCIL, WEIGHTS)
                    for b, wb in zip(STENCIL, WEIGHTS)
                ]
            for choice in itertools.product(*parts):
                rows = [_BASIS[c] for c in choice] + [_ZERO] * (5 - k)
                for a4, a5, w in shifts:
                    for key, v in zip(cols, (stage, rows, a4, a5, w, min(k, 3) - 1, k, forms)):
                        cols[key].append(v)
                    cols["coeff"].append(1j ** sum(part for _, part in choice))
            forms += 1
    tables = {key: np.array(v) for key, v in cols.items()}
    stage = tables["stage"]
    tables["last"] = np.append(stage[1:] != stage[:-1], True)
    return tables, tuple(first) + (forms,)


_TABLES, _FIRST_FORM = _tables()
EVALUATIONS = len(_TABLES["stage"])


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


class Schedule:
    r"""The evaluations of $\ell_2$ (module docstring) as the steps of a loop: the state (a
    dict) holds the counter, the forms' sums and the stages' results; :meth:`evaluation` gives
    the shift of the point and the directions $(t_1, t_2, t_3)$ of the next evaluation of the
    third-order jet, :meth:`advance` adds its derivatives and, after a stage's last one, solves
    the stage. ``n`` the dimension of the state, $L = J$ the linearization, $Jq = i\omega q$,
    $|q| = 1$, $J^Tp = -i\omega p$, $\bar p^Tq = 1$."""

    def __init__(self, n, dtype):
        self.n, self.dtype = n, dtype
        self.cdtype = np.result_type(dtype, np.complex64)

    def initial_state(self, L, omega, q, p) -> dict:
        n, cdtype = self.n, self.cdtype
        zc, zr = jnp.zeros(n, cdtype), jnp.zeros(n, self.dtype)
        return dict(
            e=jnp.asarray(0, jnp.int32),
            acc=jnp.zeros((_FIRST_FORM[-1], n), cdtype),
            L=jnp.asarray(L, self.dtype),
            omega=jnp.asarray(omega, self.dtype),
            q=jnp.asarray(q, cdtype),
            p=jnp.asarray(p, cdtype),
            H20=zc,
            H11=zr,
            H30=zc,
            G21=zc[0],
            H21=zc,
            H31=zc,
            H22=zr,
            G32=zc[0],
        )

    def _directions(self, st):
        """The five directions of the next evaluation, ``(5, n)``."""
        q, vec = st["q"], dict(st)
        vec.update(qb=jnp.conj(q), H20b=jnp.conj(st["H20"]), H21b=jnp.conj(st["H21"]))
        rows = [part(vec[a]) for a in _COMPLEX for part in (jnp.real, jnp.imag)]
        rows += [vec[a] for a in _REAL] + [jnp.zeros(self.n, self.dtype)]
        e = jnp.minimum(st["e"], EVALUATIONS - 1)
        return jnp.stack(rows)[jnp.asarray(_TABLES["rows"])[e]]

    def evaluation(self, st):
        """``(shift, t, scale)``: the jet's point is the base point plus ``shift``, its
        directions ``t[0]``, ``t[1]``, ``t[2]``; ``scale`` goes to :meth:`advance`."""
        t = self._directions(st)
        e = jnp.minimum(st["e"], EVALUATIONS - 1)
        n4, n5 = jnp.linalg.norm(t[3]), jnp.linalg.norm(t[4])
        u4 = t[3] / jnp.where(n4 > 0, n4, 1.0)
        u5 = t[4] / jnp.where(n5 > 0, n5, 1.0)
        h = jnp.asarray(STEP, self.dtype)
        a4, a5 = (jnp.asarray(_TABLES[k], self.dtype)[e] for k in ("a4", "a5"))
        scale = jnp.stack([jnp.ones((), self.dtype), n4 / h, n4 * n5 / h**2])
        order = jnp.asarray(_TABLES["order"])[e]
        return h * (a4 * u4 + a5 * u5), t[:3], scale[jnp.clip(order - 3, 0, 2)]

    def advance(self, st, scale, d1, d2, d3):
        """The state after one evaluation (its derivatives ``d1``, ``d2``, ``d3`` along the
        directions of :meth:`evaluation`); after a stage's last evaluation, the stage's
        solves."""
        e = jnp.minimum(st["e"], EVALUATIONS - 1)
        table = {k: jnp.asarray(_TABLES[k])[e] for k in ("pick", "form", "last", "stage")}
        weight = jnp.asarray(_TABLES["weight"], self.dtype)[e] * scale
        d = jnp.stack([d1, d2, d3])[table["pick"]]
        term = jnp.asarray(_TABLES["coeff"], self.cdtype)[e] * (weight * d).astype(self.cdtype)
        st = {**st, "acc": st["acc"].at[table["form"]].add(term), "e": st["e"] + 1}

        def update(k):
            def f(st):
                v = st["acc"][_FIRST_FORM[k] : _FIRST_FORM[k + 1]]
                c = _stage_update(k, st["L"], st["omega"], st["q"], st["p"], st, v)
                return jax.tree.map(lambda x, y: jnp.asarray(x, y.dtype), c, st)

            return f

        branches = [update(k) for k in range(len(_STAGES))] + [lambda st: st]
        index = jnp.where(table["last"], table["stage"], len(_STAGES))
        return jax.lax.switch(index, branches, st)

    def done(self, st):
        return st["e"] >= EVALUATIONS

    @staticmethod
    def result(st):
        r"""$\ell_2 = \mathrm{Re}\,G_{32}/(12\omega)$."""
        return jnp.real(st["G32"]) / (12 * st["omega"])


def second_lyapunov_coefficient(F, x0, omega, q, p):
    r"""Kuznetsov's second Lyapunov coefficient $\ell_2 = \mathrm{Re}\,G_{32}/(12\omega)$ (module
    docstring) of the vector field ``F`` at the Hopf point ``x0``, with $Jq = i\omega q$,
    $|q| = 1$, $J^Tp = -i\omega p$, $\bar p^Tq = 1$. Meaningful where $\ell_1 = 0$ (a Bautin
    point): there $\ell_2 < 0$ means the cycles born on the hard side ($\ell_1 > 0$) turn back
    at a fold of cycles and a large stable cycle exists. Derivatives of ``F`` along directions
    only: one traced third-order jet (:func:`._field.jets_by_row`) in a loop over
    :class:`Schedule`."""
    x0 = jnp.asarray(x0)
    schedule = Schedule(x0.shape[0], x0.dtype)
    st = schedule.initial_state(jax.jacfwd(F)(x0), omega, q, p)

    def body(_, st):
        shift, t, scale = schedule.evaluation(st)
        d1, d2, d3 = jets_by_row(F, x0 + shift, t[None], size=x0.shape[0])
        return schedule.advance(st, scale, d1[0], d2[0], d3[0])

    return Schedule.result(jax.lax.fori_loop(0, EVALUATIONS, body, st))
