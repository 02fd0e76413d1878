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

from ..ensemble import _dop853 as D
from ._field import chain_moments, rates

__all__ = ["HALO", "Halo", "Whole"]

HALO = 16
# Bodies per block: measured on one core (AMD EPYC, 2 MiB L2, 32 MiB L3; benchmarks/README.md).
BLOCK = 4096


class Whole(NamedTuple):
    """The plain plan: the whole lattice's arrays on one device (any lattice)."""

    size: int

    def sum(self, x):
        return jnp.sum(x)

    def any(self, x):
        return jnp.any(x)

    def field(self, problem):
        return problem.f

    def step(self, problem, t, y, f0, h, h_abs, store, last, first, cfg):
        """``(y_new, K, err)``: :func:`rbo_jax.ensemble._dop853.stages` and the error norm of
        the whole state."""
        y_new, K = D.stages(problem.f, t, y, f0, h, store, last, first=first)
        err = D.error_norm(K, y, y_new, h_abs, cfg.rtol, cfg.atol, total=self.sum, size=self.size)
        return y_new, K, err

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

    def any(self, x):
        a = jnp.any(x)
        if self.axis is None:
            return a
        return lax.psum(a.astype(jnp.int32), self.axis) > 0

    def _offset(self):
        if self.axis is None:
            return 0
        return lax.axis_index(self.axis) * self.local

    def _extend(self, x):
        """``(c, n)`` local rows → ``(c, n + 2H)``: the H bodies before and after, from the
        neighbouring shards (or this chain's own ends: a periodic chain on one device, or
        positions an open chain's weights leave uncoupled)."""
        H = HALO
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

    def field(self, problem):
        """The slopes of this device's bodies (the halo exchanged): for the initial step."""
        H, n = HALO, self.local

        def f(t, y):
            ext = self._extend(jnp.stack(y))
            k = _open_field(problem, self._weights(ext.dtype))(t, tuple(ext))
            return tuple(v[H : H + n] for v in k)

        return f

    def step(self, problem, t, y, f0, h, h_abs, store, last, first, cfg):
        """:func:`rbo_jax.ensemble._dop853.stages` of this device's bodies, block by block, and
        the error norm of the whole chain: ``(y_new, R, err)``. The 16 slopes of a block stay in
        the cache: the block adds its bodies' terms to the two sums of the error norm
        (:func:`~rbo_jax.ensemble._dop853.error_sums`; the last block counts only the bodies the
        others did not) and keeps of its slopes only what the step needs afterwards, ``R`` one
        ``(6, n)`` array per component: the first slope K[0], the slope at the new point K[12]
        (the next first slope) and the four sums of the dense output
        (:func:`~rbo_jax.ensemble._dop853.dense_sums`; read by :meth:`slope` and
        :meth:`dense_sums`). Written out whole, the slopes were 16 × 6 numbers a body per step,
        read again by the norm; keeping 6 rows made a step of 10⁶ bodies 7 % faster on one core
        (benchmarks/README.md, 2026-11-27)."""
        H, n = HALO, self.local
        ext = self._extend(jnp.stack(tuple(y) + tuple(f0)))  # (12, n + 2H)
        w_ext = self._weights(ext.dtype)
        nb = math.ceil(n / self.block)
        B = math.ceil(n / nb)  # equal blocks: the last overlaps its neighbour by < nb bodies
        dtype = ext.dtype
        inner = slice(H, H + B)

        def one(b, carry):
            R, y_new, t5, t3 = carry
            s = jnp.minimum(b * B, n - B)  # the last block overlaps its neighbour: same values
            seg = lax.dynamic_slice_in_dim(ext, s, B + 2 * H, axis=1)
            w = lax.dynamic_slice_in_dim(w_ext, s, B + 2 * H)
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
            Kb = tuple(k[:, inner] for k in Kb)
            yb = tuple(v[inner] for v in yb)
            y0b = tuple(v[inner] for v in seg[:6])
            s5, s3 = D.error_sums(Kb, y0b, yb, cfg.rtol, cfg.atol)
            new = (s + jnp.arange(B)) >= b * B  # bodies no earlier block counted
            t5 = t5 + jnp.sum(jnp.where(new, s5, 0.0))
            t3 = t3 + jnp.sum(jnp.where(new, s3, 0.0))
            kept = tuple(jnp.stack([k[0], k[D.NS], *D.dense_sums(Kb, i)]) for i, k in enumerate(Kb))
            R = tuple(lax.dynamic_update_slice_in_dim(Rg, r, s, axis=1) for Rg, r in zip(R, kept))
            y_new = tuple(
                lax.dynamic_update_slice_in_dim(yg, v, s, axis=0) for yg, v in zip(y_new, yb)
            )
            return R, y_new, t5, t3

        zero = jnp.zeros((), dtype)
        R0 = tuple(jnp.zeros((6, n), dtype) for _ in range(6))
        y0 = tuple(jnp.zeros((n,), dtype) for _ in range(6))
        if nb == 1:
            R, y_new, t5, t3 = one(0, (R0, y0, zero, zero))
        else:
            R, y_new, t5, t3 = lax.fori_loop(0, nb, one, (R0, y0, zero, zero))
        err = D.error_of_sums(self.sum(t5), self.sum(t3), h_abs, 6 * self.size)
        return y_new, R, err

    def slope(self, R, j):
        """K[0] or K[12] from :meth:`step`'s ``R``."""
        row = {0: 0, D.NS: 1}[j]
        return tuple(r[row] for r in R)

    def dense_sums(self, R, i):
        """The four dense-output sums of component ``i`` from :meth:`step`'s ``R``."""
        return tuple(R[i][2 + r] for r in range(4))
