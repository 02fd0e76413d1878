r"""The linear solvers that a model's structure asks for.

Every Newton step, implicit derivative and bordered continuation step solves with the
Jacobian of a residual. How that Jacobian is built and factored depends on the structure of
the problem, which the model declares (:meth:`rbo_jax.mechanics.AbstractMechanics.linear_solver`):

- :class:`Dense`: a few unknowns (a rigid body, an extended Hopf system): the whole Jacobian by
  forward mode, an LU solve;
- :class:`Tridiagonal`: $N$ blocks of $m$ unknowns, block $i$ coupled to $i \pm 1$ only (an
  open chain of bodies, a rod): the blocks from $3m$ Jacobian-vector products
  (:func:`tridiagonal_jacobian`), block Gaussian elimination (:func:`tridiagonal_solve`), O(N);
- :class:`LeastSquares`: a consistent over-determined system (a flutter point followed in a
  multiple eigenspace): rows equilibrated, QR (:func:`equilibrated_lstsq`).

**Block-tridiagonal Jacobians.** A function $R(x)$ of $N$ blocks of $m$ unknowns whose block
$i$ depends on blocks $i-1$, $i$, $i+1$ only has a block-tridiagonal Jacobian
$J = \mathrm{tridiag}(L_i, D_i, U_i)$, whose blocks come from $3m$ Jacobian-vector products
(the blocks coloured $i \bmod 3$ perturbed together: Curtis, Powell & Reid 1974), not $Nm$;
$Jx = b$ is solved by block Gaussian elimination (the block Thomas algorithm), one ``lax.scan``
forward and one back, each block an $m\times m$ LU with partial pivoting. Both cost
O(N m³), memory O(N m²). The solve is linear in $b$ and differentiable (its transpose is a
solve with $J^T$), so an implicit derivative costs one more solve.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ._least_squares import value_and_jacfwd


class AbstractLinearSolver(eqx.Module):
    """How the Jacobian of a residual is built (:meth:`value_and_jacobian`), solved with
    (:meth:`solve`) and made harmless where a solve failed (:meth:`identity_where`).
    ``matrix``: the Jacobian is the dense matrix of the flattened unknowns (forward mode)."""

    matrix: ClassVar[bool] = False

    @abc.abstractmethod
    def value_and_jacobian(self, fn, x):
        """``(fn(x), J)``: the value and the Jacobian of ``fn`` at ``x`` (``fn(x)`` of the shape
        of ``x`` for a square structure) in this solver's form, from one trace of ``fn`` (a
        Newton step needs both: a model's residual is costly to trace)."""

    def jacobian(self, fn, x):
        """The Jacobian of :meth:`value_and_jacobian` (the value unused, left out by XLA)."""
        return self.value_and_jacobian(fn, x)[1]

    @abc.abstractmethod
    def solve(self, operator, b):
        """$x$ with $J x = b$ (least squares for :class:`LeastSquares`), ``x`` shaped as the
        unknowns."""

    @abc.abstractmethod
    def identity_where(self, bad, operator):
        """``operator``, or the identity where ``bad`` (so that a failed solve's derivative is a
        finite zero, not NaN, in a batch)."""

    def det_sign(self, operator):
        r"""The sign of $\\det J$ (branch-point tests)."""
        raise NotImplementedError(f"{type(self).__name__} has no determinant.")


class Dense(AbstractLinearSolver):
    """The whole Jacobian (forward mode over the flattened unknowns), solved by LU."""

    matrix: ClassVar[bool] = True

    def value_and_jacobian(self, fn, x):
        return _value_and_jacfwd(fn, x)

    def solve(self, operator, b):
        return jnp.reshape(jnp.linalg.solve(operator, jnp.ravel(b)), jnp.shape(b))

    def identity_where(self, bad, operator):
        return jnp.where(bad, jnp.eye(operator.shape[0], dtype=operator.dtype), operator)

    def det_sign(self, operator):
        return jnp.linalg.slogdet(operator)[0]


