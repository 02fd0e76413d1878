"""The first-order optimisers of :func:`rbo_jax.fit` (optax): Adam and L-BFGS with reverse-mode
gradients through the ODE solves."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..solvers import record_loss
from ._residuals import loss, loss_and_grad


def run_optax(
    model, datas, spec, learning_rate, u, optimizer, tol, max_steps, history, bar, verbose
):
    """Adam or L-BFGS from ``u`` on the loss of ``model`` and ``datas``; the signature from ``u``
    on is :func:`rbo_jax.solvers.run_least_squares`'s. Returns ``(u, steps, converged,
    message)``."""
    opt = optax.adam(learning_rate) if optimizer == "adam" else optax.lbfgs()
    state = opt.init(u)

    @eqx.filter_jit
    def update(u, state, value, grad, model, datas):
        # optax's own arithmetic mixes dtypes (optax 0.2.8: ``decay ** count`` with an int32
        # count), which a user's ``jax_numpy_dtype_promotion = "strict"`` refuses: optax runs
        # with standard promotion, whatever the caller's setting
        with jax.numpy_dtype_promotion("standard"):
            return _update(u, state, value, grad, model, datas)

    def _update(u, state, value, grad, model, datas):
        if optimizer == "lbfgs":
            updates, state = opt.update(
                grad,
                state,
                u,
                value=value,
                grad=grad,
                value_fn=lambda v: loss(v, model, datas, spec),
            )
        else:
            updates, state = opt.update(grad, state, u)
        return optax.apply_updates(u, updates), state

    value, grad = loss_and_grad(u, model, datas, spec)
    record_loss(history, value, bar, verbose)
    steps = 0
    for steps in range(1, max_steps + 1):
        u, state = update(u, state, value, grad, model, datas)
        new_value, grad = loss_and_grad(u, model, datas, spec)
        record_loss(history, new_value, bar, verbose)
        gnorm = float(np.sqrt(sum(float(jnp.sum(x**2)) for x in jax.tree_util.tree_leaves(grad))))
        if abs(float(value) - float(new_value)) <= tol * abs(float(value)) and gnorm <= tol:
            return u, steps, True, "converged"
        value = new_value
    return u, steps, False, f"max_steps = {max_steps} reached before convergence"
