r"""Regular precession of the rigid body oscillator and its stability, section 4.7.

A regular precession (4.110)–(4.111) is $\theta(t) = \vartheta\,Q(\psi(t)k)\cdot p$ with
$\vartheta$, $\dot\psi$ constant and $p\perp k$; its left angular velocity is
$\omega = Q(\psi k)\cdot\omega_0$,
$\omega_0 = \dot\psi[(1-\cos\vartheta)k + \sin\vartheta\,k\times p]$ (4.112), and the rate
follows from (4.113) (:func:`rbo_jax.analytic.precession_rate`).

Stability (4.115)–(4.118): in the precessing frame, $\theta = Q(\psi k)\cdot x$,
$\omega = Q(\psi k)\cdot w$, the equations of motion of a model invariant under turns about $k$
become autonomous,

$$\dot x = Z(x)\cdot w - \dot\psi\,k\times x,\qquad
  \dot w = P(x)\cdot\dot\Omega\big(x, P^T(x)\cdot w\big) - \dot\psi\,k\times w,$$

(using the isotropy (4.12) of Z and $\dot\omega = P\cdot\dot\Omega$), and the precession is their
fixed point $(\vartheta p, \omega_0)$. Linearizing with $x = \vartheta p + \varepsilon\varphi$,
$w = \omega_0 + \varepsilon\eta$ — exactly the perturbation (4.117) — gives the constant-coefficient
system for $(\varphi, \eta)$, here by automatic differentiation (the printed equations after (4.118)
are partly garbled; reading R8 of docs/readings.md).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Complex, Float

from ._custom_types import Scalar, Vector
from .analytic import precession_rate
from .kinematics import Turn, as_vector, cross3, turn_tensor
from .models.rigid_body import RigidBodyOscillator

__all__ = [
    "RegularPrecession",
    "regular_precession",
    "precessing_frame_vector_field",
    "precession_variational_matrix",
    "precession_spectrum",
    "precession_residual",
]


class RegularPrecession(eqx.Module):
    r"""A regular precession (4.110)–(4.113): nutation angle ``vartheta``, unit vectors ``p`` ⊥
    ``k``, rate ``rate`` = $\dot\psi$, and its initial state ``theta0`` = ϑp, ``omega0`` (4.112),
    ``Omega0`` = $P^T\omega_0$."""

    vartheta: Float[Array, ""]
    p: Float[Array, "3"]
    k: Float[Array, "3"]
    rate: Float[Array, ""]

    @property
    def theta0(self) -> Vector:
        return self.vartheta * self.p

    @property
    def omega0(self) -> Vector:
        """(4.112): ω0 = ψ̇[(1 − cosϑ)k + sinϑ k×p]."""
        th = self.vartheta
        return self.rate * ((1 - jnp.cos(th)) * self.k + jnp.sin(th) * jnp.cross(self.k, self.p))

    @property
    def Omega0(self) -> Vector:
        return turn_tensor(self.theta0).T @ self.omega0

    def theta(self, t) -> Vector:
        """θ(t) = ϑ Q(ψ̇t k)·p (4.110)."""
        return turn_tensor(self.rate * t * self.k) @ self.theta0


def _symmetry_axis(model: RigidBodyOscillator, k) -> Vector:
    """``k`` (normalised) if given, else the foundation's symmetry axis (4.24)."""
    if k is not None:
        k = as_vector(k, "k")
        return k / jnp.linalg.norm(k)
    foundation = model.foundation
    axis = foundation.symmetry_axis()
    if axis is not None:
        return axis
    if foundation.isotropic:
        raise TypeError(
            f"regular_precession needs the symmetry axis k: the foundation "
            f"{type(foundation).__name__} is isotropic, hence transversely isotropic about any "
            "axis; pass k=..."
        )
    raise TypeError(
        f"regular_precession needs a transversely isotropic foundation (4.24), invariant under "
        f"turns about an axis k; {type(foundation).__name__} has no symmetry axis. Build it from "
        "QuadraticFoundation, BarrierFoundation, TransverselyIsotropicFoundation(F, k) or "
        "IsotropicFoundation terms (sums of terms with one axis k are fine)."
    )


def _inertia_about(model: RigidBodyOscillator, k, p):
    A = model.inertia
    A1, A3 = p @ A @ p, k @ A @ k
    # The inertia must be transversely isotropic about k (4.40) for (4.113) to hold.
    residual = jnp.max(jnp.abs(A - (A1 * (jnp.eye(3) - jnp.outer(k, k)) + A3 * jnp.outer(k, k))))
    A1 = eqx.error_if(
        A1,
        residual > 1e-9 * jnp.max(jnp.abs(A)),
        "regular_precession: the inertia tensor is not transversely isotropic about the "
        "foundation's axis k (eq. 4.40).",
    )
    return A1, A3


