r"""The queue of :func:`rbo_jax.ensemble._solve.solve_lanes`: what a lane holds, what is
recorded of a finished trajectory, and the order in which the trajectories take the lanes.

A lane's ``status`` is :data:`RUNNING` while it integrates its trajectory, :data:`PARKED` when
the trajectory spent its probe (below), or the trajectory's final status (a
:class:`rbo_jax.SolveStatus` code); a lane that is not running is idle and takes the next
trajectory of the queue at a refill, once its own result is recorded (:func:`record`) or its
state saved (:func:`save`).

**Longest first** (issue 31). A batch's last trajectories to start set its end: refilled lanes
in the batch's order left the longest ones, started late, running on few lanes long after the
rest (a chunk of the `rbo-jax sweep` benchmark, Nikolai final states at t1 = 600: 1,048 to
343,397 steps a trajectory, mean 88,900). So the queue is run twice. First the *probe*: every
trajectory makes at most :data:`PROBE` step attempts; the ones that end there are done, the
others are parked (their lanes' states saved by trajectory, :func:`save`). When every
trajectory has started once, the parked ones are queued again, longest first, by their
remaining work extrapolated from the probe: attempts so far × (t1 − t) / (t − t0)
(:func:`longest_first`), and each resumes from its saved state, so every trajectory takes the
same steps with the same bits as in one go. The lanes still running then (the last started)
go on to their ends unparked: waiting for their probes would idle the other lanes, and a batch
without long trajectories would lose its narrower tail (``_solve.tail_widths``).
"""

from __future__ import annotations

import jax.numpy as jnp

from ..trajectory import status_code as code

RUNNING = -1
PARKED = -2  # the status of a lane whose trajectory spent its probe (a trajectory of the queue)
PROBE = 256
# Only a batch of several waves and from this many trajectories on (a long run) is ordered: the
# order's program (the saves, the sort) adds to XLA's compilation of a batch
# (benchmarks/README.md, History), which a small batch's first answer would pay for a short tail.
ORDER_FROM = 2048


def record(c, N):
    """The statuses and step counts of the lanes that hold a finished (or parked) trajectory."""
    done = c["st"]["status"] != RUNNING
    tid = jnp.where(done, c["tid"], N)
    c = dict(c)
    c["status_out"] = c["status_out"].at[tid].set(c["st"]["status"], mode="drop")
    c["nacc_out"] = c["nacc_out"].at[tid].set(c["st"]["nacc"], mode="drop")
    return c


def pack(st, idx):
    """A lane's state as two rows: ``x`` its 14 reals (t, y, f, h), ``n`` its 4 integers (the
    rejection flag, accepted steps, attempts, next sample). Saved and restored as two arrays,
    not 18 (one scatter and one gather each: a smaller program)."""
    x = jnp.stack([st["t"], *st["y"], *st["f"], st["h"]], -1)
    n = jnp.stack([st["rej"].astype(jnp.int32), st["nacc"], st["natt"], idx], -1)
    return x, n


def unpack(x, n):
    """The running state and next sample of lanes restored from :func:`pack`'s rows."""
    st = dict(
        t=x[:, 0],
        y=tuple(x[:, 1 + i] for i in range(6)),
        f=tuple(x[:, 7 + i] for i in range(6)),
        h=x[:, 13],
        rej=n[:, 0] != 0,
        status=jnp.full(n.shape[0], RUNNING, jnp.int32),
        nacc=n[:, 1],
        natt=n[:, 2],
    )
    return st, n[:, 3]


def save(c, slots):
    """``c`` with the states of the parked lanes among ``slots`` (out of range: none) saved
    under their trajectories' ids, with their next sample's index."""
    B = c["tid"].shape[0]
    N = c["status_out"].shape[0]
    at = jnp.minimum(slots, B - 1)
    ids = jnp.where((slots < B) & (c["st"]["status"][at] == PARKED), c["tid"][at], N)
    x, n = pack(c["st"], c["idx"])
    c = dict(c)
    c["saved"] = {
        "x": c["saved"]["x"].at[ids].set(x[at], mode="drop"),
        "n": c["saved"]["n"].at[ids].set(n[at], mode="drop"),
    }
    return c


def longest_first(c, t0, t_end):
    """The end of the probe (every trajectory started once): the idle lanes' results recorded
    or their states saved, those lanes emptied, and the queue made of the parked trajectories,
    the most remaining work first. The lanes still running keep their trajectories."""
    B = c["tid"].shape[0]
    N = c["status_out"].shape[0]
    c = record(save(c, jnp.arange(B)), N)
    running = c["st"]["status"] == RUNNING
    c["tid"] = jnp.where(running, c["tid"], N)
    idle = jnp.asarray(code("successful"), jnp.int32)
    c["st"] = dict(c["st"], status=jnp.where(running, RUNNING, idle))
    parked = c["status_out"] == PARKED
    t, natt = c["saved"]["x"][:, 0], c["saved"]["n"][:, 2].astype(t0.dtype)
    rest = jnp.where(t > t0, natt * (t_end - t) / jnp.where(t > t0, t - t0, 1), jnp.inf)
    c["order"] = jnp.argsort(-jnp.where(parked, rest, -1), stable=True).astype(jnp.int32)
    c["queued"] = jnp.sum(parked).astype(jnp.int32)
    c["next"] = jnp.zeros((), jnp.int32)
    c["phase"] = jnp.ones((), jnp.int32)
    return c
