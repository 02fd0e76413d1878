r"""External moments $M_{ex}$ acting on the body: sections 4.3–4.6.

Every load is an :class:`equinox.Module` with

- ``moment(t, theta, omega)``: the moment as a **world-frame** (spatial) vector, as a function
  of the time ``t``, the turn-vector ``theta`` and the **left** (world-frame) angular velocity
  ``omega`` $= \omega = P\cdot\Omega$, $P = Q(\theta)$;
- ``potential_energy(theta)``: the potential $V(\theta)$ of the load if it has one (4.52), else
  0. A load with a potential is $M = -Z^T\cdot dV/d\theta$, eq. (4.23).

Parameters are float array leaves (differentiable, sweepable); unit axes ``k`` are normalised
on construction. Concrete parameters are validated eagerly (``ValueError`` naming the parameter),
traced ones by the solvers that use them (``parameter_checks``), exactly as the foundations
(:mod:`rbo_jax.foundations`).
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._custom_types import Scalar, ScalarLike, Vector, VectorLike
from ._validation import (
    FINITE,
    NONNEGATIVE,
    callable_leaf,
    check_value,
    error_if,
    float_dtype,
    is_traced,
    requirement_checks,
    set_parameters,
    unit_axis,
)
from .foundations import AbstractFoundation, body_potential_moment, potential_moment
from .kinematics import Turn, as_vector, dot3

__all__ = [
    "AbstractLoad",
    "DeadMoment",
    "FollowerMoment",
    "SemiTangentialMoment",
    "Friction",
    "PotentialLoad",
    "CallableLoad",
    "as_load",
]


def _zero():
    return jnp.zeros((), dtype=float_dtype())


class AbstractLoad(eqx.Module):
    """An external moment acting on the body (world frame).

    ``depends_on_velocity`` says whether the moment can depend on the angular velocity; the
    linearization at rest uses it (a velocity-independent load has no damping block). A load
    class that does not set it is assumed to depend on the velocity.
    """

    depends_on_velocity: ClassVar[bool] = True

    @abc.abstractmethod
    def moment(self, t: ScalarLike, theta: VectorLike, omega: VectorLike) -> Vector:
        r"""The world-frame moment at time ``t``, turn-vector ``theta`` and left angular
        velocity ``omega``."""

    @abc.abstractmethod
    def potential_energy(self, theta: VectorLike) -> Scalar:
        r"""The potential $V(\theta)$ of the load, eq. (4.52); 0 for non-potential loads."""

    def parameter_checks(self) -> list:
        """``(valid, message)`` pairs of the parameters (traced values are checked by the solvers,
        see :meth:`rbo_jax.RigidBodyOscillator.parameter_status`)."""
        return requirement_checks(self)

    def body_moment(self, t: ScalarLike, theta: Vector, Omega: Vector, turn: Turn) -> Vector:
        r"""The moment in the body frame, $P^T\cdot M_{ex}$ (the right-hand side of (4.55)),
        given the right angular velocity $\Omega$ and the turn $P = Q(\theta)$ as a
        :class:`rbo_jax.kinematics.Turn` (made once by the caller; ``turn @ v`` is $P\cdot v$,
        ``turn.T @ v`` is $P^T\cdot v$). By default $P^T\cdot$ :meth:`moment`
        $(t, \theta, P\cdot\Omega)$; loads with a simpler body-frame form override it (a
        follower moment is constant there), which spares the right-form vector field the
        turn-tensor."""
        return turn.rotate_back(self.moment(t, theta, turn.rotate(Omega)))


class _AbstractAxialMoment(AbstractLoad):
    """A moment of magnitude ``M`` about the unit axis ``k`` (dead or follower)."""

    M: Scalar
    k: Vector

    depends_on_velocity: ClassVar[bool] = False

    _requirements: ClassVar = (("M", FINITE, ""),)

    def __init__(self, M: ScalarLike, k: VectorLike):
        set_parameters(self, M=M)
        self.k = unit_axis(k, type(self).__name__)

    def potential_energy(self, theta) -> Scalar:
        return _zero()


class DeadMoment(_AbstractAxialMoment):
    r"""A dead moment of fixed world direction, $M_{ex} = M k$: (4.75) with $l_1 = 1$, $l_2 = 0$.

    Not potential (its work depends on the path), so ``potential_energy`` is 0.
    """

    def moment(self, t, theta, omega) -> Vector:
        """M k, eq. (4.75) with l1 = 1, l2 = 0."""
        return self.M * self.k

    def body_moment(self, t, theta, Omega, turn) -> Vector:
        """Pᵀ·(M k)."""
        return turn.rotate_back(self.M * self.k)


class FollowerMoment(_AbstractAxialMoment):
    r"""A follower (tangential) moment turning with the body, $M_{ex} = M\,P\cdot k$,
    $P = Q(\theta)$, eq. (4.57); (4.75) with $l_1 = 0$, $l_2 = 1$.

    Non-conservative (the source of the Nikolai paradox, section 4.4); ``potential_energy`` is 0.
    """

    def moment(self, t, theta, omega) -> Vector:
        """M P(θ)·k, eq. (4.57)."""
        return self.M * Turn(theta).rotate(self.k)

    def body_moment(self, t, theta, Omega, turn) -> Vector:
        """Pᵀ·(M P·k) = M k: constant in the body frame."""
        return self.M * self.k


class SemiTangentialMoment(AbstractLoad):
    r"""The moment of eq. (4.75): $M_{ex} = \gamma M\,(l_1 k + l_2 P\cdot k)$,
    $\gamma = (l_1^2 + l_2^2 + 2 l_1 l_2\,k\cdot P\cdot k)^{-1/2}$ (reading R9 of
    docs/readings.md), so that $|M_{ex}| = |M|$.

    $l_1 = l_2 = 1$ (the default) is the semi-tangential moment; $(1, 0)$ is dead and $(0, 1)$
    follower. Since $|P\cdot k| = 1$, $\gamma^{-2} = |l_1 k + l_2 P\cdot k|^2$, which is how it is
    evaluated (no cancellation in the direction near the degenerate point).

    The direction is undefined where $l_1 k + l_2 P\cdot k = 0$, i.e. $|l_1| = |l_2|$ and
    $P\cdot k = -\mathrm{sign}(l_1 l_2)\,k$ (for the semi-tangential moment: the axis turned
    upside down). There :meth:`moment` raises via :func:`equinox.error_if` instead of returning
    NaN or a meaningless direction (inside a solve with ``throw=False``: NaN, which stops the
    solve with a non-finite state).
    """

    M: Scalar
    k: Vector
    l1: Scalar
    l2: Scalar

    _requirements: ClassVar = (
        ("M", FINITE, ""),
        ("l1", FINITE, "dead part"),
        ("l2", FINITE, "follower part"),
    )

    def __init__(self, M: ScalarLike, k: VectorLike, l1: ScalarLike = 1.0, l2: ScalarLike = 1.0):
        set_parameters(self, M=M, l1=l1, l2=l2)
        self.k = unit_axis(k, type(self).__name__)
        # concrete weights are compared on the host (an eager JAX comparison would compile)
        l1, l2 = (x if is_traced(x) else np.asarray(x) for x in (self.l1, self.l2))
        self.l1 = check_value(self.l1, self._weights_valid(l1, l2), self._weights_message())

    @staticmethod
    def _weights_valid(l1, l2):
        return (l1 != 0) | (l2 != 0)

    def _weights_message(self) -> str:
        return f"{type(self).__name__}: the parameters l1 and l2 must not both be zero"

    def parameter_checks(self) -> list:
        return super().parameter_checks() + [
            (self._weights_valid(self.l1, self.l2), self._weights_message())
        ]

    depends_on_velocity: ClassVar[bool] = False

    def gamma(self, theta: VectorLike) -> Scalar:
        r"""$\gamma = (l_1^2 + l_2^2 + 2l_1l_2\,k\cdot P\cdot k)^{-1/2}$ of eq. (4.75)."""
        theta = as_vector(theta)
        return 1.0 / self._norm(self.l1 * self.k + self.l2 * Turn(theta).rotate(self.k))

    def _norm(self, v):
        """|v| for v = l1 k + l2 P·k (or its body-frame image, of the same length), raising
        where the direction of (4.75) is undefined."""
        n2 = dot3(v, v)
        # |v| is zero only at the degenerate configuration; the rounding floor of v is
        # ~eps(|l1| + |l2|). Double where: no NaN in the reverse pass at v = 0.
        tol = 64 * jnp.finfo(n2.dtype).eps * (jnp.abs(self.l1) + jnp.abs(self.l2))
        degenerate = n2 <= tol**2
        norm = jnp.sqrt(jnp.where(degenerate, jnp.ones_like(n2), n2))
        return error_if(
            norm,
            degenerate,
            "SemiTangentialMoment: l1 k + l2 P.k = 0 (|l1| = |l2| and the turned axis P.k is "
            "-sign(l1 l2) k), so the direction of the moment (4.75) is undefined.",
        )

    def moment(self, t, theta, omega) -> Vector:
        """γM(l1 k + l2 P·k), eq. (4.75)."""
        v = self.l1 * self.k + self.l2 * Turn(theta).rotate(self.k)
        return (self.M / self._norm(v)) * v

    def body_moment(self, t, theta, Omega, turn) -> Vector:
        """Pᵀ·M_ex = γM(l1 Pᵀ·k + l2 k) (|Pᵀ·v| = |v|: the same γ)."""
        v = self.l1 * turn.rotate_back(self.k) + self.l2 * self.k
        return (self.M / self._norm(v)) * v

    def potential_energy(self, theta) -> Scalar:
        return _zero()


class Friction(AbstractLoad):
    r"""Viscous friction $M_{ex} = -b\,\omega$, $b \ge 0$, eq. (4.84) (left angular velocity)."""

    b: Scalar

    depends_on_velocity: ClassVar[bool] = True

    _requirements: ClassVar = (("b", NONNEGATIVE, "friction"),)

    def __init__(self, b: ScalarLike):
        set_parameters(self, b=b)

    def moment(self, t, theta, omega) -> Vector:
        """−b ω, eq. (4.84)."""
        return -self.b * as_vector(omega, "omega")

    def body_moment(self, t, theta, Omega, turn) -> Vector:
        """Pᵀ·(−b P·Ω) = −b Ω."""
        return -self.b * Omega

    def potential_energy(self, theta) -> Scalar:
        return _zero()


class PotentialLoad(AbstractLoad):
    r"""The potential part of the external moment, $-Z^T(\theta)\cdot dV/d\theta$, eq. (4.52).

    ``V`` is any scalar function of the turn-vector (a foundation included); the moment is
    :func:`rbo_jax.potential_moment` of ``V`` and ``potential_energy`` is $V(\theta)$.
    """

    V: Callable[[Vector], Scalar]

    def __init__(self, V: Callable[[Vector], Scalar]):
        self.V = callable_leaf(V, "PotentialLoad", "V")

    def moment(self, t, theta, omega) -> Vector:
        """−Zᵀ·dV/dθ, eqs. (4.52), (4.23)."""
        return potential_moment(self.V, theta)

    depends_on_velocity: ClassVar[bool] = False

    def body_moment(self, t, theta, Omega, turn) -> Vector:
        """Pᵀ·(−Zᵀ·dV/dθ) = −Z·dV/dθ, by Zᵀ = P·Z (4.13)."""
        return body_potential_moment(self.V, theta)

    def potential_energy(self, theta) -> Scalar:
        out = jnp.asarray(self.V(as_vector(theta)))
        if out.shape != ():
            raise ValueError(f"PotentialLoad: V must return a scalar, got shape {out.shape}.")
        return out


class CallableLoad(AbstractLoad):
    r"""A user moment ``fn(t, theta, omega)`` → world-frame (3,) vector, e.g. time-dependent
    forcing. ``omega`` is the left angular velocity. ``potential_energy`` is 0.

    If ``fn`` is an :class:`equinox.Module`, its float leaves are differentiable parameters.
    """

    fn: Callable

    def __init__(self, fn: Callable):
        self.fn = callable_leaf(fn, "CallableLoad", "fn")

    def moment(self, t, theta, omega) -> Vector:
        out = jnp.asarray(self.fn(t, theta, omega))
        if out.shape != (3,):
            raise ValueError(
                "CallableLoad: fn(t, theta, omega) must return a world-frame moment of shape "
                f"(3,), got shape {out.shape}."
            )
        return out

    def potential_energy(self, theta) -> Scalar:
        return _zero()


def as_load(x) -> AbstractLoad:
    """``x`` if it is an :class:`AbstractLoad`; a callable ``fn(t, theta, omega)`` wrapped in
    :class:`CallableLoad`; anything else raises ``TypeError``."""
    if isinstance(x, AbstractLoad):
        return x
    if getattr(x, "needs_positions", False):
        raise TypeError(
            f"as_load: {type(x).__name__} is a load on bodies that translate; a rigid body "
            "oscillator and the bodies of a lattice turn about fixed points and have no position "
            "to apply it at. Build a rod (rbo_jax.lattice.rod(..., loads=...)), or give a moment "
            "(DeadMoment, FollowerMoment)."
        )
    if isinstance(x, AbstractFoundation):
        raise TypeError(
            f"as_load: got a foundation ({type(x).__name__}), which is an energy U(theta), not a "
            "load fn(t, theta, omega). Pass it as the model's foundation, or as "
            "PotentialLoad(foundation) for a potential external moment (4.52)."
        )
    if callable(x):
        return CallableLoad(x)
    raise TypeError(
        "as_load: expected an AbstractLoad or a callable fn(t, theta, omega) -> (3,) world-frame "
        f"moment, got {type(x).__name__}: {x!r}."
    )
