r"""The one diffrax solve of the equations of motion, for every model.

:func:`solve` integrates $\dot y = f(t, y)$ with :func:`diffrax.diffeqsolve` from the pieces
diffrax has: the term (the model's field), the solver (default ``Dopri8``), the step-size
controller (default a PID controller of ``rtol``, ``atol``), the adjoint (default
``RecursiveCheckpointAdjoint``) and the events that stop the solve, sampled at ``ts``. It returns
the samples, a :class:`rbo_jax.SolveStatus` (diffrax's result and the events, mapped by
:func:`status_from_solution`) and the accepted steps; failures are statuses, never exceptions
here (the callers raise them with ``throw``: :func:`rbo_jax.trajectory.raise_failure`).

:func:`run` calls a model's solve: inside a transformation (a traced input) the solve itself,
in the caller's program; with concrete inputs the model's compiled program (each model chooses
its own: the program store, XLA's options for small programs), without diffrax's own checks of
the inputs where rbo_jax checked them on the host (:func:`trusted`, :func:`check_start`): those
checks are host callbacks, and JAX's persistent compilation cache keeps no program that holds
one.

The singular spheres $|\theta| = 2\pi k$ of $Z$ (4.11), where a body's equations (4.54)/(4.56)
break down off the plane, stop a solve: :func:`singular_events`.
"""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from .._validation import checked_inputs_trusted, is_traced, library_code_only
from ..kinematics import distance_to_singularity, safe_norm
from ..trajectory import SolveStatus

__all__ = ["check_start", "run", "singular_events", "solve", "status_from_solution", "trusted"]


def status_from_solution(sol, event_names, bad_input=False):
    """The :class:`rbo_jax.SolveStatus` of a diffrax solution: ``successful``,
    ``max_steps_reached``, ``step_size_collapse`` (diffrax's ``dt_min_reached``), the status
    ``event_names[i]`` of the event that stopped it, ``solver_error`` for any other failure;
    ``nonfinite_input`` where ``bad_input``."""
    result = sol.result
    R = diffrax.RESULTS
    status = SolveStatus.successful
    status = SolveStatus.where(result == R.successful, status, SolveStatus.solver_error)
    status = SolveStatus.where(result == R.max_steps_reached, SolveStatus.max_steps_reached, status)
    status = SolveStatus.where(result == R.dt_min_reached, SolveStatus.step_size_collapse, status)
    if sol.event_mask is not None:
        for name, mask in zip(event_names, sol.event_mask):
            status = SolveStatus.where(
                (result == R.event_occurred) & mask, getattr(SolveStatus, name), status
            )
    return SolveStatus.where(bad_input, SolveStatus.nonfinite_input, status)


def _near_singular_cond(transverse, singular_tol, t, y, args, **kwargs):
    theta, trans = transverse(t, y)
    return (distance_to_singularity(theta) < singular_tol) & trans


def _singular_crossing_cond(transverse, t, y, args, **kwargs):
    theta, trans = transverse(t, y)
    n = safe_norm(theta)
    f = jnp.where(n < jnp.pi, jnp.ones_like(n), jnp.sin(0.5 * n))
    return jnp.where(trans, f, jnp.ones_like(n))


def singular_events(transverse, singular_tol):
    r"""Two diffrax event conditions for the singular spheres $|\theta| = 2\pi k$ of Z (4.11).

    ``transverse(t, y) -> (theta, is_transverse)``. The first (boolean) fires when a step ends
    within ``singular_tol`` of a sphere; the second (continuous) fires when a step jumps across
    one: it is $\sin(|\theta|/2)$ (positive on $[\pi, 2\pi)$, sign change at every $2\pi k$)
    clamped to 1 on $[0, \pi)$. Both are disarmed for plane motion ($\theta\times\Omega = 0$),
    which crosses the spheres harmlessly.

    The conditions (and ``transverse``) are ``jax.tree_util.Partial``s of module-level functions,
    not closures: diffrax's ``diffeqsolve`` is ``eqx.filter_jit``-ed and treats functions as
    static, so a fresh closure per call would recompile the solve on every call.
    """
    return (
        jax.tree_util.Partial(_near_singular_cond, transverse, singular_tol),
        jax.tree_util.Partial(_singular_crossing_cond, transverse),
    )


