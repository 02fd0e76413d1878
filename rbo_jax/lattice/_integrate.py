r"""DOP853 for a whole lattice: one system of $6N$ equations, SciPy's steps.

The lattice is one ODE system: one step size, one error norm over all $6N$ scalars (SciPy's
``DOP853._estimate_error_norm`` of the whole state), SciPy's controller and initial step — the
steps ``scipy.integrate.solve_ivp(method="DOP853")`` takes on the flattened system. The step is
:mod:`rbo_jax.integrate.dop853`'s (the same tableau, stages in one loop, dense output on steps
with samples), with the state as six ``(N,)`` component arrays; only the norms sum over the
bodies. Memory is bounded: the sixteen slopes of a step, ``16 × 6 × N`` numbers (a chain in
blocks keeps ``6 × 6 × N`` of them, :mod:`._halo`), and the samples asked for.

**Turns across the singular spheres.** $Z(\theta)$ (4.11) is singular at $|\theta| = 2\pi k$;
a body in plane motion ($\theta\times\Omega = 0$) crosses these spheres harmlessly (a kink of a
chain turns its bodies by $2\pi$) and goes on. A body that nears one off the plane has its
turn-vector **re-centred** after the step, $\theta \to \theta\,(1 - 2\pi k/|\theta|)$ — the same
turn-tensor, a turn-vector far from the sphere — and its turn count ``turns`` increased by $k$;
the next step starts with a new first slope. Energies that depend on the turn only through the
turn-tensor (the couplings, :class:`rbo_jax.CosineFoundation`, no foundation) are unchanged by
it; a foundation such as (4.50) is then evaluated at the re-centred vector. With
``recenter=False`` the solve stops there with ``singular_point``, as :func:`rbo_jax.simulate`.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from ..integrate import dop853 as D
from ..kinematics import distance_to_singularity, storing
from ..models.lattice import Lattice, rates, right_forms
from ..models.rigid_body import RightForm
from ..trajectory import crossed_sphere
from ..trajectory import status_code as code
from ._halo import Whole
from ._recentre import recentre, recentre_due, transverse

__all__ = ["Config", "Problem", "solve"]

RUNNING = -1
# the checks of a step, in :meth:`Problem.flags`'s order
NONFINITE, DOMAIN, SINGULAR, RECENTRE = range(4)


class Config(NamedTuple):
    """The static settings of a lattice solve."""

    rtol: float
    atol: float
    max_steps: int
    singular_tol: float
    recenter: bool
    recenter_margin: float


def _norm(theta):
    return jnp.sqrt(theta[0] * theta[0] + theta[1] * theta[1] + theta[2] * theta[2])


class Problem(eqx.Module):
    """The lattice's equations of motion on the state tuple (θ0, θ1, θ2, Ω0, Ω1, Ω2), each
    component an ``(N,)`` array, and its checks."""

    lattice: Lattice
    forms: RightForm

    @classmethod
    def of(cls, lattice: Lattice) -> Problem:
        return cls(lattice, right_forms(lattice, throw=False))

    def f(self, t, y):
        dth, dOm = rates(self.lattice, self.forms, t, jnp.stack(y[:3]), jnp.stack(y[3:]))
        return (dth[0], dth[1], dth[2], dOm[0], dOm[1], dOm[2])

    def flags(self, y_old, y_new, cfg: Config):
        """Whether any of these bodies fails each check of an accepted step, a bool vector
        indexed by :data:`NONFINITE`, :data:`DOMAIN`, :data:`SINGULAR` and :data:`RECENTRE`: a
        non-finite state; a body outside its foundation's domain; a body off the plane that
        jumped across a singular sphere |θ| = 2πk in the step, or (``recenter=False``) came
        within ``singular_tol`` of one; a body that re-centring would move (``recenter=True``,
        :func:`._field.recentre`). Over the bodies given (the whole lattice, or a block of a
        chain: :mod:`._halo`)."""
        y_old, y_new = lax.stop_gradient((tuple(y_old), tuple(y_new)))
        theta = jnp.stack(y_new[:3])
        n, n_old = _norm(theta), _norm(jnp.stack(y_old[:3]))
        singular = crossed_sphere(n, n_old)
        if not cfg.recenter:
            near = jax.vmap(distance_to_singularity, in_axes=1)(theta) < cfg.singular_tol
            singular = singular | near
        moving = transverse(theta, jnp.stack(y_new[3:]))
        bodies = self.lattice.site_bodies()
        margin = jax.vmap(lambda b, th: b.domain_margin(th), in_axes=(self.lattice.body_axes(), 1))(
            bodies, theta
        )
        due = jnp.zeros_like(moving)
        if cfg.recenter:
            due = recentre_due(n, moving, cfg.recenter_margin)[1]
        return jnp.stack(
            [
                jnp.any(~jnp.isfinite(jnp.stack(y_new))),
                jnp.any(~(margin > 0)),
                jnp.any(singular & moving),
                jnp.any(due),
            ]
        )

    @staticmethod
    def status_of(flags):
        """The status code of an accepted step with these :meth:`flags` (over all bodies): the
        failure that must stop the solve, else ``successful``."""
        status = jnp.where(flags[DOMAIN], code("domain_error"), code("successful"))
        status = jnp.where(flags[SINGULAR], code("singular_point"), status)
        return jnp.where(flags[NONFINITE], code("nonfinite_state"), status)

    def recenter(self, y, cfg: Config):
        """:func:`._field.recentre` on the state tuple: ``(y, k per body)``."""
        theta, k = recentre(jnp.stack(y[:3]), jnp.stack(y[3:]), cfg.recenter_margin)
        return (theta[0], theta[1], theta[2]) + tuple(y[3:]), k


def _attempt(problem: Problem, c: dict, ts, cfg: Config, store, plan):
    """One step attempt of the whole lattice (SciPy's ``RungeKutta._step_impl``), the samples
    it passes written, the step's checks, and the re-centring after it: the new carry.
    ``plan``: how the stages are made and the bodies summed (:mod:`._halo`)."""
    c = dict(c)
    nts, t_bound = ts.shape[0], ts[-1]
    t, y, f0, rej, idx = c["t"], c["y"], c["f"], c["rej"], c["idx"]
    t_new, h, h_abs, too_small = D.trial_step(t, c["h"], rej, t_bound)
    dense = (idx < nts) & (ts[jnp.minimum(idx, nts - 1)] <= t_new)
    last = jnp.where(dense, D.N_EXT, D.NS + 1)
    f_start = tuple(jnp.where(c["first"] == 0, jnp.zeros_like(v), v) for v in f0)
    y_new, K, err, flags = plan.step(problem, t, y, f_start, h, h_abs, store, last, c["first"], cfg)
    err = lax.stop_gradient(err)
    accept, h_next = D.controller(err, h_abs, rej)
    go = ~too_small
    commit = go & accept
    step = (commit, t, y, y_new, K, h)
    turns = c["turns"]

    def write(carry_out, i, mask, values):
        out, tout = carry_out
        out = out.at[jnp.where(mask, i, nts)].set(values, mode="drop")
        tout = tout.at[jnp.where(mask, i, nts)].set(turns, mode="drop")
        return out, tout

    c["idx"], (c["out"], c["turns_out"]) = D.emit(
        step,
        ts,
        idx,
        (c["out"], c["turns_out"]),
        t_new,
        write,
        D.dense_sampler(step, ts, t_new, plan.slope, plan.dense_sums),
    )
    status = jnp.where(too_small, code("step_size_collapse"), c["status"])
    status = jnp.where(~jnp.isfinite(err), code("nonfinite_state"), status)
    failed = problem.status_of(flags)
    status = jnp.where(commit & (failed != code("successful")), failed, status)
    status = jnp.where(
        commit & (t_new >= t_bound) & (status == RUNNING), code("successful"), status
    )
    y_next = tuple(jnp.where(commit, a, b) for a, b in zip(y_new, y))
    # the next first slope: K[12] at the new point, or K[0] (the slope at (t, y)) after a reject
    f_next = tuple(jnp.where(commit, a, b) for a, b in zip(plan.slope(K, D.NS), plan.slope(K, 0)))
    first_next = jnp.asarray(1, jnp.int32)
    if cfg.recenter:
        # the bodies are re-centred only on a step that found one due (rare: one pass over the
        # state then, none otherwise); the predicate is the same on every shard of a chain
        moved = flags[RECENTRE] & commit & (status == RUNNING)

        def move(args):
            y, turns = args
            y_rec, k = problem.recenter(y, cfg)
            return y_rec, turns + k, jnp.sum(k > 0, dtype=jnp.int32)

        def keep(args):
            return args + (jnp.zeros((), jnp.int32),)

        y_next, c["turns"], count = lax.cond(moved, move, keep, (y_next, turns))
        c["nrec"] = c["nrec"] + count  # this shard's bodies: totalled once, at the end
        first_next = jnp.where(moved, 0, first_next)  # the state changed: a new first slope
    natt = c["natt"] + go.astype(jnp.int32)
    status = jnp.where(
        (status == RUNNING) & (natt >= cfg.max_steps), code("max_steps_reached"), status
    )
    c.update(
        t=jnp.where(commit, t_new, t),
        y=y_next,
        f=f_next,
        h=jnp.where(go, h_next, h_abs),
        rej=go & ~accept,
        status=status,
        nacc=c["nacc"] + commit.astype(jnp.int32),
        natt=natt,
        first=first_next,
    )
    return c


def solve(problem: Problem, y0, ts, cfg: Config, plan=None):
    """Integrate from ``y0`` (six ``(N,)`` components) at ``ts[0]`` and sample at ``ts``: a
    dict of ``samples`` (T, N, 6), ``turns`` (T, N) (re-centrings so far at each sample),
    ``status`` (a :class:`rbo_jax.SolveStatus` code), ``num_steps`` (accepted) and
    ``num_recentred`` (bodies re-centred in all). ``plan``: :class:`._halo.Whole` (default) or
    :class:`._halo.Halo` (a chain in blocks; inside ``shard_map``, this device's bodies)."""
    y0 = tuple(y0)
    N, nts = y0[0].shape[0], ts.shape[0]
    plan = Whole(N) if plan is None else plan
    store = D.Store(D.runtime_one((problem.lattice, y0, ts)))
    with storing(store):
        f0, h0, flags0 = plan.initial(problem, ts[0], y0, ts[-1], cfg)
        failed = problem.status_of(flags0)
        status0 = jnp.where(failed == code("successful"), RUNNING, failed).astype(jnp.int32)
        status0 = jnp.where(nts == 1, code("successful"), status0)
        first = jnp.where(status0 == RUNNING, jnp.stack(y0, -1), jnp.inf)
        out = jnp.full((nts, N, 6), jnp.inf, dtype=ts.dtype).at[0].set(first)
        zero = jnp.asarray(0, jnp.int32)
        c = dict(
            t=ts[0],
            y=y0,
            f=tuple(f0),
            h=h0,
            rej=jnp.asarray(False),
            status=status0,
            nacc=zero,
            natt=zero,
            idx=jnp.asarray(1, jnp.int32),
            out=out,
            turns=jnp.zeros(N, jnp.int32),
            turns_out=jnp.zeros((nts, N), jnp.int32),
            first=jnp.asarray(1, jnp.int32),
            nrec=zero,
        )
        c = lax.while_loop(
            lambda c: c["status"] == RUNNING,
            lambda c: _attempt(problem, c, ts, cfg, store, plan),
            c,
        )
    return dict(
        samples=c["out"],
        turns=c["turns_out"],
        status=c["status"],
        num_steps=c["nacc"],
        num_recentred=plan.sum(c["nrec"]).astype(jnp.int32),
    )
