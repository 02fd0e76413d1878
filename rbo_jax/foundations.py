r"""Elastic foundations: the energy $U(\theta)$ and its potential moment, sections 4.2.3 and 4.3.

A foundation is an :class:`equinox.Module` holding its stiffness parameters as differentiable
float array leaves. Every foundation provides

- ``energy(theta)``: the formula $U(\theta)$ itself, with no domain check. It is traceable,
  differentiable and cheap: use it inside ODE vector fields and loss functions;
- ``domain_margin(theta)``: a dimensionless scalar, $> 0$ strictly inside the domain of
  definition of the formula and $\le 0$ outside ($+\infty$ where the formula holds everywhere);
- ``foundation(theta)``: the energy with a domain check (:func:`equinox.error_if`), for users.

The moment exerted on the body is $M_e = -Z^T(\theta)\cdot dU/d\theta$, eqs. (4.23)/(4.46); it is
computed by automatic differentiation for any energy with :func:`potential_moment`. For the
transversely isotropic energies (4.24) it has the form (4.47),
$M_e = -C\theta - D\,Z^T\cdot k$, with the coefficients $C$, $D$ of (4.48) returned by
:func:`transverse_coefficients`.

Parameters may be given as Python/NumPy numbers (validated eagerly: bad values raise
``ValueError`` naming the parameter) or as traced JAX values (foundations may be built inside
``jax.vmap``/``jax.jit``/``jax.grad``; bad values then raise at run time via
:func:`equinox.error_if`). Unit axes ``k`` are normalised on construction. All parameters are
stored as float arrays, so changing their values never triggers a recompilation.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ._custom_types import Scalar, ScalarLike, Vector, VectorLike
from ._validation import (
    NONNEGATIVE,
    POSITIVE,
    POSITIVE_OR_INF,
    callable_leaf,
    error_if,
    requirement_checks,
    set_parameters,
    unit_axis,
)
from .kinematics import Turn, as_vector, cosc, dot3, sinc, stored

__all__ = [
    "AbstractFoundation",
    "QuadraticFoundation",
    "BarrierFoundation",
    "IsotropicFoundation",
    "CosineFoundation",
    "ZeroFoundation",
    "TransverselyIsotropicFoundation",
    "SumFoundation",
    "AbstractTransverselyIsotropicFoundation",
    "potential_moment",
    "body_potential_moment",
    "transverse_coefficients",
]


def _axial_split(theta, k):
    r"""$x = k\cdot\theta$ and $\theta_\perp^2 = |\theta - x k|^2 = \theta^2 - (k\cdot\theta)^2$.

    The perpendicular part is formed before squaring, which avoids the cancellation of
    $\theta^2 - (k\cdot\theta)^2$ when $\theta$ is nearly parallel to $k$.
    """
    x = dot3(k, theta)
    perp = theta - x * k
    return x, dot3(perp, perp)


class AbstractFoundation(eqx.Module):
    r"""An elastic foundation: an energy $U(\theta)$ of the turn-vector (section 4.3).

    Subclasses implement :meth:`energy` and :meth:`domain_margin` and may set the class
    attribute ``domain_description`` (used in error messages). Calling the foundation,
    ``foundation(theta)``, returns the energy and raises (:func:`equinox.error_if`) when
    ``theta`` lies outside the domain of definition. Foundations add up: ``f + g`` is a
    :class:`SumFoundation`.
    """

    domain_description: ClassVar[str] = "domain_margin(theta) > 0"

    @abc.abstractmethod
    def energy(self, theta: VectorLike) -> Scalar:
        r"""The energy $U(\theta)$: the raw formula, no domain check (traceable)."""

    @abc.abstractmethod
    def domain_margin(self, theta: VectorLike) -> Scalar:
        r"""$> 0$ strictly inside the domain of definition of :meth:`energy`, $\le 0$
        outside; ``inf`` for energies defined everywhere."""

    @property
    def isotropic(self) -> bool:
        r"""Whether the energy depends on $\theta^2$ only (section 4.2.3)."""
        return False

    def gradient(self, theta: VectorLike) -> Vector:
        r"""$dU/d\theta$, the derivative in the elastic moment $-Z^T\cdot dU/d\theta$ (4.23):
        by automatic differentiation of :meth:`energy`; the transversely isotropic foundations
        use the closed form $C\theta + D k$ of (4.47)–(4.48) instead."""
        return jax.grad(lambda th: _as_scalar_output(self.energy(th), "energy"))(as_vector(theta))

    def coefficients(self, theta: VectorLike) -> tuple[Scalar, Scalar]:
        r"""$C$ and $D$ of (4.48), $dU/d\theta = C\theta + D k$, for transversely isotropic
        foundations (4.24); a general foundation has none and raises ``TypeError``."""
        raise TypeError(
            "transverse_coefficients: expected a QuadraticFoundation, BarrierFoundation, "
            "TransverselyIsotropicFoundation, IsotropicFoundation or a SumFoundation of them, got "
            f"{type(self).__name__}. Wrap the energy as a TransverselyIsotropicFoundation(F, k)."
        )

    def parameter_checks(self) -> list:
        """``(valid, message)`` pairs of the parameters (traced values are checked by the solvers,
        see :meth:`rbo_jax.RigidBodyOscillator.parameter_status`)."""
        return requirement_checks(self)

    def symmetry_axis(self) -> Vector | None:
        """The axis $k$ about which the energy is invariant (4.24), or ``None``: for a general
        foundation, and for an isotropic one, which is symmetric about every axis (see
        ``isotropic``)."""
        return None

    def __call__(self, theta: VectorLike) -> Scalar:
        """The energy U(θ), raising an error when θ is outside the domain of definition.

        Inside ``jax.jit`` the error is raised when the computation runs (``equinox.error_if``).
        """
        theta = as_vector(theta)
        energy = self.energy(theta)
        return eqx.error_if(
            energy,
            self.domain_margin(theta) <= 0,
            f"theta is outside the domain of definition of the energy of {_describe(self)}.",
        )

    def __add__(self, other):
        if not isinstance(other, AbstractFoundation):
            return NotImplemented
        return SumFoundation((self, other))


def _describe(foundation: AbstractFoundation) -> str:
    if isinstance(foundation, SumFoundation):
        return "SumFoundation (" + "; ".join(_describe(f) for f in foundation.terms) + ")"
    return f"{type(foundation).__name__}, which requires {foundation.domain_description}"


class AbstractTransverselyIsotropicFoundation(AbstractFoundation):
    r"""A foundation invariant under turns about its unit axis $k$: $U = F(k\cdot\theta,
    \theta^2)$, eq. (4.24). Subclasses give the coefficients (4.48), $C = 2\,\partial
    U/\partial(\theta^2)$ and $D = \partial U/\partial(k\cdot\theta)$, from which the gradient
    is $C\theta + D k$ and the elastic moment (4.47) $M_e = -C\theta - D\,Z^T\cdot k$; the
    regular precessions of section 4.7 and the fast paths of the equations of motion use them."""

    k: eqx.AbstractVar[Vector]

    @abc.abstractmethod
    def coefficients(self, theta: VectorLike) -> tuple[Scalar, Scalar]:
        r"""$C$ and $D$ of (4.48) at $\theta$."""

    def gradient(self, theta: VectorLike) -> Vector:
        r"""$dU/d\theta = C\theta + D k$ (4.47)."""
        theta = as_vector(theta)
        C, D = self.coefficients(theta)
        return C * theta + stored(D) * self.k

    def symmetry_axis(self) -> Vector:
        return self.k


# the stiffnesses c, d of (4.50) and (4.49), checked at construction
_STIFFNESSES = (("c", POSITIVE, "bending stiffness"), ("d", POSITIVE, "torsional stiffness"))


class QuadraticFoundation(AbstractTransverselyIsotropicFoundation):
    r"""The quadratic transversely isotropic foundation, eq. (4.50):

    $U = \tfrac12 c\,(\theta^2 - (k\cdot\theta)^2) + \tfrac12 d\,(k\cdot\theta)^2$,

    with bending stiffness $c > 0$, torsional stiffness $d > 0$ and unit axis $k$. Its moment
    is (4.51), $M_e = -c\theta - (d - c)(k\cdot\theta)\,Z^T(\theta)\cdot k$. Defined everywhere.
    """

    c: Scalar
    d: Scalar
    k: Vector

    domain_description: ClassVar[str] = "nothing (it is defined everywhere)"

    _requirements: ClassVar = _STIFFNESSES

    def __init__(self, c: ScalarLike, d: ScalarLike, k: VectorLike):
        set_parameters(self, c=c, d=d)
        self.k = unit_axis(k, type(self).__name__)

    def energy(self, theta: VectorLike) -> Scalar:
        """U of eq. (4.50)."""
        theta = as_vector(theta)
        x, perp2 = _axial_split(theta, self.k)
        return 0.5 * self.c * perp2 + 0.5 * self.d * x**2

    def domain_margin(self, theta: VectorLike) -> Scalar:
        return _everywhere(theta)

    def coefficients(self, theta: VectorLike) -> tuple[Scalar, Scalar]:
        r"""(4.51): $C = c$, $D = (d - c)\,k\cdot\theta$."""
        theta = as_vector(theta)
        return self.c, (self.d - self.c) * dot3(self.k, theta)


class BarrierFoundation(AbstractTransverselyIsotropicFoundation):
    r"""The transversely isotropic foundation with barriers, eq. (4.49):

    $U = \frac12\frac{\alpha^2 c\,\theta^2}{\alpha^2 - \theta^2 + (k\cdot\theta)^2}
       + \frac12\frac{\beta^2 (d - c)(k\cdot\theta)^2}{\beta^2 - (k\cdot\theta)^2}$,

    with $\alpha^2$ = ``alpha**2``, $\beta^2$ = ``beta**2``, $c, d > 0$ and unit axis $k$.

    Reading of (4.49): implemented exactly as printed — the first numerator carries the full
    $\theta^2$ (not $\theta_\perp^2 = \theta^2 - (k\cdot\theta)^2$) and the second carries
    $(d - c)$. As $\alpha, \beta \to \infty$ this gives $\frac12 c\theta^2 +
    \frac12(d - c)(k\cdot\theta)^2$, which is (4.50), as the text states; replacing $\theta^2$
    by $\theta_\perp^2$ in the first numerator would *not* reduce to (4.50) with this second
    term. ``alpha = inf`` / ``beta = inf`` switch the corresponding barrier off (the formula is
    coded as $\frac12 c\theta^2/(1 - \theta_\perp^2/\alpha^2) + \dots$, exactly (4.50) then).

    Note that the torsional term has the sign of $d - c$: for $d < c$ it tends to $-\infty$ at
    the torsion barrier. The domain of definition is $\theta_\perp^2 < \alpha^2$ and
    $(k\cdot\theta)^2 < \beta^2$; :meth:`domain_margin` is
    $\min\big((\alpha^2 - \theta_\perp^2)/\alpha^2,\ (\beta^2 - (k\cdot\theta)^2)/\beta^2\big)$.
    """

    c: Scalar
    d: Scalar
    alpha: Scalar
    beta: Scalar
    k: Vector

    domain_description: ClassVar[str] = (
        "theta^2 - (k.theta)^2 < alpha^2 (bending barrier) and (k.theta)^2 < beta^2 "
        "(torsion barrier), eq. (4.49)"
    )

    _requirements: ClassVar = _STIFFNESSES + (
        ("alpha", POSITIVE_OR_INF, "bending barrier; inf switches it off"),
        ("beta", POSITIVE_OR_INF, "torsion barrier; inf switches it off"),
    )

    def __init__(
        self,
        c: ScalarLike,
        d: ScalarLike,
        alpha: ScalarLike,
        beta: ScalarLike,
        k: VectorLike,
    ):
        set_parameters(self, c=c, d=d, alpha=alpha, beta=beta)
        self.k = unit_axis(k, type(self).__name__)

    def _reduced(self, theta):
        """x = k·θ, θ² and the barrier factors 1 − θ_⊥²/α², 1 − x²/β²."""
        # alpha**-2 rather than 1/alpha**2: finite derivatives at alpha = inf too.
        x, perp2 = _axial_split(theta, self.k)
        t = perp2 + x**2
        a = 1.0 - perp2 * self.alpha**-2
        b = 1.0 - x**2 * self.beta**-2
        return x, t, a, b

    def energy(self, theta: VectorLike) -> Scalar:
        """U of eq. (4.49) (no domain check)."""
        theta = as_vector(theta)
        x, t, a, b = self._reduced(theta)
        return 0.5 * self.c * t / a + 0.5 * (self.d - self.c) * x**2 / b

    def domain_margin(self, theta: VectorLike) -> Scalar:
        theta = as_vector(theta)
        _, _, a, b = self._reduced(theta)
        return jnp.minimum(a, b)

    def coefficients(self, theta: VectorLike) -> tuple[Scalar, Scalar]:
        r"""$C$ and $D$ of (4.48) for (4.49), in closed form:

        $C = c\,(1 + x^2/\alpha^2)/(1 - \theta_\perp^2/\alpha^2)^2$,
        $D = -c\,\theta^2 x/\big(\alpha^2(1 - \theta_\perp^2/\alpha^2)^2\big)
             + (d - c)\,x/(1 - x^2/\beta^2)^2$, $x = k\cdot\theta$.
        """
        theta = as_vector(theta)
        x, t, a, b = self._reduced(theta)
        C = self.c * (1.0 + x**2 * self.alpha**-2) / a**2
        D = -self.c * t * x * self.alpha**-2 / a**2 + (self.d - self.c) * x / b**2
        return C, D


def _everywhere(theta: VectorLike) -> Scalar:
    """The domain margin of an energy defined everywhere: ``inf``."""
    theta = as_vector(theta)
    return jnp.full((), jnp.inf, dtype=theta.dtype)


class _AbstractIsotropicFoundation(AbstractFoundation):
    r"""An isotropic foundation $U = F(\theta^2)$ (section 4.2.3), defined everywhere.
    Subclasses give :meth:`coefficients` (4.48), $C = 2F'(\theta^2)$ and $D = 0$, from which the
    gradient is $dU/d\theta = C\theta$."""

    @property
    def isotropic(self) -> bool:
        return True

    def domain_margin(self, theta: VectorLike) -> Scalar:
        return _everywhere(theta)

    def gradient(self, theta: VectorLike) -> Vector:
        r"""$dU/d\theta = 2F'(\theta^2)\,\theta = C\theta$."""
        theta = as_vector(theta)
        return self.coefficients(theta)[0] * theta


