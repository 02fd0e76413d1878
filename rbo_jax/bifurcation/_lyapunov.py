r"""Kuznetsov's first Lyapunov coefficient from directional derivatives of the vector field.

With $Jq = i\omega q$, $|q| = 1$, $J^Tp = -i\omega p$, $\bar p^Tq = 1$ and $q = a + ib$ (Kuznetsov,
*Elements of Applied Bifurcation Theory*, 3rd ed., eq. (3.20)):

$$\ell_1 = \frac{1}{2\omega}\mathrm{Re}\Big[\langle p, C(q, q, \bar q)\rangle
  - 2\langle p, B(q, J^{-1}B(q, \bar q))\rangle
  + \langle p, B(\bar q, (2i\omega E - J)^{-1}B(q, q))\rangle\Big].$$

The real forms $B = D^2F$, $C = D^3F$ are extended to complex arguments by multilinearity and
symmetry, so that only real directional derivatives are needed (twelve at most, in two stages,
the second needing the first's solves):

- stage one: $B(a, a)$, $B(b, b)$, $B(a, b)$, giving $B(q, \bar q) = B(a, a) + B(b, b)$,
  $B(q, q) = B(a, a) - B(b, b) + 2iB(a, b)$, then $h_{11} = J^{-1}B(q, \bar q)$ (real) and
  $h_{20} = (2i\omega E - J)^{-1}B(q, q) = c + id$;
- stage two: $B(q, h_{11}) = B(a, h_{11}) + iB(b, h_{11})$,
  $B(\bar q, h_{20}) = B(a, c) + B(b, d) + i[B(a, d) - B(b, c)]$ and
  $C(q, q, \bar q) = C(a, a, a) + C(a, b, b) + i[C(a, a, b) + C(b, b, b)]$
  (the symmetric product $(a + ib)^2(a - ib) = (a + ib)(a^2 + b^2)$).

The rows of the stages are directions for :func:`._field.jets_by_row`; the Hopf program
evaluates them in one loop around one traced jet (:func:`._hopf_program.lyapunov`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._field import jets_by_row

__all__ = [
    "STAGE_TWO_ROWS",
    "first_lyapunov_coefficient",
    "from_stage_two",
    "stage_one",
    "stage_two_rows",
]

STAGE_TWO_ROWS = 10


def stage_one(J, omega, Baa, Bbb, Bab):
    r"""$(h_{11}, h_{20})$ from $B(a, a)$, $B(b, b)$, $B(a, b)$ (module docstring)."""
    n = J.shape[0]
    h11 = jnp.linalg.solve(J, Baa + Bbb)
    Bqq = jax.lax.complex(Baa - Bbb, 2 * Bab)
    h20 = jnp.linalg.solve(jax.lax.complex(-J, 2 * omega * jnp.eye(n, dtype=J.dtype)), Bqq)
    return h11, h20


def stage_two_rows(a, b, h11, h20):
    """The ``(STAGE_TWO_ROWS, 3, n)`` directions of stage two (module docstring)."""
    c, d = jnp.real(h20), jnp.imag(h20)
    z = jnp.zeros_like(a)
    rows = [
        (a, h11, z),
        (b, h11, z),
        (a, c, z),
        (b, d, z),
        (a, d, z),
        (b, c, z),
        (a, a, a),
        (a, b, b),
        (a, a, b),
        (b, b, b),
    ]
    return jnp.stack([jnp.stack(r) for r in rows])


def from_stage_two(p, omega, D2, D3):
    r"""$\ell_1$ from the second (``D2``) and third (``D3``) derivatives along the rows of
    :func:`stage_two_rows` (module docstring)."""
    B_qh11 = jax.lax.complex(D2[0], D2[1])
    B_qbh20 = jax.lax.complex(D2[2] + D2[3], D2[4] - D2[5])
    C_qqqb = jax.lax.complex(D3[6] + D3[7], D3[8] + D3[9])
    total = jnp.vdot(p, C_qqqb) - 2 * jnp.vdot(p, B_qh11) + jnp.vdot(p, B_qbh20)
    return jnp.real(total) / (2 * omega)


def first_lyapunov_coefficient(F, x0, omega, q, p):
    r"""Kuznetsov's first Lyapunov coefficient $\ell_1$ (eq. (3.20) of his book; module
    docstring) of the vector field ``F`` at the Hopf point ``x0``, with $Jq = i\omega q$,
    $\langle q, q\rangle = 1$ and $J^Tp = -i\omega p$, $\langle p, q\rangle = 1$. Second and
    third derivatives of ``F`` along directions only (:func:`._field.jets_by_row`)."""
    x0 = jnp.asarray(x0)
    J = jax.jacfwd(F)(x0)
    a, b = jnp.real(q).astype(x0.dtype), jnp.imag(q).astype(x0.dtype)
    z = jnp.zeros_like(a)
    _, D2, _ = jets_by_row(
        F, x0, jnp.stack([jnp.stack(r) for r in ((a, a, z), (b, b, z), (a, b, z))])
    )
    h11, h20 = stage_one(J, omega, D2[0], D2[1], D2[2])
    _, D2, D3 = jets_by_row(F, x0, stage_two_rows(a, b, h11, h20))
    return from_stage_two(p, omega, D2, D3)
