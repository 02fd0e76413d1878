r"""The implicit midpoint rule for a chain of bodies, with block-tridiagonal Newton solves.

A rod or an open chain of $N$ bodies couples each body to its neighbours only: with the
unknowns ordered body by body ($m$ a body), the Jacobian $J = \partial f/\partial x$ of its
equations of motion $\dot x = f(x)$ is block-tridiagonal. One step of the implicit midpoint
rule,

$$x_{n+1} = x_n + h\,f\!\left(t_n + \tfrac h2, \tfrac12 (x_n + x_{n+1})\right),$$

is second order, symmetric and A-stable, and it keeps every quadratic invariant exactly: on a
linear elastic system its energy is kept to the Newton tolerance at any step. A mode of
frequency $\omega$ keeps its amplitude at every $h$ and turns by
$2\arctan(\omega h/2)$ a step instead of $\omega h$ (a relative phase error
$(\omega h)^2/12$ where $\omega h \ll 1$). So the stiff stretch and shear waves of a slender
rod, which hold every explicit step below $2/\omega_{max}$, neither limit the step nor lose
their energy (an L-stable method damps them, a loss the size of their share of the energy);
the step is chosen for the slow motion that is wanted.

**Newton.** Each step solves $G(y) = y - x_n - h f((x_n + y)/2) = 0$ by the chord method from
$y = x_n + h\,s$, $s$ the rates $(x_{k+1} - x_k)/h_k$ of the last :data:`PREDICTOR_RATES`
steps, each at its step's midpoint, extrapolated to $t_n + h/2$ by their Lagrange polynomial
(:func:`_extrapolated`; fewer at the first steps, $x_0$ at the first): the start's error is
$O(h^4)$, so fewer iterations reach the tolerance than from the last rate alone ($O(h^2)$).
(From the last two rates, $O(h^3)$, the iterations left an error that raised a vibrating
cantilever's energy at every step: a drift 13 times that from one rate, 200 times that from
three; benchmarks/README.md, History.) The chord iterations use the matrix $I - \tfrac h2 J$: its
blocks from $3m$ forward differences of $f$, in one loop with $f$ itself
(:func:`rbo_jax.solvers.tridiagonal_differences`: copies of $f$ compile faster than its
linearisation, and the chord iterations converge whatever the matrix's $10^{-8}$ relative
error; the derivatives below use the exact Jacobian), factored by block elimination
(:func:`rbo_jax.solvers.tridiagonal_factor`), each iteration two scans
(:class:`~rbo_jax.solvers.FactoredTridiagonal`, in the project's one loop of Newton updates:
:func:`~rbo_jax.solvers.iterate`, :func:`~rbo_jax.solvers.newton_update`): O(N m³) to factor,
O(N m²) an iteration. The Jacobian is kept from step to step (a small motion barely changes it)
and computed anew, at the midpoint of the last iterate, only when the iterations do not
converge within ``max_newton`` (up to :data:`MAX_REFRESH` times a step); after such a step the
next :data:`EAGER_STEPS` steps start with a new one (a rod that turns: its stiff directions turn
with it, and a kept matrix fails at every step). The iterations stop when the iterate's error,
estimated from the contraction of the last two updates, is within ``atol + rtol |y|`` in every
component (:meth:`_Stepper.newton`). A step that still does not converge is taken as 2, 4,
..., :data:`MAX_SUBSTEPS` equal substeps (the first count whose every substep converges); where
none does, the solve ends: ``ok`` is false and the samples from there on are ``inf``. Only the
factors are kept between steps: a step longer or shorter than theirs by more than
:data:`REFACTOR` begins with a new matrix.

**Batches.** Each step's attempts (the chord iterations, a new matrix where asked, substeps)
are one loop (:meth:`_Stepper.substeps`) of one iteration for a common step, and the steps of
an interval a loop whose length does not depend on the state. Under ``jax.vmap`` a loop whose
condition is batched copies its carry with a select at each iteration; so a batch of rods
copies the factors once a step, and costs per rod what one rod costs alone
(benchmarks/README.md).

**Steps longer than the samples.** The caller may lay the steps on a uniform grid of its own
(:func:`step_grid`) and take the samples from the grid's states by cubic Hermite interpolation
(:func:`hermite_samples`), whose $O(H^3)$ error is that of the rule's own step: the cost then
follows the step chosen for the motion, not the samples wanted.

**Derivatives.** Each step's (or substep's) solution $y(x_n, p)$ is differentiated by the
project's one implicit-derivative rule (:func:`rbo_jax.solvers.implicit`):
$dy = (I - \tfrac h2 J)^{-1} [(I + \tfrac h2 J)\,dx_n + h\,\partial_p f\,dp]$ with $J$ at
the midpoint, its block-tridiagonal
matrix from $3m$ products and one block elimination; the chord iterations are never
differentiated. With the steps' counts known before tracing (``max_count``) every loop has a
fixed length, so ``jax.grad`` (reverse mode) runs through the solve: it transposes one
block-tridiagonal solve per step, each step recomputed on the way back (``jax.checkpoint``:
memory of one state per step); forward mode (``jax.jvp``) works with traced counts too.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..solvers import (
    RUNNING,
    FactoredTridiagonal,
    Implicit,
    Tridiagonal,
    implicit,
    iterate,
    newton_update,
    tridiagonal_differences,
    tridiagonal_factor,
)

__all__ = ["hermite_samples", "midpoint", "step_grid"]

# after a step whose kept Jacobian failed, the next steps begin with a new one (at the
# predicted midpoint) instead of chord iterations that would fail first
EAGER_STEPS = 8
# the new Jacobians a step may take when its chord iterations do not converge
MAX_REFRESH = 2
# the most substeps of a step whose Newton iterations do not converge (2, 4, ... of them)
MAX_SUBSTEPS = 8
# the relative change of the step beyond which the next step begins with a new matrix
# I - h/2 J (a matrix of a step within it still contracts the chord iterations: by about half
# of it)
REFACTOR = 0.05
# the steps whose rates give the chord's start (module docstring): a quadratic in time
PREDICTOR_RATES = 3


def _once_if(pred, fn, x):
    """``fn(x)`` where ``pred``, else ``x``: a ``while`` loop of at most one iteration, which
    under ``jax.vmap`` runs ``fn`` only when a member needs it (a ``cond`` would run both)."""

    def body(c):
        return False, fn(c[1])

    return lax.while_loop(lambda c: c[0], body, (pred, x))[1]


def _frozen(tree):
    """``tree`` with its float leaves cut from differentiation (the chord iterations)."""
    dynamic, static = eqx.partition(tree, eqx.is_inexact_array)
    return eqx.combine(lax.stop_gradient(dynamic), static)


def _no_rates(x0, h0):
    """The carry of :func:`_remember` before the first step: no rate yet."""
    return (
        jnp.zeros((PREDICTOR_RATES, *x0.shape), x0.dtype),
        jnp.full((PREDICTOR_RATES,), h0),
        jnp.asarray(0, jnp.int32),
    )


def _remember(rates, rate, h):
    """``rates`` with the last step's ``rate`` over its step ``h`` first (the oldest dropped)."""
    r, hs, k = rates
    return (
        jnp.concatenate([rate[None], r[:-1]]),
        jnp.concatenate([jnp.reshape(h, (1,)).astype(hs.dtype), hs[:-1]]),
        jnp.minimum(k + 1, PREDICTOR_RATES),
    )


