r"""``fast_simulate``: the lean DOP853 ensemble integrator of the rigid body oscillator.

The general path is :func:`rbo_jax.simulate` (diffrax: any solver, adjoints, events, the left
form). This one is the hot path of sweeps and fits: the right form (4.55)–(4.56) of the model —
the same vector field, :meth:`rbo_jax.RigidBodyOscillator.right_form` — integrated by DOP853 with
SciPy's tableau, error norm, step-size controller and initial step, so that every trajectory
takes the steps ``scipy.integrate.solve_ivp(method="DOP853")`` takes.

It is written for one trajectory and batched with ``jax.vmap``, as :func:`rbo_jax.simulate`; a
batching rule (:func:`jax.custom_batching.custom_vmap`) then runs the batch as a structure of
arrays on up to 1000 refilled lanes on a CPU, 2¹⁸ on a GPU (``_solve.py``, where the layout is
explained); a batch whose inputs are sharded over several devices (a ``NamedSharding``) runs
each device's share on lanes of its own under ``jax.shard_map`` (``_sharded.py``).
Forward-mode derivatives (``jax.jvp``, ``jax.jacfwd``, also under ``vmap``) are a
:func:`jax.custom_jvp` rule: with respect to model parameters and the initial state, one loop
carries the primal and all tangent directions (``_tangents.py``: ``jax.jacfwd`` does not batch a
differentiated loop, which cost tens of seconds of tracing and compilation); with respect to the
sample times, JAX's JVP of the per-trajectory loop. Reverse mode is :func:`rbo_jax.simulate`'s.

Modules: ``_problem`` (the model as a function of the six state components, the per-step
checks), ``_solve`` (the per-trajectory loop and the refilled lanes), ``_sharded`` (a sharded
batch, a share on each device), ``_tangents`` (the loop of forward-mode derivatives); the step
itself, shape-polymorphic, and its samples are :mod:`rbo_jax.integrate.dop853`'s (the
coefficients: :mod:`rbo_jax.integrate.tableau`), shared with the lattices' DOP853.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from .. import _enumeration as enum
from .._programs import stored
from ..models.rigid_body import RigidBodyOscillator
from ..trajectory import SolveStatus, Trajectory, finish, prepare_inputs, status_code
from ._problem import Problem
from ._sharded import batch_mesh, over_mesh
from ._solve import WAVES, Config, solve_lanes, solve_one
from ._tangents import solve_one_tangents

__all__ = ["fast_simulate"]

LANES = 1000  # the most on a CPU (benchmarks/README.md; fewer for a small batch: _solve.lane_count)
# Lanes on an accelerator: enough to fill a GPU (an H100/H200 holds ~270,000 resident threads);
# each loop iteration is a host-driven sequence of kernel launches, so fewer, wider iterations
# win there (benchmarks/README.md, "GPUs").
ACCELERATOR_LANES = 2**18


def lanes() -> tuple[int, int]:
    """The most refilled lanes of a batch (:func:`._solve.solve_lanes`) on JAX's default backend
    and the waves it is cut into at least (:func:`._solve.lane_count`): :data:`LANES` and
    :data:`._solve.WAVES` on a CPU; :data:`ACCELERATOR_LANES` and 1 on a GPU or TPU (a lane
    per trajectory up to that many: an iteration costs a host round trip there, so few wide
    iterations win)."""
    if jax.default_backend() == "cpu":
        return LANES, WAVES
    return ACCELERATOR_LANES, 1


def _per_trajectory(cfg: Config):
    def one(problem, y0, ts):
        return solve_one(problem, tuple(y0[i] for i in range(6)), ts, cfg)

    return one


@functools.lru_cache(maxsize=64)
def _integrator(cfg: Config):
    """``integrate(problem, y0 (6,), ts) -> (samples (n_ts, 6), status code, accepted steps)``
    with the batching rule and the forward-mode rule (cached per configuration)."""
    one = _per_trajectory(cfg)

    @jax.custom_batching.custom_vmap
    def batched(problem, y0, ts):
        return one(problem, y0, ts)

    @batched.def_vmap
    def _rule(axis_size, in_batched, problem, y0, ts):
        p_batched, y_batched, ts_batched = in_batched
        if not y_batched:
            y0 = jnp.broadcast_to(y0, (axis_size, 6))
        if ts_batched:  # every trajectory has its own times: lockstep per-trajectory loops
            axes = (jax.tree_util.tree_map(lambda b: 0 if b else None, p_batched), 0, 0)

            def local(problem, y0, ts):
                return jax.vmap(one, in_axes=axes)(problem, y0, ts)

        else:

            def local(problem, y0, ts):
                y = tuple(y0[:, i] for i in range(6))
                return solve_lanes(problem, p_batched, y, ts, cfg, *lanes())

        args = (problem, y0, ts)
        mesh = batch_mesh(args)  # inputs sharded over several devices: each runs its share
        if mesh is None:
            return local(*args), (True, True, True)
        return over_mesh(local, mesh, args, (p_batched, True, ts_batched)), (True, True, True)

    integrate = jax.custom_jvp(batched)

    def _jvp(primals, tangents):
        problem, y0, ts = primals
        dproblem, dy0, dts = tangents
        dyn, static = eqx.partition(problem, eqx.is_inexact_array)
        if not isinstance(dts, SymbolicZero) or jax.tree_util.tree_leaves(static):
            # derivatives w.r.t. the times (or a problem with non-float arrays): JAX's JVP of
            # the loop
            return jax.jvp(
                one,
                primals,
                jax.tree_util.tree_map(
                    _instantiate, tangents, is_leaf=lambda t: isinstance(t, SymbolicZero)
                ),
            )
        d_dyn = eqx.filter(
            jax.tree_util.tree_map(
                _instantiate, dproblem, is_leaf=lambda t: isinstance(t, SymbolicZero)
            ),
            jax.tree_util.tree_map(eqx.is_inexact_array, problem),
        )
        samples, code, nacc, dsamples = _tangent_solver(cfg, static)(
            dyn, y0, ts, d_dyn, _instantiate(dy0)
        )
        zero = np.zeros((), jax.dtypes.float0)
        return (samples, code, nacc), (dsamples, zero, zero)

    integrate.defjvp(_jvp, symbolic_zeros=True)
    return integrate


def _instantiate(t):
    """A tangent as an array (zeros for a symbolic zero)."""
    if not isinstance(t, SymbolicZero):
        return t
    if t.dtype == jax.dtypes.float0:
        return np.zeros(t.shape, jax.dtypes.float0)
    return jnp.zeros(t.shape, t.dtype)


@jax.custom_batching.custom_vmap
def _batched_probe(args):
    return np.False_


@_batched_probe.def_vmap
def _batched_probe_rule(axis_size, in_batched, args):
    return np.True_, False


def _batched(args) -> bool:
    """Whether a ``jax.vmap`` being traced batches one of the arrays in ``args`` here, so that
    a :func:`jax.custom_batching.custom_vmap` function called with them now would run its rule,
    not its function: a custom_vmap probe, whose rule answers True as a constant (False, or a
    traced value inside ``jit`` alone, otherwise)."""
    out = _batched_probe(args)
    return not isinstance(out, jax.core.Tracer) and bool(out)


def _tangent_solver(cfg: Config, static):
    """``(dyn, y0, ts, d_dyn, dy0) -> (samples, status, steps, tangents of the samples)`` for
    one tangent direction; batched over directions alone (``jax.jacfwd``) it runs them all in
    one loop (:mod:`._tangents`), otherwise (a batch of trajectories) it is ``vmap`` of that.

    A custom_vmap function is traced when it is called, also where a ``vmap`` then runs its rule
    instead: for ``jax.jacfwd`` (a fit's Jacobian) that traced the loop for one direction (which the
    program does not hold) before the rule traced it for K. Where :func:`_batched` says a vmap
    batches the arguments, the call goes to a custom_vmap with the same rule whose function only
    gives the outputs' shapes (NaN samples, never run: the same vmap runs the rule); elsewhere to
    the one that runs the loop for one direction."""

    def one_direction(dyn, y0, ts, d_dyn, dy0):
        d_dyn = jax.tree_util.tree_map(lambda x: x[None], d_dyn)
        out, code, nacc, dout = solve_one_tangents(dyn, static, y0, ts, cfg, d_dyn, dy0[None])
        return out, code, nacc, dout[0]

    @jax.custom_batching.custom_vmap
    def solver(dyn, y0, ts, d_dyn, dy0):
        return one_direction(dyn, y0, ts, d_dyn, dy0)

    @jax.custom_batching.custom_vmap
    def batched_solver(dyn, y0, ts, d_dyn, dy0):
        nan = jnp.full((ts.shape[0], 6), jnp.nan, ts.dtype)
        failed = jnp.asarray(status_code("nonfinite_state"), jnp.int32)
        return nan, failed, jnp.zeros((), jnp.int32), nan

    def _rule(axis_size, in_batched, dyn, y0, ts, d_dyn, dy0):
        primal_batched = any(jax.tree_util.tree_leaves(in_batched[:3]))
        if primal_batched:
            axes = jax.tree_util.tree_map(lambda b: 0 if b else None, tuple(in_batched))
            return jax.vmap(one_direction, in_axes=axes)(dyn, y0, ts, d_dyn, dy0), (
                True,
                True,
                True,
                True,
            )
        d_dyn, dy0 = jax.tree_util.tree_map(
            lambda x, b: x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x))),
            (d_dyn, dy0),
            tuple(in_batched[3:]),
        )
        return solve_one_tangents(dyn, static, y0, ts, cfg, d_dyn, dy0), (False, False, False, True)

    solver.def_vmap(_rule)
    batched_solver.def_vmap(_rule)

    def call(*args):
        return (batched_solver if _batched(args) else solver)(*args)

    return call


def _solve(cfg: Config, model: RigidBodyOscillator, throw: bool, theta0, Omega0, ts):
    """``(theta samples, Omega samples, status code, accepted steps)`` of one trajectory."""
    problem = Problem(model.right_form(throw))
    samples, code, nacc = _integrator(cfg)(problem, jnp.concatenate([theta0, Omega0]), ts)
    return samples[:, :3], samples[:, 3:], code, nacc


_compiled = stored(eqx.filter_jit(_solve))  # kept traced by the program store, when on


def _run(cfg: Config, model: RigidBodyOscillator, throw: bool, theta0, Omega0, ts):
    """Compiled once per configuration and model structure (``cfg`` is static: Python numbers)
    when called outside ``jax.jit``, with $A^{-1}$ and the state's layout inside the program (no
    small eager programs); inside a transformation, the integrator itself, so that
    ``jax.jvp``/``jax.jacfwd`` trace only the derivative rule, not the primal loop too (an inner
    ``jit`` would trace both)."""
    args = (cfg, model, throw, theta0, Omega0, ts)
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(args)):
        return _solve(*args)
    return _compiled(*args)


def fast_simulate(
    model: RigidBodyOscillator,
    theta0,
    Omega0,
    ts,
    *,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    singular_tol: float = 1e-3,
    throw: bool = True,
) -> Trajectory:
    r"""Integrate the right form (4.55)–(4.56) from $(\theta_0, \Omega_0)$ at ``ts[0]`` and
    sample it at ``ts``, with DOP853 exactly as SciPy's ``solve_ivp(method="DOP853")``.

    **Arguments:** as :func:`rbo_jax.simulate`: the model, the initial turn-vector and right
    angular velocity (3,), strictly increasing sample times ``ts`` (the solve runs from ``ts[0]``
    to ``ts[-1]``); ``rtol``, ``atol`` (Python numbers); ``max_steps``, the budget of step
    attempts; ``singular_tol``; ``throw``.

    **Samples.** ``ts[0]`` is the initial state; a sample inside a step is the method's 7th-order
    dense output (SciPy's ``Dop853DenseOutput``: three more stages on each step that contains
    samples); a sample at the end of a step — ``ts[-1]`` always — is the step's own state. The
    samples do not change the steps (as ``t_eval`` in SciPy).

    **Statuses** (:class:`rbo_jax.SolveStatus`), checked on every accepted step: ``successful``;
    ``max_steps_reached``; ``step_size_collapse`` (the step fell below SciPy's minimum
    ``10 |nextafter(t) − t|``); ``nonfinite_state`` (the error estimate or the state is NaN or
    inf); ``singular_point`` (the turn within ``singular_tol`` of a sphere $|\theta| = 2\pi k$ of
    $Z$ (4.11), or across one, while $\theta\times\Omega \ne 0$); ``domain_error`` (outside the
    domain of the foundation energy, e.g. a barrier of (4.49)); ``nonfinite_input``,
    ``invalid_parameters`` and (traced ``ts`` not finite and strictly increasing)
    ``invalid_times`` before the solve. Samples after a failure are ``inf`` (NaN for invalid
    parameters or times); ``throw=True`` raises the status message instead. With
    ``throw=False`` the compiled program holds no host callback, so JAX's persistent
    compilation cache can keep it.

    **Batches.** ``jax.jit(jax.vmap(lambda c: fast_simulate(model_of(c), ...)))(cs)`` runs the
    batch as a structure of arrays on refilled lanes (module docstring): build the models inside
    the vmapped function, as for :func:`rbo_jax.simulate`. With ``cs`` placed on a
    :class:`jax.sharding.NamedSharding` over several devices (or under ``jax.set_mesh``), every
    device of its mesh runs its share of the batch on lanes of its own, with no communication
    inside the loop, and the outputs are the bits of the same batch on one device; inputs on
    one device run on that device. Forward-mode derivatives (``jax.jvp``,
    ``jax.jacfwd``) with respect to model parameters and the initial state work, also batched;
    step sizes are constants for them. Reverse mode: use :func:`rbo_jax.simulate`.
    """
    if not isinstance(model, RigidBodyOscillator):
        raise TypeError(f"model must be a RigidBodyOscillator, got {type(model).__name__}.")
    try:
        cfg = Config(float(rtol), float(atol), int(max_steps), float(singular_tol))
    except (TypeError, jax.errors.ConcretizationTypeError):
        raise TypeError(
            "fast_simulate: rtol, atol, max_steps and singular_tol must be Python "
            "numbers (they are compiled in); use simulate for traced tolerances."
        )
    if not (cfg.rtol > 0 and cfg.atol > 0 and cfg.max_steps >= 1 and cfg.singular_tol > 0):
        raise ValueError(
            f"fast_simulate: need rtol, atol, singular_tol > 0 and max_steps >= 1, got {cfg}."
        )
    inputs = prepare_inputs(model, theta0, Omega0, ts, rtol, atol, throw)
    theta, Omega, code, nacc = _run(cfg, model, throw, inputs.theta0, inputs.Omega0, inputs.ts)
    status = enum.from_code(SolveStatus, code)
    return finish(model, inputs, theta, Omega, status, nacc, throw)
