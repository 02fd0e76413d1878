"""``LatticeTrajectory``: the samples of a lattice's motion and what follows from them."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..models.lattice import Lattice, kinetic_moment, total_energy
from ..trajectory import OMEGA_ATTRS, THETA_ATTRS, AbstractTrajectory, SolveStatus, per_sample

__all__ = ["LatticeTrajectory"]


def _of_sample(fn, lattice, theta, Omega):
    """``fn(lattice, theta (3, N), Omega (3, N))`` of one sample's ``(N, 3)`` arrays."""
    return fn(lattice, theta.T, Omega.T)


class LatticeTrajectory(AbstractTrajectory):
    r"""Samples of a lattice's motion (:func:`rbo_jax.lattice.simulate`).

    Fields: ``ts`` (T,); ``theta`` (T, N, 3) the turn-vectors and ``Omega`` (T, N, 3) the right
    angular velocities of the bodies (sites in the lattice's row-major order; :meth:`on_grid`
    gives them the grid's shape); ``turns`` (T, N) how often each body's turn-vector was
    re-centred by $2\pi k$ before the sample (``rbo_jax.lattice._integrate``); ``lattice``;
    ``status`` a :class:`rbo_jax.SolveStatus`; ``num_steps`` the accepted steps;
    ``num_recentred``. Samples after a failure are ``inf``.

    Derived (computed on access, one compiled program each): ``energy`` (T,), the total
    mechanical energy $\sum_i K_i + U$ (conserved without friction and non-potential loads),
    and ``kinetic_moment`` (T, 3), $\sum_i Q(\theta_i)\cdot A_i\cdot\Omega_i$ (conserved in
    Kelvin's medium).
    """

    # the fields of rbo_jax.Trajectory with a site axis (other shapes: declared here, not shared)
    ts: Float[Array, " T"]
    theta: Float[Array, "T N 3"]
    Omega: Float[Array, "T N 3"]
    turns: Int[Array, "T N"]
    lattice: Lattice
    status: SolveStatus
    num_steps: Int[Array, ""]
    num_recentred: Int[Array, ""]

    def _map(self, fn):
        """``fn(lattice, theta, Omega)`` for every sample: one compiled program per quantity
        and lattice structure (:func:`rbo_jax.trajectory.per_sample`)."""
        f = jax.tree_util.Partial(_of_sample, fn, self.lattice)
        return per_sample(f, self.theta, self.Omega)

    @property
    def energy(self) -> Float[Array, " T"]:
        return self._map(total_energy)

    @property
    def kinetic_moment(self) -> Float[Array, "T 3"]:
        return self._map(kinetic_moment)

    def on_grid(self, x):
        """A per-site sample array ``(T, N, ...)`` reshaped to the lattice's shape,
        ``(T, *shape, ...)``, e.g. ``traj.on_grid(traj.theta)``."""
        x = jnp.asarray(x)
        return jnp.reshape(x, x.shape[:1] + self.lattice.shape + x.shape[2:])

    def to_xarray(self, **attrs):
        """The samples as an :class:`xarray.Dataset` (concrete, unbatched): dimensions ``t``,
        ``site`` and ``component``; variables ``theta``, ``Omega``, ``turns``, ``energy``;
        attributes ``status``, ``message``, ``num_steps``, ``shape``, plus ``attrs``."""
        vec = ("t", "site", "component")
        data = {
            "theta": (vec, np.asarray(self.theta), THETA_ATTRS),
            "Omega": (vec, np.asarray(self.Omega), OMEGA_ATTRS),
            "turns": (
                ("t", "site"),
                np.asarray(self.turns),
                {"long_name": "re-centrings of the turn-vector by 2 pi k"},
            ),
            "energy": (
                "t",
                np.asarray(self.energy),
                {"long_name": "total mechanical energy", "units": "J"},
            ),
        }
        coords = {"site": np.arange(self.lattice.size), "component": ["x", "y", "z"]}
        return self._dataset(data, coords, shape=list(self.lattice.shape), **attrs)
