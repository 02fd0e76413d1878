r"""The one loop of every iterative solve in rbo_jax.

A solver is a function ``step(y, state) -> (y, state, code)``: ``y`` the unknowns (any pytree),
``state`` the solver's own carry (its phase, its last evaluation, its matrices), ``code`` the
status it reaches in this step, or :data:`RUNNING` to go on. :func:`iterate` applies it until a
step returns a status, or ``max_steps`` steps are done (then the status is ``exhausted``), in one
``lax.while_loop``: one traced copy of the step, so that a program holds each derivative of the
model it loops over once (STYLE.md, point 17).

Newton's method (:func:`rbo_jax.solvers.newton_step`) is the step of most solves; the Hopf and
Bautin programs run their phases (an equilibrium, a start from an eigenpair, Newton on the
extended system, the Lyapunov coefficients) as steps of the same loop.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["RUNNING", "iterate"]

RUNNING = -1  # the code of a solve that goes on: not a status


class _Carry(NamedTuple):
    y: Any
    state: Any
    code: jax.Array
    num_steps: jax.Array


def iterate(
    step: Callable, y, state, *, max_steps: int, exhausted
) -> tuple[Any, Any, jax.Array, jax.Array]:
    """Run ``step(y, state) -> (y, state, code)`` until ``code`` is not :data:`RUNNING` or
    ``max_steps`` steps are done. Returns ``(y, state, code, num_steps)``; ``code`` is
    ``exhausted`` (an int, the solver's "did not converge") where the budget ran out."""

    def running(c: _Carry):
        return (c.code == RUNNING) & (c.num_steps < max_steps)

    def body(c: _Carry) -> _Carry:
        y, state, code = step(c.y, c.state)
        return _Carry(y, state, jnp.asarray(code, jnp.int32), c.num_steps + 1)

    init = _Carry(y, state, jnp.asarray(RUNNING, jnp.int32), jnp.asarray(0, jnp.int32))
    c = jax.lax.while_loop(running, body, init)
    code = jnp.where(c.code == RUNNING, jnp.asarray(exhausted, jnp.int32), c.code)
    return c.y, c.state, code, c.num_steps