class LeastSquares(AbstractLinearSolver):
    """A consistent over-determined system: the least-squares solution, rows equilibrated
    (:func:`equilibrated_lstsq`)."""

    matrix: ClassVar[bool] = True

    def value_and_jacobian(self, fn, x):
        return _value_and_jacfwd(fn, x)

    def solve(self, operator, b):
        return equilibrated_lstsq(operator, jnp.ravel(b))

    def identity_where(self, bad, operator):
        n, m = operator.shape
        return jnp.where(bad, jnp.eye(n, m, dtype=operator.dtype), operator)


class TruncatedLeastSquares(AbstractLinearSolver):
    """The minimum-norm least-squares solution, singular values below ``rcond`` times the
    largest truncated (SVD): a Jacobian with a kernel (a family of periodic orbits) steps
    orthogonally to it."""

    matrix: ClassVar[bool] = True
    rcond: float = eqx.field(static=True, default=1e-9)

    def value_and_jacobian(self, fn, x):
        return _value_and_jacfwd(fn, x)

    def solve(self, operator, b):
        return jnp.linalg.lstsq(operator, jnp.ravel(b), rcond=self.rcond)[0]

    def identity_where(self, bad, operator):
        n, m = operator.shape
        return jnp.where(bad, jnp.eye(n, m, dtype=operator.dtype), operator)


class Tridiagonal(AbstractLinearSolver):
    """$N$ blocks of $m$ unknowns coupled to their neighbours: ``(L, D, U)`` blocks
    (:func:`tridiagonal_jacobian`), block elimination (:func:`tridiagonal_solve`)."""

    def value_and_jacobian(self, fn, x):
        return _tridiagonal(fn, x)

    def solve(self, operator, b):
        return tridiagonal_solve(*operator, b)

    def identity_where(self, bad, operator):
        L, D, U = operator
        eye = jnp.broadcast_to(jnp.eye(D.shape[-1], dtype=D.dtype), D.shape)
        zero = jnp.zeros_like(L)
        return jnp.where(bad, zero, L), jnp.where(bad, eye, D), jnp.where(bad, zero, U)

    def det_sign(self, operator):
        pivots, _ = _factor(*operator)
        return jnp.prod(jnp.linalg.slogdet(pivots)[0])


class FactoredTridiagonal(AbstractLinearSolver):
    """:class:`Tridiagonal` whose operator is kept factored (:func:`tridiagonal_factor`): a
    chord iteration solves many times with one matrix, each solve two scans."""

    def value_and_jacobian(self, fn, x):
        value, blocks = _tridiagonal(fn, x)
        return value, tridiagonal_factor(*blocks)

    def solve(self, operator, b):
        return tridiagonal_substitute(operator, b)

    def identity_where(self, bad, operator):
        raise NotImplementedError("FactoredTridiagonal keeps no blocks to replace.")


def equilibrated_lstsq(J, b):
    r"""The least-squares solution of $Jx = b$, each row divided by its norm first (1 for a zero
    row), by QR. A stiff system (a rod's shear and stretch rows $10^{12}$ times its bending
    rows) unscaled leaves the soft rows' rounding at the stiff rows' level."""
    scale = jnp.linalg.norm(J, axis=1)
    scale = jnp.where(scale > 0, scale, 1.0)
    Q, R = jnp.linalg.qr(J / scale[:, None])
    return jax.scipy.linalg.solve_triangular(R, Q.T @ (b / scale))


def bordered_solve(linear: AbstractLinearSolver, operator, b, c, d, f, g):
    r"""$(x, s)$ with $\begin{pmatrix} J & b\\ c^T & d\end{pmatrix}\begin{pmatrix} x\\ s
    \end{pmatrix} = \begin{pmatrix} f\\ g\end{pmatrix}$ by Keller's bordering algorithm: two
    solves with $J$ (``linear``, its structure kept), $a = J^{-1}f$, $z = J^{-1}b$, then
    $s = (g - c\cdot a)/(d - c\cdot z)$, $x = a - s z$. Also returns $z$ and the pivot
    $d - c\cdot z$ (the bordered determinant is $\det J$ times it)."""
    a, z = jax.vmap(lambda rhs: linear.solve(operator, rhs))(jnp.stack([f, b]))
    pivot = d - jnp.sum(c * z)
    s = (g - jnp.sum(c * a)) / pivot
    return a - s * z, s, z, pivot


