r"""One DOP853 step, exactly as SciPy's ``solve_ivp(method="DOP853")`` takes it.

Everything here is *shape-polymorphic*: the state is a tuple of components that are scalars (one
trajectory) or ``(B,)`` arrays (B trajectories in lockstep, structure of arrays), and the same
code serves both. It follows ``scipy/integrate/_ivp/rk.py`` (``RungeKutta._step_impl``,
``DOP853._estimate_error_norm``, ``Dop853DenseOutput``) and ``common.py``
(``select_initial_step``):

- the 12-stage step with the tableau of :mod:`.tableau` (each row through its non-zero
  coefficients, SciPy's order of summation), and the slope at the new point as the 13th
  evaluation (reused as the first stage of the next step);
- the error norm $\|e\| = h\,\|e_5\|^2/\sqrt{(\|e_5\|^2 + 0.01\,\|e_3\|^2)\,n}$ with the scale
  $atol + rtol\max(|y|, |y_{new}|)$;
- the controller: accept if $\|e\| < 1$, factor $0.9\,\|e\|^{-1/8}$ within $[0.2, 10]$, at most 1
  after a rejection within the same step, and SciPy's ``max(0.2, nan) = 0.2`` for a NaN norm;
- the initial step of Hairer, Nørsett & Wanner (II.4), ``min_step = 10 |nextafter(t) − t|`` and the
  end-point clipping;
- the 7th-order dense output (three more stages, only on steps that have samples).

**One traced copy of the vector field per loop.** The stages of a step (and the dense output's
three extra ones) are a ``fori_loop`` over the rows of the tableau (:func:`stages`), the two
evaluations of the initial step a loop of two (:func:`initial_step`): a solver program holds the
vector field twice (once more on lanes, for the refill), not ~17 times; it compiles in less time
and runs a little slower than the unrolled step (benchmarks/README.md, History).

Step sizes and the error norm are constants for differentiation (``lax.stop_gradient``):
forward-mode derivatives are those of the Runge–Kutta map along the step sequence the primal
took, which converge to the solution's sensitivities as the tolerance tightens.

**Stored values.** XLA on CPU copies cheap element-wise producers into every consumer, so the
(once unrolled) 12-stage step was recomputed ~10 times over. Dividing a value by a run-time 1.0
makes XLA store it (a divide is never duplicated; the result is exact); :class:`Store` does that
to every stage input and output, and the right-hand side does it to its shared intermediates
(:func:`rbo_jax.kinematics.stored`).

**Samples** (:func:`emit`, :func:`dense_sampler`): the states at the sample times within a step
come from the 7th-order dense output, made only on steps that hold a sample; a sample at the end
of a step is the step's own state. :func:`runtime_one` makes the run-time 1.0 of :class:`Store`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from . import tableau as T

NS = T.N_STAGES  # 12
N_EXT = T.N_STAGES_EXTENDED  # 16: with the dense output's three extra stages
SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 10.0
ERROR_EXPONENT = -1.0 / (T.ERROR_ESTIMATOR_ORDER + 1)  # -1/8
INITIAL_EXPONENT = 1.0 / (T.ERROR_ESTIMATOR_ORDER + 1)


class Store:
    """``store(values)`` divides each value by a run-time 1.0 (see the module docstring)."""

    def __init__(self, one):
        self.one = one

    def __call__(self, values):
        return tuple(v / self.one for v in values)

    def one_value(self, v):
        return v / self.one


def _combine(coefs, K, i):
    """Σ_j coefs[j] K[i][j] with the literal coefficients, zeros skipped (SciPy's order). ``K``:
    the slopes, one array per state component with the slope index first (:func:`stages`)."""
    acc = None
    for j, a in enumerate(coefs):
        if a != 0.0:
            term = K[i][j] * a
            acc = term if acc is None else acc + term
    return acc


def _sparse_rows(rows):
    """The non-zero coefficients of each tableau row, in column order, padded with zeros to the
    longest row: (column indices, coefficients), two ``(len(rows), width)`` NumPy arrays."""
    width = max(sum(1 for a in row if a != 0.0) for row in rows)
    cols = np.zeros((len(rows), width), np.int32)
    coefs = np.zeros((len(rows), width))
    for s, row in enumerate(rows):
        nz = [(j, a) for j, a in enumerate(row) if a != 0.0]
        cols[s, : len(nz)] = [j for j, _ in nz]
        coefs[s, : len(nz)] = [a for _, a in nz]
    return cols, coefs


_COLS, _COEFS = _sparse_rows(T.A)  # (16, 9): at most 9 non-zero coefficients in a row


def _row_sum(cols, coefs, k):
    """Σ_m coefs[m] k[cols[m]]: one row of the tableau (run-time index) applied to the slopes
    ``k`` (first axis the slope index). The non-zero terms come in column order and the padding
    adds exact zeros, so the sum is :func:`_combine`'s (SciPy's order) for finite slopes."""
    acc = k[cols[0]] * coefs[0]
    for m in range(1, cols.shape[0]):
        acc = acc + k[cols[m]] * coefs[m]
    return acc


# The stages of a step as one loop (False, the default) or unrolled (True). On a GPU each
# iteration of a loop is a host-driven launch of its kernels and a test of its condition on the
# host: unrolled, the ensemble runs faster there but compiles in twice the time
# (benchmarks/README.md, "GPUs"); so the loop stays the default everywhere, and a long GPU run
# may set this to True before its first call.
UNROLL: bool = False


def stages(f, t, y, f0, h, store: Store, last=NS + 1, first=1):
    """``rk_step`` with the stages in one loop: K[0] = f0, K[s] = f(t + c_s h, y + h Σ_j A[s, j]
    K[j]) for s = 1 … ``last`` − 1, y_new = y + h Σ B K. Row 12 of the tableau is B and c_12 = 1,
    so stage 12 is the slope at the new point, K[12] = f(t + h, y_new) (the first stage of the
    next step); rows 13–15 (``last`` = 16) are the dense output's three extra stages. Returns
    (y_new, K), K one ``(16, *shape)`` array per state component, the slope index first (rows
    from ``last`` on are zeros; :func:`slope` reads one). The slopes stay in these arrays, not
    split into rows: rows handed on separately were each copied.

    One ``fori_loop`` over the rows of the tableau holds the program's only traced copy of the
    vector field f in a step (the unrolled step held 15: compile time grows with the copies, as
    diffrax measured when it moved its stages into a loop). Each row is applied through its non-zero
    coefficients only (:func:`_sparse_rows`). ``first = 0`` (traced or not) makes the first slope
    again, K[0] = f(t, y) (row 0 of the tableau is zero), in place of ``f0``: after the state was
    changed between steps (a lattice's re-centred turn-vectors)."""
    if UNROLL:
        return _stages_unrolled(f, t, y, f0, h, store, last, first)
    n = len(y)
    dtype = jnp.result_type(*y)
    cols, coefs = jnp.asarray(_COLS), jnp.asarray(_COEFS, dtype)
    C = jnp.asarray(T.C, dtype)
    K0 = tuple(jnp.zeros((N_EXT, *jnp.shape(y[i])), dtype).at[0].set(f0[i]) for i in range(n))

    def body(s, K):
        row_cols, row_coefs = cols[s], coefs[s]
        ys = store(tuple(y[i] + _row_sum(row_cols, row_coefs, K[i]) * h for i in range(n)))
        k = store(f(t + C[s] * h, ys))
        return tuple(K[i].at[s].set(k[i]) for i in range(n))

    K = lax.fori_loop(first, last, body, K0)
    y_new = store(tuple(y[i] + h * _combine(T.B, K, i) for i in range(n)))
    return y_new, K


def _stages_unrolled(f, t, y, f0, h, store: Store, last, first):
    """:func:`stages` with the rows of the tableau unrolled (:data:`UNROLL`): the same sums in
    the same order, the vector field traced once per row; the dense output's three extra rows in
    a ``lax.cond`` when ``last`` is traced. K in the same layout, one ``(16, *shape)`` array per
    component."""
    n = len(y)
    C = T.C

    def row(rows, s):
        ys = store(tuple(y[i] + _combine(T.A[s], [[r[i] for r in rows]], 0) * h for i in range(n)))
        return store(f(t + C[s] * h, ys))

    def again():  # K[0] = f(t, y) again (row 0 of the tableau is zero)
        return store(f(t + C[0] * h, store(tuple(y))))

    if isinstance(first, (int, np.integer)):
        rows = [again() if first == 0 else tuple(f0)]
    else:
        rows = [lax.cond(first == 0, again, lambda: tuple(f0))]
    for s in range(1, NS + 1):
        rows.append(row(rows, s))

    def extra(done):
        done = list(done)
        for s in range(NS + 1, N_EXT):
            done.append(row(done, s))
        return tuple(done[NS + 1 :])

    zeros = tuple(tuple(jnp.zeros_like(v) for v in rows[0]) for _ in range(N_EXT - NS - 1))
    if isinstance(last, (int, np.integer)):
        rows += list(extra(rows)) if last > NS + 1 else list(zeros)
    else:
        rows += list(lax.cond(last > NS + 1, extra, lambda _: zeros, tuple(rows)))
    K = tuple(jnp.stack([r[i] for r in rows]) for i in range(n))
    y_new = store(tuple(y[i] + h * _combine(T.B, K, i) for i in range(n)))
    return y_new, K


def slope(K, j):
    """The slope K[j] of :func:`stages`' layout as a state tuple."""
    return tuple(k[j] for k in K)


def _identity(x):
    return x


def error_sums(K, y, y_new, rtol, atol):
    """The two sums of squares of ``DOP853._estimate_error_norm`` over the n components, element
    by element: ``(s5, s3)``, each of the components' shape (:func:`error_norm` totals them)."""
    s5 = s3 = None
    for i in range(len(y)):
        scale = atol + jnp.maximum(jnp.abs(y[i]), jnp.abs(y_new[i])) * rtol
        a = _combine(T.E5, K, i) / scale
        b = _combine(T.E3, K, i) / scale
        s5 = a * a if s5 is None else s5 + a * a
        s3 = b * b if s3 is None else s3 + b * b
    return s5, s3


def error_of_sums(t5, t3, h_abs, count):
    """The error norm from the totals ``t5``, ``t3`` of :func:`error_sums` over ``count``
    scalars."""
    # SciPy squares np.linalg.norm: the square of the square root, rounded alike
    e5, e3 = jnp.sqrt(t5) ** 2, jnp.sqrt(t3) ** 2
    zero = (e5 == 0.0) & (e3 == 0.0)
    denom = jnp.where(zero, 1.0, e5 + 0.01 * e3)
    return jnp.where(zero, 0.0, h_abs * e5 / jnp.sqrt(denom * count))


def error_norm(K, y, y_new, h_abs, rtol, atol, total=_identity, size=1):
    """``DOP853._estimate_error_norm`` (RMS over the n components). Each component is one lane's
    scalar (``total`` the identity), or an array of ``size`` scalars of one system (a lattice's
    bodies) that ``total`` sums: the norm is then over all ``n × size`` scalars, as SciPy's."""
    s5, s3 = error_sums(K, y, y_new, rtol, atol)
    return error_of_sums(total(s5), total(s3), h_abs, len(y) * size)


def controller(err, h_abs, rejected):
    """(accept, next |h|) as ``RungeKutta._step_impl``."""
    accept = err < 1.0
    safe = jnp.where(err == 0.0, 1.0, err)
    factor = SAFETY * safe**ERROR_EXPONENT
    grow = jnp.where(err == 0.0, MAX_FACTOR, jnp.minimum(factor, MAX_FACTOR))
    grow = jnp.where(rejected, jnp.minimum(grow, 1.0), grow)
    shrink = jnp.where(factor > MIN_FACTOR, factor, MIN_FACTOR)  # max(0.2, nan) = 0.2
    return accept, h_abs * jnp.where(accept, grow, shrink)


def _rms_of(v, total=_identity, size=1):
    s = None
    for x in v:
        s = x * x if s is None else s + x * x
    return jnp.sqrt(total(s) / (len(v) * size))


def initial_guess(d0, d1, interval):
    """``select_initial_step``'s first guess h0 from the RMS norms d0 = ‖y0/scale‖, d1 =
    ‖f0/scale‖, clipped at ``interval``: ``(h0, d1)``."""
    h0 = jnp.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / jnp.where(d1 == 0, 1.0, d1))
    return jnp.minimum(h0, interval), d1


