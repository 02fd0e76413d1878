r"""A chain's DOP853 step on segments with halos: blocks that fit in the cache, shards on devices.

A body's slope depends on its own state and its neighbours' turn-vectors (a stencil of width
one), so the $s$-th stage of a step at body $i$ depends on the step's start at bodies
$i - s \dots i + s$ only. The whole step (all stages, the dense output's three extra ones
included) of the bodies $[a, b)$ is therefore made from the state and first slope on
$[a - H, b + H)$, $H = 16$ (more than the 16 evaluations of a step: the first slope made again
after a re-centring, 12 stages, 3 for the dense output), integrated as an **open** segment
(:func:`rbo_jax.lattice._field.chain_moments`): the values on $[a, b)$ are the whole chain's bit
for bit — the same operations on the same operands. This makes

- **blocks**: the step of a long chain is a loop over blocks of ``block`` bodies whose 16 slopes
  and every intermediate of the right-hand side stay in the cache, one pass over memory per step
  instead of one per XLA kernel and stage (the state of $10^6$ bodies is 48 MB per slope); a
  block adds its bodies' terms to the error norm's sums and writes out only the slopes the
  step needs afterwards (6 of 16 rows: K[0], K[12], the dense output's four sums);
- **shards**: a chain split over devices (``jax.shard_map``), each device integrating its own
  bodies with halos of $H$ bodies from its two neighbours (``lax.ppermute``, once per step), the
  error norm one ``psum`` of the shards' sums: every shard takes the same step, SciPy's step of
  the whole $6N$ system.

Global index of an extended position $p$ of a shard holding bodies $[o, o + n)$: $g = o - H +
p$. The pair $(p, p+1)$ is coupled (weight 1) on a periodic chain, on an open one while
$0 \le g \le N - 2$; the last position of a segment has no partner (weight 0).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
from jax import lax

from ..integrate import dop853 as D
from ..models.lattice import chain_moments, rates

__all__ = ["HALO", "Halo", "Whole"]

HALO = 16
# Bodies per block: for a core's caches (benchmarks/README.md, History).
BLOCK = 4096


class Whole(NamedTuple):
    """The plain plan: the whole lattice's arrays on one device (any lattice)."""

    size: int

    def sum(self, x):
        return jnp.sum(x)

    def initial(self, problem, t0, y0, t_bound, cfg):
        """``(f0, h0, flags)``: :func:`rbo_jax.integrate.dop853.initial_step` and the checks of
        the initial state (:meth:`._integrate.Problem.flags`)."""
        f0, h0 = D.initial_step(
            problem.f, t0, y0, t_bound, cfg.rtol, cfg.atol, total=self.sum, size=self.size
        )
        return f0, h0, problem.flags(y0, y0, cfg)

    def step(self, problem, t, y, f0, h, h_abs, store, last, first, cfg):
        """``(y_new, K, err, flags)``: :func:`rbo_jax.integrate.dop853.stages`, the error norm
        of the whole state and the checks of the step (:meth:`._integrate.Problem.flags`)."""
        y_new, K = D.stages(problem.f, t, y, f0, h, store, last, first=first)
        err = D.error_norm(K, y, y_new, h_abs, cfg.rtol, cfg.atol, total=self.sum, size=self.size)
        return y_new, K, err, problem.flags(y, y_new, cfg)

    def slope(self, K, j):
        return D.slope(K, j)

    def dense_sums(self, K, i):
        return D.dense_sums(K, i)


def _open_field(problem, weight):
    """The slopes of an open segment whose pairs carry ``weight``, on the state tuple."""
    lattice, forms = problem.lattice, problem.forms

    def f(t, y):
        theta, Omega = jnp.stack(y[:3]), jnp.stack(y[3:])
        m = chain_moments(lattice, theta, weight)
        dth, dOm = rates(lattice, forms, t, theta, Omega, moments=m)
        return (dth[0], dth[1], dth[2], dOm[0], dOm[1], dOm[2])

    return f