def _extrapolated(rates, h):
    r"""The rate over the next step $h$ from the last ``k`` steps' rates $s_i$ (newest first),
    each at its step's midpoint $\tau_i$ (relative to $t_n$): their Lagrange polynomial at
    $h/2$, $\sum_i s_i \prod_{j \ne i} (h/2 - \tau_j)/(\tau_i - \tau_j)$ (equal steps: $3s_1
    - 3s_2 + s_3$); zero before the first step."""
    r, hs, k = rates
    tau = 0.5 * hs - jnp.cumsum(hs)
    at = 0.5 * h
    out = jnp.zeros_like(r[0])
    for m in range(1, PREDICTOR_RATES + 1):  # through the last m rates
        value = 0.0
        for i in range(m):
            w = 1.0
            for j in range(m):
                if j != i:
                    w = w * (at - tau[j]) / (tau[i] - tau[j])
            value = value + w * r[i]
        out = jnp.where(k == m, value, out)
    return out


class _Residual(eqx.Module):
    r"""$G(y \oplus d) = y + d - x - h\,f(t + h/2, (x + y + d)/2)$ of one step, at the
    parameters ``(args, x, t, h, root, converged)`` (:func:`rbo_jax.solvers.implicit`)."""

    field: Callable = eqx.field(static=True)

    def __call__(self, y, d, params):
        args, x, t, h, _, _ = params
        z = y + d
        return z - x - h * self.field(t + 0.5 * h, 0.5 * (x + z), args)


