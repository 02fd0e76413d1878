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
$\hat x_0$) for $(x_0, T)$ by Newton's method (the one loop of :mod:`rbo_jax.solvers`) on the
7×7 system

$$\begin{pmatrix} M - E & F(\varphi_T(x_0)) \\ F(\hat x_0)^T & 0\end{pmatrix}
  \begin{pmatrix}\delta x_0 \\ \delta T\end{pmatrix} = -\begin{pmatrix}\varphi_T(x_0) - x_0 \\
  F(\hat x_0)\cdot(x_0 - \hat x_0)\end{pmatrix},$$

solved in the least-squares sense (singular values below $10^{-9}$ of the largest truncated).

**Conservative families.** Where the energy $E = K + U + V$
(:meth:`rbo_jax.RigidBodyOscillator.energy`, conserved without friction and non-potential loads)
is a first integral, periodic orbits are not isolated: they come in one-parameter families along
$E$, a second multiplier equals 1 (the tangent to the family, a Jordan block with $F$), and the
7×7 matrix above is singular — Newton wanders along the family (to the rest state, or away).
Following Muñoz-Almaraz, Freire, Galán, Doedel and Vanderbauwhede (Physica D 181 (2003) 1–38)
the system is *unfolded* by the viscous moment $-\varepsilon\,\omega$ of (4.84) with a signed
parameter $\varepsilon$, whose energy rate is $\dot E = -\varepsilon\,|\Omega|^2$, and the
energy condition is added:

$$\varphi_T(x_0;\varepsilon) - x_0 = 0,\qquad F(\hat x_0)\cdot(x_0 - \hat x_0) = 0,\qquad
  E(x_0) - E_* = 0,$$

eight equations for $(x_0, T, \varepsilon)$, by Newton's method on

$$\begin{pmatrix} M - E & F_\varepsilon(\varphi_T) & \partial_\varepsilon\varphi_T \\
  F(\hat x_0)^T & 0 & 0 \\ \nabla E(x_0)^T & 0 & 0\end{pmatrix}
  \begin{pmatrix}\delta x_0 \\ \delta T \\ \delta\varepsilon\end{pmatrix} = -r.$$

