r"""Loads on the bodies of a rod (:mod:`._rod`): forces and moments at the tip or on any body,
dead or follower, weight and distributed dead forces; actuation (muscle torques, a rest
curvature that changes with time) and a ground with anisotropic friction (:mod:`._actuation`).

A load gives, per body, a world-frame force $F_i$ (at the body's centre) and a body-frame
moment $M_i$, at the bodies' turn-tensors, positions and velocities and at the time
(:class:`Motion`); ``scale`` multiplies it (the load steps of
:func:`rbo_jax.lattice.equilibrium`). A follower vector is given in the body's frame and turns
with it: the force analogue of (4.57).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..._validation import float_dtype, is_traced

__all__ = [
    "AbstractRodLoad",
    "Motion",
    "DistributedForce",
    "Gravity",
    "TipForce",
    "TipMoment",
    "as_rod_loads",
    "real_array",
]


def real_array(x, name: str, owner: str = "rod"):
    """``x`` as a real float array (NumPy when concrete), or an error naming ``name``."""
    if isinstance(x, (list, tuple)):
        x = np.asarray(x) if not any(is_traced(e) for e in x) else jnp.stack(x)
    if not is_traced(x):
        x = np.asarray(x)
        if np.iscomplexobj(x) or not np.issubdtype(x.dtype, np.number):
            raise TypeError(f"{owner}: {name} must be real numbers, got {x.dtype}.")
        x = x.astype(float_dtype())
    return x


class Motion(NamedTuple):
    """Where and when the loads act: the bodies' turn-tensors ``Q`` (N+1, 3, 3), positions ``r``,
    body-frame angular velocities ``Omega`` and velocities ``v`` (N+1, 3) (``None`` at rest:
    the statics), and the time ``t`` (0 in the statics)."""

    Q: jax.Array
    r: jax.Array
    Omega: jax.Array | None
    v: jax.Array | None
    t: jax.Array | float


class AbstractRodLoad(eqx.Module):
    """A load on the bodies of a rod: world-frame forces and body-frame moments, ``(N+1, 3)``
    each, at the turn-tensors, positions and velocities of the bodies and at the time
    (:class:`Motion`). ``needs_positions``: a force needs bodies that translate (a plain
    lattice of bodies with fixed points refuses it); ``needs_velocity``: it depends on the
    velocities (friction: the explicit splitting then evaluates it at predicted velocities)."""

    needs_positions = True
    needs_velocity = False

    def check(self, rod) -> None:
        """Refuse a load that does not fit ``rod`` (a body that does not exist)."""

    def forces(self, rod, rotate, scale, at: Motion):
        """``(F (N+1, 3) world, M (N+1, 3) body)``; ``rotate(i, x, back)`` turns ``x`` by the
        turn of body ``i`` (or back); ``at``: the bodies' motion and the time."""
        raise NotImplementedError

    def rest_turns(self, rod, t):
        """The rest value ``(N, 3)`` this load adds to every coupling's relative turn at time
        ``t`` (an actuation of the rest curvature), or ``None``."""
        return None


def _body_index(body, rod, owner: str) -> int:
    nb = rod.n_bodies
    i = int(body)
    if not -nb <= i < nb:
        raise ValueError(
            f"{owner}: body={body} does not exist: the rod has bodies 0 … {nb - 1} (0 the "
            f"base, {nb - 1} the tip; negative indices count from the tip)."
        )
    i %= nb
    if i == 0 and rod.base == "clamped":
        raise ValueError(
            f"{owner}: body=0 is the clamped base, which no load can move; load bodies 1 … "
            f"{nb - 1}."
        )
    return i


class _PointLoad(AbstractRodLoad):
    vector: Float[Array, "3"]
    follower: bool = eqx.field(static=True)
    body: int = eqx.field(static=True)

    def __init__(self, vector, follower: bool = False, *, body: int = -1):
        owner = type(self).__name__
        v = real_array(vector, self._what, owner)
        if tuple(np.shape(v)) != (3,):
            raise ValueError(f"{owner}: {self._what} must be a 3-vector, got shape {np.shape(v)}.")
        if not is_traced(v) and not np.all(np.isfinite(v)):
            raise ValueError(f"{owner}: {self._what} must be finite, got {np.asarray(v).tolist()}.")
        self.vector = v
        self.follower = bool(follower)
        self.body = int(body)

    def check(self, rod) -> None:
        _body_index(self.body, rod, type(self).__name__)