def _found(params):
    """The step's solution, found by the chord iterations before (``params[4]``)."""
    return Implicit(params[4], None, params[5], None)


class _Stepper(eqx.Module):
    """The steps of :func:`midpoint`: the chord iterations (on frozen arguments: never
    differentiated) and each step's differentiable solution through :func:`_found`."""

    field: Callable = eqx.field(static=True)
    args: object
    frozen: object
    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    max_newton: int = eqx.field(static=True)
    project: Callable | None = eqx.field(static=True)

    def factor(self, J, h):
        L, D, U = J
        eye = jnp.eye(D.shape[-1], dtype=D.dtype)
        return tridiagonal_factor(-0.5 * h * L, eye[None] - 0.5 * h * D, -0.5 * h * U)

    def newton(self, x, y0, fac, h, t):
        r"""The chord iterations of one step from ``y0``: the project's one loop
        (:func:`rbo_jax.solvers.iterate`) of Newton's update with the step's factors. With
        $\|\cdot\|$ the largest component over ``atol + rtol |y|`` and the contraction
        $\theta_k = \|\Delta_k\|/\|\Delta_{k-1}\|$, the iterate after the update $\Delta_k$
        is within $\theta_k/(1 - \theta_k)\,\|\Delta_k\|$ of the root: the iterations stop
        when that is at most 1 (or $\|\Delta_k\| \le 1$) (Hairer & Wanner, *Solving ODEs
        II*, IV.8). An update that grows does not end them: the chord's transient growth
        (measured: a stiff tip's rate) is followed by convergence."""
        residual = _Residual(self.field)

        def chord(y, last):
            r = residual(y, 0.0, (self.frozen, x, t, h, None, None))
            y_new, d, done, finite = newton_update(
                r, fac, FactoredTridiagonal(), y, rtol=self.rtol, atol=self.atol
            )
            size = jnp.max(jnp.abs(d) / (self.atol + self.rtol * jnp.abs(y)))
            theta = size / last  # 0 at the first update (last = inf)
            close = (theta < 1) & (theta * size <= 1 - theta) & jnp.isfinite(last)
            code = jnp.where(finite, jnp.where(done | close, 0, RUNNING), 1)
            return y_new, size, code

        y, _, code, _ = iterate(
            chord, y0, jnp.asarray(jnp.inf, y0.dtype), max_steps=self.max_newton, exhausted=1
        )
        return y, code == 0

    def substeps(self, fac, refreshes, x, y0, h, t, eager, ok):
        """``(fac, refreshes, states, count, converged, rounds)`` of one step from ``x``,
        one loop of attempts, each a chord solve (:meth:`newton`), a new matrix first where
        asked: the whole step from ``y0`` with the kept matrix (a new one first where
        ``eager``), then up to :data:`MAX_REFRESH` new ones at the midpoint of the chord's last
        iterate; where that fails, 2, 4, ... :data:`MAX_SUBSTEPS` equal substeps, each count's
        first substep with a new matrix, each substep with its own new ones, until a count's
        every substep converges. ``states[j]``: the state after substep ``j`` (``states[0] =
        x``); ``rounds``: the most attempts of one solve (more than one: the kept matrix
        failed). One loop, so that the program holds one copy of the iterations and of the
        Jacobian's products, and under ``jax.vmap`` a common step (one attempt) copies the
        factors by one select (module docstring). Nothing is done where ``ok`` is false (a
        step after a failure)."""

        def attempt(c):
            fac, refreshes, states, count, j, tries, y, rounds, _, _ = c
            hs = h / count.astype(h.dtype)
            xj, tj = states[j], t + j.astype(h.dtype) * hs
            first = jnp.where(count == 1, eager, j == 0)  # a new matrix before the first try

            def jacobian(c):
                fac, refreshes, y = c
                y = jnp.where(jnp.all(jnp.isfinite(y)), y, xj)
                J = tridiagonal_differences(
                    lambda z: self.field(tj + 0.5 * hs, z, self.frozen), 0.5 * (xj + y)
                )
                return self.factor(J, hs), refreshes + 1, y

            need = (tries > 0) | first
            fac, refreshes, y = _once_if(need, jacobian, (fac, refreshes, y))
            y, conv = self.newton(xj, y, fac, hs, tj)
            tries, rounds = tries + 1, jnp.maximum(rounds, tries + 1)
            states = states.at[j + 1].set(y)  # (a failed iterate: overwritten by a retry)
            whole = conv & (j + 1 == count)  # the step's every substep converged
            failed = ~conv & (tries > MAX_REFRESH)  # this solve is given up: more substeps
            last = failed & (count >= MAX_SUBSTEPS)
            count = jnp.where(failed, 2 * count, count)
            j = jnp.where(conv, j + 1, jnp.where(failed, 0, j))
            tries = jnp.where(conv | failed, 0, tries)
            y = jnp.where(conv | failed, states[j], y)  # a substep starts from its state
            return fac, refreshes, states, count, j, tries, y, rounds, whole, whole | last

        states = jnp.zeros((MAX_SUBSTEPS + 1, *x.shape), x.dtype).at[0].set(x)
        zero = jnp.asarray(0)
        start = (fac, refreshes, states, zero + 1, zero, zero, y0, zero, ~ok, ~ok)
        out = lax.while_loop(lambda c: ~c[9], attempt, start)
        fac, refreshes, states, count, _, _, _, rounds, conv, _ = out
        return fac, refreshes, states, jnp.minimum(count, MAX_SUBSTEPS), conv & ok, rounds

    def step(self, c):
        """One step of the carry ``(x, rates, fac, h, t, ok, refreshes, eager_left)``
        (``rates``: :func:`_remember`'s)."""
        x, rates, fac, h, t, ok, refreshes, eager_left = c
        xs, hs = lax.stop_gradient(x), lax.stop_gradient(h)
        y0 = xs + hs * _extrapolated(lax.stop_gradient(rates), hs)  # the chord's start
        fac, refreshes, states, count, conv, rounds = self.substeps(
            fac, refreshes, xs, y0, hs, t, eager_left > 0, ok
        )
        # a new matrix first for the next steps where the kept one failed (or was for substeps)
        fresh = (rounds > 1) | (count > 1)
        eager_left = jnp.where(fresh, EAGER_STEPS, jnp.maximum(eager_left - 1, 0))
        y = self.chain(x, t, h, states, count, conv)
        rates = _remember(rates, (y - x) / h, h)  # the next step's start
        if self.project is not None:
            y = self.project(y)
        good = ok & conv & jnp.all(jnp.isfinite(y))
        return jnp.where(good, y, x), rates, fac, h, t + h, good, refreshes, eager_left

    def chain(self, x, t, h, states, count, conv):
        """The step's solution through its ``count`` substeps' roots ``states[1:]``, each
        differentiated by the implicit-derivative rule (the rest skipped)."""
        residual, hs = _Residual(self.field), h / jnp.asarray(count).astype(h.dtype)

        def one(y, j):
            def solved(y):
                params = (
                    self.args,
                    y,
                    t + jnp.asarray(j).astype(hs.dtype) * hs,
                    hs,
                    states[j + 1],
                    conv,
                )
                return implicit(_found, residual, params, linear=Tridiagonal()).y

            return lax.cond(j < count, solved, lambda y: y, y), None

        return lax.scan(one, x, jnp.arange(MAX_SUBSTEPS))[0]