def initial_choice(h0, d1, d2, interval):
    """``select_initial_step``'s step from the guess h0, d1 and d2 = ‖(f1 − f0)/scale‖/h0."""
    tiny = (d1 <= 1e-15) & (d2 <= 1e-15)
    h1 = jnp.where(
        tiny,
        jnp.maximum(1e-6, h0 * 1e-3),
        (0.01 / jnp.where(tiny, 1.0, jnp.maximum(d1, d2))) ** INITIAL_EXPONENT,
    )
    return lax.stop_gradient(jnp.minimum(jnp.minimum(100 * h0, h1), interval))


def initial_step(f, t0, y0, t_bound, rtol, atol, total=_identity, size=1):
    """The first slope f0 = f(t0, y0) and ``common.select_initial_step`` (no maximal step,
    forward direction): ``(f0, h)``. Its two evaluations, f(t0, y0) and f(t0 + h0, y0 + h0 f0),
    are one loop of two iterations (one traced copy of f; the first runs at h0 = 0 from zero
    slopes, i.e. at (t0, y0) exactly). ``total``, ``size``: as :func:`error_norm` (the RMS
    norms over one system's ``n × size`` scalars)."""
    interval = jnp.abs(t_bound - t0)
    scale = [atol + jnp.abs(y) * rtol for y in y0]

    def _rms(v):
        return _rms_of(v, total, size)

    d0 = _rms([y / s for y, s in zip(y0, scale)])

    def first_guess(f0):
        return initial_guess(d0, _rms([v / s for v, s in zip(f0, scale)]), interval)

    def body(i, slopes):
        f0, _ = slopes
        h0 = jnp.where(i == 0, 0.0, first_guess(f0)[0])
        v = f(t0 + h0, tuple(y + h0 * d for y, d in zip(y0, f0)))
        return tuple(jnp.where(i == 0, a, b) for a, b in zip(v, f0)), v

    zeros = tuple(jnp.zeros_like(y) for y in y0)
    f0, f1 = lax.fori_loop(0, 2, body, (zeros, zeros))
    h0, d1 = first_guess(f0)
    d2 = _rms([(a - b) / s for a, b, s in zip(f1, f0, scale)]) / h0
    return f0, initial_choice(h0, d1, d2, interval)