def _default_p(k):
    e = jnp.eye(3, dtype=k.dtype)[jnp.argmin(jnp.abs(k))]
    p = e - (e @ k) * k
    return p / jnp.linalg.norm(p)


def regular_precession(
    model: RigidBodyOscillator, vartheta, p=None, *, k=None
) -> RegularPrecession:
    r"""The regular precession of ``model`` with nutation angle $\vartheta$ (4.110)–(4.113).

    Requires a transversely isotropic foundation (axis $k$) with $D = 0$ at $k\cdot\theta = 0$ (the
    restriction before (4.113)) and an inertia transversely isotropic about $k$ (4.40); ``k``
    defaults to the foundation's axis (pass it for an isotropic foundation). ``p`` (⊥ k)
    defaults to a unit vector orthogonal to $k$. The rate is
    $\dot\psi = \sqrt{C\vartheta/(\sin\vartheta[A_3(1-\cos\vartheta)+A_1\cos\vartheta])}$ (4.113);
    NaN if no regular precession exists at this $\vartheta$.
    """
    k = _symmetry_axis(model, k)
    if p is None:
        p = _default_p(k)
    else:
        p = as_vector(p, "p")
        p = p - (p @ k) * k
        p = p / jnp.linalg.norm(p)
    vartheta = jnp.asarray(vartheta, dtype=k.dtype)
    C, D = model.foundation.coefficients(vartheta * p)
    C = eqx.error_if(
        C,
        jnp.abs(D) > 1e-12 * (jnp.abs(C) + 1.0),
        "regular_precession: D(theta^2, k.theta) != 0 at k.theta = 0; (4.113) assumes it vanishes.",
    )
    A1, A3 = _inertia_about(model, k, p)
    return RegularPrecession(vartheta=vartheta, p=p, k=k, rate=precession_rate(C, vartheta, A1, A3))


def precessing_frame_vector_field(model: RigidBodyOscillator, k, rate):
    r"""The autonomous vector field of the precessing frame, $(x, w) \mapsto (\dot x, \dot w)$
    (module docstring), for a frame turning at ``rate`` about ``k``."""

    rhs = model.right_form()

    def f(x, w):
        turn = Turn(x)
        _, Omega_dot = rhs(0.0, (x, turn.rotate_back(w)))
        x_dot = turn.Z(w) - rate * cross3(k, x)
        w_dot = turn.rotate(Omega_dot) - rate * cross3(k, w)
        return x_dot, w_dot

    return f


def precession_variational_matrix(
    model: RigidBodyOscillator, precession: RegularPrecession
) -> Float[Array, "6 6"]:
    r"""The 6×6 constant coefficient matrix of the variational equations of section 4.7 for
    $(\varphi, \eta)$, $\theta_\varepsilon = Q(\psi k)\cdot(\vartheta p + \varepsilon\varphi)$,
    $\omega_\varepsilon = Q(\psi k)\cdot(\omega_0 + \varepsilon\eta)$ (4.117), by autodiff."""
    f = precessing_frame_vector_field(model, precession.k, precession.rate)

    def flat(z):
        x_dot, w_dot = f(z[:3], z[3:])
        return jnp.concatenate([x_dot, w_dot])

    return jax.jacfwd(flat)(jnp.concatenate([precession.theta0, precession.omega0]))


def precession_spectrum(
    model: RigidBodyOscillator, precession: RegularPrecession
) -> Complex[Array, "6"]:
    """Eigenvalues of :func:`precession_variational_matrix`: perturbations of the regular
    precession grow as exp(max Re p · t) in the precessing frame."""
    return jnp.sort(jnp.linalg.eigvals(precession_variational_matrix(model, precession)))


def precession_residual(model: RigidBodyOscillator, precession: RegularPrecession) -> Scalar:
    """|f(ϑp, ω0)| of the precessing-frame field: zero (to rounding) on an exact regular
    precession; a check of the rate and of the model's invariance about k."""
    f = precessing_frame_vector_field(model, precession.k, precession.rate)
    x_dot, w_dot = f(precession.theta0, precession.omega0)
    return jnp.sqrt(jnp.sum(x_dot**2) + jnp.sum(w_dot**2))
