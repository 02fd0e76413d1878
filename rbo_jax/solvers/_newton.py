r"""Newton's update and the one convergence test of every solve.

A step solves $J\,\delta = -r$ with the linear solver of the problem's structure
(:mod:`._linear`) and moves the unknowns by $\delta$ — added, or through the model's own
retraction (turns composed, positions added: :meth:`rbo_jax.mechanics.AbstractMechanics.retract`).
It has converged when every component of the step is below ``atol + rtol·|y|``
(:func:`converged`), or the residual is already at the rounding level (``floor``): from there
on the steps are rounding, amplified by the stiffest rows.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

__all__ = ["converged", "newton_step", "newton_update"]


def converged(step, y, rtol, atol):
    r"""Whether every component of ``step`` is at most ``atol + rtol·|y|`` (``atol`` may be an
    array of the step's shape: a scale per component; ``y`` is not read where ``rtol`` is 0,
    as for increments in a chart, whose unknowns are not the step's coordinates)."""
    bound = jnp.broadcast_to(atol, jnp.shape(step))
    if not (isinstance(rtol, (int, float)) and rtol == 0):
        bound = bound + rtol * jnp.abs(jnp.reshape(y, jnp.shape(step)))
    return jnp.all(jnp.abs(step) <= bound)


def _add(y, step):
    return y + step


def newton_update(
    r, operator, linear, y, *, rtol, atol, retract: Callable | None = None, floor=0.0
):
    r"""Newton's update from the residual ``r`` and its Jacobian ``operator`` at ``y``:
    $\delta = -J^{-1}r$ (least squares for a consistent over-determined system), then
    ``retract(y, δ)`` (default: ``y + δ``). Returns ``(y_new, step, done, finite)``: ``done``
    whether the step is below the tolerances (:func:`converged`) or the residual's max norm is
    at most ``floor``, ``finite`` whether the step and the residual are finite (``y_new`` is
    ``y`` where they are not)."""
    step = linear.solve(operator, -r)
    finite = jnp.all(jnp.isfinite(step)) & jnp.all(jnp.isfinite(r))
    moved = (retract or _add)(y, step)
    y_new = jax.tree_util.tree_map(lambda a, b: jnp.where(finite, a, b), moved, y)
    done = converged(step, y, rtol, atol) | (jnp.max(jnp.abs(r)) <= floor)
    return y_new, step, done & finite, finite


def newton_step(
    residual: Callable, linear, y, *, rtol, atol, retract: Callable | None = None, floor=0.0
):
    r"""One Newton step from ``y``: ``residual(y) -> (r, operator, aux)`` with ``operator`` the
    Jacobian in the structure of ``linear`` (:class:`rbo_jax.solvers.AbstractLinearSolver`),
    then :func:`newton_update`. Returns ``(y_new, step, evaluation, done, finite)``,
    ``evaluation`` the ``(r, operator, aux)`` at ``y``."""
    r, operator, aux = residual(y)
    y_new, step, done, finite = newton_update(
        r, operator, linear, y, rtol=rtol, atol=atol, retract=retract, floor=floor
    )
    return y_new, step, (r, operator, aux), done, finite
