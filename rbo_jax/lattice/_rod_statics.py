r"""Static equilibria of a rod: Newton's method on the balance of forces and moments.

The unknowns of a step are, per body, a turn increment $\delta_i$ in its frame and a
displacement $d_i$ (:mod:`._rod_field`); the residual is the body-frame moment and the force on
every body, $R_i = (M_i, F_i)$, zero at an equilibrium. A body couples to its neighbours only,
so the Jacobian is block-tridiagonal ($6\times6$ blocks, from 18 Jacobian-vector products) and
a step costs O(N) (:mod:`._banded`). After a step the turns are composed,
$\theta_i \leftarrow \mathrm{compose}(\theta_i, \delta_i)$ (4.5), so a turn-vector never grows
past $\pi$ and no singular sphere of $Z$ (4.11) is met, whatever the deflection (a rod rolled
into a full circle has a tip turn of $2\pi$: the identity).

Large deflections: ``steps`` load steps, $\lambda = 1/s, 2/s, \dots, 1$ times every load, each
from the previous shape. Derivatives: the solution $x^*(p)$ of $R(x, p) = 0$ is differentiated
by the implicit function theorem, $dx = -J^{-1}\partial_pR\,dp$, as one last Newton step whose
Jacobian is held constant: ``jax.grad`` of a tip deflection with respect to $EI$ costs one
transposed block-tridiagonal solve.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from .. import _programs
from .._validation import _is_traced
from ..kinematics import compose, integrating_tensor_inv
from ._banded import tridiagonal_jacobian, tridiagonal_solve
from ._rod import Rod, RodState
from ._rod_field import body_forces

__all__ = ["RodEquilibrium", "RodEquilibriumStatus", "equilibrium", "solve_equilibrium"]


class RodEquilibriumStatus(eqx.Enumeration):
    """Outcome of :func:`solve_equilibrium`."""

    successful = ""
    not_converged = (
        "Newton's method on the balance of forces and moments did not converge: take more load "
        "steps (steps=...), raise max_steps, or start from a guess nearer the solution."
    )
    non_finite = (
        "Newton's method met a non-finite residual or step (a singular stiffness: the rod may be "
        "at a buckling load, or a parameter is not finite)."
    )
    invalid_parameters = (
        "a parameter of the rod is invalid (a negative stiffness, a zero mass, ...: values "
        "traced at construction, which the constructors could not check); "
        "Rod.parameter_status() names it."
    )


class RodEquilibrium(eqx.Module):
    """The result of :func:`solve_equilibrium`: ``state`` (at rest), ``status``
    (:class:`RodEquilibriumStatus`), ``iterations`` (Newton steps, all load steps together) and
    ``residual`` (max |R| at the end)."""

    state: RodState
    status: RodEquilibriumStatus
    iterations: jax.Array
    residual: jax.Array

    @property
    def ok(self):
        return enum.code(self.status) == enum.code(RodEquilibriumStatus.successful)


def _residual(rod: Rod, theta, r, x, scale):
    r"""The moment and force balance of every body at the increments ``x`` (N+1, 6); on the held
    coordinates of the base their distance from the held values, $d_0 + r_0 - r_{base}$ and
    $\delta_0 + Z^{-T}(	heta_0)(	heta_0 - 	heta_{base})$ (zero there; and so the base's
    position and turn are parameters that the implicit derivatives see)."""
    M, F = body_forces(rod, theta, r, x[:, :3], x[:, 3:], scale=scale)
    turn, pos = rod.free_masks()
    fixed_t = jnp.asarray(~turn, x.dtype)[:, None]
    fixed_p = jnp.asarray(~pos, x.dtype)[:, None]
    to_turn = integrating_tensor_inv(theta[0]).T @ (theta[0] - jnp.asarray(rod.base_turn))
    to_pos = r[0] - jnp.asarray(rod.base_position)
    held_t = x[:, :3] + jnp.zeros_like(x[:, :3]).at[0].set(to_turn)
    held_p = x[:, 3:] + jnp.zeros_like(x[:, 3:]).at[0].set(to_pos)
    return jnp.concatenate([M + fixed_t * held_t, F + fixed_p * held_p], axis=1)


def _newton_step(rod, theta, r, scale):
    x0 = jnp.zeros(theta.shape[:-1] + (6,), theta.dtype)
    fn = lambda x: _residual(rod, theta, r, x, scale)  # noqa: E731
    R = fn(x0)
    blocks = tridiagonal_jacobian(fn, x0)
    return -tridiagonal_solve(*blocks, R), R, blocks


def _apply(theta, r, step):
    return jax.vmap(compose)(theta, step[:, :3]), r + step[:, 3:]


# Newton's step cannot fall below the rounding of the balance: the tolerance is at least this many
# units of the state's machine epsilon (1.2e-5 in float32; 2.2e-14 in float64, below the default)
_RESOLUTION = 100


def _solve(rod: Rod, theta, r, steps: int, rtol, max_steps: int):
    """Newton's method over the load steps: ``(theta, r, iterations, failed, max |R|, blocks)``,
    ``blocks`` the Jacobian of the last step (the implicit function theorem reuses it)."""
    length = jnp.maximum(jnp.max(jnp.abs(r)), 1.0)
    rtol = max(rtol, _RESOLUTION * float(jnp.finfo(theta.dtype).eps))  # float32: 1.2e-5
    nb = theta.shape[0]
    no_blocks = tuple(jnp.zeros((nb, 6, 6), theta.dtype) for _ in range(3))

    def cond(carry):
        it, done, bad = carry[2:5]
        return (~done) & (~bad) & (it < max_steps)

    def one_load(carry, scale):
        theta, r, total, bad, blocks = carry

        def body(c):
            theta, r, it, _, _, _, total, _ = c
            step, R, blocks = _newton_step(rod, theta, r, scale)
            theta, r = _apply(theta, r, step)
            size = jnp.maximum(
                jnp.max(jnp.abs(step[:, :3])), jnp.max(jnp.abs(step[:, 3:])) / length
            )
            bad = ~jnp.all(jnp.isfinite(step)) | ~jnp.all(jnp.isfinite(R))
            return theta, r, it + 1, size <= rtol, bad, jnp.max(jnp.abs(R)), total + 1, blocks

        init = (theta, r, 0, False, bad, jnp.asarray(jnp.inf, theta.dtype), total, blocks)
        theta, r, _, done, bad, res, total, blocks = jax.lax.while_loop(cond, body, init)
        return (theta, r, total, bad | ~done, blocks), res

    scales = jnp.arange(1, steps + 1, dtype=theta.dtype) / steps
    init = (theta, r, 0, False, no_blocks)
    (theta, r, total, failed, blocks), res = jax.lax.scan(one_load, init, scales)
    return theta, r, total, failed, res[-1], blocks


@eqx.filter_custom_jvp
def _solution(rod, theta, r, *, steps, rtol, max_steps):
    return _solve(rod, theta, r, steps, rtol, max_steps)


@_solution.def_jvp
def _solution_jvp(primals, tangents, *, steps, rtol, max_steps):
    r"""The implicit function theorem: $R(x^*(p), p) = 0$ gives $dx = -J^{-1}\partial_pR\,dp$
    in the increments (one block-tridiagonal solve with the Jacobian of the last Newton step,
    a step of at most ``rtol`` away; transposed by reverse mode), turned into
    the tangents of $\theta$ and $r$ through :func:`rbo_jax.compose`. The guess has no
    influence on the solution."""
    rod, theta, r = primals
    out = _solution(rod, theta, r, steps=steps, rtol=rtol, max_steps=max_steps)
    theta_s, r_s = out[0], out[1]
    x0 = jnp.zeros(theta_s.shape[:-1] + (6,), theta_s.dtype)
    L, D, U = (jax.lax.stop_gradient(b) for b in out[5])  # the last Newton step's Jacobian
    _, dR = eqx.filter_jvp(lambda rd: _residual(rd, theta_s, r_s, x0, 1.0), (rod,), (tangents[0],))
    if dR is None:  # the balance does not depend on the differentiated parameters
        dR = jnp.zeros_like(x0)
    dx = -tridiagonal_solve(L, D, U, dR)
    d_theta = jax.jvp(lambda de: jax.vmap(compose)(theta_s, de), (x0[:, :3],), (dx[:, :3],))[1]
    zeros = tuple(jnp.zeros_like(o) if eqx.is_inexact_array(o) else None for o in out[2:5])
    tangent_out = (d_theta, dx[:, 3:]) + zeros + (jax.tree_util.tree_map(jnp.zeros_like, out[5]),)
    return out, tangent_out


def _equilibrium(rod: Rod, theta, r, steps, rtol, max_steps):
    theta_s, r_s, total, failed, res, _ = _solution(
        rod, theta, r, steps=steps, rtol=rtol, max_steps=max_steps
    )
    nonfinite = ~(jnp.all(jnp.isfinite(theta_s)) & jnp.all(jnp.isfinite(r_s)))
    S = RodEquilibriumStatus
    status = jnp.where(
        nonfinite,
        enum.code(S.non_finite),
        jnp.where(failed, enum.code(S.not_converged), enum.code(S.successful)),
    )
    # the parameters that were traced at construction, checked here (Rod.parameter_checks):
    # an invalid rod has no equilibrium, its state NaN
    ok = rod.parameter_status()[0]
    status = jnp.where(ok, status, enum.code(S.invalid_parameters))
    theta_s, r_s = (jnp.where(ok, x, jnp.nan) for x in (theta_s, r_s))
    return RodState.at_rest(theta_s, r_s), status, total, res


_equilibrium_program = _programs.jit(_equilibrium, fast_compile=True)


def solve_equilibrium(
    rod: Rod,
    guess: RodState | None = None,
    *,
    steps: int = 1,
    rtol: float = 1e-10,
    max_steps: int = 50,
) -> RodEquilibrium:
    r"""The static state of ``rod`` under its loads, with a status (module docstring).

    **Arguments:** `guess` (a :class:`RodState`; the straight rod by default), `steps` (load
    steps), `rtol` (Newton stops when no turn increment exceeds it and no displacement exceeds
    it times the rod's size; never below 100 machine epsilons of the state's precision, so
    that a float32 rod, with ``JAX_ENABLE_X64=0``, stops at 1.2e-5), `max_steps` (Newton
    steps per load step).

    Returns a :class:`RodEquilibrium`; a solve that fails reports ``status`` (the state is the
    last iterate), never NaN silently. A rod whose parameters were traced at construction
    (under ``jax.vmap`` or ``jax.grad``) is checked here (:meth:`Rod.parameter_checks`): an
    invalid one gets the status ``invalid_parameters`` and a NaN state. Differentiable with
    respect to every float of ``rod`` by the implicit function theorem (one extra solve).
    """
    if not isinstance(rod, Rod):
        raise TypeError(f"equilibrium: expected a Rod (rbo_jax.lattice.rod), got {type(rod)}.")
    steps, max_steps = int(steps), int(max_steps)
    if steps < 1:
        raise ValueError(f"equilibrium: steps must be >= 1, got {steps}.")
    if max_steps < 1:
        raise ValueError(f"equilibrium: max_steps must be >= 1, got {max_steps}.")
    if not np.isfinite(rtol) or rtol <= 0:
        raise ValueError(f"equilibrium: rtol must be > 0, got {rtol}.")
    guess = rod.straight() if guess is None else guess
    if not isinstance(guess, RodState):
        raise TypeError(f"equilibrium: guess must be a RodState, got {type(guess).__name__}.")
    shape = (rod.n_bodies, 3)
    if tuple(np.shape(guess.theta)) != shape or tuple(np.shape(guess.r)) != shape:
        raise ValueError(
            f"equilibrium: the guess must have theta and r of shape {shape} (one row per body, "
            f"the base first), got {np.shape(guess.theta)} and {np.shape(guess.r)}."
        )
    state, status, total, res = _equilibrium_program(
        rod, jnp.asarray(guess.theta), jnp.asarray(guess.r), steps, float(rtol), max_steps
    )
    return RodEquilibrium(state, enum.from_code(RodEquilibriumStatus, status), total, res)


def equilibrium(rod: Rod, guess: RodState | None = None, **kwargs) -> RodState:
    """The static state of ``rod`` (:func:`solve_equilibrium`'s ``state``), raising an error
    (:func:`equinox.error_if` inside ``jit``) when the solve fails."""
    sol = solve_equilibrium(rod, guess, **kwargs)
    code = enum.code(sol.status)
    if not _is_traced(code) and int(code) == enum.code(RodEquilibriumStatus.successful):
        return sol.state  # called eagerly, and solved: nothing to raise (no eager checks)
    valid = valid_parameters(sol)
    state = checked_parameters(rod, (sol.state.theta, sol.state.r), "lattice.equilibrium", valid)
    message = "lattice.equilibrium: Newton's method failed (see solve_equilibrium's status)."
    return RodState.at_rest(*eqx.error_if(state, ~sol.ok, message))


def valid_parameters(sol: RodEquilibrium):
    """Whether the rod of ``sol`` passed its parameter checks (its status is not
    ``invalid_parameters``): a Python bool for a concrete status, else traced."""
    code, invalid = enum.code(sol.status), enum.code(RodEquilibriumStatus.invalid_parameters)
    return code != invalid if _is_traced(code) else int(code) != int(invalid)


def checked_parameters(rod: Rod, x, caller: str, valid=None):
    """``x`` (a pytree), raising (:func:`equinox.branched_error_if`, inside ``jit`` too) with
    the message of the first of the rod's parameter checks that fails
    (:meth:`Rod.parameter_status`). ``valid``: whether they pass, computed in the caller's
    compiled program: when it is concrete and true nothing runs (the checks op by op, eagerly,
    cost 0.6-0.9 s of small compilations)."""
    if valid is not None and not _is_traced(valid) and bool(valid):
        return x
    ok, which, messages = rod.parameter_status()
    return eqx.branched_error_if(x, ~ok, which, [f"{caller}: {m}" for m in messages])