class IsotropicFoundation(_AbstractIsotropicFoundation):
    r"""An isotropic foundation $U = F(\theta^2)$, $\theta^2 = \theta\cdot\theta$ (section 4.2.3).

    ``F`` maps a scalar to a scalar. Its moment is $M_e = -2F'(\theta^2)\,\theta$; it satisfies
    $(a - Q(\theta)\cdot a)\cdot M_e = 0$ for every $a$ (after (4.26)). If ``F`` is an
    :class:`equinox.Module`, its float leaves are differentiable parameters. Defined
    everywhere (as far as this class knows).
    """

    F: Callable[[Scalar], Scalar]

    domain_description: ClassVar[str] = "nothing (it is treated as defined everywhere)"

    def __init__(self, F: Callable[[Scalar], Scalar]):
        self.F = callable_leaf(F, "IsotropicFoundation", "F")

    def energy(self, theta: VectorLike) -> Scalar:
        r"""$U = F(\theta\cdot\theta)$."""
        theta = as_vector(theta)
        return _as_scalar_output(self.F(dot3(theta, theta)), "IsotropicFoundation: F")

    def coefficients(self, theta: VectorLike) -> tuple[Scalar, Scalar]:
        r"""$C = 2F'(\theta^2)$ and $D = 0$ (an isotropic energy is transversely isotropic about
        every axis)."""
        theta = as_vector(theta)
        dF = jax.grad(lambda t_: _as_scalar_output(self.F(t_), "F"))(dot3(theta, theta))
        return 2.0 * dF, jnp.zeros_like(dF)


