r"""The two loops of the ensemble integrator, around one shape-polymorphic step attempt.

- :func:`solve_one` integrates one trajectory (scalar components): a ``lax.while_loop`` of step
  attempts. It is what ``jax.jvp`` differentiates and what ``jax.vmap`` of a derivative batches
  (then in lockstep).
- :func:`solve_lanes` integrates N trajectories on B lanes, a structure of arrays: every iteration
  makes one step attempt on every lane (accept and reject by masks, which reproduces SciPy's step
  sequence per lane), and when at least R lanes are idle, up to R of them take the next trajectories
  from the queue ("refill"). Lockstep batching wastes the iterations that fast lanes spend waiting
  for the slowest; refilling keeps most lane work useful. The queue is run longest first
  (:mod:`._queue`): every trajectory makes a few step attempts, then the unfinished ones resume from
  their saved states in the order of their extrapolated remaining work, so that the longest do not
  start last. When the queue is empty, a large batch's running lanes are gathered into a narrower
  loop (:func:`tail_widths`), so that its last, longest trajectories do not cost every lane.

The layout (refilled lanes rather than ``jax.vmap`` of the per-trajectory loop or lockstep
lanes; benchmarks/README.md, History): stages as a tuple of ``(B,)`` arrays (not stacked
``(6, B)`` arrays, not a ``(13, 6, B)`` array with ``tensordot``), the stages in a loop over the
tableau's rows (one traced copy of the vector field, :func:`rbo_jax.integrate.dop853.stages`),
every stage value stored (:class:`rbo_jax.integrate.dop853.Store`).

Samples at ``ts`` come from the method's dense output (7th order), computed only on steps that
contain a sample (three more evaluations, made by the step's stage loop when a lane has a sample
ahead); a sample at the end of a step is the step's own state. Samples after a failure stay
``inf``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from ..integrate import dop853 as D
from ..kinematics import storing
from ..trajectory import status_code as code
from . import _queue as Q
from ._problem import Problem, lane_axes, lanes, to_lanes, traced_once
from ._queue import PARKED, RUNNING, record


class Config(NamedTuple):
    """The static settings of a solve."""

    rtol: float
    atol: float
    max_steps: int
    singular_tol: float


def _initial(f, failure, t0, y0, t_bound, cfg: Config):
    """The solver state at t0; an initial state that fails the per-step checks (outside the
    domain, at a singular point) ends the solve at once with that status."""
    f0, h = D.initial_step(f, t0, y0, t_bound, cfg.rtol, cfg.atol)
    shape = jnp.shape(y0[0])
    failed = failure(y0, y0, cfg.singular_tol)
    status = jnp.where(failed == code("successful"), RUNNING, failed).astype(jnp.int32)
    return dict(
        t=jnp.full(shape, t0),
        y=tuple(y0),
        f=tuple(f0),
        h=h,
        rej=jnp.zeros(shape, bool),
        status=jnp.broadcast_to(status, shape),
        nacc=jnp.zeros(shape, jnp.int32),
        natt=jnp.zeros(shape, jnp.int32),
    )


def attempt(
    f, failure, st, t_bound, cfg: Config, store: D.Store, stages=D.stages, wants_dense=None
):
    """One step attempt for every running lane (``RungeKutta._step_impl`` unrolled by one attempt).
    Returns the new state and what the dense output needs. ``stages``: the Runge–Kutta map,
    :func:`rbo_jax.integrate.dop853.stages` or one that also pushes tangents through it.
    ``wants_dense(t_new)``: whether a lane has a sample in (t, t_new]; if any running lane has, the
    stage loop also makes the dense output's three extra stages (used only if the step is accepted:
    a rejected step with a sample wastes them, a rare case); ``False``: never (only the ends of the
    interval are sampled, :func:`rbo_jax.integrate.dop853.samplers`)."""
    t, y, f0, rej, status = st["t"], st["y"], st["f"], st["rej"], st["status"]
    running = status == RUNNING
    t_new, h, h_abs, too_small = D.trial_step(t, st["h"], rej, t_bound)
    if wants_dense is False:
        last = D.NS + 1
    else:
        dense = running if wants_dense is None else running & wants_dense(t_new)
        last = jnp.where(jnp.any(dense), D.N_EXT, D.NS + 1)
    y_new, K = stages(f, t, y, f0, h, store, last)
    err = lax.stop_gradient(D.error_norm(K, y, y_new, h_abs, cfg.rtol, cfg.atol))
    accept, h_next = D.controller(err, h_abs, rej)
    go = running & ~too_small
    commit = go & accept
    natt = st["natt"] + go.astype(jnp.int32)
    new = dict(
        t=jnp.where(commit, t_new, t),
        y=tuple(jnp.where(commit, a, b) for a, b in zip(y_new, y)),
        f=tuple(jnp.where(commit, a, b) for a, b in zip(D.slope(K, D.NS), f0)),
        h=jnp.where(go, h_next, h_abs),
        rej=(go & ~accept) | (~go & rej),
        nacc=st["nacc"] + commit.astype(jnp.int32),
        natt=natt,
    )
    status = jnp.where(running & too_small, code("step_size_collapse"), status)
    status = jnp.where(commit & (t_new >= t_bound), code("successful"), status)
    status = jnp.where(running & ~jnp.isfinite(err), code("nonfinite_state"), status)
    failed = failure(y, y_new, cfg.singular_tol)
    status = jnp.where(commit & (failed != code("successful")), failed, status)
    new["status"] = jnp.where(
        (status == RUNNING) & (natt >= cfg.max_steps), code("max_steps_reached"), status
    )
    return new, (commit, t, y, y_new, K, h)


def solve_one(problem: Problem, y0, ts, cfg: Config):
    """One trajectory: ``(samples (n_ts, 6), status, accepted steps)``."""
    store = D.Store(D.runtime_one((problem, y0, ts)))
    t_bound = ts[-1]
    with storing(store):
        f = traced_once(problem, store)
        st = _initial(f, problem.failure, ts[0], tuple(y0), t_bound, cfg)
        y_first = jnp.where(st["status"] == RUNNING, jnp.stack(y0), jnp.inf)
        out = jnp.full((ts.shape[0], 6), jnp.inf, dtype=ts.dtype).at[0].set(y_first)

        def write(out, idx, mask, values):
            return out.at[jnp.where(mask, idx, ts.shape[0])].set(values, mode="drop")

        def body(c):
            st, idx, out = c
            wants, sampler = D.samplers(ts, idx, block=ts.shape[0] > 2)
            st, step = attempt(f, problem.failure, st, t_bound, cfg, store, wants_dense=wants)
            sampler = sampler(step, st["t"])
            idx, out = D.emit(step, ts, idx, out, st["t"], write, sampler, block=SAMPLE_BLOCK)
            return st, idx, out

        st, _, out = lax.while_loop(
            lambda c: c[0]["status"] == RUNNING, body, (st, jnp.ones((), jnp.int32), out)
        )
    return out, st["status"], st["nacc"]


def _gather(pool, batched, ids):
    """The problems ``ids`` of the pool, in lane layout (batch last). Leaves may be NumPy arrays
    (``jax.vmap`` without ``jit`` passes batched NumPy input as it is): indexed as JAX arrays."""
    picked = jax.tree_util.tree_map(lambda x, b: jnp.asarray(x)[ids] if b else x, pool, batched)
    return jax.tree_util.tree_map(lambda x, b: jnp.moveaxis(x, 0, -1) if b else x, picked, batched)


def _put(lanes_tree, new_tree, batched, slots):
    """Write the lane-layout ``new_tree`` into the lanes ``slots`` (out of range: dropped)."""
    return jax.tree_util.tree_map(
        lambda a, v, b: a.at[..., slots].set(v, mode="drop") if b else a,
        lanes_tree,
        new_tree,
        batched,
    )


class _Lanes:
    """The per-lane problem functions of one loop: vmaps over the lanes' batch-last leaves."""

    def __init__(self, batched):
        self.batched = batched

    def f(self, problem):
        axes = lane_axes(problem, self.batched)
        return lambda t, y: lanes("f", problem, axes, t, y)

    def failure(self, problem):
        axes = lane_axes(problem, self.batched)
        return lambda y_old, y_new, tol: lanes("failure", problem, axes, y_old, y_new, tol)


