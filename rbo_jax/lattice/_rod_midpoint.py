r"""The implicit midpoint rule for a rod (``lattice.simulate(..., method="midpoint")``) and
the default method's choice between it and the explicit one (:func:`auto`).

The rod's state is packed body by body, ``(N+1, 12)`` (turn, position, angular velocity,
velocity), and integrated by :func:`rbo_jax.integrate.midpoint.midpoint` with the rod's
equations (:func:`rbo_jax.models.rod.rates`) as the field: steps set by the motion wanted, not
by the stiff waves. With concrete inputs the program is compiled once per structure of the rod
and kept by the program store when it is on (:func:`rbo_jax.enable_compilation_cache`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .. import _programs
from .._validation import is_traced
from ..integrate.midpoint import hermite_samples, midpoint, step_grid
from ..models.rod import RodState, rates
from ._recentre import nearest_turn, within_pi
from ._rod_verlet import (
    _static_zeros,
    failed_after_first,
    fixed_step_status,
    host_counts,
    stable_step,
    step_of,
    traced_counts,
)

__all__ = ["auto", "midpoint_rod", "step_bound"]


# method="auto" takes the midpoint rule where the splitting's stable step (which holds every
# explicit method near it) is below STIFF_RATIO times the midpoint rule's step: there the
# explicit method takes more steps than the midpoint rule, each of 12 evaluations against the
# midpoint step's 3-4 (measured: benchmarks/README.md, History)
STIFF_RATIO = 1.0
# the midpoint rule's default step: the shortest interval of ts, and at most span/MIDPOINT_STEPS
MIDPOINT_STEPS = 1000


def _midpoint_step(ts, xp=np):
    """The default step of ``method="midpoint"``: the shortest interval between samples, at
    most the span over :data:`MIDPOINT_STEPS`."""
    return xp.minimum(xp.min(xp.diff(ts)), (ts[-1] - ts[0]) / MIDPOINT_STEPS)


def _primal(x):
    """The value of ``x`` where it is known before the program runs: ``x`` itself when
    concrete, the value under ``jax.grad`` or ``jax.jvp`` outside ``jax.jit`` (a tracer's
    primal); ``None`` under ``jax.jit`` and ``jax.vmap``."""
    while isinstance(x, jax.core.Tracer):
        x = getattr(x, "primal", None)
        if x is None:
            return None
    return x


def step_bound(rod):
    r"""An upper bound of :func:`._rod_verlet.stable_step` from the rod's stiffnesses and
    masses alone (host, NumPy; ``None`` where they are traced or give none): the largest
    eigenvalue of the mass-scaled stiffness is at least its Rayleigh quotient at a unit
    translation of a free body $i$, at least $\sum_s \min_j k^g_{s,j}/m_i$ over its couplings
    $s$ (the gap's derivative in a body's position is a rotation), and the stable step
    decreases with it: where the bound is below the midpoint rule's step, so is the stable
    step, and :func:`auto` needs no program to choose."""
    leaves = (rod.gap_stiffness, rod.mass, rod.turn_damping, rod.gap_damping)
    if any(is_traced(x) for x in leaves):
        return None
    k = np.min(np.asarray(rod.gap_stiffness, np.float64), axis=1)
    per_body = np.concatenate([k, [0.0]]) + np.concatenate([[0.0], k])
    free = rod.free_masks()[1]
    lam = np.max(per_body[free] / np.asarray(rod.mass, np.float64)[free], initial=0.0)
    if not (np.isfinite(lam) and lam > 0):
        return None
    eta = max(np.max(np.asarray(rod.turn_damping)), np.max(np.asarray(rod.gap_damping)))
    return step_of(np.sqrt(lam), eta, xp=np)


def auto(rod, state0, ts, solver, traced, dt=None):
    """The default method: ``"midpoint"`` for a stiff rod (its explicit stable step below
    the midpoint rule's step, :data:`STIFF_RATIO`), else ``"explicit"``; ``"explicit"``
    with a ``solver``. The choice is made from the values (under ``jax.grad`` and ``jax.jvp``
    their primal values, so that a derivative is the derivative of the same solve); where they
    are unknown before the program runs (``jax.jit``, ``jax.vmap``), ``"midpoint"``, which
    works for every rod."""
    if solver is not None:
        return "explicit"
    if traced:
        leaves, tree = jax.tree_util.tree_flatten((rod, state0, ts, dt))
        known = [_primal(x) for x in leaves]
        if any(k is None for k in known):
            return "midpoint"
        rod, state0, ts, dt = jax.tree_util.tree_unflatten(tree, known)
    if is_traced(ts) or is_traced(dt):
        return "midpoint"
    h_mid = float(_midpoint_step(np.asarray(ts, dtype=np.float64)) if dt is None else dt)
    if not (np.isfinite(h_mid) and h_mid > 0):  # a bad dt: the midpoint rule says so
        return "midpoint"
    bound = step_bound(rod)
    if bound is not None and bound < STIFF_RATIO * h_mid:  # no program compiled to know it
        return "midpoint"
    h = stable_step(rod, state0)
    if is_traced(h):
        return "midpoint"
    return "midpoint" if float(h) < STIFF_RATIO * h_mid else "explicit"


def _pack(state: RodState):
    """``(N+1, 12)``: each body's turn, position, angular velocity and velocity."""
    return jnp.concatenate([state.theta, state.r, state.Omega, state.v], axis=-1)


def _unpack(x) -> RodState:
    return RodState(x[..., 0:3], x[..., 3:6], x[..., 6:9], x[..., 9:12])


def _recentred(x):
    """The packed state with its turn-vectors within π (:func:`._recentre.within_pi`)."""
    return x.at[:, 0:3].set(within_pi(x[:, 0:3]))


def _aligned(ref, x):
    """The packed state ``x`` with its turns in the chart of ``ref``'s (an interpolation)."""
    return x.at[:, 0:3].set(nearest_turn(x[:, 0:3], ref[:, 0:3]))


def _field(t, x, rod):
    """The rod's equations on the packed state ``(N+1, 12)`` (the midpoint rule's field)."""
    return _pack(rates(rod, _unpack(x), 1.0, t))


def _field_undamped(t, x, rod):
    """:func:`_field` of a rod whose forces do not read the velocities (``_static_zeros``)."""
    return _pack(rates(rod, _unpack(x), 1.0, t, damped=False))


def _midpoint_program(rod, state0, ts, dt, rtol, atol, max_steps, damped=True):
    """``(states, ok, steps, too_many, bad_dt)`` of ``method="midpoint"``
    (:func:`rbo_jax.integrate.midpoint.midpoint`), the step counts in the program."""
    if dt is None:
        dt = _midpoint_step(ts, jnp)
    counts, steps, too_many, bad_dt = traced_counts(ts, dt, max_steps)
    xs, ok, _ = midpoint(
        _field if damped else _field_undamped, _pack(state0), ts, counts, steps, args=rod,
        rtol=rtol, atol=atol, project=_recentred,
    )  # fmt: skip
    states = failed_after_first(_unpack(xs), too_many | bad_dt)
    return states, ok, jnp.sum(counts.astype(jnp.result_type(int))), too_many, bad_dt


def _midpoint_fixed(rod, state0, ts, counts, steps, rtol, atol, max_count, uniform, damped=True):
    """``(states, ok)`` of ``method="midpoint"`` with the counts known before tracing: loops
    of fixed length (``max_count``; ``uniform``: every count that long), which ``jax.grad``
    runs through."""
    xs, ok, _ = midpoint(
        _field if damped else _field_undamped, _pack(state0), ts, counts, steps, args=rod,
        rtol=rtol, atol=atol, project=_recentred, max_count=max_count, uniform=uniform,
    )  # fmt: skip
    return _unpack(xs), ok


def _sampled(states, grid, ts):
    """The states at ``ts`` from those on the step grid (:func:`hermite_samples`)."""
    xs = hermite_samples(_pack(states), grid, ts, align=_aligned)
    return _unpack(jax.vmap(_recentred)(xs))


def _midpoint_packed(*args):
    """:func:`_midpoint_program` with the states packed (plain arrays: the program store)."""
    states, *rest = _midpoint_program(*args)
    return (_pack(states), *rest)


def _sampled_packed(states, grid, ts):
    return _pack(_sampled(states, grid, ts))


_midpoint_stored = _programs.program(_midpoint_packed, small=True)
_sampled_stored = _programs.program(_sampled_packed, small=True)


def _midpoint_jit(*args):
    """The eager midpoint program, kept by the program store when it is on
    (:func:`rbo_jax.enable_compilation_cache`)."""
    x, *rest = _midpoint_stored(*args)
    return (_unpack(x), *rest)


def _sampled_jit(states, grid, ts):
    return _unpack(_sampled_stored(states, grid, ts))


_midpoint_fixed_jit = _programs.jit(_midpoint_fixed, small=True)

_MIDPOINT_FAILED = (
    "the midpoint rule's Newton iterations did not converge (method='midpoint'{}): the step "
    "is too long for the motion, or the motion blew up; pass a smaller dt."
)


def midpoint_rod(rod, state0, ts, bad_times, dt, rtol, atol, max_steps, staged):
    """``method="midpoint"``: ``(states, status, steps, messages)``. With concrete ``ts`` and
    ``dt`` the step and its counts are checked on the host first (a ``ValueError``); under a
    transformation every loop then has a fixed length (``jax.grad`` runs through it), in an
    eager call each interval runs its own count (a ``while`` loop, faster a step than the loop
    of fixed length: benchmarks/README.md). With traced ones the counts are computed in the
    program."""
    if not is_traced(ts) and not is_traced(dt):
        ts_host = np.asarray(ts, dtype=np.float64)
        h = float(_midpoint_step(ts_host)) if dt is None else float(dt)
        if not (np.isfinite(h) and h > 0):
            raise ValueError(f"lattice.simulate: dt must be finite and > 0, got {h}.")
        # steps longer than an interval of ts: on a uniform grid, the samples interpolated
        grid = step_grid(ts_host, h) if h > np.min(np.diff(ts_host)) * (1 + 1e-9) else None
        run = ts_host if grid is None else grid
        span, counts, total = host_counts(run, h, max_steps, "midpoint")
        stripped, damped = _static_zeros(rod)  # zero offsets and no damping: a smaller program
        if staged:
            states, ok = _midpoint_fixed_jit(
                stripped, state0, jnp.asarray(run), jnp.asarray(counts.astype(np.int32)),
                jnp.asarray(span / counts, dtype=jnp.result_type(float)), float(rtol),
                float(atol), int(np.max(counts)), bool(np.all(counts == counts[0])), damped,
            )  # fmt: skip
        else:
            dt = jnp.asarray(h, dtype=jnp.result_type(float))
            states, ok, _, _, _ = _midpoint_jit(
                stripped, state0, jnp.asarray(run), dt, float(rtol), float(atol),
                int(max_steps), damped,
            )  # fmt: skip
        if grid is not None:
            states = _sampled_jit(states, jnp.asarray(grid), jnp.asarray(ts))
        steps, too_many, bad_dt = jnp.asarray(total), False, False
    else:
        ts = jnp.where(bad_times, jnp.zeros_like(ts), ts) if is_traced(ts) else ts
        if dt is not None:
            dt = jnp.asarray(dt, dtype=jnp.result_type(float))
        stripped, damped = _static_zeros(rod)  # what is concretely zero, as above
        states, ok, steps, too_many, bad_dt = _midpoint_program(
            stripped, state0, jnp.asarray(ts), dt, float(rtol), float(atol), int(max_steps),
            damped,
        )  # fmt: skip
    status, messages = fixed_step_status(
        ok, too_many, bad_dt, "midpoint", max_steps, _MIDPOINT_FAILED.format("")
    )
    return states, status, steps, messages
