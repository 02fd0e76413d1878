r"""Turn-vectors kept away from the singular spheres of $Z$ (4.11) during a lattice's motion: the
bodies that move off the plane and come near $|\theta| = 2\pi k$ are re-centred to the same
turn-tensor (:func:`recentre`), as :func:`rbo_jax.simulate` does for one body."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax import lax

from ..trajectory import is_transverse

__all__ = ["nearest_turn", "recentre", "recentre_due", "transverse", "within_pi"]

TWO_PI = 2.0 * math.pi


def _per_body(fn, *args):
    return jax.vmap(fn, in_axes=tuple(jnp.ndim(a) - 1 for a in args), out_axes=-1)(*args)


def transverse(theta, Omega):
    """Per body: whether its motion is off the plane (θ×Ω ≠ 0, beyond the tolerance of
    :func:`rbo_jax.simulate`)."""
    return _per_body(is_transverse, theta, Omega)


def recentre_due(n, moving, margin):
    r"""Per body of turn-vector norm ``n`` (``moving``: off the plane, :func:`transverse`):
    ``(k, due)``, the nearest singular sphere's $k \ge 1$ and whether the body lies within
    ``margin`` of it (and past $\pi$), i.e. whether :func:`recentre` moves it."""
    k = jnp.maximum(jnp.round(n / TWO_PI), 1.0)
    near = jnp.abs(n - TWO_PI * k) < margin
    return k, near & (n >= math.pi) & moving


def recentre(theta, Omega, margin):
    r"""The bodies off the plane within ``margin`` of a singular sphere $|\theta| = 2\pi k$ of
    $Z$ (4.11) re-centred, $\theta \to \theta\,(1 - 2\pi k/|\theta|)$: the same turn-tensor,
    a turn-vector far from the sphere. Returns ``(theta, k per body (0: not moved))``."""
    n = lax.stop_gradient(jnp.sqrt(theta[0] ** 2 + theta[1] ** 2 + theta[2] ** 2))
    k, move = recentre_due(n, lax.stop_gradient(transverse(theta, Omega)), margin)
    scale = jnp.where(move, 1.0 - TWO_PI * k / jnp.where(move, n, 1.0), 1.0)
    return theta * scale[None, :], jnp.where(move, k, 0.0).astype(jnp.int32)


def _norm(theta):
    size2 = jnp.sum(theta * theta, axis=-1, keepdims=True)
    positive = size2 > 0
    return jnp.sqrt(jnp.where(positive, size2, 1.0)), positive  # double where: finite at 0


def within_pi(theta):
    r"""Turn-vectors ``(..., 3)`` beyond $|\theta| = \pi$ replaced by the same turn's
    $\theta\,(1 - 2\pi/|\theta|)$, away from the singular sphere $|\theta| = 2\pi$ of $Z$."""
    size, _ = _norm(theta)
    far = jnp.sum(theta * theta, axis=-1, keepdims=True) > math.pi**2
    return theta * jnp.where(far, 1.0 - TWO_PI / size, 1.0)


def nearest_turn(theta, ref):
    r"""The representative $\theta + 2\pi k\,\theta/|\theta|$, $k \in \{-1, 0, 1\}$, of each
    turn ``theta`` ``(N, 3)`` nearest to ``ref``: a turn that :func:`within_pi` moved
    across $|\theta| = \pi$ put back beside its neighbour in time (an interpolation)."""
    size, positive = _norm(theta)
    axis = jnp.where(positive, theta / size, 0.0)
    candidates = theta[None] + TWO_PI * jnp.array([-1.0, 0.0, 1.0])[:, None, None] * axis[None]
    distance = jnp.sum((candidates - ref[None]) ** 2, axis=-1)  # (3, N)
    pick = jnp.argmin(distance, axis=0)
    return jnp.take_along_axis(candidates, pick[None, :, None], axis=0)[0]