def min_step(t):
    t = lax.stop_gradient(t)
    return 10.0 * jnp.abs(jnp.nextafter(t, jnp.inf) - t)


def trial_step(t, h_abs, rejected, t_bound):
    """The step an attempt from ``t`` tries (``RungeKutta._step_impl``): ``h_abs`` raised to
    :func:`min_step` unless the last attempt was rejected, the end clipped at ``t_bound``.
    Returns ``(t_new, h, |h|, too_small)``; ``too_small``: below :func:`min_step` (the solve
    stops with ``step_size_collapse``)."""
    h_min = min_step(t)
    h_abs = jnp.where(~rejected & (h_abs < h_min), h_min, h_abs)
    too_small = h_abs < h_min
    t_new = jnp.minimum(t + h_abs, t_bound)
    h = lax.stop_gradient(t_new - t)
    return t_new, h, jnp.abs(h), too_small


def dense_sums(K, i):
    """The four sums Σ_j D[r, j] K[i][j] of the interpolant for state component i, in literal
    order (element-wise code XLA fuses)."""
    return tuple(_combine(T.D[r], K, i) for r in range(4))


def interpolant(K, y_old, y_new, f_old, f_new, h, sums=dense_sums):
    """The 7 coefficient tuples F of the interpolant from the 16 slopes K (``sums(K, i)``: the
    four D-row sums of component i, :func:`dense_sums`, or the same for another layout of K):
    linear in (K, y_old, y_new, f_old, f_new) for a given step h."""
    n = len(y_old)
    dy = tuple(y_new[i] - y_old[i] for i in range(n))
    F = [
        dy,
        tuple(h * f_old[i] - dy[i] for i in range(n)),
        tuple(2 * dy[i] - h * (f_new[i] + f_old[i]) for i in range(n)),
    ]
    DK = [sums(K, i) for i in range(n)]
    for r in range(4):
        F.append(tuple(h * DK[i][r] for i in range(n)))
    return F