On a periodic solution $0 = E(\varphi_T) - E(x_0) = -\varepsilon\int_0^T|\Omega|^2\,dt$, so
$\varepsilon = 0$ unless the orbit is a rest state: every solution is an orbit of the
conservative model, of energy $E_*$, and at an orbit with exactly two multipliers 1 the matrix
is regular (quadratic convergence). Regular precessions (4.110)–(4.113) are such orbits: their
two multipliers 1 are the double zero exponent of :func:`rbo_jax.precession_spectrum`, the other
four are $e^{\lambda T}$ (:func:`floquet_multipliers`). With further first integrals — the
axial one (4.78) of a transversely isotropic body on a transversely isotropic foundation (its
turns about $k$ carry orbits to orbits), the three (4.94) of the isotropic oscillator (4.83) —
the orbits of one energy still form families, more multipliers equal 1 and the matrix keeps a
kernel. Its least-squares solution, singular values below ``rcond`` times the largest truncated
(numerically they are $\sim 10^{-12}$ of it), is the minimum-norm step: Newton moves
orthogonally to the family's directions, the residual converges all the same and the orbit
returned is one of the family near the guess (each step the smallest correction; not
necessarily the nearest orbit overall).
"""

from __future__ import annotations

import functools
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float, Int

from .. import _enumeration as enum
from .._programs import jit, program
from ..ensemble import fast_simulate
from ..kinematics import as_vector
from ..loads import AbstractLoad, PotentialLoad
from ..models.rigid_body import RigidBodyOscillator
from ..solvers import Outcome, TruncatedLeastSquares, iterate, newton_update
from ..trajectory import SolveStatus
from ._field import flat_field

__all__ = [
    "OrbitStatus",
    "PeriodicOrbit",
    "flow",
    "is_conservative",
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
    unfolded = (
        "The unfolding parameter of conservative shooting did not vanish at the solution: the "
        "model is not conservative (a non-potential load that does not vanish), so the orbit "
        "found belongs to the model with the friction -eps omega added."
    )


class PeriodicOrbit(Outcome):
    r"""A periodic orbit: the corrected initial state ``theta0``, ``Omega0``, the ``period`` $T$,
    the six Floquet ``multipliers`` (sorted by decreasing modulus), the shooting ``residual``
    (max norm of the shooting system at the solution), Newton's ``num_steps``, the ``status``
    (:class:`OrbitStatus`) and, for conservative shooting, the ``unfolding`` parameter
    $\varepsilon$ at the solution (0 otherwise)."""

    # this result's own fields, declared here (its pytree and its docs); `ok` is Outcome's
    theta0: Float[Array, "3"]
    Omega0: Float[Array, "3"]
    period: Float[Array, ""]
    multipliers: Complex[Array, "6"]
    residual: Float[Array, ""]
    num_steps: Int[Array, ""]
    status: OrbitStatus
    unfolding: Float[Array, ""] = eqx.field(default_factory=lambda: np.zeros(()))

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
    return jnp.concatenate([as_vector(theta0, "theta0"), as_vector(Omega0, "Omega0")])


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


def shooting_newton(system, z0, tol, max_newton, rcond=1e-9, step_tol=True):
    r"""Newton's method (:func:`rbo_jax.solvers.newton_update` in the one loop
    :func:`rbo_jax.solvers.iterate`) on ``system(z) -> (r, A, M, ok)`` (residual, its Jacobian,
    the monodromy matrix and the solver's flag) from ``z0``, minimum-norm least-squares steps
    truncated below ``rcond`` (:class:`rbo_jax.solvers.TruncatedLeastSquares`); ``z[6]`` is the
    period. It stops where the residual's max norm is at most ``tol`` (or, with ``step_tol``,
    the step at most ``tol``/100), where the integration fails or the period is not positive,
    or after ``max_newton`` steps, without moving then. Returns ``(z, k, M, residual, ok, A)``,
    ``M`` and ``A`` at the last ``z``: one evaluation per iteration, so the loop stops on the
    monodromy matrix it carries, without a second compiled copy."""
    linear = TruncatedLeastSquares(rcond)

    def step(z, carry):
        k = carry[0]
        r, A, M, ok = system(z)
        new, _, done, finite = newton_update(
            r, A, linear, z, rtol=0, atol=0.01 * tol if step_tol else -1.0, floor=tol
        )
        stop = done | ~ok | ~finite | (z[6] <= 0) | (k == max_newton)
        z = jnp.where(stop, z, new)
        return z, (k + 1, M, jnp.max(jnp.abs(r)), ok, A), jnp.where(stop, 0, -1)

    carry = jax.eval_shape(lambda: step(z0, (jnp.asarray(0),) + (None,) * 4)[1])
    carry = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), carry)
    z, (k, M, residual, ok, A), _, _ = iterate(step, z0, carry, max_steps=max_newton + 1,
                                               exhausted=0)  # fmt: skip
    return z, k - 1, M, residual, ok, A


def _outcome(T, M, residual, ok, tol):
    """The status (:class:`OrbitStatus`) and the sorted multipliers (NaN if the solve failed)."""
    S = OrbitStatus
    status = S.where(residual <= tol, S.successful, S.not_converged)
    status = S.where(ok, status, S.solve_failed)
    status = S.where(T > 0, status, S.nonpositive_period)
    mu = _sorted(jnp.linalg.eigvals(M))
    return status, jnp.where(ok, mu, jnp.full_like(mu, jnp.nan))


def _shoot(model, x_ref, period, tol, max_newton, rtol, atol, max_steps):
    """The shooting loop of :func:`periodic_orbit`, as plain arrays (a stored program)."""
    F = flat_field(model, throw=False)
    solver = dict(rtol=rtol, atol=atol, max_steps=max_steps)

    def system(z):
        return shooting_system(model, F, z[:6], z[6], x_ref, solver)

    z0 = jnp.concatenate([x_ref, jnp.asarray(period, dtype=x_ref.dtype)[None]])
    z, k, M, residual, ok, _ = shooting_newton(system, z0, tol, max_newton)
    status, mu = _outcome(z[6], M, residual, ok, tol)
    return z[:6], z[6], mu, residual, k, enum.code(status)


# With the program store on (rbo_jax.enable_compilation_cache) a second process loads it traced;
# models holding a plain callable (no stable name across processes) are traced as usual.
_shoot_program = program(_shoot, small=True)  # XLA's options for small programs


class _Unfolding(AbstractLoad):
    r"""The unfolding term of a conservative family: the viscous moment $-\varepsilon\,\omega$
    of :class:`rbo_jax.Friction` with a signed $\varepsilon$ and no check on it (Friction asks
    $b \ge 0$); its energy rate is $-\varepsilon\,|\Omega|^2$."""

    eps: Float[Array, ""]

    depends_on_velocity: ClassVar[bool] = True

    def moment(self, t, theta, omega):
        return -self.eps * as_vector(omega, "omega")

    def body_moment(self, t, theta, Omega, turn):
        """Pᵀ·(−ε P·Ω) = −ε Ω."""
        return -self.eps * Omega

    def potential_energy(self, theta):
        return jnp.zeros((), dtype=self.eps.dtype)


def _unfolded(model: RigidBodyOscillator, eps) -> RigidBodyOscillator:
    """``model`` with the load :class:`_Unfolding` ``(eps)`` appended (same structure for any
    ``eps``, so one traced program)."""
    return eqx.tree_at(lambda m: m.loads, model, model.loads + (_Unfolding(eps),))


def is_conservative(model: RigidBodyOscillator) -> bool:
    r"""Whether every load of ``model`` is a :class:`rbo_jax.PotentialLoad` (4.52), so that the
    energy $K + U + V$ (:meth:`rbo_jax.RigidBodyOscillator.energy`) is a first integral: the
    foundation is a potential (4.46) and the gyroscopic term $\Omega\times A\cdot\Omega$ does no
    work. Decided from the model's structure, not its values: :class:`rbo_jax.Friction` (4.84),
    :class:`rbo_jax.FollowerMoment` (4.57), :class:`rbo_jax.SemiTangentialMoment` (4.75),
    :class:`rbo_jax.CallableLoad` and :class:`rbo_jax.DeadMoment` make it non-conservative.

    A dead moment $M k$ has no potential (``potential_energy`` is 0): its power $M k\cdot\omega$
    is not the rate of any $V(\theta)$, not even locally, since the form $k\cdot\omega$ on the
    rotations is not closed: small turns $\alpha a$, $\beta b$, $-\alpha a$, $-\beta b$ make a
    closed loop of $P$ (their commutator is the turn $\alpha\beta\,a\times b$) on which it does
    the work $\pm M\alpha\beta\,k\cdot(a\times b) + O(3) \ne 0$. For a transversely isotropic model
    about the moment's axis, (4.78) with $l_1 = 1$, $l_2 = 0$ shows the pumping directly."""
    return all(isinstance(load, PotentialLoad) for load in model.loads)


