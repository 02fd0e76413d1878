r"""Block-tridiagonal Jacobians and solves: O(N) linear algebra for chains.

A function $R(x)$ of $N$ blocks of $m$ unknowns whose block $i$ depends on blocks $i-1$, $i$,
$i+1$ only (a chain of bodies coupled to their neighbours) has a block-tridiagonal Jacobian
$J = \mathrm{tridiag}(L_i, D_i, U_i)$. :func:`tridiagonal_jacobian` gets its blocks from
$3m$ Jacobian-vector products (the blocks coloured $i \bmod 3$ perturbed together: Curtis,
Powell & Reid 1974), not $Nm$; :func:`tridiagonal_solve` solves $Jx = b$ by block Gaussian
elimination (the block Thomas algorithm), one ``lax.scan`` forward and one back, each block an
$m\times m$ LU with partial pivoting. Both cost O(N m³), memory O(N m²). The solve is linear in
$b$ and differentiable (its transpose is a solve with $J^T$), so the implicit function theorem
costs one more solve.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["tridiagonal_jacobian", "tridiagonal_solve"]


def tridiagonal_jacobian(fn, x):
    r"""``(L, D, U)``, each ``(N, m, m)``, of the Jacobian of ``fn: (N, m) -> (N, m)`` at ``x``:
    $\partial R_i/\partial x_{i-1}$ (``L[0]`` zero), $\partial R_i/\partial x_i$,
    $\partial R_i/\partial x_{i+1}$ (``U[-1]`` zero). ``fn`` must couple neighbours only."""
    N, m = x.shape
    colour = jnp.arange(N) % 3
    eye = jnp.eye(m, dtype=x.dtype)
    # tangents (3 m, N, m): colour c, direction j on every block of colour c
    same = colour[None, None, :, None] == jnp.arange(3)[:, None, None, None]
    tangents = jnp.where(same, eye[None, :, None, :], 0.0).reshape(3 * m, N, m)
    _, lin = jax.linearize(fn, x)
    out = jax.vmap(lin)(tangents).reshape(3, m, N, m)  # [colour, j, i, row]

    def block(offset):
        # the block (i, i + offset): colour of i + offset, columns j, rows of R_i
        c = (jnp.arange(N) + offset) % 3
        b = out[c, :, jnp.arange(N), :]  # (N, j, row)
        return jnp.swapaxes(b, 1, 2)  # (N, row, j)

    lo = jnp.where((jnp.arange(N) > 0)[:, None, None], block(-1), 0.0)
    hi = jnp.where((jnp.arange(N) < N - 1)[:, None, None], block(1), 0.0)
    return lo, block(0), hi


def _factor(L, D, U):
    """The pivots of block elimination: $D'_0 = D_0$, $D'_i = D_i - L_i D'^{-1}_{i-1} U_{i-1}$,
    and the multipliers $W_i = L_i D'^{-1}_{i-1}$."""

    def step(Dp, inputs):
        Li, Di, Ui_prev = inputs
        W = jnp.linalg.solve(Dp.T, Li.T).T
        new = Di - W @ Ui_prev
        return new, (new, W)

    Uprev = jnp.concatenate([jnp.zeros_like(U[:1]), U[:-1]])
    _, (Dp, W) = jax.lax.scan(step, jnp.eye(D.shape[1], dtype=D.dtype), (L, D, Uprev))
    # the first step: W_0 = L_0 (zero) D'^{-1}, D'_0 = D_0 - 0
    return Dp, W


def tridiagonal_solve(L, D, U, b):
    r"""$x$ with $\mathrm{tridiag}(L, D, U)\,x = b$, ``b`` ``(N, m)``: forward elimination and
    back substitution (module docstring). Differentiable in ``b`` (and in the blocks)."""
    Dp, W = _factor(L, D, U)

    def forward(y_prev, inputs):
        Wi, bi = inputs
        y = bi - Wi @ y_prev
        return y, y

    _, y = jax.lax.scan(forward, jnp.zeros_like(b[0]), (W, b))

    def back(x_next, inputs):
        Dpi, Ui, yi = inputs
        x = jnp.linalg.solve(Dpi, yi - Ui @ x_next)
        return x, x

    _, x = jax.lax.scan(back, jnp.zeros_like(b[0]), (Dp, U, y), reverse=True)
    return x