class CosineFoundation(_AbstractIsotropicFoundation):
    r"""The isotropic foundation $U = c\,(1 - \cos\theta)
    = \tfrac c2\,(3 - \mathrm{tr}\,Q(\theta))$, $\theta = |\theta|$ (section 4.2.3,
    $F(\theta^2) = c(1 - \cos\sqrt{\theta^2})$): the
    pendulum among foundations. Its energy depends on the turn only through the turn-tensor
    (4.3), so $\theta$ and $\theta - 2\pi\theta/|\theta|$ have the same energy; near rest it is
    the quadratic foundation with $c = d$. Its moment is $M_e = -c\,\frac{\sin\theta}{\theta}
    \,\theta$ ($C = c\sin\theta/\theta$, $D = 0$ in (4.47)). Plane rotations $\theta = \varphi
    k$ of a chain of such bodies, coupled by a quadratic foundation of the relative turn, are
    the discrete sine-Gordon (Frenkel–Kontorova) chain (:mod:`rbo_jax.lattice`). Energy, moment
    and their derivatives are exact at $\theta = 0$ ($1 - \cos\theta = \theta^2\,(1 - \cos
    \theta)/\theta^2$ by a series there). Defined everywhere; ``c >= 0``.
    """

    c: Scalar

    domain_description: ClassVar[str] = "nothing (it is defined everywhere)"

    _requirements: ClassVar = (("c", NONNEGATIVE, "stiffness"),)

    def __init__(self, c: ScalarLike):
        set_parameters(self, c=c)

    def energy(self, theta: VectorLike) -> Scalar:
        r"""$U = c\,(1 - \cos\theta) = c\,\theta^2\,\frac{1 - \cos\theta}{\theta^2}$."""
        theta = as_vector(theta)
        t = dot3(theta, theta)
        return self.c * t * cosc(t)

    def coefficients(self, theta: VectorLike) -> tuple[Scalar, Scalar]:
        r"""$C = c\sin\theta/\theta$, $D = 0$ (4.48): $dU/d\theta = c\,\frac{\sin\theta}{\theta}
        \,\theta$."""
        theta = as_vector(theta)
        C = self.c * sinc(dot3(theta, theta))
        return C, jnp.zeros_like(C)


