r"""What every analysis needs of a mechanical system.

A system of bodies that turn (and, for a rod, translate) is described to the analyses by

- its **configuration** (the model's own type: a turn-vector $\theta$ of shape (3,) for a rigid
  body, (N, 3) for a lattice, a :class:`rbo_jax.lattice.RodState` at rest for a rod) and the
  **local increments** on it: $N_b$ blocks of $b$ unknowns ``x`` (:meth:`block_shape`), and
  the configuration ``retract(config, x)`` they lead to (a turn-vector added for a body on a
  foundation, whose energy $U(\theta)$ tells the turns apart; turns composed,
  $Q(\theta_i)Q(\delta_i)$ (4.5), and positions added for a rod);
- the **balance of forces and moments at rest** in those blocks (:meth:`static_residual`),
  with every load scaled by a load factor, the held coordinates (a clamped base) replaced by
  their distance to the held values, and the **linear solver** its structure asks for
  (:meth:`structure`: ``"dense"`` for a rigid body or a grid, ``"tridiagonal"`` for an open
  chain or a rod; :func:`rbo_jax.solvers.linear_solver` turns it into a solver);
- its **first-order equations of motion** over the free coordinates, in the chart of the
  increments at a configuration (:meth:`field`): $x = [q, w]$, $q$ the increments of the bodies
  that move, $w$ their (right, body-frame) angular velocities and velocities, $\dot x = F(x)$
  — for one body the right form (4.55)–(4.56), $\dot q = Z^T(\theta + q)\cdot\Omega$,
  $A\dot\Omega = M - \Omega\times A\Omega$; its masses, damping, gyroscopic and circulatory
  terms are all in $F$;
- its parameter checks (:meth:`parameter_status`) and the configurations where its equations
  are undefined (:meth:`configuration_status`: a singular sphere $|\theta| = 2\pi k$ of
  $Z$ (4.11), the edge of a foundation's domain (4.49)).

Every analysis is written once against these: an equilibrium is Newton's method on
:meth:`static_residual` (:func:`rbo_jax.solve_equilibrium`), the linearisation the Jacobian of
:meth:`field` at zero (:func:`rbo_jax.linearize`), a Hopf point an extended system in
:meth:`field` and its directional derivatives (:func:`rbo_jax.hopf_point`).
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp

__all__ = [
    "STRUCTURES",
    "AbstractMechanics",
    "checked_parameters",
    "first_order_field",
    "zero_increments",
]

STRUCTURES = ("dense", "tridiagonal")  # of the static Jacobian (AbstractMechanics.structure)


class AbstractMechanics(eqx.Module):
    """A mechanical system as the analyses see it (module docstring). Final subclasses:
    :class:`rbo_jax.RigidBodyOscillator`, :class:`rbo_jax.lattice.Lattice`,
    :class:`rbo_jax.lattice.Rod`."""

    # ---- configuration and increments ------------------------------------------------------

    @abc.abstractmethod
    def rest(self):
        """The reference configuration (the default guess of an equilibrium)."""

    @abc.abstractmethod
    def configuration(self, guess, name: str = "guess"):
        """The configuration from a user's ``guess`` (``None``: :meth:`rest`), its shape
        checked (a ``ValueError`` naming ``name``)."""

    @abc.abstractmethod
    def block_shape(self) -> tuple[int, int]:
        """``(N_b, b)``: the blocks of the increments and of the static residual (static)."""

    @abc.abstractmethod
    def retract(self, config, x):
        """The configuration at the increments ``x`` (``block_shape()``) from ``config``."""

    @abc.abstractmethod
    def increment_scale(self, config):
        """The size against which a Newton step of the increments is measured, per increment
        (a step below ``rtol`` times it has converged)."""

    @abc.abstractmethod
    def static_residual(self, t, config, x, load_scale=1.0):
        """The balance of forces and moments at rest at ``retract(config, x)`` with every load
        times ``load_scale``, in the blocks of the increments; zero at an equilibrium. Held
        coordinates give their distance to the held value instead."""

    @abc.abstractmethod
    def structure(self) -> str:
        r"""The structure of :meth:`static_residual`'s Jacobian in the increments (one of
        :data:`STRUCTURES`, static): ``"tridiagonal"`` where block $i$ depends on blocks
        $i \pm 1$ only."""

    @abc.abstractmethod
    def configuration_status(self, config, singular_tol: float):
        r"""``EquilibriumStatus.successful``, or why the configuration is not admissible
        (``singular_point`` within ``singular_tol`` of a singular sphere of $Z$ (4.11),
        ``domain_error``; items of :class:`rbo_jax.EquilibriumStatus`)."""

    @abc.abstractmethod
    def parameter_status(self):
        """``(ok, which, messages)``: whether every parameter check passes, the index of the
        first that fails, every message (static)."""

    # ---- motion ----------------------------------------------------------------------------

    @abc.abstractmethod
    def free_size(self) -> int:
        """$m$: the free coordinates of the configuration (static); the first-order state has
        $2m$."""

    @abc.abstractmethod
    def free_increments(self, q):
        """The increments (``block_shape()``) of the free coordinates ``q`` ``(m,)`` (zero on the
        held ones): the configuration ``retract(config, free_increments(q))`` is the one the
        chart of :meth:`field` at ``config`` gives ``q``."""

    @abc.abstractmethod
    def field(self, t, config, *, throw: bool = False):
        """``F(x)``: the first-order equations of motion over the free coordinates in the chart
        of the increments at ``config``, ``x = [q (m,), w (m,)]`` (module docstring).
        ``throw=False``: undefined configurations give NaN (no host callback)."""

    @abc.abstractmethod
    def depends_on_velocity(self) -> bool:
        r"""Whether a force depends on the velocities (friction, Kelvin–Voigt damping, a load of
        the angular velocity): decided from the model's structure, a traced damping counting
        as nonzero. Where none does, the velocity block of the linearisation at rest is zero
        (the gyroscopic terms are quadratic) and the spectrum is $\pm\sqrt{\lambda}$ of an
        $m\times m$ matrix (:func:`rbo_jax.fast_spectrum`)."""

    @abc.abstractmethod
    def state_at_rest(self, config):
        """The configuration as the user sees an equilibrium (the model's own type)."""


def first_order_field(model: AbstractMechanics, t, config, *, throw: bool = False):
    """:meth:`AbstractMechanics.field` (a function of the flat first-order state)."""
    return model.field(t, config, throw=throw)


def zero_increments(model: AbstractMechanics, dtype=None):
    """The zero increments of ``model`` (``block_shape()``)."""
    return jnp.zeros(model.block_shape(), dtype or jnp.result_type(float))


def checked_parameters(model: AbstractMechanics, x, caller: str, ok=None):
    """``x`` (a pytree), raising (:func:`equinox.branched_error_if`, inside ``jit`` too) with the
    message of the first of the model's parameter checks that fails
    (:meth:`AbstractMechanics.parameter_status`). ``ok``: whether they pass, computed in the
    caller's compiled program; where it is concrete and true nothing runs (the checks op by op,
    eagerly, cost small compilations)."""
    if ok is not None and not isinstance(ok, jax.core.Tracer) and bool(ok):
        return x
    valid, which, messages = model.parameter_status()
    return eqx.branched_error_if(x, ~valid, which, [f"{caller}: {m}" for m in messages])
