r"""The rigid body oscillator: equations of motion (4.53)–(4.56).

A rigid body with a fixed point, inertia tensor $A$ (reference position), on an elastic
foundation of energy $U(\theta)$, under external moments. The state is the turn-vector $\theta$
and the right (body-frame) angular velocity $\Omega$; the turn-tensor is $P = Q(\theta)$ and the
left (world-frame) angular velocity $\omega = P\cdot\Omega$.

Right form, eqs. (4.55)–(4.56), used for simulation:

$$A\cdot\dot\Omega + \Omega\times A\cdot\Omega + Z(\theta)\cdot\frac{d(U+V)}{d\theta}
  = P^T\cdot M_{ex}, \qquad \dot\theta = Z^T(\theta)\cdot\Omega.$$

Left form, eqs. (4.53)–(4.54), with the kinetic moment $L = P\cdot A\cdot P^T\cdot\omega$ (4.43):

$$\dot L + Z^T(\theta)\cdot\frac{d(U+V)}{d\theta}
  = M_{ex}, \qquad \dot\theta = Z(\theta)\cdot\omega.$$

The elastic moment $-Z^T\cdot dU/d\theta$ is :func:`rbo_jax.potential_moment` (4.23), (4.46); since
$P^T\cdot Z^T = Z$ (4.13) the body-frame form of (4.55) follows. Loads are world-frame moments
$M(t, \theta, \omega)$, potential ones (4.52) included; the right form takes each in the body
frame, $P^T\cdot M$, through :meth:`rbo_jax.AbstractLoad.body_moment`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._custom_types import Matrix, Scalar, Vector
from .._validation import array_namespace, checks_status, failures_as_nan, on_host
from ..foundations import AbstractFoundation
from ..inertia import check_inertia, inertia_checks
from ..kinematics import (
    Turn,
    as_vector,
    cross3,
    distance_to_singularity,
    dot3,
    integrating_tensor_inv,
    matvec3,
    stored,
    turn_tensor,
)
from ..loads import AbstractLoad, as_load
from ..mechanics import AbstractMechanics, EquilibriumStatus

__all__ = ["RigidBodyOscillator", "RightForm", "LeftForm"]


def inverse3(A: Matrix) -> Matrix:
    """Inverse of a 3×3 matrix by cofactors, written out component by component (cheaper than
    an LU call inside vmapped solvers)."""
    c0 = cross3(A[1], A[2])
    c1 = cross3(A[2], A[0])
    c2 = cross3(A[0], A[1])
    det = dot3(A[0], c0)
    return jnp.stack([c0, c1, c2], axis=1) / det


class RightForm(eqx.Module):
    r"""The right form (4.55)–(4.56) of a model, ready to evaluate: ``rhs(t, (theta, Omega))``
    returns $(\dot\theta, \dot\Omega)$. Made by :meth:`RigidBodyOscillator.right_form`, which
    computes $A^{-1}$ once; solvers make it once per solve, outside their step loop.

    $\dot\Omega = A^{-1}\cdot(P^T\cdot M - \Omega\times A\cdot\Omega)$ with the body-frame
    moment $P^T\cdot M = -Z\cdot dU/d\theta + \sum P^T\cdot M_{ex}$ (the elastic part by
    $P^T\cdot Z^T = Z$, (4.13)), and $\dot\theta = Z^T\cdot\Omega$ (4.14). Everything is
    written component by component (:class:`rbo_jax.kinematics.Turn`): no batched 3×3 products
    under ``vmap``, one source of truth for :func:`rbo_jax.simulate` and
    :func:`rbo_jax.fast_simulate`.
    """

    model: RigidBodyOscillator
    inertia_inv: Float[Array, "3 3"]
    throw: bool = eqx.field(static=True, default=True)

    def __call__(self, t, y, args=None) -> tuple[Vector, Vector]:
        theta, Omega = y
        with failures_as_nan(not self.throw):
            return self.rates(t, theta, Omega, self.model.foundation.gradient(theta))

    def rates(
        self, t, theta, Omega, gradient, moment=None, load_scale=None
    ) -> tuple[Vector, Vector]:
        r"""$(\dot\theta, \dot\Omega)$ of (4.55)–(4.56) with ``gradient`` in place of
        $d(U+V)/d\theta$ (the foundation's own in :meth:`__call__`), ``moment`` a further
        body-frame moment $P^T\cdot M$ (the couplings to other bodies of a lattice,
        :mod:`rbo_jax.lattice`), and every load times ``load_scale`` (``None``: 1)."""
        model = self.model
        with failures_as_nan(not self.throw):
            turn = Turn(theta)
            M = -turn.Z(gradient)
            if moment is not None:
                M = M + moment
            for load in model.loads:
                m = load.body_moment(t, theta, Omega, turn)
                M = M + (m if load_scale is None else load_scale * m)
            r = stored(M - cross3(Omega, matvec3(model.inertia, Omega)))
            return turn.ZT(Omega), matvec3(self.inertia_inv, r)


class LeftForm(eqx.Module):
    r"""The left form (4.53)–(4.54) on the state ``(theta, L)``, $L$ the kinetic moment (4.43):
    $\dot L = M$, $\dot\theta = Z\cdot\omega$ with $\omega = P\cdot A^{-1}\cdot P^T\cdot L$.
    Made by :meth:`RigidBodyOscillator.left_form`."""

    # fields and call as RightForm's: two small forms of one model, clearer apart than in a base
    model: RigidBodyOscillator
    inertia_inv: Float[Array, "3 3"]
    throw: bool = eqx.field(static=True, default=True)

    def __call__(self, t, y, args=None) -> tuple[Vector, Vector]:
        theta, L = y
        with failures_as_nan(not self.throw):
            turn = Turn(theta)
            omega = turn.rotate(matvec3(self.inertia_inv, turn.rotate_back(L)))
            return turn.Z(omega), self.model.world_moment(t, theta, omega)


class RigidBodyOscillator(AbstractMechanics):
    r"""Rigid body with a fixed point on an elastic foundation, eqs. (4.53)–(4.56).

    **Arguments:**

    - `inertia`: the inertia tensor $A$ in the reference position, any symmetric positive
      definite 3×3 (see :func:`rbo_jax.transversely_isotropic_inertia` (4.40) and
      :func:`rbo_jax.principal_inertia` (4.39)).
    - `foundation`: the elastic foundation, an :class:`rbo_jax.AbstractFoundation` giving
      $U(\theta)$.
    - `loads`: external moments $M_{ex}$: a load or a sequence of loads
      (:class:`rbo_jax.DeadMoment`, :class:`rbo_jax.FollowerMoment`, ...), or plain callables
      ``f(t, theta, omega) -> (3,)`` giving a world-frame moment. They add up.

    All float leaves (inertia entries, stiffnesses, load magnitudes) can be differentiated,
    vmapped over and fitted; the model may be built inside ``jax.vmap``/``jax.jit``.
    """

    inertia: Float[Array, "3 3"]
    foundation: AbstractFoundation
    loads: tuple[AbstractLoad, ...]

    def __init__(
        self,
        inertia,
        foundation: AbstractFoundation,
        loads: AbstractLoad | Callable | Sequence[AbstractLoad | Callable] = (),
    ):
        self.inertia = check_inertia(inertia)
        if not isinstance(foundation, AbstractFoundation):
            raise TypeError(
                "foundation must be an rbo_jax foundation (QuadraticFoundation, BarrierFoundation, "
                "IsotropicFoundation(F), TransverselyIsotropicFoundation(F, k), or a sum of them); "
                f"got {type(foundation).__name__}."
            )
        self.foundation = foundation
        if (
            isinstance(loads, AbstractLoad)
            or getattr(loads, "needs_positions", False)
            or (callable(loads) and not isinstance(loads, Sequence))
        ):
            loads = (loads,)
        self.loads = tuple(as_load(load) for load in loads)

    # ---------------------------------------------------------------------------------------
    # Energies and kinetic quantities.
    # ---------------------------------------------------------------------------------------

    def potential_energy(self, theta) -> Scalar:
        r"""Elastic energy $U(\theta)$ plus the potential $V(\theta)$ of potential loads (4.52)."""
        theta = as_vector(theta)
        V = sum((load.potential_energy(theta) for load in self.loads), jnp.zeros(()))
        return self.foundation.energy(theta) + V

    def kinetic_energy(self, Omega) -> Scalar:
        r"""$K = \frac12\,\Omega\cdot A\cdot\Omega$."""
        Omega = as_vector(Omega, "Omega")
        return 0.5 * Omega @ self.inertia @ Omega

    def energy(self, theta, Omega) -> Scalar:
        """Total mechanical energy $K + U + V$ (conserved without friction and non-potential
        loads, (4.124))."""
        return self.kinetic_energy(Omega) + self.potential_energy(theta)

    def omega(self, theta, Omega) -> Vector:
        r"""Left angular velocity $\omega = P\cdot\Omega$ (definition before (4.14))."""
        return turn_tensor(theta) @ as_vector(Omega, "Omega")

    def kinetic_moment(self, theta, Omega) -> Vector:
        r"""Kinetic moment $L = P\cdot A\cdot\Omega$ (4.44), equal to $P A P^T\omega$ (4.43)."""
        return turn_tensor(theta) @ (self.inertia @ as_vector(Omega, "Omega"))

    def inertia_world(self, theta) -> Matrix:
        r"""Inertia tensor in the actual position $A^{(t)} = P\cdot A\cdot P^T$ (4.41)."""
        P = turn_tensor(theta)
        return P @ self.inertia @ P.T

    def domain_margin(self, theta) -> Scalar:
        """Margin of θ inside the domain of the foundation energy (> 0 inside)."""
        return self.foundation.domain_margin(as_vector(theta))

    # ---------------------------------------------------------------------------------------
    # Moments and vector fields.
    # ---------------------------------------------------------------------------------------

    def parameter_checks(self) -> list:
        """``(valid, message)`` pairs of every parameter: the inertia (:func:`inertia_checks`),
        the foundation's and each load's, and no NaN anywhere."""
        leaves = jax.tree_util.tree_leaves(eqx.filter(self, eqx.is_inexact_array))
        xp = array_namespace(leaves)
        no_nan = xp.logical_not(xp.any(xp.stack([xp.any(xp.isnan(x)) for x in leaves])))
        checks = [(no_nan, "RigidBodyOscillator: a model parameter is NaN.")]
        checks += inertia_checks(self.inertia) + self.foundation.parameter_checks()
        for load in self.loads:
            checks += load.parameter_checks()
        return checks

    def parameter_status(self) -> tuple[Bool[Array, ""], Int[Array, ""], tuple[str, ...]]:
        """``(ok, which, messages)``: whether every parameter is valid, the index of the first
        failed check and the messages of all checks (static). Solvers use it to refuse a model
        built from invalid traced values: with ``throw=True`` they raise ``messages[which]``
        (:func:`equinox.branched_error_if`), with ``throw=False`` they return the status
        ``invalid_parameters``. Concrete invalid values rarely get here (the constructors raise):
        a model whose parameters are all concrete is checked in NumPy (NumPy ``ok`` and
        ``which``), compiling nothing."""
        leaves = jax.tree_util.tree_leaves(self)
        if array_namespace(leaves) is np:
            checks = on_host(self).parameter_checks()
            valid = np.array([bool(np.all(v)) for v, _ in checks])
            return np.bool_(valid.all()), np.int32(np.argmin(valid)), tuple(m for _, m in checks)
        return checks_status(self.parameter_checks())

    def inertia_inverse(self) -> Matrix:
        """$A^{-1}$ (by cofactors)."""
        return inverse3(self.inertia)

    def world_moment(self, t, theta, omega, load_scale=None) -> Vector:
        r"""Total world-frame moment on the body: $-Z^T\cdot dU/d\theta$ (4.46) plus every load
        (4.52), times ``load_scale`` (``None``: 1)."""
        theta = as_vector(theta)
        M = -Turn(theta).ZT(self.foundation.gradient(theta))
        for load in self.loads:
            m = load.moment(t, theta, omega)
            M = M + (m if load_scale is None else load_scale * m)
        return M

    def right_form(self, throw: bool = True) -> RightForm:
        """The right form (4.55)–(4.56), ready to evaluate (:class:`RightForm`; $A^{-1}$ computed
        here, once). ``throw=False``: a configuration where the equations are undefined (e.g.
        the degenerate direction of (4.75)) gives NaN instead of a runtime error (a host
        callback), for solvers that report failures as a status."""
        return RightForm(self, self.inertia_inverse(), throw)

    def left_form(self, throw: bool = True) -> LeftForm:
        """The left form (4.53)–(4.54), ready to evaluate (:class:`LeftForm`; ``throw`` as in
        :meth:`right_form`)."""
        return LeftForm(self, self.inertia_inverse(), throw)

    def vector_field(self, t, y, args=None) -> tuple[Vector, Vector]:
        r"""Right form (4.55)–(4.56) on the state ``y = (theta, Omega)``:
        $\dot\Omega = A^{-1}\cdot(P^T\cdot M - \Omega\times A\cdot\Omega)$,
        $\dot\theta = Z^T\cdot\Omega$ (4.14), (4.16). Evaluates :meth:`right_form`; solvers make
        that once and call it instead."""
        return self.right_form()(t, y, args)

    def left_vector_field(self, t, y, args=None) -> tuple[Vector, Vector]:
        r"""Left form (4.53)–(4.54) on the state ``y = (theta, L)``, $L$ the kinetic moment (4.43):
        $\dot L = M$, $\dot\theta = Z\cdot\omega$ with $\omega = P\cdot A^{-1}\cdot P^T\cdot L$."""
        return self.left_form()(t, y, args)

    def Omega_from_kinetic_moment(self, theta, L) -> Vector:
        r"""$\Omega = A^{-1}\cdot P^T\cdot L$, inverse of (4.44)."""
        return matvec3(self.inertia_inverse(), Turn(theta).rotate_back(as_vector(L, "L")))

    def Omega_from_rate(self, theta, theta_dot) -> Vector:
        r"""$\Omega = Z^{-T}\cdot\dot\theta$ (4.19)."""
        return integrating_tensor_inv(theta).T @ as_vector(theta_dot, "theta_dot")

    # ---------------------------------------------------------------------------------------
    # The mechanics (rbo_jax.mechanics.AbstractMechanics): one block of three turn increments,
    # added to the turn-vector (the foundation's energy U(theta) tells the turns apart: a turn
    # by 2*pi is another configuration).
    # ---------------------------------------------------------------------------------------

    def rest(self) -> Vector:
        r"""$\theta = 0$."""
        return jnp.zeros(3, jnp.result_type(float))

    def configuration(self, guess, name: str = "theta_guess") -> Vector:
        """``guess`` as a turn-vector (3,) (``None``: 0)."""
        return self.rest() if guess is None else as_vector(guess, name)

    def block_shape(self) -> tuple[int, int]:
        r"""One block of the three components of $\theta$."""
        return (1, 3)

    def retract(self, theta, x) -> Vector:
        r"""$\theta + x$."""
        return theta + x[0]

    def increment_scale(self, theta):
        r"""$1 + |\theta_i|$: a step is small against 1 or against the component."""
        return (1.0 + jnp.abs(theta))[None]

    def static_residual(self, t, theta, x, load_scale=1.0):
        r"""The world-frame moment at rest, $M(\theta + x)$ ((4.61) in general form)."""
        scale = None if isinstance(load_scale, float) and load_scale == 1.0 else load_scale
        return self.world_moment(t, theta + x[0], jnp.zeros(3, x.dtype), scale)[None]

    def structure(self) -> str:
        """Three unknowns: ``"dense"``."""
        return "dense"

    def configuration_status(self, theta, singular_tol: float = 1e-6):
        r"""``singular_point`` on a singular sphere $|\theta| = 2\pi k$ of $Z$ (4.11),
        ``domain_error`` outside the foundation's domain (4.49)."""
        S = EquilibriumStatus
        status = S.where(self.domain_margin(theta) > 0, S.successful, S.domain_error)
        return S.where(distance_to_singularity(theta) > singular_tol, status, S.singular_point)

    def free_size(self) -> int:
        r"""The three components of $\theta$."""
        return 3

    def free_increments(self, q):
        """The one block ``(1, 3)``."""
        return jnp.reshape(q, (1, 3))

    def field(self, t, theta, *, throw: bool = False):
        r"""$x = [q, \Omega] \mapsto [\dot\theta, \dot\Omega]$ of the right form (4.55)–(4.56)
        at $\theta + q$."""
        rhs = self.right_form(throw)

        def F(x):
            theta_dot, Omega_dot = rhs(t, (theta + x[:3], x[3:]))
            return jnp.concatenate([theta_dot, Omega_dot])

        return F

    def depends_on_velocity(self) -> bool:
        """Whether a load depends on the angular velocity
        (:attr:`rbo_jax.AbstractLoad.depends_on_velocity`: friction (4.84), ...)."""
        return any(load.depends_on_velocity for load in self.loads)

    def state_at_rest(self, theta) -> Vector:
        """The turn-vector itself."""
        return theta