class ZeroFoundation(_AbstractIsotropicFoundation):
    r"""No foundation, $U = 0$: a free body (Kelvin's medium, where the bodies of a lattice are
    held by their couplings alone, :mod:`rbo_jax.lattice`)."""

    domain_description: ClassVar[str] = "nothing (it is defined everywhere)"

    def energy(self, theta: VectorLike) -> Scalar:
        theta = as_vector(theta)
        return jnp.zeros((), dtype=theta.dtype)

    def coefficients(self, theta: VectorLike) -> tuple[Scalar, Scalar]:
        theta = as_vector(theta)
        zero = jnp.zeros((), dtype=theta.dtype)
        return zero, zero

    def gradient(self, theta: VectorLike) -> Vector:
        return jnp.zeros_like(as_vector(theta))


class TransverselyIsotropicFoundation(AbstractTransverselyIsotropicFoundation):
    r"""A transversely isotropic foundation $U = F(k\cdot\theta, \theta^2)$, eq. (4.24).

    ``F(x, t)`` takes $x = k\cdot\theta$ and $t = \theta^2$ in this order, as in (4.24). The
    moment is (4.25), $M_e = -2\,\partial F/\partial(\theta^2)\,\theta
    - \partial F/\partial(k\cdot\theta)\,Z^T\cdot k$, and satisfies $(k - Q(\theta)\cdot k)\cdot
    M_e = 0$ (4.26). If ``F`` is an :class:`equinox.Module`, its float leaves are differentiable
    parameters. Treated as defined everywhere.
    """

    F: Callable[[Scalar, Scalar], Scalar]
    k: Vector

    domain_description: ClassVar[str] = "nothing (it is treated as defined everywhere)"

    def __init__(self, F: Callable[[Scalar, Scalar], Scalar], k: VectorLike):
        name = type(self).__name__
        self.F = callable_leaf(F, name, "F")
        self.k = unit_axis(k, name)

    def energy(self, theta: VectorLike) -> Scalar:
        r"""$U = F(k\cdot\theta, \theta\cdot\theta)$, eq. (4.24)."""
        theta = as_vector(theta)
        return _as_scalar_output(
            self.F(dot3(self.k, theta), dot3(theta, theta)),
            "TransverselyIsotropicFoundation: F",
        )

    def domain_margin(self, theta: VectorLike) -> Scalar:
        return _everywhere(theta)

    def coefficients(self, theta: VectorLike) -> tuple[Scalar, Scalar]:
        r"""$C = 2\,\partial F/\partial t$, $D = \partial F/\partial x$ by automatic
        differentiation of ``F`` on the two scalars (4.48)."""
        theta = as_vector(theta)
        D, dF_dt = jax.grad(lambda x_, t_: _as_scalar_output(self.F(x_, t_), "F"), argnums=(0, 1))(
            dot3(self.k, theta), dot3(theta, theta)
        )
        return 2.0 * dF_dt, D