class TipForce(_PointLoad):
    r"""A force on the tip body (or on ``body``), at its centre. ``follower=False``: the vector
    is fixed in space (a dead load, $-F\cdot r$ is its potential); ``follower=True``: it is
    given in the body's frame and turns with it, $F = Q_{tip}\cdot f$ (Beck's column:
    ``TipForce([0, 0, -P], follower=True)``, a compressive force along the tip's axis), the
    force analogue of the follower moment (4.57)."""

    _what = "force"

    @property
    def force(self):
        return self.vector

    def forces(self, rod, rotate, scale, at):
        i = self.body % rod.n_bodies
        f = scale * jnp.asarray(self.vector)
        F = rotate(i, f, False) if self.follower else f
        Fs = jnp.zeros((rod.n_bodies, 3), F.dtype).at[i].set(F)
        return Fs, jnp.zeros_like(Fs)


class TipMoment(_PointLoad):
    r"""A moment on the tip body (or on ``body``). ``follower=False``: fixed in space (as
    :class:`rbo_jax.DeadMoment`); ``follower=True``: given in the body's frame, turning with it
    (as :class:`rbo_jax.FollowerMoment`, (4.57)). A moment $2\pi EI/L$ about a transverse axis
    rolls a clamped rod into a circle."""

    _what = "moment"

    @property
    def moment(self):
        return self.vector

    def forces(self, rod, rotate, scale, at):
        i = self.body % rod.n_bodies
        m = scale * jnp.asarray(self.vector)
        M = m if self.follower else rotate(i, m, True)
        Ms = jnp.zeros((rod.n_bodies, 3), M.dtype).at[i].set(M)
        return jnp.zeros_like(Ms), Ms


class Gravity(AbstractRodLoad):
    r"""Weight: the force $m_i\,g$ on every body (``g`` a world vector, e.g. ``[0, 0, -9.81]``).
    Potential $-\sum_i m_i\,g\cdot r_i$ (in the energy)."""

    g: Float[Array, "3"]

    def __init__(self, g=(0.0, 0.0, -9.81)):
        g = real_array(g, "g", "Gravity")
        if tuple(np.shape(g)) != (3,):
            raise ValueError(f"Gravity: g must be a 3-vector, got shape {np.shape(g)}.")
        self.g = g

    def forces(self, rod, rotate, scale, at):
        F = scale * jnp.asarray(rod.mass)[:, None] * jnp.asarray(self.g)[None, :]
        return F, jnp.zeros_like(F)


class DistributedForce(AbstractRodLoad):
    r"""A dead force per unit length ``q`` (world frame) along the whole rod, lumped on the bodies
    by their shares of the length (half a segment at either end)."""

    q: Float[Array, "3"]

    def __init__(self, q):
        q = real_array(q, "q", "DistributedForce")
        if tuple(np.shape(q)) != (3,):
            raise ValueError(f"DistributedForce: q must be a 3-vector, got shape {np.shape(q)}.")
        self.q = q

    def forces(self, rod, rotate, scale, at):
        F = scale * jnp.asarray(rod.share)[:, None] * jnp.asarray(self.q)[None, :]
        return F, jnp.zeros_like(F)


def as_rod_loads(loads) -> tuple:
    if isinstance(loads, AbstractRodLoad):
        loads = (loads,)
    loads = tuple(loads)
    for load in loads:
        if not isinstance(load, AbstractRodLoad):
            raise TypeError(
                "rod: loads must be rbo_jax.lattice loads (TipForce, TipMoment, Gravity, "
                "DistributedForce, MuscleTorques, RestCurvature, FrictionalPlane), got "
                f"{type(load).__name__}. Moments of a single body's "
                "foundation go in `foundation`."
            )
    return loads
