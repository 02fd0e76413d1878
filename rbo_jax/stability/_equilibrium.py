r"""Equilibria of any model: Newton's method on the balance of forces and moments at rest.

The unknowns of a step are the model's local increments $x$ at the current configuration
(:meth:`rbo_jax.mechanics.AbstractMechanics.block_shape`: a turn increment per body, and a
displacement for a body that translates); the residual is the balance of forces and moments at
rest, $R(x) = 0$ at an equilibrium ((4.61) for one body, the moment and force on every body of
a rod). A step solves $J\delta = -R$ with the solver of the model's structure (dense for a
rigid body or a grid, block-tridiagonal for an open chain or a rod: O(N), :mod:`rbo_jax.solvers`)
and moves the configuration by $\delta$ (:meth:`~rbo_jax.mechanics.AbstractMechanics.retract`:
turn-vectors added for bodies on a foundation, turns composed (4.5) for a rod, whose turn-vectors
then never grow past $\pi$). Newton stops when every component of the step is below ``rtol``
times the model's scale of it (:meth:`~rbo_jax.mechanics.AbstractMechanics.increment_scale`).

**Large deflections**: ``steps`` load steps, every load times $\lambda = 1/s, 2/s, \dots, 1$,
each from the previous configuration.

**Derivatives**: the solution $c^*(p)$ of $R(c^*, p) = 0$ is differentiated with respect to
every float of the model by the implicit function theorem, $dx = -J^{-1}\partial_pR\,dp$ at the
solution (:func:`rbo_jax.solvers.implicit`, the Jacobian of the last Newton step, within
``rtol`` of the solution): ``jax.grad`` of a tip deflection with respect to $EI$ costs one
transposed solve.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from .. import _programs
from ..mechanics import AbstractMechanics, EquilibriumStatus, checked_parameters
from ..solvers import Implicit, Outcome, implicit, iterate, linear_solver, newton_step

__all__ = [
    "EquilibriumSolution",
    "equilibrium",
    "newton_equilibrium",
    "solve_equilibrium",
]

# Newton's step cannot fall below the rounding of the balance: the tolerance is at least this many
# units of the state's machine epsilon (1.2e-5 in float32; 2.2e-14 in float64, below the default)
RESOLUTION = 100


class EquilibriumSolution(Outcome):
    """The result of :func:`solve_equilibrium`: the equilibrium ``state`` (the model's own
    configuration: a turn-vector (3,) for a rigid body, (N, 3) for a lattice, a
    :class:`rbo_jax.lattice.RodState` at rest for a rod), ``status``
    (:class:`EquilibriumStatus`), ``residual`` (max |R| at ``state``) and
    ``num_steps`` (Newton steps, all load steps together). ``theta``: the turn-vectors;
    ``iterations``: ``num_steps``."""

    state: Any
    status: EquilibriumStatus
    residual: jax.Array
    num_steps: jax.Array

    @property
    def theta(self):
        """The turn-vector(s) of the equilibrium."""
        return getattr(self.state, "theta", self.state)

    @property
    def iterations(self):
        """The Newton steps (:attr:`num_steps`)."""
        return self.num_steps


def _codes():
    return {name: int(np.asarray(enum.code(getattr(EquilibriumStatus, name))))
            for name in enum.names(EquilibriumStatus)}  # fmt: skip


def _zero_operator(linear, fn, x0):
    """Zeros shaped as the Jacobian of the square residual ``fn`` at ``x0`` in ``linear``'s
    form: those of the identity's of ``fn``'s output, so that the residual's Jacobian is not
    traced for its shape (only the residual, for its dtype)."""
    out = jax.eval_shape(fn, x0)
    shapes = jax.eval_shape(lambda x: linear.jacobian(lambda z: z, x), out)
    return jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)


def _newton(model, t, config, scale, tol, max_steps, linear, operator0):
    """Newton's method at the load factor ``scale`` from ``config`` (``operator0``: zeros shaped
    as the Jacobian): ``(config, operator, residual, code, steps)``."""
    codes = _codes()

    def residual(config):
        x0 = jnp.zeros(model.block_shape(), jnp.result_type(*jax.tree_util.tree_leaves(config)))
        fn = lambda x: model.static_residual(t, config, x, scale)  # noqa: E731
        return *linear.value_and_jacobian(fn, x0), None

    def step(config, carry):
        atol = tol * model.increment_scale(config)
        new, _, (r, operator, _), done, finite = newton_step(
            residual, linear, config, rtol=0, atol=atol, retract=model.retract
        )
        code = jnp.where(done, codes["successful"], -1)
        code = jnp.where(finite, code, codes["nonfinite"])
        return new, (operator, jnp.max(jnp.abs(r))), code

    carry = (operator0, jnp.asarray(jnp.inf, jnp.result_type(*jax.tree_util.tree_leaves(config))))
    config, (operator, res), code, steps = iterate(
        step, config, carry, max_steps=max_steps, exhausted=codes["not_converged"]
    )
    return config, operator, res, code, steps


def _solve(params, steps, tol, max_steps, singular_tol) -> Implicit:
    """Newton's method over the load steps (module docstring), with the status."""
    model, guess, t = params
    linear = linear_solver(model.structure())
    codes = _codes()
    dtype = jnp.result_type(*jax.tree_util.tree_leaves(guess))
    scales = jnp.arange(1, steps + 1, dtype=dtype) / steps
    x0 = jnp.zeros(model.block_shape(), dtype)
    op0 = _zero_operator(linear, lambda x: model.static_residual(t, guess, x, scales[0]), x0)

    def one_load(carry, scale):
        config, _, total, code = carry
        new, operator, res, new_code, k = _newton(model, t, config, scale, tol, max_steps, linear,
                                                  op0)  # fmt: skip
        failed = code != codes["successful"]
        carry = (new, operator, total + k, jnp.where(failed, code, new_code))
        return carry, res

    init = (guess, op0, jnp.asarray(0, jnp.int32), jnp.asarray(codes["successful"], jnp.int32))
    (config, operator, total, code), _ = jax.lax.scan(one_load, init, scales)
    S = EquilibriumStatus
    status = enum.from_code(S, code)
    finite = jnp.all(
        jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(config)])
    )
    ok = status == S.successful
    admissible = model.configuration_status(config, singular_tol)
    status = S.where(ok & (admissible != S.successful), admissible, status)
    status = S.where(finite, status, S.nonfinite)
    valid = model.parameter_status()[0]
    status = S.where(valid, status, S.invalid_parameters)
    config = jax.tree_util.tree_map(lambda x: jnp.where(valid, x, jnp.nan), config)
    good = status == S.successful
    final = jnp.max(
        jnp.abs(model.static_residual(t, config, jnp.zeros(model.block_shape(), dtype)))
    )
    return Implicit(config, operator, good, (enum.code(status), final, total))