class SumFoundation(AbstractFoundation):
    """The sum of several foundations: energies add, the domain margin is the smallest margin.

    Built by ``f + g``; nested sums are flattened.
    """

    terms: tuple[AbstractFoundation, ...]

    def __init__(self, terms):
        terms = tuple(terms)
        if len(terms) == 0:
            raise ValueError("SumFoundation: terms must contain at least one foundation.")
        flat = []
        for term in terms:
            if isinstance(term, SumFoundation):
                flat.extend(term.terms)
            elif isinstance(term, AbstractFoundation):
                flat.append(term)
            else:
                raise TypeError(
                    "SumFoundation: every term must be an AbstractFoundation, got "
                    f"{type(term).__name__}."
                )
        self.terms = tuple(flat)

    def energy(self, theta: VectorLike) -> Scalar:
        theta = as_vector(theta)
        return sum((f.energy(theta) for f in self.terms[1:]), self.terms[0].energy(theta))

    def domain_margin(self, theta: VectorLike) -> Scalar:
        theta = as_vector(theta)
        return jnp.min(jnp.stack([f.domain_margin(theta) for f in self.terms]))

    def gradient(self, theta: VectorLike) -> Vector:
        """The sum of the terms' gradients."""
        theta = as_vector(theta)
        return sum((f.gradient(theta) for f in self.terms[1:]), self.terms[0].gradient(theta))

    @property
    def isotropic(self) -> bool:
        return all(f.isotropic for f in self.terms)

    def parameter_checks(self) -> list:
        return [c for f in self.terms for c in f.parameter_checks()]

    def _axes(self):
        """The axes of the non-isotropic terms, or None if a term has no symmetry axis."""
        axes = []
        for f in self.terms:
            if f.isotropic:
                continue
            k = f.symmetry_axis()
            if k is None:
                return None
            axes.append(k)
        return axes

    def _common(self, x, axes):
        """``x``, checked (:func:`equinox.error_if`) that all ``axes`` are equal."""
        if len(axes) < 2:
            return x
        mismatch = jnp.max(jnp.stack([jnp.max(jnp.abs(a - axes[0])) for a in axes[1:]]))
        return error_if(
            x,
            mismatch > 1e-12,
            "SumFoundation: the transversely isotropic terms have different axes k, so the sum "
            "is not transversely isotropic (its moment is not of the form (4.47)).",
        )

    def symmetry_axis(self) -> Vector | None:
        """The common axis of the transversely isotropic terms (checked equal), ``None`` if a
        term has no axis or every term is isotropic."""
        axes = self._axes()
        if not axes:
            return None
        return self._common(axes[0], axes)

    def coefficients(self, theta: VectorLike) -> tuple[Scalar, Scalar]:
        """The sums of the terms' $C$ and $D$ (4.48), provided all transversely isotropic terms
        share one axis $k$ (checked with :func:`equinox.error_if`)."""
        theta = as_vector(theta)
        coefficients = [f.coefficients(theta) for f in self.terms]
        C = sum(c for c, _ in coefficients[1:]) + coefficients[0][0]
        D = sum(d for _, d in coefficients[1:]) + coefficients[0][1]
        return C, self._common(D, self._axes() or [])