class Halo(NamedTuple):
    """A chain's plan on segments: ``size`` bodies in all, ``local`` of them on this device
    (``devices`` shards along the mesh axis ``axis``; one device: ``axis`` None), the step made
    in blocks of at most ``block`` bodies (:mod:`._halo`)."""

    size: int
    local: int
    periodic: bool
    block: int = BLOCK
    devices: int = 1
    axis: str | None = None

    def sum(self, x):
        s = jnp.sum(x)
        return s if self.axis is None else lax.psum(s, self.axis)

    def _totals(self, sums, flags):
        """The chain's totals of this shard's ``sums`` (floats) and ``flags`` (bools): one
        ``psum`` of both over the shards."""
        if self.axis is None:
            return sums, flags
        v = lax.psum(jnp.concatenate([sums, flags.astype(sums.dtype)]), self.axis)
        return v[: sums.shape[0]], v[sums.shape[0] :] > 0

    def _offset(self):
        if self.axis is None:
            return 0
        return lax.axis_index(self.axis) * self.local

    def _extend(self, x):
        """``(c, n)`` local rows → ``(c, n + 2H)``: the H bodies before and after, from the
        neighbouring shards (or this chain's own ends: a periodic chain on one device, or
        positions an open chain's weights leave uncoupled)."""
        H = HALO
        if x.shape[1] < H:  # the callers split only chains of at least H bodies a segment
            raise ValueError(f"a segment of a chain needs at least {H} bodies, got {x.shape[1]}")
        if self.axis is None:
            left, right = x[:, -H:], x[:, :H]
        else:
            d = self.devices
            left = lax.ppermute(x[:, -H:], self.axis, [(i, (i + 1) % d) for i in range(d)])
            right = lax.ppermute(x[:, :H], self.axis, [(i, (i - 1) % d) for i in range(d)])
        return jnp.concatenate([left, x, right], axis=1)

    def _weights(self, dtype):
        H, n = HALO, self.local
        p = jnp.arange(n + 2 * H)
        if self.periodic:
            w = p < n + 2 * H - 1
        else:
            g = self._offset() - H + p
            w = (g >= 0) & (g <= self.size - 2) & (p < n + 2 * H - 1)
        return w.astype(dtype)

    def _blocks(self, ext, one, carry):
        """``one(seg, w, s, new, carry) → carry`` over the blocks of this device's bodies:
        ``seg`` the block's rows of ``ext`` (:meth:`_extend`) with H bodies either side, ``w``
        their pairs' weights, ``s`` the block's first body, ``new`` (B,) which of its bodies no
        earlier block had (the last block overlaps its neighbour by < nb bodies: the same
        values again, counted once in sums). One block: no loop."""
        H, n = HALO, self.local
        w_ext = self._weights(ext.dtype)
        nb = math.ceil(n / self.block)
        B = math.ceil(n / nb)  # equal blocks

        def body(b, carry):
            s = jnp.minimum(b * B, n - B)
            seg = lax.dynamic_slice_in_dim(ext, s, B + 2 * H, axis=1)
            w = lax.dynamic_slice_in_dim(w_ext, s, B + 2 * H)
            return one(seg, w, s, (s + jnp.arange(B)) >= b * B, carry)

        return body(0, carry) if nb == 1 else lax.fori_loop(0, nb, body, carry)

    def _rows(self, values, B):
        """Inner rows ``[H, H + B)`` of a block's segment values."""
        return tuple(v[HALO : HALO + B] for v in values)

    def _put(self, arrays, values, s):
        """``values`` (one block's) written into ``arrays`` from body ``s`` on."""
        return tuple(
            lax.dynamic_update_slice_in_dim(a, v, s, axis=a.ndim - 1)
            for a, v in zip(arrays, values)
        )

    def initial(self, problem, t0, y0, t_bound, cfg):
        """:func:`rbo_jax.integrate.dop853.initial_step` in blocks, and the checks of the initial
        state: ``(f0, h0, flags)``. As there, a loop of two passes (one traced copy of the
        field): pass 0 makes f0 = f(t0, y0) from zero slopes at h = 0, with the sums of squares
        of d0 = ‖y0/scale‖ and d1 = ‖f0/scale‖ and the checks; pass 1, at the first guess h0,
        f1 = f(t0 + h0, y0 + h0 f0) and the sum of d2 = ‖(f1 − f0)/scale‖ (the same sum as d1's,
        f0 being zero in pass 0). The halos of y0 and f0 are exchanged and the shards' sums
        totalled (one ``psum``) once a pass. The sums' order is the blocks', so h0 agrees with
        the whole arrays' to rounding."""
        n, dtype = self.local, y0[0].dtype
        nb = math.ceil(n / self.block)
        B = math.ceil(n / nb)
        interval = jnp.abs(t_bound - t0)
        count = 6 * self.size
        zero = jnp.zeros((), dtype)

        def scaled_sum(v, y, keep):
            total = zero
            for a, b in zip(v, y):
                x = a * keep / (cfg.atol + jnp.abs(b) * cfg.rtol)
                total = total + jnp.sum(x * x)
            return total

        def guess(totals):
            return D.initial_guess(
                jnp.sqrt(totals[0] / count), jnp.sqrt(totals[1] / count), interval
            )

        def one_pass(i, carry):
            f0, totals, flags = carry
            h0 = jnp.where(i == 0, 0.0, guess(totals)[0])

            def block(seg, w, s, new, carry):
                f0, sums, flags = carry
                y1 = tuple(a + h0 * b for a, b in zip(seg[:6], seg[6:]))
                k = self._rows(_open_field(problem, w)(t0 + h0, y1), B)
                y_in, f_in = self._rows(tuple(seg[:6]), B), self._rows(tuple(seg[6:]), B)
                keep = new.astype(dtype)
                d = tuple(a - b for a, b in zip(k, f_in))  # pass 0: f_in = 0
                sums = sums + jnp.stack([scaled_sum(y_in, y_in, keep), scaled_sum(d, y_in, keep)])
                f0 = self._put(f0, tuple(jnp.where(i == 0, a, b) for a, b in zip(k, f_in)), s)
                return f0, sums, flags | problem.flags(y_in, y_in, cfg)

            ext = self._extend(jnp.stack(tuple(y0) + tuple(f0)))
            f0, sums, flags = self._blocks(ext, block, (f0, jnp.zeros((2,), dtype), flags))
            sums, flags = self._totals(sums, flags)
            # totals: [y0's, f0's (pass 0), f1 − f0's (pass 1)]
            totals = jnp.where(
                i == 0, jnp.stack([sums[0], sums[1], zero]), totals.at[2].set(sums[1])
            )
            return f0, totals, flags

        f0 = tuple(jnp.zeros((n,), dtype) for _ in range(6))
        carry = (f0, jnp.zeros((3,), dtype), jnp.zeros((4,), bool))
        f0, totals, flags = lax.fori_loop(0, 2, one_pass, carry)
        h0, d1 = guess(totals)
        d2 = jnp.sqrt(totals[2] / count) / h0
        return f0, D.initial_choice(h0, d1, d2, interval), flags

    def step(self, problem, t, y, f0, h, h_abs, store, last, first, cfg):
        """:func:`rbo_jax.integrate.dop853.stages` of this device's bodies, block by block, the
        error norm of the whole chain and the step's checks: ``(y_new, R, err, flags)``. The 16
        slopes of a block stay in the cache: the block adds its bodies' terms to the two sums of
        the error norm (:func:`~rbo_jax.integrate.dop853.error_sums`; the last block counts only
        the bodies the others did not), makes its bodies' checks
        (:meth:`._integrate.Problem.flags`) and keeps of its slopes only what the step needs
        afterwards, ``R`` one ``(6, n)`` array per component: the first slope K[0], the slope at
        the new point K[12] (the next first slope) and the four sums of the dense output
        (:func:`~rbo_jax.integrate.dop853.dense_sums`; read by :meth:`slope` and
        :meth:`dense_sums`): written out whole, the slopes were 16 × 6 numbers a body per step,
        read again by the norm, and the checks two more passes over the whole state
        (benchmarks/README.md, History)."""
        n = self.local
        nb = math.ceil(n / self.block)
        B = math.ceil(n / nb)
        dtype = y[0].dtype

        def one(seg, w, s, new, carry):
            R, y_new, t5, t3, flags = carry
            yb, Kb = D.stages(
                _open_field(problem, w),
                t,
                tuple(seg[:6]),
                tuple(seg[6:]),
                h,
                store,
                last,
                first=first,
            )
            Kb = tuple(k[:, HALO : HALO + B] for k in Kb)
            yb, y0b = self._rows(yb, B), self._rows(tuple(seg[:6]), B)
            s5, s3 = D.error_sums(Kb, y0b, yb, cfg.rtol, cfg.atol)
            t5 = t5 + jnp.sum(jnp.where(new, s5, 0.0))
            t3 = t3 + jnp.sum(jnp.where(new, s3, 0.0))
            flags = flags | problem.flags(y0b, yb, cfg)
            kept = tuple(jnp.stack([k[0], k[D.NS], *D.dense_sums(Kb, i)]) for i, k in enumerate(Kb))
            return self._put(R, kept, s), self._put(y_new, yb, s), t5, t3, flags

        zero = jnp.zeros((), dtype)
        R0 = tuple(jnp.zeros((6, n), dtype) for _ in range(6))
        y0 = tuple(jnp.zeros((n,), dtype) for _ in range(6))
        ext = self._extend(jnp.stack(tuple(y) + tuple(f0)))  # (12, n + 2H)
        carry = (R0, y0, zero, zero, jnp.zeros((4,), bool))
        R, y_new, t5, t3, flags = self._blocks(ext, one, carry)
        (t5, t3), flags = self._totals(jnp.stack([t5, t3]), flags)
        err = D.error_of_sums(t5, t3, h_abs, 6 * self.size)
        return y_new, R, err, flags

    def slope(self, R, j):
        """K[0] or K[12] from :meth:`step`'s ``R``."""
        row = {0: 0, D.NS: 1}[j]
        return tuple(r[row] for r in R)

    def dense_sums(self, R, i):
        """The four dense-output sums of component ``i`` from :meth:`step`'s ``R``."""
        return tuple(R[i][2 + r] for r in range(4))
