r"""The one implicit-derivative rule of every solve.

A solve finds $y^*(p)$ with $R(y^*, p) = 0$. Its derivative with respect to the parameters
$p$ (every float leaf of the model and of the solve's other inputs) follows from the implicit
function theorem,

$$dy = -J^{-1}\,\partial_pR\,dp, \qquad J = \partial_xR(y^* \oplus x, p)\big|_{x = 0},$$

with $x$ an increment in the chart of the unknowns ($y \oplus x$: added, or the model's
retraction: turns composed) and $J^{-1}$ the solve's own linear solver at the solution (dense,
least squares for a consistent over-determined system, block-tridiagonal). The tangent is one
Jacobian-vector product of the residual in $p$ and one linear solve; it is linear in $dp$, so
``jax.grad`` transposes it (a solve with $J^T$). The iteration that found $y^*$ is never
differentiated: its starting point has no influence, and the derivative costs one solve
whatever the number of Newton steps (optimistix's ``ImplicitAdjoint``, ``implicit_jvp``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

__all__ = ["Implicit", "implicit"]


class Implicit(NamedTuple):
    """What a solve returns to :func:`implicit`: the solution ``y`` (differentiated), the
    Jacobian ``operator`` of the residual in the chart at ``y`` (in the form of the solve's
    linear solver; ``None``: computed by forward mode when the solve is first differentiated,
    in the tangent's own program, where the solve steers its iteration with a cheaper one),
    whether the solve succeeded (``good``: the derivative is zero elsewhere),
    anything ``extra`` (statuses, counts, diagnostics: not differentiated), and the
    residual's derivatives in the parameters where the solve has them (``partials``: the
    structure of ``params``, a matrix ``(residual size, leaf size)`` per leaf, ``None`` for a
    leaf the residual does not depend on; ``None``: computed by the tangent)."""

    y: Any
    operator: Any
    good: jax.Array
    extra: Any
    partials: Any = None


def _add(y, x, params):
    return jax.tree_util.tree_map(jnp.add, y, x)


def _zeros(y, params):
    return jax.tree_util.tree_map(jnp.zeros_like, y)


@eqx.filter_custom_jvp
def _solution(params, *, solve, residual, linear, retract, increment, forward, exact):
    return solve(params)


@_solution.def_jvp
def _solution_jvp(primals, tangents, *, solve, residual, linear, retract, increment, forward,
                  exact):  # fmt: skip
    (params,) = primals
    (dparams,) = tangents
    if exact is None:
        out = _solution(params, solve=solve, residual=residual, linear=linear, retract=retract,
                        increment=increment, forward=forward, exact=exact)  # fmt: skip
        derivatives = out
    else:  # the solve that also returns the exact operator and partials; the primal as solve's
        # (called as this custom_jvp function, as above: its program runs as a known value
        # under jax.grad's linearisation, not split into known and unknown parts)
        derivatives = _solution(params, solve=exact, residual=residual, linear=linear,
                                retract=retract, increment=increment, forward=forward,
                                exact=None)  # fmt: skip
        out = derivatives._replace(operator=None, partials=None)
    none = jax.tree_util.tree_map(lambda _: None, out)  # no tangent, leaf by leaf
    if dparams is None or not jax.tree_util.tree_leaves(dparams):
        return out, none
    dynamic = eqx.filter(params, eqx.is_inexact_array)
    # which leaves have a tangent at all (static: the forward-mode matrix skips the others)
    marks = jax.tree_util.tree_map(
        lambda p, d: None if p is None else d is not None,
        dynamic,
        dparams,
        is_leaf=lambda d: d is None,
    )
    given = tuple(jax.tree_util.tree_leaves(marks)) if forward else None  # in dyn's leaf order
    dparams = jax.tree_util.tree_map(
        lambda p, d: None if p is None else (jnp.zeros_like(p) if d is None else d),
        dynamic,
        dparams,
        is_leaf=lambda d: d is None,
    )
    dy = _tangent(
        jax.lax.stop_gradient(out.y), jax.lax.stop_gradient(derivatives.operator), out.good,
        params, dparams, jax.lax.stop_gradient(derivatives.partials), residual=residual,
        linear=linear, retract=retract, increment=increment, forward=given,
    )  # fmt: skip
    return out, none._replace(y=dy)


@eqx.filter_jit
def _tangent(y, operator, good, params, dparams, partials, *, residual, linear, retract, increment,
             forward):  # fmt: skip
    """$dy$ (module docstring): one product with the residual's derivative in the parameters,
    one solve, through the retraction; zero where the solve failed. Compiled once per
    structure (the callables are static: give equal ones for equal problems)."""
    x0 = increment(y, params)
    dyn, static = eqx.partition(params, eqx.is_inexact_array)

    def at(dyn, x=x0):
        return residual(y, x, eqx.combine(dyn, static))

    if partials is not None:  # the solve's own derivatives: matrix products only
        is_none = lambda v: v is None  # noqa: E731
        mats = jax.tree_util.tree_leaves(partials, is_leaf=is_none)
        ds = jax.tree_util.tree_leaves(dparams, is_leaf=is_none)
        if len(mats) != len(ds) or operator is None or not linear.matrix:
            raise ValueError("implicit: partials need params' structure and a matrix operator.")
        pairs = [(P, d) for P, d in zip(mats, ds) if P is not None and d is not None]
        rows = jnp.zeros(jnp.shape(operator)[0], jnp.result_type(operator))
        dr = sum((P @ jnp.ravel(d) for P, d in pairs), rows)
    elif forward is None:  # one Jacobian-vector product in the parameters
        if operator is None:  # the solve left it to the first derivative
            operator = linear.jacobian(lambda x: residual(y, x, params), x0)
        _, dr = jax.jvp(at, (dyn,), (dparams,))
    else:  # the residual's derivative in the parameters as a matrix, by forward mode, in the
        # leaves that have a tangent (``forward``: which, in leaf order)
        leaves, tree = jax.tree_util.tree_flatten(dyn)
        dleaves = jax.tree_util.tree_leaves(dparams)
        live = [i for i, g in enumerate(forward) if g]
        flat, unravel = ravel_pytree([leaves[i] for i in live])
        dflat, _ = ravel_pytree([dleaves[i] for i in live])

        def of_live(f, x=x0):
            new = list(leaves)
            for i, v in zip(live, unravel(f)):
                new[i] = v
            return jnp.ravel(at(jax.tree_util.tree_unflatten(tree, new), x))

        if operator is None and linear.matrix:  # one pass over [x, parameters] gives both
            xflat, unravel_x = ravel_pytree(x0)
            nx = xflat.shape[0]
            both = jax.jacfwd(lambda w: of_live(w[nx:], unravel_x(w[:nx])))
            columns = both(jnp.concatenate([xflat, flat.astype(xflat.dtype)]))
            operator, dr = columns[:, :nx], columns[:, nx:] @ dflat
        else:
            if operator is None:
                operator = linear.jacobian(lambda x: residual(y, x, params), x0)
            dr = jax.jacfwd(of_live)(flat) @ dflat
        dr = jnp.reshape(dr, jnp.shape(at(dyn)))
    bad = ~good
    operator = linear.identity_where(bad, operator)
    dr = jax.tree_util.tree_map(lambda v: jnp.where(bad, jnp.zeros_like(v), v), dr)
    dx = jax.tree_util.tree_map(jnp.negative, linear.solve(operator, dr))
    _, dy = jax.jvp(lambda x: retract(y, x, params), (x0,), (dx,))
    return jax.tree_util.tree_map(lambda v: jnp.where(bad, jnp.zeros_like(v), v), dy)


def implicit(
    solve: Callable,
    residual: Callable,
    params,
    *,
    linear,
    retract: Callable | None = None,
    increment: Callable | None = None,
    forward: bool = False,
    exact: Callable | None = None,
) -> Implicit:
    r"""``solve(params) -> Implicit`` (module docstring), differentiable with respect to every
    float leaf of ``params`` by the implicit function theorem.

    - ``residual(y, x, params)``: the residual at ``y ⊕ x``, zero at the solution for ``x = 0``;
    - ``linear``: the linear solver of ``Implicit.operator``
      (:class:`rbo_jax.solvers.AbstractLinearSolver`);
    - ``retract(y, x, params)``: ``y ⊕ x`` (default ``y + x``);
    - ``increment(y, params)``: the zero increment at ``y`` (default ``zeros_like(y)``);
    - ``forward``: the residual's derivative in the parameters as a matrix, by forward mode
      (one pass per parameter that has a tangent), so that reverse mode transposes a matrix
      product: for a residual through a solve that only has forward-mode derivatives
      (:func:`rbo_jax.fast_simulate`), or one whose reverse mode would compile a second
      program (the flutter system, :func:`rbo_jax.hopf_point`: with a matrix ``linear`` and
      no operator from the solve, one forward pass over the unknowns and the parameters gives
      both); by default one Jacobian-vector product;
    - ``exact(params) -> Implicit``: the same solve, run instead of ``solve`` when the solution
      is differentiated, that also returns the exact ``operator`` and ``partials`` (a program
      that has them from derivatives it computes anyway: :func:`rbo_jax.hopf_point`'s third-order
      jet); the tangent is then matrix products and one solve, no program of the residual's
      derivatives. ``solve`` returns neither (``None``).

    ``solve``, ``residual``, ``retract`` and ``increment`` must not close over traced values:
    everything they differentiate or trace (the model, the time) belongs in ``params``. The
    tangent is one compiled program per structure of ``params`` and per ``residual``,
    ``retract``, ``increment`` and ``linear``: pass module-level functions or hashable
    callables (equal for equal problems), so that a second derivative reuses it."""
    return _solution(
        params,
        solve=solve,
        residual=residual,
        linear=linear,
        retract=retract or _add,
        increment=increment or _zeros,
        forward=bool(forward),
        exact=exact,
    )
