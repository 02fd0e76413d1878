r"""Equilibria, linearization and spectra: sections 4.2.4, 4.4 and 4.7 of the paper.

At an equilibrium $\theta_{eq}$ ($\Omega = 0$, zero total moment (4.61)) the perturbation method of
4.2.4, $\theta = \theta_{eq} + \varepsilon\varphi$, $\Omega = \varepsilon\eta$ (4.28), (4.63), gives
the linear system (4.66)–(4.67); here it is obtained by automatic differentiation of the
equations of motion (4.55)–(4.56):

$$\dot\varphi = Z^T(\theta_{eq})\cdot\eta,\qquad
  \dot\eta = J_\theta\cdot\varphi + J_\Omega\cdot\eta,$$

$J_\theta = \partial\dot\Omega/\partial\theta$, $J_\Omega = \partial\dot\Omega/\partial\Omega$ at
$(\theta_{eq}, 0)$. Eliminating $\eta = Z^{-T}\dot\varphi$ gives the second-order form

$$\mathsf M\ddot\varphi + \mathsf C\dot\varphi + \mathsf K\varphi = 0,\quad
  \mathsf M = Z^{-1}AZ^{-T},\ \mathsf C = -Z^{-1}AJ_\Omega Z^{-T},\ \mathsf K = -Z^{-1}AJ_\theta,$$

in which, for a purely potential problem, $\mathsf K = \partial^2(U+V)/\partial\theta^2$ is
symmetric; follower loads add the antisymmetric (circulatory) part of $\mathsf K$. The spectrum
solves $\det(p^2 E - pB - C_\theta) = 0$, $B = Z^TJ_\Omega Z^{-T}$, $C_\theta = Z^TJ_\theta$.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Complex, Float, Int

from ._custom_types import Matrix, Scalar, Vector
from ._programs import jit
from .kinematics import (
    _as_vector,
    distance_to_singularity,
    integrating_tensor,
    integrating_tensor_inv,
)
from .model import RigidBodyOscillator

__all__ = [
    "EquilibriumStatus",
    "EquilibriumSolution",
    "solve_equilibrium",
    "equilibrium",
    "linearize",
    "SecondOrderForm",
    "second_order_form",
    "spectrum",
    "fast_spectrum",
    "StabilityKind",
    "classify",
    "spectral_abscissa",
]


# --------------------------------------------------------------------------------------------
# Equilibria (4.60)-(4.62)
# --------------------------------------------------------------------------------------------


class EquilibriumStatus(eqx.Enumeration):
    """Outcome of :func:`solve_equilibrium`."""

    successful = ""
    not_converged = (
        "Newton's method did not converge to an equilibrium (zero total moment, eq. 4.61): try "
        "another theta_guess or increase max_steps."
    )
    singular_point = (
        "The equilibrium search reached a singular point |theta| = 2*pi*k of the integrating "
        "tensor Z (eq. 4.11)."
    )
    domain_error = "The equilibrium search left the domain of the foundation energy (eq. 4.49)."
    nonfinite = "The equilibrium search produced a non-finite turn-vector or moment."
    invalid_parameters = (
        "A model parameter is invalid (built from traced values its constructors could not "
        "check); RigidBodyOscillator.parameter_status() names it."
    )


class EquilibriumSolution(eqx.Module):
    """Result of :func:`solve_equilibrium`: ``theta``, ``status``, ``residual`` (|moment|),
    ``num_steps``."""

    theta: Float[Array, "3"]
    status: EquilibriumStatus
    residual: Float[Array, ""]
    num_steps: Int[Array, ""]

    @property
    def ok(self):
        return self.status == EquilibriumStatus.successful


def _static_moment(model: RigidBodyOscillator, t):
    def fn(theta, args):
        return model.world_moment(t, theta, jnp.zeros_like(theta))

    return fn


@functools.partial(jit, small=True)
def solve_equilibrium(
    model: RigidBodyOscillator,
    theta_guess,
    *,
    t=0.0,
    rtol: float = 1e-12,
    atol: float = 1e-12,
    max_steps: int = 64,
    singular_tol: float = 1e-6,
) -> EquilibriumSolution:
    r"""Solve the moment balance at rest, $M(\theta) = -Z^T\cdot dU/d\theta + M_{ex}(t, \theta, 0)
    = 0$ ((4.61) in general form), by Newton's method (optimistix) from ``theta_guess``.

    Never raises (use :func:`equilibrium` for that): the status tells whether Newton converged,
    and flags a singular point of Z, an exit from the foundation's domain or non-finite values.
    Compiled once per model structure (``eqx.filter_jit``); new parameter values reuse it.
    """
    theta_guess = _as_vector(theta_guess, "theta_guess")
    fn = _static_moment(model, t)
    sol = optx.root_find(
        fn, optx.Newton(rtol=rtol, atol=atol), theta_guess, max_steps=max_steps, throw=False
    )
    theta = sol.value
    residual = jnp.linalg.norm(fn(theta, None))
    S = EquilibriumStatus
    status = S.where(sol.result == optx.RESULTS.successful, S.successful, S.not_converged)
    status = S.where(model.domain_margin(theta) > 0, status, S.domain_error)
    status = S.where(distance_to_singularity(theta) > singular_tol, status, S.singular_point)
    status = S.where(jnp.all(jnp.isfinite(theta)) & jnp.isfinite(residual), status, S.nonfinite)
    ok, _, _ = model.parameter_status()
    status = S.where(ok, status, S.invalid_parameters)
    theta = jnp.where(ok, theta, jnp.nan)
    return EquilibriumSolution(theta, status, residual, sol.stats["num_steps"])


def equilibrium(model: RigidBodyOscillator, theta_guess, **kwargs) -> Vector:
    r"""The turn-vector $\theta_{eq}$ of an equilibrium ($\Omega = 0$, zero total moment (4.61)),
    found by Newton's method from ``theta_guess``. Raises with a message naming the cause when
    the solve fails (keyword arguments: see :func:`solve_equilibrium`).

    For the quadratic foundation (4.50) under a follower moment (4.57) this is
    $\theta_{eq} = (M/d)\,k$ (4.62).
    """
    ok, which, messages = model.parameter_status()
    theta_guess = eqx.branched_error_if(
        _as_vector(theta_guess, "theta_guess"), ~ok, which, messages
    )
    sol = solve_equilibrium(model, theta_guess, **kwargs)
    return sol.status.error_if(sol.theta, ~sol.ok)


# --------------------------------------------------------------------------------------------
# Linearization (4.28)-(4.38), (4.63)-(4.67)
# --------------------------------------------------------------------------------------------


def linearize(model: RigidBodyOscillator, theta_eq, *, t=0.0) -> Float[Array, "6 6"]:
    r"""The 6×6 Jacobian of $(\dot\theta, \dot\Omega)$ (4.55)–(4.56) with respect to the flat
    state $[\theta, \Omega]$ at $(\theta_{eq}, 0)$, by forward-mode autodiff: the perturbation
    equations (4.63)–(4.67) computed by the machine."""
    theta_eq = _as_vector(theta_eq, "theta_eq")

    rhs = model.right_form()

    def flat(x):
        th_dot, Om_dot = rhs(t, (x[:3], x[3:]))
        return jnp.concatenate([th_dot, Om_dot])

    return jax.jacfwd(flat)(jnp.concatenate([theta_eq, jnp.zeros_like(theta_eq)]))


def spectrum(model: RigidBodyOscillator, theta_eq, *, t=0.0) -> Complex[Array, "6"]:
    r"""The six eigenvalues of :func:`linearize` at $(\theta_{eq}, 0)$: the exponents $p$ of the
    perturbations $\propto e^{pt}$ ((4.69), (4.72) for the Nikolai problem). Sorted
    lexicographically (real part, then imaginary part)."""
    return jnp.sort(jnp.linalg.eigvals(linearize(model, theta_eq, t=t)))


def _blocks(model, theta_eq, t):
    """Z(θ_eq), J_θ = ∂Ω̇/∂θ and J_Ω = ∂Ω̇/∂Ω at (θ_eq, 0)."""
    theta_eq = _as_vector(theta_eq, "theta_eq")
    zero = jnp.zeros_like(theta_eq)
    rhs = model.right_form()
    J_theta = jax.jacfwd(lambda th: rhs(t, (th, zero))[1])(theta_eq)
    J_Omega = jax.jacfwd(lambda Om: rhs(t, (theta_eq, Om))[1])(zero)
    return integrating_tensor(theta_eq), J_theta, J_Omega


class SecondOrderForm(eqx.Module):
    r"""$\mathsf M\ddot\varphi + (\mathsf D + \mathsf G)\dot\varphi
    + (\mathsf K_s + \mathsf K_c)\varphi = 0$ at an equilibrium: mass $\mathsf M$ (symmetric),
    damping $\mathsf D$ (symmetric), gyroscopic $\mathsf G$ (antisymmetric), conservative
    stiffness $\mathsf K_s$ (symmetric) and circulatory stiffness $\mathsf K_c$ (antisymmetric,
    zero for potential problems)."""

    mass: Matrix
    damping: Matrix
    gyroscopic: Matrix
    stiffness: Matrix
    circulatory: Matrix

    @property
    def full_stiffness(self) -> Matrix:
        return self.stiffness + self.circulatory


def second_order_form(model: RigidBodyOscillator, theta_eq, *, t=0.0) -> SecondOrderForm:
    r"""The linearized equations at $(\theta_{eq}, 0)$ in second-order form in the turn-vector
    perturbation $\varphi$ (see the module docstring): $\mathsf M = Z^{-1}AZ^{-T}$,
    $\mathsf C = -Z^{-1}AJ_\Omega Z^{-T}$, $\mathsf K = -Z^{-1}AJ_\theta$, split into symmetric
    and antisymmetric parts. Follower loads (4.57) make $\mathsf K$ non-symmetric: its
    antisymmetric part is the circulatory stiffness behind the Nikolai paradox."""
    _, J_theta, J_Omega = _blocks(model, theta_eq, t)
    A = model.inertia
    Zinv = integrating_tensor_inv(theta_eq)
    ZinvA = Zinv @ A
    mass = ZinvA @ Zinv.T
    C = -ZinvA @ J_Omega @ Zinv.T
    K = -ZinvA @ J_theta
    return SecondOrderForm(
        mass=0.5 * (mass + mass.T),
        damping=0.5 * (C + C.T),
        gyroscopic=0.5 * (C - C.T),
        stiffness=0.5 * (K + K.T),
        circulatory=0.5 * (K - K.T),
    )


def _velocity_independent(model: RigidBodyOscillator) -> bool:
    """Whether no load depends on ω (:attr:`rbo_jax.AbstractLoad.depends_on_velocity`), so that
    J_Ω = 0 at Ω = 0 (the gyroscopic term Ω×AΩ is quadratic in Ω). Decided from the model's
    structure, at trace time."""
    return not any(load.depends_on_velocity for load in model.loads)


def fast_spectrum(model: RigidBodyOscillator, theta_eq, *, t=0.0) -> Complex[Array, "6"]:
    r"""Same eigenvalues as :func:`spectrum`, computed from the block structure at $\Omega = 0$.

    When no load depends on the angular velocity, $J_\Omega = 0$ and
    $\det(p^2E - C_\theta) = 0$ with $C_\theta = Z^T J_\theta$ (3×3): the six roots are
    $p = \pm\sqrt{\lambda}$ for the three eigenvalues $\lambda$ of $C_\theta$, at a third of the
    cost of the 6×6 eigenproblem (and only $\partial\dot\Omega/\partial\theta$ is differentiated).
    Otherwise the 6×6 companion $[[0, Z^T], [J_\theta, J_\Omega]]$ is used. Unlike
    :func:`spectrum` the result is not sorted (sorting costs as much as the rest in a vmapped map;
    :func:`rbo_jax.stability_map` sorts on the host); in the first case it is ordered
    $(p_1, p_2, p_3, -p_1, -p_2, -p_3)$. Same eigenvalues as :func:`spectrum` to rounding.
    """
    if _velocity_independent(model):
        theta_eq = _as_vector(theta_eq, "theta_eq")
        zero = jnp.zeros_like(theta_eq)
        rhs = model.right_form()
        J_theta = jax.jacfwd(lambda th: rhs(t, (th, zero))[1])(theta_eq)
        lam = jnp.linalg.eigvals(integrating_tensor(theta_eq).T @ J_theta)
        r = jnp.sqrt(lam)
        return jnp.concatenate([r, -r])
    Z, J_theta, J_Omega = _blocks(model, theta_eq, t)
    top = jnp.concatenate([jnp.zeros_like(Z), Z.T], axis=1)
    bottom = jnp.concatenate([J_theta, J_Omega], axis=1)
    return jnp.linalg.eigvals(jnp.concatenate([top, bottom], axis=0))


# --------------------------------------------------------------------------------------------
# Classification
# --------------------------------------------------------------------------------------------


class StabilityKind(eqx.Enumeration):
    """Classification of an equilibrium from its spectrum (Lyapunov's first method)."""

    asymptotically_stable = "asymptotically stable: every Re p < 0"
    marginally_stable = (
        "marginally stable in the linear approximation: every Re p = 0 within tolerance (the "
        "conservative case; nonlinear terms or a Jordan block decide)"
    )
    divergence = "unstable by divergence: a real root p > 0 (static buckling)"
    flutter = "unstable by flutter: a complex pair with Re p > 0 (growing oscillation)"
    undefined = "undefined: the spectrum is not finite (the equilibrium could not be computed)"


def spectral_abscissa(eigenvalues) -> Scalar:
    """max Re p."""
    return jnp.max(jnp.real(eigenvalues))


def classify(eigenvalues, *, rtol: float = 1e-9) -> tuple[StabilityKind, Scalar]:
    r"""Classify an equilibrium from its eigenvalues; returns ``(kind, abscissa)``.

    ``rtol`` is relative to $\max|p|$: real parts within $\pm$``rtol``$\cdot\max|p|$ count as
    zero, so conservative spectra (roots on the imaginary axis up to rounding) come out
    ``marginally_stable``. An unstable root whose imaginary part is also below that tolerance is
    ``divergence``, otherwise ``flutter``. Growth rates below the tolerance are not resolved:
    the Nikolai roots have Re p ≈ |M|/(4√(A1 c)) for small M, so at |M| ≲ 1e-8 the default calls
    the equilibrium marginal; pass a smaller ``rtol`` (e.g. 1e-12) to resolve them.
    """
    p = jnp.asarray(eigenvalues)
    scale = jnp.maximum(jnp.max(jnp.abs(p)), jnp.finfo(jnp.real(p).dtype).tiny)
    tol = rtol * scale
    re = jnp.real(p)
    a = jnp.max(re)
    i_max = jnp.argmax(re)
    K = StabilityKind
    kind = K.where(a < -tol, K.asymptotically_stable, K.marginally_stable)
    unstable = K.where(jnp.abs(jnp.imag(p[i_max])) > tol, K.flutter, K.divergence)
    kind = K.where(a > tol, unstable, kind)
    kind = K.where(jnp.all(jnp.isfinite(p)), kind, K.undefined)
    return kind, a