def _refill(c, pool, batched, y0, ts, cfg: Config, fns: _Lanes, R: int, ordered: bool):
    """Up to R idle lanes take the next trajectories of the queue (``order``): their results
    are recorded (a parked lane's state saved, :func:`._queue.save`), their problems and states
    replaced: a new trajectory's initial state in the probe, a parked one's saved state after
    it (``ordered``: a batch run longest first; otherwise the probe is the whole run)."""
    B = c["tid"].shape[0]
    N = c["status_out"].shape[0]
    idle = c["st"]["status"] != RUNNING
    slots = jnp.nonzero(idle, size=R, fill_value=B)[0]
    new = c["next"] + jnp.arange(R, dtype=jnp.int32)
    ok = (slots < B) & (new < c["queued"])
    gid = jnp.where(ok, c["order"][jnp.minimum(new, N - 1)], N - 1)
    sl = jnp.where(ok, slots, B)
    c = Q.save(c, sl) if ordered else dict(c)
    done = jnp.where(ok, c["tid"][jnp.minimum(slots, B - 1)], N)
    c["status_out"] = (
        c["status_out"].at[done].set(c["st"]["status"][jnp.minimum(slots, B - 1)], mode="drop")
    )
    c["nacc_out"] = (
        c["nacc_out"].at[done].set(c["st"]["nacc"][jnp.minimum(slots, B - 1)], mode="drop")
    )
    problem = _gather(pool, batched, gid)

    def fresh(_):
        st = _initial(
            fns.f(problem), fns.failure(problem), ts[0], tuple(v[gid] for v in y0), ts[-1], cfg
        )
        return st, jnp.ones(R, jnp.int32)

    def resumed(_):
        return Q.unpack(c["saved"]["x"][gid], c["saved"]["n"][gid])

    st, idx = lax.cond(c["phase"] == 0, fresh, resumed, None) if ordered else fresh(None)
    c["st"] = jax.tree_util.tree_map(lambda a, v: a.at[sl].set(v, mode="drop"), c["st"], st)
    c["problem"] = _put(c["problem"], problem, batched, sl)
    c["tid"] = c["tid"].at[sl].set(gid, mode="drop")
    c["idx"] = c["idx"].at[sl].set(idx, mode="drop")
    c["next"] = c["next"] + jnp.sum(ok).astype(jnp.int32)
    return c


