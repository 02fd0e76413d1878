r"""Simulation of the rigid body oscillator with diffrax.

:func:`simulate` integrates the right form (4.55)–(4.56) (or the left form (4.53)–(4.54)) and
returns a :class:`Trajectory`. :func:`solve_darboux` integrates the turn-vector for a given
angular-velocity history, the left and right Darboux problems (4.15), (4.16).

Failures are never silent. The solve stops, with a :class:`SolveStatus` naming the cause, when

- the step budget ``max_steps`` is exhausted;
- the step size collapses below ``dtmin`` (non-finite vector field, stiff blow-up);
- the turn-vector approaches a singular sphere $|\theta| = 2\pi k$ of the integrating tensor (4.11)
  while $\theta\times\Omega \ne 0$ (within ``singular_tol``): there $\det Z = \infty$;
- the state leaves the domain of the foundation energy (e.g. the barriers of (4.49));
- the initial state is not finite or a model parameter is NaN.

With ``throw=True`` (default) a failure raises an error carrying that message; with ``throw=False``
the status is returned in the trajectory and the samples after the failure are ``inf`` (sweeps use
this to flag a point and carry on).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from . import _enumeration as enum
from ._custom_types import Vector
from ._programs import stored
from ._validation import common_float_dtype
from .integrate import diffeq
from .kinematics import as_vector, integrating_tensor, turn_tensor
from .models.rigid_body import RigidBodyOscillator
from .trajectory import (
    SolveStatus,
    Trajectory,
    all_finite,
    check_times,
    finish,
    is_transverse,
    prepare_inputs,
    raise_failure,
    warn_if_float32,
)

__all__ = ["SolveStatus", "Trajectory", "simulate", "DarbouxSolution", "solve_darboux"]


def _right_to_theta_Omega(model, y):
    return y


def _left_to_theta_Omega(model, y):
    return y[0], model.Omega_from_kinetic_moment(*y)


def _state_transverse(to_theta_Omega, t, y):
    theta, Omega = to_theta_Omega(y)
    return theta, is_transverse(theta, Omega)


def _domain_cond(model, t, y, args, **kwargs):
    return ~(model.domain_margin(y[0]) > 0)


def simulate(
    model: RigidBodyOscillator,
    theta0,
    Omega0,
    ts,
    *,
    t0=None,
    solver: diffrax.AbstractSolver | None = None,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    dt0=None,
    dtmin=None,
    max_steps: int = 100_000,
    adjoint: diffrax.AbstractAdjoint | None = None,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    singular_tol: float = 1e-3,
    form: str = "right",
    throw: bool = True,
    progress: bool = False,
    dense: bool = False,
) -> Trajectory:
    r"""Integrate the rigid body oscillator from $(\theta_0, \Omega_0)$ and sample it at ``ts``.

    **Arguments:**

    - `model`: a :class:`RigidBodyOscillator`.
    - `theta0`, `Omega0`: initial turn-vector and right angular velocity, shape (3,).
    - `ts`: strictly increasing sample times (n,); the solve runs from ``t0`` (default
      ``ts[0]``) to ``ts[-1]``.
    - `solver`: a diffrax solver; default ``diffrax.Dopri8()`` (8th order, adaptive), the
      efficient choice at the tight float64 tolerances used here.
    - `rtol`, `atol`: tolerances of the PID step-size controller (default 1e-10).
    - `dt0`: initial step (default: chosen automatically). `dtmin`: step size below which the
      solve stops as ``step_size_collapse`` (default ``1e-12·(t1 − t0)``).
    - `max_steps`: step budget (default 100 000).
    - `adjoint`: diffrax adjoint for reverse-mode gradients (default
      ``RecursiveCheckpointAdjoint``, memory logarithmic in the step count); pass
      ``diffrax.ForwardMode()`` for forward-mode autodiff (``jax.jvp``, ``jax.jacfwd``).
    - `stepsize_controller`: a diffrax step-size controller replacing the default
      ``diffrax.PIDController(rtol, atol, dtmin)`` (``rtol``, ``atol`` and ``dtmin`` are then
      ignored), e.g. ``diffrax.ConstantStepSize()`` with ``dt0`` for fixed steps (convergence
      studies); a fixed step never reports ``step_size_collapse``.
    - `singular_tol`: stop when $\big||\theta| - 2\pi k\big| <$ ``singular_tol`` while the motion
      is not plane ($|\theta\times\Omega| > 10^{-6}|\theta||\Omega|$).
    - `form`: ``"right"`` integrates (4.55)–(4.56) in $(\theta, \Omega)$; ``"left"`` integrates
      (4.53)–(4.54) in $(\theta, L)$ and converts back to $\Omega$.
    - `throw`: raise on failure (default) or return the status in the trajectory.
    - `progress`: show a tqdm progress bar (for long single runs; needs ``tqdm`` installed).
    - `dense`: sample ``ts`` from the solution's dense output after the solve instead of inside
      it (:func:`rbo_jax.integrate.diffeq.solve`): the same samples, a reverse-mode gradient
      through thousands of them at half the cost, memory proportional to ``max_steps`` (so
      give a ``max_steps`` near the steps the solve needs).

    jit-, vmap- and grad-compatible: parameters of ``model`` and the initial state may be traced.
    """
    if not isinstance(model, RigidBodyOscillator):
        raise TypeError(f"model must be a RigidBodyOscillator, got {type(model).__name__}.")
    if form not in ("right", "left"):
        raise ValueError(f"form must be 'right' or 'left', got {form!r}.")
    inputs = prepare_inputs(model, theta0, Omega0, ts, rtol, atol, throw)
    diffeq.check_start(t0, dt0, inputs.ts)
    options = _Options(
        t0,
        solver,
        rtol,
        atol,
        dt0,
        dtmin,
        max_steps,
        adjoint,
        stepsize_controller,
        singular_tol,
        form,
        throw,
        progress,
        dense,
    )
    args = (model, inputs.theta0, inputs.Omega0, inputs.ts, inputs.bad_times, inputs.dtype, options)
    # Concrete inputs: one compiled program for everything between the checks and the result
    # (the step-size bounds, A^-1, the statuses), not a dozen small eager ones.
    checked = diffeq.trusted(model, solver, adjoint, stepsize_controller)
    theta, Omega, code, steps = diffeq.run(_solve_compiled, _solve, args, checked)
    status = enum.from_code(SolveStatus, code)
    return finish(model, inputs, theta, Omega, status, steps, throw)


class _Options(NamedTuple):
    """The keyword arguments of :func:`simulate` as given (in its order), passed whole to its
    solve."""

    t0: Any
    solver: diffrax.AbstractSolver | None
    rtol: Any
    atol: Any
    dt0: Any
    dtmin: Any
    max_steps: int
    adjoint: diffrax.AbstractAdjoint | None
    stepsize_controller: diffrax.AbstractStepSizeController | None
    singular_tol: Any
    form: str
    throw: bool
    progress: bool
    dense: bool = False


def _solve(model, theta0, Omega0, ts, bad_times, dtype, options: _Options):
    """The diffrax solve of :func:`simulate` from checked inputs: ``(theta, Omega, status code,
    accepted steps)``, plain arrays (a program the store can keep)."""
    o = options
    # Bad traced times (throw=False) are replaced by zeros: then t0 = t1 = 0 too.
    t0 = ts[0] if o.t0 is None else jnp.where(bad_times, ts[0], jnp.asarray(o.t0, dtype))
    t1 = ts[-1]
    dtmin = 1e-12 * jnp.maximum(t1 - t0, 1e-300) if o.dtmin is None else o.dtmin
    controller = o.stepsize_controller
    if controller is None:
        controller = diffrax.PIDController(rtol=o.rtol, atol=o.atol, dtmin=dtmin, force_dtmin=False)

    if o.form == "right":
        y0 = (theta0, Omega0)
        vf = model.right_form(o.throw)
        to_theta_Omega = jax.tree_util.Partial(_right_to_theta_Omega, model)
    else:
        y0 = (theta0, model.kinetic_moment(theta0, Omega0))
        vf = model.left_form(o.throw)
        to_theta_Omega = jax.tree_util.Partial(_left_to_theta_Omega, model)

    # Partials of module-level functions, not closures: see diffeq.singular_events.
    transverse = jax.tree_util.Partial(_state_transverse, to_theta_Omega)
    singular = diffeq.singular_events(transverse, jnp.asarray(o.singular_tol, dtype))
    domain_cond = jax.tree_util.Partial(_domain_cond, model)
    events = [("singular_point", c) for c in singular] + [("domain_error", domain_cond)]
    ys, status, steps = diffeq.solve(
        vf,
        o.solver,
        y0,
        ts,
        t0=t0,
        dt0=o.dt0,
        controller=controller,
        events=events,
        adjoint=o.adjoint,
        max_steps=o.max_steps,
        progress=o.progress,
        dense=o.dense,
    )
    theta, Omega = jax.vmap(lambda a, b: to_theta_Omega((a, b)))(*ys)
    return theta, Omega, enum.code(status), steps


# With the program store on (rbo_jax.enable_compilation_cache) a second process loads it traced;
# a program with host callbacks (a user function in the model, progress=True, throw=True with a
# check in the equations of motion) is marked unexportable and traced as usual.
_solve_compiled = stored(eqx.filter_jit(_solve))


# --------------------------------------------------------------------------------------------
# Darboux problems (4.15), (4.16).
# --------------------------------------------------------------------------------------------


class DarbouxSolution(eqx.Module):
    """Turn-vector path of a Darboux problem: ``ts`` (n,), ``theta`` (n, 3), ``status``."""

    ts: Float[Array, " n"]
    theta: Float[Array, "n 3"]
    status: SolveStatus

    @property
    def turn_tensor(self) -> Float[Array, "n 3 3"]:
        return jax.vmap(turn_tensor)(self.theta)


def _velocity_function(angular_velocity) -> Callable[[Array], Vector]:
    if callable(angular_velocity):
        return angular_velocity
    try:
        t_s, w_s = angular_velocity
    except (TypeError, ValueError):
        raise TypeError(
            "angular_velocity must be a callable t -> (3,) or a pair (times (m,), samples (m, 3))."
        ) from None
    t_s = check_times(t_s)
    w_s = jnp.asarray(w_s, dtype=t_s.dtype)
    if w_s.shape != (t_s.shape[0], 3):
        raise ValueError(
            f"angular velocity samples must have shape ({t_s.shape[0]}, 3), got {w_s.shape}."
        )
    coeffs = diffrax.backward_hermite_coefficients(t_s, w_s)
    interp = diffrax.CubicInterpolation(t_s, coeffs)
    return interp.evaluate


def _darboux_left(w, t, theta, args):
    return integrating_tensor(theta) @ w(t)


def _darboux_right(w, t, theta, args):
    return integrating_tensor(theta).T @ w(t)


def _darboux_transverse(w, t, theta):
    return theta, is_transverse(theta, w(t))


# keyword arguments named as fast_simulate's: each public solver spells out its own signature
def solve_darboux(
    angular_velocity,
    theta0,
    ts,
    *,
    frame: str = "left",
    solver: diffrax.AbstractSolver | None = None,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    singular_tol: float = 1e-3,
    throw: bool = True,
) -> DarbouxSolution:
    r"""Integrate the turn-vector for a given angular velocity: the Darboux problems.

    ``frame="left"``: $\dot\theta = Z(\theta)\cdot\omega(t)$ (4.10), (4.15);
    ``frame="right"``: $\dot\theta = Z^T(\theta)\cdot\Omega(t)$ (4.14), (4.16);
    $\theta(t_0) = \theta_0$.

    `angular_velocity` is a callable ``t -> (3,)`` or samples ``(times, values)`` (interpolated by
    cubic Hermite splines). The solve stops with ``SolveStatus.singular_point`` near
    $|\theta| = 2\pi k$ unless $\theta\times\omega = 0$.
    """
    if frame not in ("left", "right"):
        raise ValueError(f"frame must be 'left' or 'right', got {frame!r}.")
    w = _velocity_function(angular_velocity)
    theta0 = as_vector(theta0, "theta0")
    ts = check_times(ts)
    # The precision of the angular velocity counts too (as the model's in simulate): float32
    # theta0 with a float64 angular velocity is integrated in float64.
    dtype = common_float_dtype(theta0, ts, jax.eval_shape(w, ts[0]).dtype)
    theta0, ts = theta0.astype(dtype), ts.astype(dtype)
    warn_if_float32(dtype, rtol, atol)

    # Partials of module-level functions, not closures: see diffeq.singular_events.
    vf = jax.tree_util.Partial(_darboux_left if frame == "left" else _darboux_right, w)
    transverse = jax.tree_util.Partial(_darboux_transverse, w)
    singular = diffeq.singular_events(transverse, jnp.asarray(singular_tol, theta0.dtype))
    events = [("singular_point", c) for c in singular]
    theta, status, _ = diffeq.solve(
        vf, solver, theta0, ts, rtol=rtol, atol=atol, events=events, max_steps=max_steps
    )
    status = SolveStatus.where(~all_finite(theta0), SolveStatus.nonfinite_input, status)
    return DarbouxSolution(ts=ts, theta=raise_failure(theta, status, throw), status=status)