def _as_scalar_output(u, what: str) -> Scalar:
    u = jnp.asarray(u)
    if u.shape != ():
        raise ValueError(f"{what} must return a scalar, got shape {u.shape}.")
    return u


def potential_moment(U: Callable[[Vector], Scalar], theta: VectorLike) -> Vector:
    r"""The potential moment $M = -Z^T(\theta)\cdot\frac{dU}{d\theta}$, eqs. (4.23), (4.46).

    ``U`` is any scalar function of the turn-vector; $dU/d\theta$ is obtained by automatic
    differentiation. The result is the world-frame moment whose power is $M\cdot\omega =
    -\dot U$ (4.21). ``U`` is called as given: for a foundation, ``potential_moment(f, theta)``
    includes the domain check of ``f(theta)``, while ``potential_moment(f.energy, theta)``
    differentiates the raw formula (what ODE vector fields should use).
    """
    theta = as_vector(theta)
    grad = jax.grad(lambda th: _as_scalar_output(U(th), "potential_moment: U"))(theta)
    return -Turn(theta).ZT(grad)


def body_potential_moment(U: Callable[[Vector], Scalar], theta: VectorLike) -> Vector:
    r"""The potential moment in the body frame, $P^T\cdot M = -Z(\theta)\cdot\frac{dU}{d\theta}$
    ($P = Q(\theta)$; equal to $P^T$ times :func:`potential_moment` because
    $Z^T = P\cdot Z$, eq. (4.13)): the elastic term of the right form (4.55)."""
    theta = as_vector(theta)
    grad = jax.grad(lambda th: _as_scalar_output(U(th), "potential_moment: U"))(theta)
    return -Turn(theta).Z(grad)