# --------------------------------------------------------------------------------------------
# Block-tridiagonal Jacobians and solves
# --------------------------------------------------------------------------------------------


def _coloured(x):
    r"""The tangents ``(3 m, N, m)`` of the colouring: colour $c$, direction $j$ on every block
    $i \equiv c \pmod 3$ (module docstring)."""
    N, m = x.shape
    colour = jnp.arange(N) % 3
    eye = jnp.eye(m, dtype=x.dtype)
    same = colour[None, None, :, None] == jnp.arange(3)[:, None, None, None]
    return jnp.where(same, eye[None, :, None, :], 0.0).reshape(3 * m, N, m)


def _blocks(out, scale=None):
    """``(L, D, U)`` from the responses ``out`` ``(3 m, N, m)`` to the coloured tangents,
    each column $j$ of block $(i, i + o)$ divided by ``scale[i + o, j]`` where given."""
    N, m = out.shape[1:]
    out = out.reshape(3, m, N, m)  # [colour, j, i, row]

    def block(offset):
        # the block (i, i + offset): colour of i + offset, columns j, rows of R_i
        k = jnp.arange(N) + offset
        b = out[k % 3, :, jnp.arange(N), :]  # (N, j, row)
        if scale is not None:
            b = b / scale[jnp.clip(k, 0, N - 1)][:, :, None]
        return jnp.swapaxes(b, 1, 2)  # (N, row, j)

    lo = jnp.where((jnp.arange(N) > 0)[:, None, None], block(-1), 0.0)
    hi = jnp.where((jnp.arange(N) < N - 1)[:, None, None], block(1), 0.0)
    return lo, block(0), hi


def tridiagonal_jacobian(fn, x):
    r"""``(L, D, U)``, each ``(N, m, m)``, of the Jacobian of ``fn: (N, m) -> (N, m)`` at ``x``:
    $\partial R_i/\partial x_{i-1}$ (``L[0]`` zero), $\partial R_i/\partial x_i$,
    $\partial R_i/\partial x_{i+1}$ (``U[-1]`` zero), from $3m$ Jacobian-vector products.
    ``fn`` must couple neighbours only."""
    return _tridiagonal(fn, x)[1]


def _tridiagonal(fn, x):
    """``(fn(x), (L, D, U))`` (:func:`tridiagonal_jacobian`), ``fn`` traced once."""
    value, lin = jax.linearize(fn, x)
    return value, _blocks(jax.vmap(lin)(_coloured(x)))


def _value_and_jacfwd(fn, x):
    """``(fn(x), J)``, $J$ the forward-mode Jacobian of the flattened ``fn`` in the flattened
    ``x`` (:func:`value_and_jacfwd`: ``fn`` traced once)."""
    shape = jnp.shape(x)
    value, J = value_and_jacfwd(lambda z: fn(jnp.reshape(z, shape)), jnp.ravel(x))
    return value, jnp.reshape(J, (jnp.size(value), -1))


def tridiagonal_differences(fn, x):
    r"""The blocks of :func:`tridiagonal_jacobian` by forward differences: ``fn`` at $x$ and at
    the $3m$ points $x + \epsilon\circ e_{c,j}$ (one loop, ``lax.map``: one copy of ``fn`` in
    the program, which compiles in about half the time of a ``vmap`` of copies and runs no
    slower), the steps
    $\epsilon_{ij} = \sqrt{\varepsilon}\max(|x_{ij}|, 1)$ rounded so that $x + \epsilon$ is
    exact. An entry's error is about
    $\sqrt{\varepsilon}\,(|R_i|/s_j + s_j|\partial^2_jR_i|/2)$, $s_j = \max(|x_j|, 1)$
    (rounding and truncation): $10^{-8}$ relative where $|R_i| \lesssim |J_{ij}|\,s_j$. A matrix
    to steer Newton's iterations (a chord method converges whatever its matrix's error of that
    order), compiled as ``fn`` itself instead of its linearisation (a smaller program:
    benchmarks/README.md); never for a derivative."""
    h = jnp.sqrt(jnp.finfo(x.dtype).eps) * jnp.maximum(jnp.abs(x), 1.0)
    h = (x + h) - x
    tangents = _coloured(x)
    out = jax.lax.map(
        lambda t: fn(x + h * t), jnp.concatenate([jnp.zeros_like(tangents[:1]), tangents])
    )
    return _blocks(out[1:] - out[:1], h)


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


