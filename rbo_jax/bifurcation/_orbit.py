r"""Periodic orbits by shooting, and their Floquet multipliers.

The flow $\varphi_T(x_0)$ of the right form (4.55)–(4.56), $x = [\theta, \Omega]$, is computed
with :func:`rbo_jax.fast_simulate` (DOP853) and differentiated in forward mode: the monodromy
matrix $M = \partial\varphi_T/\partial x_0$ is exact for the discrete solver (its steps are held
fixed, as in internal numerical differentiation), so it approximates the true monodromy to the
solver's tolerance. Its eigenvalues are the **Floquet multipliers**: one equals 1 (the tangent
$F(x_0)$ of an autonomous periodic orbit is carried to itself), the orbit is orbitally stable if
the others lie inside the unit circle.

**Shooting** solves $\varphi_T(x_0) - x_0 = 0$ together with the phase condition
$F(\hat x_0)\cdot(x_0 - \hat x_0) = 0$ (the correction is orthogonal to the flow at the guess
$\hat x_0$) for $(x_0, T)$ by Newton's method on the 7×7 system

$$\begin{pmatrix} M - E & F(\varphi_T(x_0)) \\ F(\hat x_0)^T & 0\end{pmatrix}
  \begin{pmatrix}\delta x_0 \\ \delta T\end{pmatrix} = -\begin{pmatrix}\varphi_T(x_0) - x_0 \\
  F(\hat x_0)\cdot(x_0 - \hat x_0)\end{pmatrix},$$

solved in the least-squares sense, so that families of orbits (conservative problems, where a
second multiplier equals 1) give the minimum-norm correction instead of a singular solve.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float, Int

from .. import _enumeration as enum
from .._programs import jit, program
from ..ensemble import fast_simulate
from ..kinematics import _as_vector
from ..model import RigidBodyOscillator
from ..trajectory import SolveStatus
from ._field import flat_field

__all__ = [
    "OrbitStatus",
    "PeriodicOrbit",
    "flow",
    "monodromy",
    "floquet_multipliers",
    "periodic_orbit",
    "split_multipliers",
]


class OrbitStatus(eqx.Enumeration):
    """Outcome of :func:`periodic_orbit`."""

    successful = ""
    not_converged = (
        "Newton's method (shooting with a phase condition) did not converge: try a better "
        "initial state or period, or a smaller solver tolerance."
    )
    solve_failed = (
        "The integration over one period failed (fast_simulate's status: a singular point, a "
        "step-size collapse, max_steps or non-finite values)."
    )
    nonpositive_period = "Newton's method drove the period to a value <= 0."


class PeriodicOrbit(eqx.Module):
    r"""A periodic orbit: the corrected initial state ``theta0``, ``Omega0``, the ``period`` $T$,
    the six Floquet ``multipliers`` (sorted by decreasing modulus), the shooting ``residual``
    (max norm of the shooting system at the solution), Newton's ``num_steps`` and the ``status``
    (:class:`OrbitStatus`)."""

    theta0: Float[Array, "3"]
    Omega0: Float[Array, "3"]
    period: Float[Array, ""]
    multipliers: Complex[Array, "6"]
    residual: Float[Array, ""]
    num_steps: Int[Array, ""]
    status: OrbitStatus

    @property
    def ok(self):
        return self.status == OrbitStatus.successful

    @property
    def trivial_multiplier(self):
        """The multiplier nearest 1 (equal to 1 up to the solver's accuracy)."""
        return split_multipliers(self.multipliers)[0]

    @property
    def stable(self):
        """Whether every multiplier but the trivial one lies inside the unit circle."""
        return jnp.max(jnp.abs(split_multipliers(self.multipliers)[1])) < 1.0


def split_multipliers(mu):
    """``(trivial, others)``: the multiplier nearest 1 and the five others."""
    i = jnp.argmin(jnp.abs(mu - 1.0))
    others = jnp.where(jnp.arange(mu.shape[0]) < i, mu, jnp.roll(mu, -1))[:-1]
    return mu[i], others


def _sorted(mu):
    return mu[jnp.argsort(-jnp.abs(mu))]


def flow(model: RigidBodyOscillator, x0, period, *, rtol=1e-10, atol=1e-10, max_steps=100_000):
    r"""$(\varphi_T(x_0), ok)$: the flat state $[\theta, \Omega]$ after time ``period`` from
    ``x0`` by :func:`rbo_jax.fast_simulate` (``throw=False``), and whether the solve succeeded.
    Forward-mode differentiable in ``x0`` and the model's parameters."""
    T = jnp.asarray(period, dtype=x0.dtype)
    T = jnp.where(T > 0, T, 1.0)  # a non-positive period is flagged by the callers
    traj = fast_simulate(
        model,
        x0[:3],
        x0[3:],
        jnp.stack([jnp.zeros_like(T), T]),
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
        throw=False,
    )
    return jnp.concatenate([traj.theta[-1], traj.Omega[-1]]), traj.status == SolveStatus.successful


def monodromy(model: RigidBodyOscillator, x0, period, **solver):
    r"""$(M, \varphi_T(x_0), ok)$ with the monodromy matrix $M = \partial\varphi_T/\partial x_0$
    (forward mode, 6 tangents)."""

    def f(x):
        xT, ok = flow(model, x, period, **solver)
        return xT, (xT, ok)

    M, (xT, ok) = jax.jacfwd(f, has_aux=True)(x0)
    return M, xT, ok


def _state(theta0, Omega0):
    return jnp.concatenate([_as_vector(theta0, "theta0"), _as_vector(Omega0, "Omega0")])


@functools.partial(jit, small=True)
def floquet_multipliers(
    model: RigidBodyOscillator, theta0, Omega0, period, *, rtol=1e-10, atol=1e-10, max_steps=100_000
) -> Complex[Array, "6"]:
    r"""The six Floquet multipliers of the periodic orbit through $(\theta_0, \Omega_0)$ with
    period $T$: the eigenvalues of the monodromy matrix $\partial\varphi_T/\partial x_0$ (module
    docstring), sorted by decreasing modulus. NaN if the integration over one period fails.

    For a regular precession (4.110)–(4.113), $T = 2\pi/\dot\psi$ and the multipliers are
    $e^{\lambda T}$ for the exponents $\lambda$ of :func:`rbo_jax.precession_spectrum`.
    """
    M, _, ok = monodromy(
        model, _state(theta0, Omega0), period, rtol=rtol, atol=atol, max_steps=max_steps
    )
    mu = _sorted(jnp.linalg.eigvals(M))
    return jnp.where(ok, mu, jnp.full_like(mu, jnp.nan))


def shooting_system(model, F, x, T, x_ref, solver):
    r"""The shooting residual $[\varphi_T(x) - x,\ F(\hat x)\cdot(x - \hat x)]$ and its
    Jacobian with respect to $(x, T)$ (module docstring), plus the monodromy matrix and the
    solver's success flag."""
    M, xT, ok = monodromy(model, x, T, **solver)
    r = jnp.concatenate([xT - x, (F(x_ref) @ (x - x_ref))[None]])
    top = jnp.concatenate([M - jnp.eye(6), F(xT)[:, None]], axis=1)
    bottom = jnp.concatenate([F(x_ref), jnp.zeros(1)])[None, :]
    return r, jnp.concatenate([top, bottom]), M, ok


def _lstsq(A, b):
    """Least-squares solution, singular values below 1e-9 of the largest truncated."""
    return jnp.linalg.lstsq(A, b, rcond=1e-9)[0]


def _shoot(model, x_ref, period, tol, max_newton, rtol, atol, max_steps):
    """The shooting loop of :func:`periodic_orbit`, as plain arrays (a stored program)."""
    F = flat_field(model, throw=False)
    solver = dict(rtol=rtol, atol=atol, max_steps=max_steps)

    # One evaluation per iteration: the carry holds the monodromy matrix at the current state,
    # so the loop stops on it (and the multipliers come from it) without a second compiled copy.
    def cond(carry):
        k, done = carry[2], carry[3]
        return (k <= max_newton) & ~done

    def body(carry):
        x, T, k, _, _, _, _ = carry
        r, A, M, ok = shooting_system(model, F, x, T, x_ref, solver)
        delta = _lstsq(A, -r)
        res = jnp.max(jnp.abs(r))
        converged = (res <= tol) | (jnp.max(jnp.abs(delta)) <= 0.01 * tol)
        done = converged | ~ok | ~jnp.isfinite(res) | (T <= 0) | (k == max_newton)
        step = jnp.where(done, 0.0, delta)
        return x + step[:6], T + step[6], k + 1, done, M, res, ok

    T0 = jnp.asarray(period, dtype=x_ref.dtype)
    init = (x_ref, T0, 0, False, jnp.zeros((6, 6)), jnp.asarray(jnp.inf), True)
    x, T, k, _, M, residual, ok = jax.lax.while_loop(cond, body, init)
    S = OrbitStatus
    status = S.where(residual <= tol, S.successful, S.not_converged)
    status = S.where(ok, status, S.solve_failed)
    status = S.where(T > 0, status, S.nonpositive_period)
    mu = _sorted(jnp.linalg.eigvals(M))
    mu = jnp.where(ok, mu, jnp.full_like(mu, jnp.nan))
    return x, T, mu, residual, k - 1, enum.code(status)


# With the program store on (rbo_jax.enable_compilation_cache) a second process loads it traced;
# models holding a plain callable (no stable name across processes) are traced as usual.
_shoot_program = program(_shoot, small=True)  # XLA's options for small programs


def periodic_orbit(
    model: RigidBodyOscillator,
    theta0,
    Omega0,
    period,
    *,
    tol=1e-9,
    max_newton: int = 20,
    rtol=1e-11,
    atol=1e-11,
    max_steps=100_000,
) -> PeriodicOrbit:
    r"""The periodic orbit near $(\theta_0, \Omega_0)$ with period near ``period``, by shooting
    (module docstring): Newton's method for the initial state and the period with the phase
    condition, ``max_newton`` iterations at most, until the shooting residual and the correction
    are below ``tol``; ``rtol``, ``atol``, ``max_steps`` go to :func:`rbo_jax.fast_simulate`.
    The Floquet multipliers come from the monodromy matrix at the solution.

    Never raises: ``status`` says whether Newton converged. jit- and vmap-compatible; one
    compiled program per model structure, kept by the program store when it is on
    (:func:`rbo_jax.enable_compilation_cache`).
    """
    x_ref = _state(theta0, Omega0)
    period = period if isinstance(period, jax.core.Tracer) else np.asarray(period, x_ref.dtype)
    x, T, mu, residual, k, code = _shoot_program(
        model, x_ref, period, tol, max_newton, rtol, atol, max_steps
    )
    return PeriodicOrbit(
        theta0=x[:3],
        Omega0=x[3:],
        period=T,
        multipliers=mu,
        residual=residual,
        num_steps=k,
        status=enum.from_code(OrbitStatus, code),
    )
