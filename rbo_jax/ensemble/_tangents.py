r"""Forward-mode derivatives of one trajectory: the primal loop and K tangent directions in one
``lax.while_loop``, with the stages of a step in a ``fori_loop``.

``jax.jacfwd`` of the per-trajectory loop would be ``jax.vmap`` of its JVP: JAX then
differentiates the loop body (a fixed point over the carries with non-zero tangents), batches the
differentiated body (a second fixed point over the batched carries), and XLA compiles a body with
~35 copies of the vector field (4.55)–(4.56) and of its derivative (benchmarks/README.md,
History). Here the loop is written once, for K directions: every step attempt is
:func:`._solve.attempt` (the same controller, checks and statuses), its stages are a
``fori_loop`` over the tableau's rows that evaluates the vector field and its derivative along
the K directions (``vmap`` of ``jax.jvp``: the value once, the tangents as a batch) — one copy
of each in the program — and the dense output's three extra stages are that loop again, run
on the steps with a sample ahead (as the primal's, :func:`._solve.attempt`).

The tableau, controller and checks are those of :mod:`rbo_jax.integrate.dop853` and
:func:`._solve.attempt`, but the sums over the slopes are dot products here (XLA's order of
summation, not SciPy's), so the primal can differ from :func:`._solve.solve_one`'s by rounding; it
takes the same steps unless an error norm lies within rounding of the acceptance threshold. The
derivatives are those of the Runge–Kutta map along that step sequence, with step sizes and error
norms constant: what ``jax.jvp`` of the per-trajectory loop computes. The sample times are constants
here; derivatives with respect to them go through ``jax.jvp`` of the loop (``rbo_jax.ensemble``).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..integrate import dop853 as D
from ..integrate import tableau as T
from ..kinematics import storing
from ._problem import traced_once
from ._queue import RUNNING
from ._solve import SAMPLE_BLOCK, Config, _initial, attempt

__all__ = ["solve_one_tangents"]

_A = np.asarray(T.A)  # (16, 16); row 12 holds B
_C = np.asarray(T.C)
N = T.N_STAGES_EXTENDED


def _jvp_k(fn, primals, tangents):
    """``fn(*primals)`` and its derivatives along K directions (leading axis of every tangent
    leaf): the primal is computed once, the tangents as a batch."""
    return jax.vmap(lambda t: jax.jvp(fn, primals, t), out_axes=(None, 0))(tangents)


def _dot(a, k):
    """Σ_j a[j] k[..., j] as one dot product (its order of summation is XLA's: the sums differ
    from :mod:`rbo_jax.integrate.dop853`'s, in SciPy's order, by rounding)."""
    return k @ a


def _fill(f_jvp, t, h, y, dy, slopes, first, last):
    """Stages ``first``..``last``-1: K[s] = f(t + C[s] h, y + (Σ_j A[s, j] K[j]) h) and their
    tangents. ``slopes`` = (K, dK): per state component (16,) and (K, 16) arrays."""
    A, C = jnp.asarray(_A, h.dtype), jnp.asarray(_C, h.dtype)

    def body(s, slopes):
        K, dK = slopes
        ys = tuple(y[i] + _dot(A[s], K[i]) * h for i in range(6))
        dys = tuple(dy[i] + _dot(A[s], dK[i]) * h for i in range(6))
        k, dk = f_jvp(t + C[s] * h, ys, dys)
        return (
            tuple(K[i].at[s].set(k[i]) for i in range(6)),
            tuple(dK[i].at[:, s].set(dk[i]) for i in range(6)),
        )

    return lax.fori_loop(first, last, body, slopes)


def _components(v):
    return tuple(v[..., i] for i in range(6))


def _by_column(K, i):
    """``sums`` of :func:`rbo_jax.integrate.dop853.interpolant` for slopes with the slope index
    last: the four D-row sums of component i as one product."""
    d = K[i] @ np.asarray(T.D).T
    return tuple(d[..., r] for r in range(4))


def solve_one_tangents(dyn, static, y0, ts, cfg: Config, d_dyn, dy0):
    """One trajectory and its K tangents: ``dyn``/``static`` the float leaves and the rest of the
    :class:`._problem.Problem` (``eqx.partition``), ``d_dyn`` tangents of ``dyn`` and ``dy0``
    (K, 6) of the initial state (leading axis K). Returns ``(samples (n_ts, 6), status,
    accepted steps, tangents of the samples (K, n_ts, 6))``.

    The first attempt also computes the tangent of the first slope f(t0, y0) (its stage loop
    starts at row 0 of the tableau, which is zero: K[0] = f(t0, y0) again, bit for bit), so the
    program holds one copy of the differentiated vector field."""
    problem = eqx.combine(dyn, static)
    store = D.Store(D.runtime_one((problem, y0, ts)))
    t_bound, nts, nk = ts[-1], ts.shape[0], dy0.shape[0]
    blocks = nts > 2  # samples a block at a time (D.emit), not for the two ends alone

    def f_jvp(t, y, dy):
        return _jvp_k(
            lambda d, y: traced_once(eqx.combine(d, static), store)(t, y), (dyn, y), (d_dyn, dy)
        )

    with storing(store):
        f = traced_once(problem, store)
        st = _initial(f, problem.failure, ts[0], tuple(y0), t_bound, cfg)
        first = st["status"] == RUNNING
        out = (
            jnp.full((nts, 6), jnp.inf, dtype=ts.dtype)
            .at[0]
            .set(jnp.where(first, jnp.stack(y0), jnp.inf))
        )
        dout = jnp.zeros((nk, nts, 6), ts.dtype).at[:, 0].set(jnp.where(first, dy0, 0.0))

        def write(outs, idx, mask, values):
            (out, dout), (value, dvalue) = outs, values
            at = jnp.where(mask, idx, nts)
            if blocks:  # (m, K, 6) samples of a block to the (K, n_ts, 6) layout
                dvalue = jnp.moveaxis(dvalue, 0, 1)
            return out.at[at].set(value, mode="drop"), dout.at[:, at].set(dvalue, mode="drop")

        def body(c):
            st, idx, outs, dy, df, started = c
            y_old, kept = st["y"], {}

            def stages(_, t, y, f0, h, store, last):
                slopes = (
                    tuple(jnp.zeros(N, ts.dtype).at[0].set(v) for v in f0),
                    tuple(jnp.zeros((nk, N), ts.dtype).at[:, 0].set(v) for v in df),
                )
                K, dK = kept["slopes"] = _fill(
                    f_jvp, t, h, y, dy, slopes, jnp.where(started, 1, 0), last
                )
                kept["dy_new"] = tuple(dy[i] + _dot(_A[T.N_STAGES], dK[i]) * h for i in range(6))
                y_new = tuple(y[i] + _dot(_A[T.N_STAGES], K[i]) * h for i in range(6))
                return y_new, K

            st, step = attempt(
                f, problem.failure, st, t_bound, cfg, store, stages, D.sample_ahead(idx, ts)
            )
            commit, t_old, _, y_new, _, h = step
            (K, dK), dy_new = kept["slopes"], kept["dy_new"]
            dK0, dK12 = (tuple(d[:, j] for d in dK) for j in (0, T.N_STAGES))

            def sampler():
                F = D.interpolant(
                    K, y_old, y_new, D.slope(K, 0), D.slope(K, T.N_STAGES), h, _by_column
                )
                dF = D.interpolant(dK, dy, dy_new, dK0, dK12, h, _by_column)
                dstep = (commit, t_old, dy, dy_new, None, h)
                return lambda i: (
                    D.sample(F, step, ts, i, st["t"], block=blocks),
                    D.sample(dF, dstep, ts, i, st["t"], block=blocks),
                )

            idx, outs = D.emit(step, ts, idx, outs, st["t"], write, sampler, block=SAMPLE_BLOCK)
            dy = tuple(jnp.where(commit, a, b) for a, b in zip(dy_new, dy))
            df = tuple(jnp.where(commit, a, b) for a, b in zip(dK12, dK0))
            return st, idx, outs, dy, df, jnp.asarray(True)

        zeros = tuple(jnp.zeros(nk, ts.dtype) for _ in range(6))
        st, _, (out, dout), _, _, _ = lax.while_loop(
            lambda c: c[0]["status"] == RUNNING,
            body,
            (st, jnp.ones((), jnp.int32), (out, dout), _components(dy0), zeros, jnp.asarray(False)),
        )
    return out, st["status"], st["nacc"], dout