def midpoint(
    field,
    x0,
    ts,
    counts,
    steps,
    *,
    args=None,
    rtol,
    atol,
    max_newton: int = 8,
    project=None,
    max_count: int | None = None,
    uniform: bool = False,
):
    r"""Samples of $\dot x = f(t, x)$ at ``ts`` ``(K+1,)`` from ``x0`` ``(N, m)``:
    ``counts[k]`` steps of ``steps[k]`` between samples $k$ and $k+1$ (module docstring).
    ``field(t, x, args)`` maps ``(N, m)`` to ``(N, m)`` and couples neighbouring blocks only;
    ``args`` (a pytree: the model) is differentiated through each step's implicit derivative;
    ``project(x)``, if given, is applied after each step (a change of chart that leaves the
    state the same, e.g. a turn-vector recentred). ``max_count``: a Python int, at least every
    count, known before tracing: each interval is then a loop of that length (reverse-mode
    derivatives); ``None``: each runs its own count (forward mode only). ``uniform``: every
    count equals ``max_count`` (no step is masked: a plain loop).

    Returns ``(xs, ok, refreshes)``: the samples ``(K+1, N, m)`` (``x0`` first; ``inf`` from a
    failed step on), whether every step converged, and how many times the Jacobian was
    computed."""
    stepper = _Stepper(field, args, _frozen(args), rtol, atol, max_newton, project)
    checkpointed = jax.checkpoint(lambda s: stepper.step(s))  # a closure: the stepper is traced

    def interval(c, inputs):
        x, rates, fac, h_fac, ok, refreshes, eager = c
        n, h, t = inputs
        # a step that differs from the kept matrix's by more than REFACTOR begins with a new
        # matrix (the spans of ts differ by rounding: within it, the kept one serves)
        again = jnp.abs(h - h_fac) > REFACTOR * h_fac
        eager = jnp.where(again, jnp.maximum(eager, 1), eager)
        before = refreshes
        inner = (x, rates, fac, h, t, ok, refreshes, eager)
        if max_count is None:  # each interval its own count
            inner = lax.while_loop(
                lambda s: s[0] < n,
                lambda s: (s[0] + 1, stepper.step(s[1])),
                (0, inner),
            )[1]
        else:  # a loop of fixed length, the steps past the count skipped

            def fixed(s, i):
                if uniform:  # after a failure the steps do nothing (flagged)
                    return checkpointed(s), None
                return lax.cond(i < n, checkpointed, lambda s: s, s), None

            inner = lax.scan(fixed, inner, jnp.arange(max_count, dtype=counts.dtype))[0]
        x, rates, fac, _, _, ok, refreshes, eager = inner
        # a new matrix was factored with h (or a substep of it: where that fails the chord,
        # the next step makes a new one)
        h_fac = jnp.where(refreshes > before, h, h_fac)
        return (x, rates, fac, h_fac, ok, refreshes, eager), jnp.where(ok, x, jnp.inf)

    # no matrix yet: the first step makes one (eager), at its predicted midpoint; every matrix
    # is made in one place (the step's attempts), so that the program holds one copy of the
    # Jacobian's products (the compilation's largest part), and only its factors are carried
    h0 = lax.stop_gradient(steps[0])
    N, m = x0.shape
    J0 = tuple(jax.ShapeDtypeStruct((N, m, m), x0.dtype) for _ in range(3))
    shapes = jax.eval_shape(stepper.factor, J0, h0)
    fac0 = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)
    carry = (x0, _no_rates(x0, h0), fac0, h0, True, 0, 1)
    carry = jax.tree_util.tree_map(jnp.asarray, carry)
    (_, _, _, _, ok, refreshes, _), xs = lax.scan(interval, carry, (counts, steps, ts[:-1]))
    return jnp.concatenate([x0[None], xs]), ok, refreshes