def newton_equilibrium(model, guess, t=0.0, *, steps=1, rtol=1e-10, max_steps=64,
                       singular_tol=1e-6):  # fmt: skip
    """The equilibrium of ``model`` from the configuration ``guess`` inside another solver's
    program (not differentiated: the caller's implicit rule covers it): ``(config, status
    code, residual, num_steps)``."""
    dtype = jnp.result_type(*jax.tree_util.tree_leaves(guess))
    tol = max(float(rtol), RESOLUTION * float(jnp.finfo(dtype).eps))
    out = _solve((model, guess, t), int(steps), tol, int(max_steps), float(singular_tol))
    code, res, total = out.extra
    return out.y, code, res, total


def _residual(config, x, params):
    model, _, t = params
    return model.static_residual(t, config, x)


def _retract(config, x, params):
    return params[0].retract(config, x)


def _zero(config, params):
    return jnp.zeros(params[0].block_shape(), jnp.result_type(*jax.tree_util.tree_leaves(config)))


def _equilibrium(model, guess, t, steps, tol, max_steps, singular_tol):
    out = implicit(
        lambda p: _solve(p, steps, tol, max_steps, singular_tol),
        _residual,
        (model, guess, t),
        linear=linear_solver(model.structure()),
        retract=_retract,
        increment=_zero,
    )
    code, res, total = out.extra
    return out.y, code, res, total


_program = _programs.jit(_equilibrium, fast_compile=True)