def dense_value(F, y_old, x):
    """``Dop853DenseOutput._call_impl`` at the fraction x = (t − t_old)/h of the step."""
    out = []
    for i in range(len(y_old)):
        acc = None
        for j, coef in enumerate(reversed(F)):
            acc = coef[i] if acc is None else acc + coef[i]
            acc = acc * x if j % 2 == 0 else acc * (1 - x)
        out.append(acc + y_old[i])
    return tuple(out)


# --------------------------------------------------------------------------------------------
# Samples at given times, and the run-time 1.0 of Store.
# --------------------------------------------------------------------------------------------


def pending(idx, ts, commit, t_new):
    """Whether the next sample ``ts[idx]`` lies in a committed step ending at ``t_new``."""
    nts = ts.shape[0]
    return commit & (idx < nts) & (ts[jnp.minimum(idx, nts - 1)] <= t_new)


def sample_ahead(idx, ts):
    """``wants_dense`` of a step attempt (:func:`rbo_jax.ensemble._solve.attempt`): the lanes
    whose next sample ``ts[idx]`` lies in the attempted step."""
    return lambda t_new: pending(idx, ts, True, t_new)


def sample(F, step, ts, idx, t_new, block=False):
    """The state at ts[idx] within the step (the new state itself at its end). ``block``: idx is
    a block of sample indices (m,) of one trajectory (scalar ``t_old`` and ``h``), the result
    has the block first, (m, ..., n_components)."""
    commit, t_old, y_old, y_new, K, h = step
    tj = ts[jnp.minimum(idx, ts.shape[0] - 1)]
    if block:  # the block on a leading axis, before the components' own axes (explicit ranks)
        tj = tj.reshape(tj.shape + (1,) * jnp.ndim(y_old[0]))
        F = [tuple(c[None] for c in row) for row in F]
        y_old, y_new = (tuple(jnp.asarray(c)[None] for c in y) for y in (y_old, y_new))
    value = dense_value(F, y_old, (tj - t_old) / h)
    return jnp.stack([jnp.where(tj == t_new, a, b) for a, b in zip(y_new, value)], axis=-1)