def conservative_system(model, x, T, eps, energy, x_ref, solver):
    r"""The residual of the unfolded shooting system (module docstring, conservative families)
    and its 8×8 Jacobian with respect to $(x_0, T, \varepsilon)$, plus the monodromy matrix
    $\partial\varphi_T/\partial x_0$ at $\varepsilon$ and the solver's success flag."""

    def f(y):
        xT, ok = flow(_unfolded(model, y[6]), y[:6], T, **solver)
        return xT, (xT, ok)

    J, (xT, ok) = jax.jacfwd(f, has_aux=True)(jnp.concatenate([x, eps[None]]))
    F = flat_field(model, throw=False)
    F_eps = flat_field(_unfolded(model, eps), throw=False)
    E, dE = jax.value_and_grad(lambda y: model.energy(y[:3], y[3:]))(x)
    r = jnp.concatenate([xT - x, (F(x_ref) @ (x - x_ref))[None], (E - energy)[None]])
    zero = jnp.zeros(2, x.dtype)
    top = jnp.concatenate([J[:, :6] - jnp.eye(6), F_eps(xT)[:, None], J[:, 6:]], axis=1)
    bottom = jnp.stack([jnp.concatenate([F(x_ref), zero]), jnp.concatenate([dE, zero])])
    return r, jnp.concatenate([top, bottom]), J[:, :6], ok