def transverse_coefficients(foundation: AbstractFoundation, theta: VectorLike):
    r"""The functions $C$ and $D$ of eq. (4.48) for a transversely isotropic foundation:

    $C = 2\,\partial U/\partial(\theta^2)$, $D = \partial U/\partial(k\cdot\theta)$,

    so that the elastic moment is (4.47), $M_e = -C\theta - D\,Z^T(\theta)\cdot k$. Returns the
    pair ``(C, D)``: ``foundation.coefficients(theta)``.

    - :class:`QuadraticFoundation` (4.50): $C = c$, $D = (d - c)\,k\cdot\theta$ (4.51);
    - :class:`BarrierFoundation` (4.49): closed forms, see
      :meth:`BarrierFoundation.coefficients`;
    - :class:`TransverselyIsotropicFoundation` (4.24): from ``F`` by automatic differentiation;
    - :class:`IsotropicFoundation`: $C = 2F'(\theta^2)$, $D = 0$;
    - :class:`SumFoundation`: the sums, provided all transversely isotropic terms share the
      same axis $k$ (checked with :func:`equinox.error_if`).

    A general :class:`AbstractFoundation` raises ``TypeError``: wrap the energy as a
    :class:`TransverselyIsotropicFoundation` instead.
    """
    return foundation.coefficients(as_vector(theta))