def step_grid(ts, dt: float):
    r"""The uniform grid of steps of at most ``dt`` over ``[ts[0], ts[-1]]`` (host, NumPy):
    $S = \max(\lceil \mathrm{span}/dt\rceil, 2)$ steps, where ``dt`` is longer than an interval
    of ``ts`` and :func:`midpoint` steps over samples (:func:`hermite_samples` then gives them)."""
    ts = np.asarray(ts, dtype=np.float64)
    span = ts[-1] - ts[0]
    steps = max(int(np.ceil(span / dt - 1e-9)), 2)
    return np.concatenate([ts[0] + span * np.arange(steps) / steps, ts[-1:]])


def hermite_samples(xs, grid, ts, align=None):
    r"""The states at ``ts`` between the states ``xs`` ``(S+1, ...)`` of the uniform ``grid``
    (:func:`step_grid`): cubic Hermite on each step, the slopes central differences of the
    neighbours (second-order one-sided at the ends), so the error is $O(H^3)$, the order of
    the midpoint rule's own error in a step, and each grid state is returned exactly.
    ``align(ref, x)``, if given, puts ``x`` in the chart of ``ref`` (e.g. the representative of a
    turn nearest to ``ref``'s) for a sample's four neighbouring states before they are
    combined. A sample next to a state that is not finite (a failed step) is ``inf``."""
    xs, grid, ts = jnp.asarray(xs), jnp.asarray(grid), jnp.asarray(ts)
    S = xs.shape[0] - 1
    u = (ts - grid[0]) * (S / (grid[-1] - grid[0]))
    left = jnp.clip(jnp.floor(u), 0, S - 1)
    j = left.astype(jnp.int32)
    s = (u - left).reshape(-1, *([1] * (xs.ndim - 1)))
    around = jnp.arange(-1, 3, dtype=jnp.int32)[None, :]
    P = xs[jnp.clip(j[:, None] + around, 0, S)]  # (K, 4, ...): states j-1, j, j+1, j+2
    if align is not None:
        P = jax.vmap(lambda p: jax.vmap(lambda q: align(p[1], q))(p))(P)
    x0, x1, x2, x3 = (P[:, i] for i in range(4))
    first, last = (j == 0).reshape(s.shape), (j == S - 1).reshape(s.shape)
    m0 = jnp.where(first, -1.5 * x1 + 2.0 * x2 - 0.5 * x3, 0.5 * (x2 - x0))  # H x'(t_j)
    m1 = jnp.where(last, 1.5 * x2 - 2.0 * x1 + 0.5 * x0, 0.5 * (x3 - x1))  # H x'(t_j+1)
    s2, s3 = s * s, s * s * s
    out = (2 * s3 - 3 * s2 + 1) * x1 + (s3 - 2 * s2 + s) * m0
    out = out + (3 * s2 - 2 * s3) * x2 + (s3 - s2) * m1
    finite = jnp.all(jnp.isfinite(P.reshape(P.shape[0], -1)), axis=1)
    return jnp.where(finite.reshape(s.shape), out, jnp.inf)
