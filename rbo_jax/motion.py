r"""The motion of any model: one front door, :func:`simulate`, each model with its own default
integrator.

- a :class:`rbo_jax.RigidBodyOscillator`: ``simulate(model, theta0, Omega0, ts, ...)``, diffrax
  on the right form (4.55)–(4.56) (:func:`rbo_jax.simulate.simulate`, the module beside this
  one; the lean DOP853 ensemble is :func:`rbo_jax.fast_simulate`);
- a :class:`rbo_jax.lattice.Lattice`: ``simulate(lattice, theta0, Omega0, ts, ...)``, SciPy's
  DOP853 on the whole lattice, and a :class:`rbo_jax.lattice.Rod`: ``simulate(rod, state0, ts,
  ...)`` with a :class:`rbo_jax.lattice.RodState`, Dopri8: both
  :func:`rbo_jax.lattice.simulate`.

The keywords are each model's integrator's; the trajectories share
:class:`rbo_jax.trajectory.AbstractTrajectory` (``ts``, ``status``, ``ok``, ``message``) and
carry an ``energy``. Every diffrax solve among them is :func:`rbo_jax.integrate.diffeq.solve`.
"""

from __future__ import annotations

from .lattice import simulate as simulate_lattice
from .mechanics import AbstractMechanics
from .models.lattice import Lattice
from .models.rigid_body import RigidBodyOscillator
from .models.rod import Rod
from .simulate import simulate as simulate_rigid

__all__ = ["simulate"]


def simulate(model: AbstractMechanics, *args, **kwargs):
    r"""The motion of ``model`` from its initial state, sampled at ``ts`` (module docstring):
    ``simulate(model, theta0, Omega0, ts, ...)`` for a rigid body (diffrax; see
    :func:`rbo_jax.simulate.simulate` for every keyword: solver, tolerances, adjoint, events,
    the left form) or a lattice (:func:`rbo_jax.lattice.simulate`), ``simulate(rod, state0,
    ts, ...)`` for a rod (the keywords of :func:`rbo_jax.lattice.simulate`'s rod). jit-, vmap-
    and grad-compatible as each integrator is."""
    if isinstance(model, RigidBodyOscillator):
        return simulate_rigid(model, *args, **kwargs)
    if isinstance(model, Rod):
        if "state0" in kwargs:  # the rod's state by name, where a lattice's theta0 stands
            args = (kwargs.pop("state0"), *args)
        return simulate_lattice(model, *args, **kwargs)
    if isinstance(model, Lattice):
        return simulate_lattice(model, *args, **kwargs)
    raise TypeError(
        f"simulate: expected a RigidBodyOscillator, a Lattice or a Rod, got {type(model).__name__}."
    )