def dense_sampler(step, ts, t_new, slope=slope, sums=dense_sums, block=False):
    """The ``sampler`` of :func:`emit` for the state: the step's dense output from its 16
    slopes (the three extra stages were made by the step's stage loop,
    ``attempt(wants_dense=...)``). ``slope(K, j)`` and ``sums(K, i)`` read the step's slopes
    (:func:`slope`, :func:`dense_sums`), or what another layout keeps of them (a lattice's
    blocks: :mod:`rbo_jax.lattice._halo`). ``block``: as :func:`sample`."""

    def sampler():
        commit, t_old, y_old, y_new, K, h = step
        F = interpolant(K, y_old, y_new, slope(K, 0), slope(K, NS), h, sums=sums)
        return lambda idx: sample(F, step, ts, idx, t_new, block)

    return sampler


def samplers(ts, idx, block=False):
    """``(wants_dense, sampler(step, t_new))`` of a loop sampling at ``ts`` (next sample
    ``ts[idx]``): :func:`sample_ahead` and :func:`dense_sampler`; when ``ts`` holds only the two
    ends of the interval (a final state: the last step ends at ``ts[-1]`` exactly), no dense
    output at all, the sample being the step's own new state (the program holds neither the
    dense output's three stages nor its interpolant). ``block``: as :func:`sample` (not for
    the two ends: :func:`emit` takes them one at a time)."""
    if ts.shape[0] == 2:
        return False, lambda step, t_new: lambda: lambda i: jnp.stack(step[3], axis=-1)
    return sample_ahead(idx, ts), lambda step, t_new: dense_sampler(step, ts, t_new, block=block)


def emit(step, ts, idx, out, t_new, write, sampler, block=1):
    """Write every sample of ts in (t_old, t_new] of the committing lanes: ``sampler()``
    returns ``value(idx)``, the samples at ``ts[idx]`` (:func:`dense_sampler`); ``write(out,
    idx, mask, values)`` scatters one sample per lane.

    ``block`` > 1 (one trajectory, scalar ``idx``; ``sampler`` made with ``block=True``): the
    samples are taken ``block`` at a time, ``value(idx + arange(block))`` and one ``write`` of
    the block with a mask (the pending samples are a prefix of it, the times increasing). A step
    holding many samples (a record at 300 Hz under steps of 50 ms) then costs a few loop
    iterations of vector work instead of one iteration per sample."""
    commit = step[0]
    block = min(block, ts.shape[0] - 1)  # the two ends alone: one at a time

    def with_samples(args):
        idx, out = args
        value = sampler()

        def body(c):
            idx, out = c
            if block == 1:  # one sample per lane
                mask = pending(idx, ts, commit, t_new)
                return idx + mask.astype(jnp.int32), write(out, idx, mask, value(idx))
            ids = idx + jnp.arange(block, dtype=idx.dtype)
            mask = pending(ids, ts, commit, t_new)
            step_idx = jnp.sum(mask, dtype=idx.dtype)
            return idx + step_idx, write(out, ids, mask, value(ids))

        return lax.while_loop(lambda c: jnp.any(pending(c[0], ts, commit, t_new)), body, (idx, out))

    return lax.cond(jnp.any(pending(idx, ts, commit, t_new)), with_samples, lambda a: a, (idx, out))


def runtime_one(x):
    """A run-time 1.0 that XLA cannot fold (from the data, finite or not)."""
    leaves = [
        jnp.ravel(v)[0]
        for v in jax.tree_util.tree_leaves(x)
        if jnp.issubdtype(jnp.result_type(v), jnp.floating) and jnp.size(v)
    ]
    s = sum(jnp.where(jnp.isfinite(v), v, 0.0) for v in leaves)
    return lax.stop_gradient(s * 0.0 + 1.0)