def solve(
    field,
    solver,
    y0,
    ts,
    *,
    max_steps: int,
    rtol=None,
    atol=None,
    controller=None,
    t0=None,
    dt0=None,
    events=(),
    adjoint=None,
    progress: bool = False,
    dense: bool = False,
):
    r"""$\dot y$ = ``field(t, y, args)`` from ``y0`` at ``t0`` (default ``ts[0]``) to ``ts[-1]``,
    sampled at ``ts``: ``(samples, status, accepted steps)``.

    ``solver``: a diffrax solver (``None``: ``Dopri8``); ``controller``: a step-size controller
    (``None``: ``PIDController(rtol, atol)``); ``dt0``: the first step (``None``: diffrax's
    choice); ``events``: ``(name, condition)`` pairs, diffrax event conditions that stop the
    solve with the status ``name``; ``adjoint``: diffrax's (``None``:
    ``RecursiveCheckpointAdjoint``, reverse mode with memory logarithmic in the steps;
    ``diffrax.ForwardMode()`` for ``jax.jvp``); ``progress``: a tqdm progress bar.

    ``dense``: sample ``ts`` after the solve, from its dense output (``SaveAt(dense=True)``,
    the solver's interpolant on each accepted step), instead of inside its loop: the same
    values, but in reverse mode the samples' cotangents flow back through one vectorised
    interpolation rather than through the loop's per-sample saves (half the cost of a gradient
    through thousands of samples, benchmarks/README.md). Memory: ``max_steps`` times the
    solver's stages, so give a ``max_steps`` near the steps needed. Samples after the time a
    stopped solve reached are ``inf``, as diffrax leaves them when it saves at ``ts``."""
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        diffrax.Dopri8() if solver is None else solver,
        t0=ts[0] if t0 is None else t0,
        t1=ts[-1],
        dt0=dt0,
        y0=y0,
        saveat=diffrax.SaveAt(t1=True, dense=True) if dense else diffrax.SaveAt(ts=ts),
        stepsize_controller=(
            diffrax.PIDController(rtol=rtol, atol=atol) if controller is None else controller
        ),
        adjoint=diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint,
        event=diffrax.Event(cond_fn=[cond for _, cond in events]) if events else None,
        max_steps=max_steps,
        throw=False,
        progress_meter=diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter(),
    )
    status = status_from_solution(sol, [name for name, _ in events])
    ys = sol.ys
    if dense:
        reached = ts <= sol.ts[-1]
        ys = jax.tree.map(
            lambda y: jnp.where(reached.reshape((-1,) + (1,) * (y.ndim - 1)), y, jnp.inf),
            jax.vmap(sol.evaluate)(ts),
        )
    return ys, status, sol.stats["num_accepted_steps"]


def trusted(model, *diffrax_objects) -> bool:
    """Whether a compiled solve may leave out diffrax's checks of the inputs (checked on the
    host): the model is rbo_jax's own code (no user function that may call ``eqx.error_if``)
    and the solver, adjoint and controller are diffrax's, not ``StepTo`` (whose own checks of
    its times would go too)."""
    return library_code_only(model) and all(
        x is None
        or (type(x).__module__.split(".")[0] == "diffrax" and not isinstance(x, diffrax.StepTo))
        for x in diffrax_objects
    )


def check_start(t0, dt0, ts):
    """Concrete ``t0`` and ``dt0`` checked on the host (diffrax's own checks of them, and of the
    sample times, are host callbacks, which a trusted solve leaves out: :func:`run`)."""
    if t0 is not None and not is_traced(t0):
        t0 = np.asarray(t0)
        if t0.shape != () or not np.isfinite(t0):
            raise ValueError(f"t0 must be a finite scalar, got {t0.tolist()!r}.")
        if not is_traced(ts) and t0 > np.asarray(ts)[0]:
            raise ValueError(
                f"t0 must not be after the first sample time ts[0] = "
                f"{float(np.asarray(ts)[0])!r}, got {float(t0)!r}."
            )
    if dt0 is not None and not is_traced(dt0):
        dt0 = np.asarray(dt0)
        if dt0.shape != () or not (np.isfinite(dt0) and dt0 > 0):
            raise ValueError(
                f"dt0 must be a finite number > 0 (the solve runs forward in "
                f"time), got {dt0.tolist()!r}."
            )


def run(program, fn, args, checked: bool):
    """``fn(*args)`` where a leaf of ``args`` is traced (the solve in the caller's program);
    otherwise ``program(*args)``, the model's compiled solve, traced without diffrax's checks of
    the inputs where rbo_jax ``checked`` them (:func:`trusted`,
    :func:`rbo_jax._validation.checked_inputs_trusted`)."""
    if any(is_traced(x) for x in jax.tree_util.tree_leaves(args)):
        return fn(*args)
    with checked_inputs_trusted(checked):
        return program(*args)