def solve_equilibrium(
    model: AbstractMechanics,
    guess=None,
    *,
    theta_guess=None,
    t=0.0,
    steps: int = 1,
    rtol: float = 1e-10,
    atol: float | None = None,
    max_steps: int = 64,
    singular_tol: float = 1e-6,
) -> EquilibriumSolution:
    r"""The equilibrium of ``model`` nearest ``guess``, with a status (module docstring).

    **Arguments:** `model` (a :class:`rbo_jax.RigidBodyOscillator`, a
    :class:`rbo_jax.lattice.Lattice` or a :class:`rbo_jax.lattice.Rod`), `guess` (the model's
    configuration: a turn-vector for a rigid body, ``(N, 3)`` or one (3,) for every body of a
    lattice, a :class:`rbo_jax.lattice.RodState` for a rod; ``None``: the configuration at rest,
    a straight rod; ``theta_guess``: the same, by its older name), `t` (the time of
    time-dependent loads), `steps` (load steps), `rtol`
    (Newton stops when every component of the step is below ``rtol`` times the model's scale of
    it: $1 + |\theta_i|$ for a turn-vector, 1 for a rod's turn increments and its size for its
    displacements; never below 100 machine epsilons of the state's precision, 1.2e-5 in
    float32), `atol` (accepted for the rigid body's older calls: the tolerance is then the
    larger of the two), `max_steps` (Newton steps per load step), `singular_tol` (a turn-vector
    this close to a singular sphere $|\theta| = 2\pi k$ of $Z$ (4.11) is ``singular_point``).

    **Returns** an :class:`EquilibriumSolution`; never raises for a failed solve (use
    :func:`equilibrium`): ``status`` says whether Newton converged, and flags a singular point
    of $Z$, an exit from a foundation's domain, non-finite values, and a model whose parameters
    (traced at construction) are invalid (its state NaN). Differentiable with respect to every
    float of the model by the implicit function theorem; ``jax.jit`` and ``jax.vmap`` work.
    One compiled program per model structure.

    For the quadratic foundation (4.50) under a follower moment (4.57) the equilibrium of one
    body is $\theta_{eq} = (M/d)\,k$ (4.62).
    """
    if not isinstance(model, AbstractMechanics):
        raise TypeError(
            "solve_equilibrium: expected a RigidBodyOscillator, a Lattice or a Rod, got "
            f"{type(model).__name__}."
        )
    steps, max_steps = int(steps), int(max_steps)
    if steps < 1:
        raise ValueError(f"solve_equilibrium: steps must be >= 1, got {steps}.")
    if max_steps < 1:
        raise ValueError(f"solve_equilibrium: max_steps must be >= 1, got {max_steps}.")
    tol = float(rtol) if atol is None else max(float(rtol), float(atol))
    if not np.isfinite(tol) or tol <= 0:
        raise ValueError(f"solve_equilibrium: rtol must be > 0, got {rtol}.")
    if theta_guess is not None:  # the rigid body's older keyword
        if guess is not None:
            raise TypeError("solve_equilibrium: give the guess once (guess or theta_guess).")
        guess = theta_guess
    config = model.configuration(guess)
    dtype = jnp.result_type(*jax.tree_util.tree_leaves(config))
    tol = max(tol, RESOLUTION * float(jnp.finfo(dtype).eps))
    state, code, res, total = _program(model, config, t, steps, tol, max_steps, float(singular_tol))
    status = enum.from_code(EquilibriumStatus, code)
    return EquilibriumSolution(
        state=model.state_at_rest(state), status=status, residual=res, num_steps=total
    )


def equilibrium(model: AbstractMechanics, guess=None, **kwargs):
    r"""The equilibrium of ``model`` (:func:`solve_equilibrium`'s ``state``: a turn-vector
    $\theta_{eq}$ for a rigid body, ``(N, 3)`` for a lattice, a
    :class:`rbo_jax.lattice.RodState` for a rod), raising with the status's message when the
    solve fails (:func:`equinox.error_if` inside ``jit``); a model whose parameters are invalid
    raises the message that names the parameter."""
    return raising_equilibrium(model, guess, "equilibrium", **kwargs)


def raising_equilibrium(model: AbstractMechanics, guess, caller: str, **kwargs):
    """:func:`equilibrium`, its messages prefixed by ``caller``."""
    sol = solve_equilibrium(model, guess, **kwargs)
    code = enum.code(sol.status)
    successful = int(enum.code(EquilibriumStatus.successful))
    if not isinstance(code, jax.core.Tracer) and int(code) == successful:
        return sol.state  # called eagerly, and solved: nothing to raise (no eager checks)
    valid = sol.status != EquilibriumStatus.invalid_parameters
    state = checked_parameters(model, sol.state, caller, valid)
    messages = [f"{caller}: {EquilibriumStatus[getattr(EquilibriumStatus, n)]}"
                for n in enum.names(EquilibriumStatus)]  # fmt: skip
    return eqx.branched_error_if(state, ~sol.ok, code, messages)