def _eliminate(W, b):
    """The forward elimination $y_i = b_i - W_i y_{i-1}$ (one ``lax.scan``)."""

    def forward(y_prev, inputs):
        Wi, bi = inputs
        y = bi - Wi @ y_prev
        return y, y

    return jax.lax.scan(forward, jnp.zeros_like(b[0]), (W, b))[1]


def tridiagonal_solve(L, D, U, b):
    r"""$x$ with $\mathrm{tridiag}(L, D, U)\,x = b$, ``b`` ``(N, m)``: forward elimination and
    back substitution (module docstring), each pivot block solved by LU with partial pivoting
    (backward stable: a stiff rod's pivots reach condition numbers of $10^{12}$).
    Differentiable in ``b`` (and in the blocks)."""
    Dp, W = _factor(L, D, U)
    lu, piv = jax.vmap(jax.scipy.linalg.lu_factor)(Dp)

    y = _eliminate(W, b)

    def back(x_next, inputs):
        lui, pivi, Ui, yi = inputs
        x = jax.scipy.linalg.lu_solve((lui, pivi), yi - Ui @ x_next)
        return x, x

    _, x = jax.lax.scan(back, jnp.zeros_like(b[0]), (lu, piv, U, y), reverse=True)
    return x


def tridiagonal_factor(L, D, U):
    r"""The block elimination of $\mathrm{tridiag}(L, D, U)$ done once for many right-hand
    sides (:func:`tridiagonal_substitute`): the multipliers $W_i$, the inverse pivots
    $D'^{-1}_i$ and $V_i = D'^{-1}_i U_i$, so that each solve is matrix-vector products only
    (4-8 times faster than LU solves inside the scans, from N = 50 to 1000). A chord iteration
    (one matrix, several solves) factors once; its solves only need to contract, so the
    explicit inverses (not backward stable for badly conditioned pivots) serve there, and
    :func:`tridiagonal_solve` keeps LU."""
    Dp, W = _factor(L, D, U)
    Dinv = jnp.linalg.inv(Dp)
    return W, Dinv, jnp.einsum("nij,njk->nik", Dinv, U)


def tridiagonal_substitute(factors, b):
    r"""$x$ with $\mathrm{tridiag}(L, D, U)\,x = b$ from :func:`tridiagonal_factor`'s
    ``factors``: $y_i = b_i - W_i y_{i-1}$ (one ``lax.scan``), $z_i = D'^{-1}_i y_i$ (all at
    once), $x_i = z_i - V_i x_{i+1}$ (one ``lax.scan`` back): O(N m²)."""
    W, Dinv, V = factors

    y = _eliminate(W, b)
    z = jnp.einsum("nij,nj->ni", Dinv, y)

    def back(x_next, inputs):
        Vi, zi = inputs
        x = zi - Vi @ x_next
        return x, x

    _, x = jax.lax.scan(back, jnp.zeros_like(b[0]), (V, z), reverse=True)
    return x


def tridiagonal_matvec(L, D, U, x):
    r"""$\mathrm{tridiag}(L, D, U)\,x$, ``x`` ``(N, m)``."""
    z = jnp.zeros_like(x[:1])
    below = jnp.concatenate([z, x[:-1]])
    above = jnp.concatenate([x[1:], z])
    mv = lambda A, y: jnp.einsum("nij,nj->ni", A, y)  # noqa: E731
    return mv(L, below) + mv(D, x) + mv(U, above)


def linear_solver(structure: str) -> AbstractLinearSolver:
    """The solver of a model's structure (:meth:`rbo_jax.mechanics.AbstractMechanics.structure`):
    ``"dense"`` or ``"tridiagonal"``."""
    if structure == "tridiagonal":
        return Tridiagonal()
    if structure == "dense":
        return Dense()
    raise ValueError(f"unknown structure {structure!r} (expected 'dense' or 'tridiagonal').")
