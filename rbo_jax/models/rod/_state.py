"""The state of a rod: per body its turn, position, angular velocity and velocity."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["RodState"]


class RodState(eqx.Module):
    r"""The state of a rod: per body (N+1, base first) the turn-vector ``theta``, the position
    ``r``, the right (body-frame) angular velocity ``Omega`` and the velocity ``v``, each
    ``(..., N+1, 3)``. ``centreline``: the positions of the N+1 nodes from the base to the tip
    (the bodies' centres for :func:`rod`)."""

    theta: Float[Array, "... B 3"]
    r: Float[Array, "... B 3"]
    Omega: Float[Array, "... B 3"]
    v: Float[Array, "... B 3"]

    @property
    def centreline(self):
        return self.r

    @property
    def tip(self):
        """The position of the last body, ``(..., 3)``."""
        return self.r[..., -1, :]

    @staticmethod
    def at_rest(theta, r) -> RodState:
        z = jnp.zeros_like(jnp.asarray(r))
        return RodState(jnp.asarray(theta), jnp.asarray(r), z, z)