# Lane counts (B) and refill widths (R) are multiples of this, so that no trajectory lands in the
# scalar remainder of a vectorised loop: XLA's CPU code for the remainder rounds some fused
# expressions differently from the vector body, which made a trajectory's last bits depend on its
# position in the batch, hence on the chunk layout and the number of devices. 16 covers AVX-512
# in float32 (and every narrower vector).
VECTOR = 16
# one trajectory's samples within a step, taken this many at a time (D.emit's block): a record
# at 300 Hz under steps of ~50 ms puts ~15 samples in a step
SAMPLE_BLOCK = 16


def _round_up(n: int, m: int) -> int:
    return -(-int(n) // m) * m


# The tail (issue 31): once the queue is empty the lanes finish one by one, and each iteration
# still costs all B of them while the last, longest trajectories run on few (with 2 devices each
# has a tail as long as one device's). From :data:`COMPACT_FROM` trajectories on (a batch of
# several waves: a long run), the running lanes are then gathered into a narrower loop of B/4
# lanes (1008 -> 256 on a CPU). Each width is one more traced copy of the step: one narrower
# loop keeps most of the gain for the least compilation (benchmarks/README.md, History);
# smaller batches, whose first answer matters more than their tail, keep the one loop.
COMPACT_FROM = 2048
COMPACT_DIVISORS = (4,)


def tail_widths(B: int, N: int) -> tuple[int, ...]:
    """The narrower widths the B lanes are compacted to once the queue is empty (none for fewer
    than :data:`COMPACT_FROM` trajectories): B / :data:`COMPACT_DIVISORS`, rounded up to
    multiples of :data:`VECTOR`, so that every lane keeps its bits."""
    if N < COMPACT_FROM:
        return ()
    widths = sorted({_round_up(max(1, B // k), VECTOR) for k in COMPACT_DIVISORS}, reverse=True)
    return tuple(w for w in widths if w < B)


def _compact(c, batched, N, width: int):
    """The running lanes of ``c`` (at most ``width``), gathered into ``width`` lanes; the others'
    results recorded first. Lanes past the running ones hold no trajectory (tid N, idle)."""
    c = record(c, N)
    B = c["tid"].shape[0]
    running = c["st"]["status"] == RUNNING
    pick = jnp.nonzero(running, size=width, fill_value=B)[0]
    held = pick < B
    at = jnp.minimum(pick, B - 1)
    new = dict(c)
    new["st"] = jax.tree_util.tree_map(lambda a: a[at], c["st"])
    new["st"]["status"] = jnp.where(held, new["st"]["status"], code("successful"))
    new["problem"] = jax.tree_util.tree_map(
        lambda x, b: x[..., at] if b else x, c["problem"], batched
    )
    new["tid"] = jnp.where(held, c["tid"][at], N)
    new["idx"] = c["idx"][at]
    return new


def _running_over(width: int):
    return lambda c: jnp.sum(c["st"]["status"] == RUNNING) > width


def _tail(c, step, batched, N, widths):
    """The loops of the tail (no queue left): ``step`` on the running lanes compacted to each
    of ``widths`` in turn, until none runs."""
    for i, width in enumerate(widths):
        c = _compact(c, batched, N, width)
        narrower = widths[i + 1] if i + 1 < len(widths) else 0
        c = lax.while_loop(_running_over(narrower), step, c)
    return c


# The lanes of a batch (issue 31): at most ``lanes_`` (1000 on a CPU), and no more than a
# :data:`WAVES`-th of the batch (but :data:`MIN_LANES`), so that the queue refills every lane
# several times before it is empty. A batch on as many lanes as trajectories is one wave, which
# lasts as long as its longest trajectory while the other lanes idle. Four waves are near the
# best for every batch up to ~4,000 trajectories; from 4,000 on it is 1008 lanes
# (benchmarks/README.md, History).
WAVES = 4
MIN_LANES = 256


def lane_count(N: int, lanes_: int, waves: int = WAVES) -> int:
    """B, the refilled lanes of N trajectories: ``min(lanes_, max(MIN_LANES, N / waves))``,
    at most N, rounded up to a multiple of :data:`VECTOR`."""
    return _round_up(min(N, lanes_, max(MIN_LANES, -(-N // waves))), VECTOR)


def _start(pool, batched, y0, ts, cfg: Config, fns: _Lanes, B: int, ordered: bool):
    """The carry of :func:`solve_lanes` before its first iteration: B idle lanes, the queue in
    the batch's order, every sample ``inf`` but the first (``inf`` too for a bad start)."""
    N, nts = y0[0].shape[0], ts.shape[0]
    # Every lane starts idle, holding no trajectory (tid N): the loop's refill gives them
    # their first ones, so the program holds the initial step once (a separate start on B
    # lanes was a second copy of the vector field)
    problem = _gather(pool, batched, jnp.zeros(B, jnp.int32))
    zero = jnp.zeros(B, ts.dtype)
    st = dict(
        t=jnp.full(B, ts[0]),
        y=(zero,) * 6,
        f=(zero,) * 6,
        h=zero,
        rej=jnp.zeros(B, bool),
        status=jnp.full(B, code("successful"), jnp.int32),
        nacc=jnp.zeros(B, jnp.int32),
        natt=jnp.zeros(B, jnp.int32),
    )
    first_ok = fns.failure(to_lanes(pool, batched))(y0, y0, cfg.singular_tol) == code("successful")
    y_first = jnp.where(first_ok[:, None], jnp.stack(y0, -1), jnp.inf)
    out = jnp.full((N, nts, 6), jnp.inf, dtype=ts.dtype).at[:, 0].set(y_first)
    c = dict(
        st=st,
        problem=problem,
        tid=jnp.full(B, N, jnp.int32),
        idx=jnp.ones(B, jnp.int32),
        out=out,
        next=jnp.asarray(0, jnp.int32),
        status_out=jnp.zeros(N, jnp.int32),
        nacc_out=jnp.zeros(N, jnp.int32),
        # the queue (longest first, :mod:`._queue`): the batch's order in the probe (phase
        # 0), then the parked trajectories (phase 1), resumed from their saved states
        phase=jnp.zeros((), jnp.int32),
        order=jnp.arange(N, dtype=jnp.int32),
        queued=jnp.asarray(N, jnp.int32),
    )
    if ordered:
        c["saved"] = {"x": jnp.zeros((N, 14), ts.dtype), "n": jnp.zeros((N, 4), jnp.int32)}
    return c


def solve_lanes(
    pool: Problem, batched, y0, ts, cfg: Config, lanes_: int = 1000, waves: int = WAVES
):
    """N trajectories (``pool``: leaves with a leading axis N where ``batched``; ``y0``: six
    ``(N,)`` components) on :func:`lane_count` refilled lanes. Returns ``(samples (N, n_ts, 6),
    status (N,), accepted steps (N,))``."""
    N = y0[0].shape[0]
    B = lane_count(N, lanes_, waves)
    R = _round_up(max(1, B // 16), VECTOR)
    fns = _Lanes(batched)
    store = D.Store(D.runtime_one((pool, y0, ts)))
    with storing(store):
        # longest first (:mod:`._queue`), not for one wave (as many lanes as trajectories:
        # every trajectory starts at once) nor for a small batch (``ORDER_FROM``)
        ordered = N >= Q.ORDER_FROM and N > B
        c = _start(pool, batched, y0, ts, cfg, fns, B, ordered)

        def probed(c):
            return (c["phase"] == 0) & (c["next"] >= N)

        def wants_refill(c):
            n_idle = jnp.sum(c["st"]["status"] != RUNNING)
            want = (c["next"] < c["queued"]) & ((n_idle >= R) | (n_idle == B))
            return (want | probed(c)) if ordered else want

        def refill(c):
            if ordered:  # the end of the probe: the parked trajectories queued, longest first
                c = lax.cond(probed(c), lambda c: Q.longest_first(c, ts[0], ts[-1]), lambda c: c, c)
            return _refill(c, pool, batched, y0, ts, cfg, fns, R, ordered)

        def step(c):
            c = dict(c)
            wants, sampler = D.samplers(ts, c["idx"])
            problem = c["problem"]
            st, step = attempt(
                fns.f(problem), fns.failure(problem), c["st"], ts[-1], cfg, store, wants_dense=wants
            )
            tid = c["tid"]

            def write(out, idx, mask, values):
                return out.at[jnp.where(mask, tid, N), idx].set(values, mode="drop")

            c["idx"], c["out"] = D.emit(
                step, ts, c["idx"], c["out"], st["t"], write, sampler(step, st["t"])
            )
            if ordered:  # the probe's attempts spent: the lane is parked
                spent = (c["phase"] == 0) & (st["status"] == RUNNING) & (st["natt"] >= Q.PROBE)
                st = dict(st, status=jnp.where(spent, PARKED, st["status"]))
            c["st"] = st
            return c

        def body(c):
            # the refill: R idle lanes at a time, until fewer than R are idle (all B lanes in
            # the first iteration)
            return step(lax.while_loop(wants_refill, refill, c))

        widths = tail_widths(B, N)
        running_over = _running_over(widths[0] if widths else 0)
        c = lax.while_loop(
            lambda c: (c["next"] < c["queued"]) | running_over(c) | (ordered & (c["phase"] == 0)),
            body,
            c,
        )
        c = _tail(c, step, batched, N, widths)
    c = record(c, N)
    return c["out"], c["status_out"], c["nacc_out"]
