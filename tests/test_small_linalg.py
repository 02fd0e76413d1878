"""Small LU factorisations and triangular solves inside a chunk program run in XLA, not LAPACK
(``rbo_jax._sharding._small_rule``, issue 31: OpenBLAS takes a process-wide lock around every
``getrf`` and ``trsm`` call, on which the devices' threads queued). They must be LAPACK's
factorisation: the same pivots, the same permutation, the same factors and solutions."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import pytest

from rbo_jax import _sharding


def _lowered(f, *args):
    """``jit(vmap(f))`` at ``args`` traced and lowered as a chunk program is
    (:func:`rbo_jax._sharding.lapack_in_blocks`), and as JAX does it alone (LAPACK)."""
    g = jax.jit(jax.vmap(f))
    with _sharding.lapack_in_blocks(1):
        small = g.lower(*args)
    return small, jax.jit(jax.vmap(f)).lower(*args)


@pytest.mark.parametrize("dtype", [np.float64, np.complex128])
@pytest.mark.parametrize("n", [1, 3, 4])
def test_small_lu_and_solve_in_xla_are_lapacks(dtype, n):
    """``lax.linalg.lu`` and ``lu_solve`` of 64 random n × n matrices (one singular: a zero
    column, whose pivot LAPACK leaves unscaled) and a unbatched right-hand side: no LAPACK call
    in the program; pivots and permutations equal, factors to 1e-14 (the same operations; a
    fused multiply-add may round the last bit differently), solutions to 8 ε cond(a)."""
    rng = np.random.default_rng(n)
    a = rng.normal(size=(64, n, n))
    if dtype is np.complex128:
        a = a + 1j * rng.normal(size=(64, n, n))
    a[5, :, 0] = 0.0
    b = rng.normal(size=(n, 2)).astype(dtype)
    a = jnp.asarray(a, dtype)

    def f(m):
        lu, piv, perm = jax.lax.linalg.lu(m)
        x = jsl.lu_solve((lu, piv), b)
        xt = jsl.lu_solve((lu, piv), b, trans=1)
        return lu, piv, perm, x, xt

    small, lapack = _lowered(f, a)
    text = small.as_text()
    assert "getrf" not in text and "trsm" not in text
    assert "getrf" in lapack.as_text()
    got, want = small.compile()(a), lapack.compile()(a)
    for k in (1, 2):
        np.testing.assert_array_equal(np.asarray(got[k]), np.asarray(want[k]))
    g, w = np.asarray(got[0]), np.asarray(want[0])
    np.testing.assert_allclose(g, w, rtol=1e-14, atol=1e-14)
    # the solutions, where a is regular: LAPACK's to its condition number times the rounding
    regular = np.arange(64) != 5
    cond = np.linalg.cond(np.asarray(a)[regular])[:, None, None]
    for k in (3, 4):
        g, w = np.asarray(got[k])[regular], np.asarray(want[k])[regular]
        assert np.all(np.abs(g - w) <= 8 * np.finfo(float).eps * cond * np.abs(w).max())
    # the factorisation itself: P A = L U
    lu, perm = np.asarray(got[0]), np.asarray(got[2])
    L = np.tril(lu, -1) + np.eye(n)
    U = np.triu(lu)
    np.testing.assert_allclose(L @ U, np.asarray(a)[np.arange(64)[:, None], perm], atol=1e-13)


@pytest.mark.parametrize("lower", [True, False])
@pytest.mark.parametrize("transpose_a", [False, True])
@pytest.mark.parametrize("unit_diagonal", [False, True])
def test_small_triangular_solves_in_xla_are_lapacks(lower, transpose_a, unit_diagonal):
    """Every left-side ``triangular_solve`` of 3 × 3 complex triangles (conjugated too): the
    residual of ``op(a) x = b`` at rounding, and LAPACK's ``trsm`` solution to 1e-13; a
    right-side solve keeps LAPACK."""
    rng = np.random.default_rng(7)
    a = rng.normal(size=(32, 3, 3)) + 1j * rng.normal(size=(32, 3, 3)) + 4 * np.eye(3)
    b = rng.normal(size=(32, 3, 2)) + 1j * rng.normal(size=(32, 3, 2))
    a, b = jnp.asarray(a), jnp.asarray(b)

    def f(m, r):
        return jax.lax.linalg.triangular_solve(
            m,
            r,
            left_side=True,
            lower=lower,
            transpose_a=transpose_a,
            conjugate_a=True,
            unit_diagonal=unit_diagonal,
        )

    small, lapack = _lowered(f, a, b)
    assert "trsm" not in small.as_text() and "trsm" in lapack.as_text()
    x, want = np.asarray(small.compile()(a, b)), np.asarray(lapack.compile()(a, b))
    np.testing.assert_allclose(x, want, rtol=1e-13, atol=1e-13)
    t = np.tril(np.asarray(a)) if lower else np.triu(np.asarray(a))
    if unit_diagonal:
        t = t - np.einsum("bii->bi", t)[:, :, None] * np.eye(3) + np.eye(3)
    op = np.conj(np.swapaxes(t, 1, 2) if transpose_a else t)
    np.testing.assert_allclose(op @ x, np.asarray(b), atol=1e-13)

    def right(m, r):
        return jax.lax.linalg.triangular_solve(m, jnp.swapaxes(r, 0, 1), left_side=False)

    small, _ = _lowered(right, a, b)
    assert "trsm" in small.as_text()
