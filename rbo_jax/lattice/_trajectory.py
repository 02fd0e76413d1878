"""``LatticeTrajectory``: the samples of a lattice's motion and what follows from them."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..trajectory import SolveStatus, _AbstractSolved
from ._field import kinetic_moment, total_energy
from ._lattice import Lattice

__all__ = ["LatticeTrajectory"]


@eqx.filter_jit
def _per_sample(fn, lattice, theta, Omega):
    """``fn(lattice, theta (3, N), Omega (3, N))`` for every sample of ``(T, N, 3)`` arrays:
    one compiled program per quantity and lattice structure."""
    return jax.vmap(lambda th, Om: fn(lattice, th.T, Om.T))(theta, Omega)


class LatticeTrajectory(_AbstractSolved):
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

    @property
    def energy(self) -> Float[Array, " T"]:
        return _per_sample(total_energy, self.lattice, self.theta, self.Omega)

    @property
    def kinetic_moment(self) -> Float[Array, "T 3"]:
        return _per_sample(kinetic_moment, self.lattice, self.theta, self.Omega)

    def on_grid(self, x):
        """A per-site sample array ``(T, N, ...)`` reshaped to the lattice's shape,
        ``(T, *shape, ...)``, e.g. ``traj.on_grid(traj.theta)``."""
        x = jnp.asarray(x)
        return jnp.reshape(x, x.shape[:1] + self.lattice.shape + x.shape[2:])

    def to_xarray(self, **attrs):
        """The samples as an :class:`xarray.Dataset` (concrete, unbatched): dimensions ``t``,
        ``site`` and ``component``; variables ``theta``, ``Omega``, ``turns``, ``energy``;
        attributes ``status``, ``message``, ``num_steps``, ``shape``, plus ``attrs``."""
        import xarray as xr

        vec = ("t", "site", "component")
        data = {
            "theta": (
                vec,
                np.asarray(self.theta),
                {"long_name": "turn-vector theta (4.1)", "units": "rad"},
            ),
            "Omega": (
                vec,
                np.asarray(self.Omega),
                {"long_name": "right (body-frame) angular velocity Omega", "units": "rad s-1"},
            ),
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
        ds = xr.Dataset(
            data,
            coords={
                "t": ("t", np.asarray(self.ts), {"units": "s"}),
                "site": np.arange(self.lattice.size),
                "component": ["x", "y", "z"],
            },
        )
        ds.attrs.update(
            status=self.status_name,
            message=self.message,
            num_steps=int(self.num_steps),
            shape=list(self.lattice.shape),
            **attrs,
        )
        return ds