def _shoot_conservative(model, x_ref, period, energy, tol, max_newton, rcond, rtol, atol, steps):
    """The unfolded shooting loop of :func:`periodic_orbit` (a stored program); ``energy`` NaN:
    the energy of ``x_ref``."""
    solver = dict(rtol=rtol, atol=atol, max_steps=steps)
    energy = jnp.asarray(energy, x_ref.dtype)
    energy = jnp.where(jnp.isnan(energy), model.energy(x_ref[:3], x_ref[3:]), energy)

    def system(z):
        return conservative_system(model, z[:6], z[6], z[7], energy, x_ref, solver)

    T0 = jnp.asarray(period, dtype=x_ref.dtype)
    z0 = jnp.concatenate([x_ref, jnp.stack([T0, jnp.zeros_like(T0)])])
    z, k, M, residual, ok, _ = shooting_newton(system, z0, tol, max_newton, rcond)
    status, mu = _outcome(z[6], M, residual, ok, tol)
    S = OrbitStatus
    status = S.where(
        (status == S.successful) & ~(jnp.abs(z[7]) <= jnp.sqrt(tol)), S.unfolded, status
    )
    return z[:6], z[6], z[7], mu, residual, k, enum.code(status)


_conservative_program = program(_shoot_conservative, small=True)


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
    energy=None,
    conservative: bool | None = None,
    rcond=1e-7,
) -> PeriodicOrbit:
    r"""The periodic orbit near $(\theta_0, \Omega_0)$ with period near ``period``, by shooting
    (module docstring): Newton's method for the initial state and the period with the phase
    condition, ``max_newton`` iterations at most, until the shooting residual and the correction
    are below ``tol``; ``rtol``, ``atol``, ``max_steps`` go to :func:`rbo_jax.fast_simulate`.
    The Floquet multipliers come from the monodromy matrix at the solution.

    **Conservative models** (``conservative``; ``None``: :func:`is_conservative`, i.e. every
    load a :class:`rbo_jax.PotentialLoad`): the unfolded system of the module docstring for
    $(x_0, T, \varepsilon)$, with the energy condition $E(x_0) = E_*$, $E_*$ = ``energy``
    (``None``: the energy of the guess, :meth:`rbo_jax.RigidBodyOscillator.energy`) and
    least-squares steps truncated below ``rcond`` times the largest singular value (``rcond`` is
    for this system only). The result's ``unfolding`` is $\varepsilon$ at the solution: 0 up to
    the tolerance, else the status is ``unfolded`` ($|\varepsilon| > \sqrt{\mathrm{tol}}$). With
    further integrals (axisymmetric models, (4.78); the isotropic oscillator, (4.94)) the orbits
    of one energy form families: the result is the orbit reached by minimum-norm steps, one of
    the family near the guess. ``conservative=True`` may be forced on a model whose
    non-potential loads vanish (``Friction(0.0)``, ``FollowerMoment(0.0, k)``) or are
    velocity-independent (dead, follower moments: the system is reversible under $(\theta,
    \Omega, t) \mapsto (\theta, -\Omega, -t)$, its symmetric orbits form families along which
    the power of the load integrates to 0); the status ``unfolded`` tells where no orbit of the
    model was found. ``energy`` is refused by plain shooting (``conservative=False`` or a
    non-conservative model).

    Never raises: ``status`` says whether Newton converged. jit- and vmap-compatible; one
    compiled program per model structure, kept by the program store when it is on
    (:func:`rbo_jax.enable_compilation_cache`).
    """
    x_ref = _state(theta0, Omega0)
    period = period if isinstance(period, jax.core.Tracer) else np.asarray(period, x_ref.dtype)
    if conservative is None:
        conservative = is_conservative(model)
    if conservative:
        energy = np.nan if energy is None else energy
        if not isinstance(energy, jax.core.Tracer):
            energy = np.asarray(energy, x_ref.dtype)
        x, T, eps, mu, residual, k, code = _conservative_program(
            model, x_ref, period, energy, tol, max_newton, rcond, rtol, atol, max_steps
        )
    elif energy is not None:
        raise ValueError(
            "periodic_orbit: energy is the extra condition of conservative shooting, not of "
            "plain shooting (conservative=False, or a model with non-potential loads: pass "
            "conservative=True if they vanish)."
        )
    else:
        x, T, mu, residual, k, code = _shoot_program(
            model, x_ref, period, tol, max_newton, rtol, atol, max_steps
        )
        eps = np.zeros((), x_ref.dtype)
    return PeriodicOrbit(
        theta0=x[:3],
        Omega0=x[3:],
        period=T,
        multipliers=mu,
        residual=residual,
        num_steps=k,
        status=enum.from_code(OrbitStatus, code),
        unfolding=eps,
    )
