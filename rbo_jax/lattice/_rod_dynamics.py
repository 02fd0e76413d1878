r"""The motion of a rod (:class:`rbo_jax.lattice.Rod`): :func:`simulate_rod`, whose samples
are a :class:`RodTrajectory`.

The rod's equations (:func:`rbo_jax.models.rod.rates`: every body's turn and translation, the
couplings' forces and moments, Kelvin–Voigt damping, the loads) are integrated by one of

- diffrax (:func:`rbo_jax.integrate.diffeq.solve`): an explicit Runge–Kutta method
  (``Dopri8``, ``method="explicit"``: the default, ``method="auto"``, for a rod that is not
  stiff, :func:`._rod_midpoint.auto`), an implicit one (``Kvaerno5``,
  ``method="implicit"``), or any diffrax solver;
- the fixed-step Lie-group position Verlet of :mod:`._rod_verlet` (``method="splitting"``: one
  force evaluation per step, the fast one where the stiffest mode holds every explicit step);
- the implicit midpoint rule with block-tridiagonal Newton solves (:mod:`._rod_midpoint`,
  :mod:`rbo_jax.integrate.midpoint`, ``method="midpoint"``): steps set by the motion wanted,
  not by the stiff waves; the default (``method="auto"``) for a stiff rod.

**Compilation.** The vector field is one jitted call (``_rates``: re-tracing it binds one
equation, and its derivatives are cached with it); the forces are
:func:`rbo_jax.models.rod.forces_tangent`'s; the solve is compiled with XLA's options for small
programs (:func:`rbo_jax._programs.small_program_options`); ``Kvaerno5``'s Newton matrix of the
stages is built by ``jax.jacfwd`` and kept as a matrix, the identity at its explicit first stage
(:class:`_JacobianChord`, :class:`_Kvaerno5`). What each of these saved, and what was tried
and not taken: benchmarks/README.md, History.

**Under jax.jit, jax.vmap, jax.grad** every method runs with the statuses in the program
(:func:`simulate_rod`); with concrete inputs the checks run on the host first.
"""

from __future__ import annotations

import contextvars

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.flatten_util import ravel_pytree

from .. import _enumeration as enum
from .. import _programs
from .._validation import is_traced
from ..integrate import diffeq
from ..mechanics import checked_parameters
from ..models.rod import Rod, RodState, energy, kinetic_moment, rates
from ..trajectory import (
    AbstractTrajectory,
    SolveStatus,
    flag,
    per_sample,
    raise_failure,
    times_ok,
    warn_if_float32,
)
from ._rod_midpoint import auto, midpoint_rod
from ._rod_verlet import (
    fixed_step_status,
    verlet,
    verlet_traced,
)

__all__ = ["RodTrajectory", "simulate_rod"]


class RodTrajectory(AbstractTrajectory):
    r"""Samples of a rod's motion (:func:`rbo_jax.lattice.simulate` of a :class:`Rod`): ``ts``
    (T,), ``states`` (a :class:`RodState` with a leading axis T), ``rod``, ``status`` (a
    :class:`rbo_jax.SolveStatus`), ``num_steps``. Derived: ``centreline`` (T, N+1, 3),
    ``energy`` (T,) (conserved without damping, follower loads, dead moments, actuation and
    friction; a rest curvature's at each sample's time),
    ``kinetic_moment`` (T, 3) about the origin (conserved by a free rod without loads); ``ok``,
    ``message``, ``status_name`` as :class:`rbo_jax.Trajectory`'s.

    Returned from ``jax.vmap`` every leaf has the batch axis in front (``status`` and
    ``num_steps`` (B,), ``centreline`` (B, T, N+1, 3), the rod's parameters too): ``ok`` is then
    a (B,) array; ``energy`` and ``kinetic_moment``, which map over the samples of one rod,
    are taken inside the vmapped function or as ``jax.vmap(lambda t: t.energy)(traj)``."""

    ts: jax.Array
    states: RodState
    rod: Rod
    status: SolveStatus
    num_steps: jax.Array

    @property
    def centreline(self):
        return self.states.r

    @property
    def energy(self):
        return per_sample(jax.tree_util.Partial(energy, self.rod), self.states, self.ts)

    @property
    def kinetic_moment(self):
        return per_sample(jax.tree_util.Partial(kinetic_moment, self.rod), self.states)


# the rod's equations as one jitted call (module docstring, Compilation)
_rates = eqx.filter_jit(rates)


# True while diffrax's Kvaerno5 traces a step and has not yet asked for its first matrix
# (_Kvaerno5.step, _JacobianChord.init)
_STEP_START = contextvars.ContextVar("rbo_jax_kvaerno5_step_start", default=False)


class _JacobianChord(diffrax.VeryChord):
    r"""diffrax's chord method (Newton's method with one matrix per step) for the stages of
    ``Kvaerno5``, its matrix $J = \partial g/\partial f$ of a stage's relation
    $g(f) = f - F(y_0 + \gamma h\,f)$ built by ``jax.jacfwd`` over the flattened state and
    handed to diffrax's own ``init`` as the linear model $f \mapsto J f$, whose linearisation
    and LU are those of $J$ (its matrix $J\cdot E$, exact). diffrax's ``init`` linearises $g$
    itself and keeps it as a function with its residuals, carried through the stages and
    traced again where it is used: the same matrix to rounding, a larger program
    (benchmarks/README.md, History). Tested against diffrax's ``Kvaerno5`` (1.5e-11 of the largest
    state at rtol 1e-10); ``jax.grad`` through it equals diffrax's (the matrix is held constant,
    as diffrax's is).

    The first matrix of a step (diffrax asks for it before the stages, at $\gamma = 0$ for
    the explicit first stage, where $J = I$ exactly; ``Kvaerno5`` replaces it at its second
    stage) is the identity, without the field's Jacobian: diffrax's ``runge_kutta.py`` builds
    it from the relation at a zero diagonal, which cost a second dense Jacobian in the
    compiled program."""

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        if "init_state" in options:  # the stages' calls, with the matrix of the step
            return super().init(fn, y, args, options, f_struct, aux_struct, tags)
        flat, unravel = ravel_pytree(y)
        if _STEP_START.get():  # the step's first matrix, at a zero diagonal: the identity
            _STEP_START.set(False)
            J = jnp.eye(flat.size, dtype=flat.dtype)
        else:
            J = jax.jacfwd(lambda x: ravel_pytree(fn(unravel(x), args)[0])[0])(flat)
            J = lax.stop_gradient(J)

        def model(x, a):
            return unravel(J @ ravel_pytree(x)[0]), None

        return super().init(model, y, args, options, f_struct, aux_struct, tags)


class _Kvaerno5(diffrax.Kvaerno5):
    """diffrax's ``Kvaerno5`` whose step marks its start for :class:`_JacobianChord` (the
    first matrix it asks for is the identity of its explicit first stage)."""

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        token = _STEP_START.set(True)
        try:
            return super().step(terms, t0, t1, y0, args, solver_state, made_jump)
        finally:
            _STEP_START.reset(token)


def _solve_program(rod, state0, ts, solver, rtol, atol, max_steps, dt0, adjoint=None):
    """The diffrax solve: ``(states at ts, status code, accepted steps)``; ``adjoint``:
    diffrax's (``diffrax.ForwardMode()`` for ``jax.jacfwd``, as
    :func:`rbo_jax.lattice.fit_trajectory`)."""

    def field(t, y, args):
        return _rates(rod, y, 1.0, t)

    ys, status, steps = diffeq.solve(
        field,
        solver,
        state0,
        ts,
        rtol=rtol,
        atol=atol,
        dt0=dt0,
        max_steps=max_steps,
        adjoint=adjoint,
    )
    return ys, enum.code(status), steps


_solve = _programs.jit(_solve_program, small=True)


# keyword arguments named as rbo_jax.simulate's: each public solver spells out its own signature
def simulate_rod(
    rod: Rod,
    state0: RodState,
    ts,
    *,
    method: str = "auto",
    solver: diffrax.AbstractSolver | None = None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    dt0: float | None = None,
    dt: float | None = None,
    throw: bool = True,
) -> RodTrajectory:
    r"""The motion of ``rod`` from ``state0`` sampled at ``ts`` (module docstring).

    ``method``:

    - ``"auto"`` (default): ``"midpoint"`` for a stiff rod, whose explicit stable step
      (:func:`._rod_verlet.stable_step`, set by its stiffest stretch and shear waves) is below
      the midpoint rule's step (``dt``), else ``"explicit"``; ``"explicit"`` with a
      ``solver``. Under ``jax.grad`` and ``jax.jvp`` the choice is made from the primal values
      (the derivative is that of the same solve); under ``jax.jit`` and ``jax.vmap``, where
      the values are unknown before the program runs, ``"midpoint"``;
    - ``"midpoint"``: the implicit midpoint rule (:mod:`rbo_jax.integrate.midpoint`): fixed
      steps of at most ``dt`` (default the shortest interval of ``ts``, and at most a
      thousandth of its span), second order, A-stable, the energy of a linear elastic rod kept
      to the Newton tolerance at any step, the stiff waves neither limiting the step nor losing
      their energy; a mode of frequency $\omega$ lags by a relative $(\omega\,dt)^2/12$, so
      ``dt`` is chosen for the slowest motion wanted; each step's Newton iterations use the
      block-tridiagonal matrix $I - \tfrac{dt}{2}J$ (O(N) a step) and stop when their error
      is estimated within ``atol + rtol |y|`` (the energy drifts by about that much a step). A
      ``dt`` longer than an interval of ``ts`` lays the steps on a uniform grid of their own
      and interpolates the samples (cubic Hermite, error $O(dt^3)$ like a step's), so the
      cost follows ``dt``, not the samples wanted; an interpolated sample's energy is not the
      rule's (its stiff gaps' strains carry the interpolation's error); with traced ``ts``
      the steps stay within the intervals;
    - ``"explicit"`` (diffrax ``Dopri8``), ``"implicit"`` (``Kvaerno5``, a dense Newton
      matrix), or any diffrax ``solver``: adaptive steps to ``rtol``, ``atol``;
    - ``"splitting"``: the Lie-group position Verlet of :mod:`._rod_verlet` (fixed steps of at
      most ``dt``, default its stable step from the stiffnesses and masses; one force
      evaluation per step; symplectic on a conservative rod).

    ``rtol``, ``atol``: the step-size controller's tolerances (``"midpoint"``: its Newton's);
    ``dt0``: the first step of the adaptive methods (default a tenth of the first interval of
    ``ts``); ``max_steps``: the most steps (``"splitting"``: checked before the run). A failed
    solve (``"splitting"``: a non-finite state, the step too long for stability) raises with
    ``throw=True``, else reports ``status`` (samples after the failure are ``inf``).

    **Under jax.jit, jax.vmap, jax.grad.** Every method runs inside a transformation: a leaf
    of ``rod`` (e.g. a rod built from a traced ``bending``), ``state0``, ``ts``, ``dt`` or
    ``dt0`` may be traced (``rtol``, ``atol``, ``max_steps``, ``method`` and ``throw`` stay
    Python values). Nothing is then checked on the host: the step of ``"splitting"``, its
    counts per interval and their total are computed in the program, and a total above
    ``max_steps`` gives the status ``max_steps_reached``, a step that is not finite and > 0
    ``invalid_parameters``, traced ``ts`` that are not finite and strictly increasing
    ``invalid_times`` (their samples NaN), each sample after a failure ``inf``; with
    ``throw=True`` a failure raises its message through :func:`equinox.error_if`. Under
    ``jax.vmap`` every member runs its own steps (those of its own call), and ``status``,
    ``num_steps`` are batched. ``jax.grad`` (reverse mode) through ``"splitting"`` needs loops
    of fixed length: a ``dt`` given as a number with concrete, evenly spaced ``ts`` (equal
    counts in every interval); forward mode (``jax.jvp``, ``jax.jacfwd``) works everywhere.
    The explicit and implicit methods differentiate by diffrax's adjoint. A concrete ``ts``
    that is not strictly increasing and a concrete ``dt`` outside (0, inf) still raise a
    ``ValueError``."""
    _check_state(rod, state0)
    traced = any(is_traced(x) for x in jax.tree_util.tree_leaves((rod, state0, ts, dt, dt0)))
    ts, bad_times, staged = _times(ts, throw, traced)
    state0 = jax.tree_util.tree_map(jnp.asarray, state0)
    if method == "auto":
        method = auto(rod, state0, ts, solver, traced, dt)
    if method == "midpoint" and solver is None:
        states, status, steps, messages = midpoint_rod(
            rod, state0, ts, bad_times, dt, rtol, atol, max_steps, staged
        )
    elif method == "splitting" and solver is None:
        if max_steps == 100_000:  # the adaptive methods' default; fixed steps are cheap: more room
            max_steps = 10_000_000
        run = _splitting_traced if staged else _splitting
        states, status, steps, messages = run(rod, state0, ts, bad_times, dt, max_steps)
    else:
        states, status, steps, messages = _diffrax(
            rod, state0, ts, bad_times, method, solver, rtol, atol, max_steps, dt0
        )
    if is_traced(ts):  # bad traced times: no result
        status, states = flag(status, states, bad_times, "invalid_times", jnp.nan)
        messages["invalid_times"] = _TIMES.removeprefix("lattice.simulate: ")
    if not is_traced(enum.code(status)):  # concrete: the host raises (a concrete rod is checked)
        name = enum.name(status)
        if throw and name != "successful":
            raise RuntimeError("lattice.simulate: " + messages[name])
        return RodTrajectory(jnp.asarray(ts), states, rod, status, steps)
    # the rod's parameters that were traced at construction, checked now (Rod.parameter_checks)
    ok = rod.parameter_status()[0]
    status, states = flag(status, states, ~ok, "invalid_parameters", jnp.nan)
    if throw:
        states = checked_parameters(rod, states, "lattice.simulate", ok)
        messages = [
            "lattice.simulate: " + (messages.get(n) or SolveStatus[getattr(SolveStatus, n)])
            for n in enum.names(SolveStatus)
        ]
        states = raise_failure(states, status, throw, messages)
    return RodTrajectory(jnp.asarray(ts), states, rod, status, steps)


_TIMES = "lattice.simulate: ts must be a strictly increasing 1-D array of >= 2 times."


def _check_state(rod, state0):
    """A :class:`RodState` with one row per body in every field."""
    if not isinstance(state0, RodState):
        raise TypeError(
            f"lattice.simulate(rod, state0, ts): state0 must be a RodState (e.g. "
            f"rod.straight() or lattice.equilibrium(rod)), got {type(state0).__name__}."
        )
    shape = (rod.n_bodies, 3)
    for name in ("theta", "r", "Omega", "v"):
        if tuple(np.shape(getattr(state0, name))) != shape:
            raise ValueError(
                f"lattice.simulate: state0.{name} must have shape {shape}, got "
                f"{np.shape(getattr(state0, name))}."
            )


def _times(ts, throw, traced):
    """``(ts, bad, staged)``. With no traced input, ``ts`` checked now (a ``ValueError``) as a
    JAX array, unless the checks are traced themselves (inside ``jax.jit`` every operation is
    staged). Otherwise (``staged``): concrete ``ts`` checked now as a NumPy array (the
    splitting counts its steps on the host); traced ones with :func:`equinox.error_if` when
    ``throw``, else flagged by ``bad`` (not finite and strictly increasing)."""
    dtype = jnp.result_type(float)
    if not traced:
        ts = jnp.asarray(ts, dtype=dtype)
        if ts.ndim != 1 or ts.shape[0] < 2:
            raise ValueError(_TIMES)
        increasing = jnp.all(jnp.diff(ts) > 0)
        if not is_traced(increasing):
            if not bool(increasing):
                raise ValueError(_TIMES)
            return ts, np.bool_(False), False
    if not is_traced(ts):
        ts = np.asarray(ts, dtype=dtype)
        if ts.ndim != 1 or ts.shape[0] < 2 or not np.all(np.diff(ts) > 0):
            raise ValueError(_TIMES)
        return ts, np.bool_(False), True
    ts = jnp.asarray(ts, dtype=dtype)
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(_TIMES)
    bad = ~times_ok(ts)
    if throw:
        ts = eqx.error_if(ts, bad, _TIMES)
    return ts, bad, True


def _solver(method, solver):
    """The diffrax solver of ``method`` (``solver`` when given)."""
    if solver is not None:
        return solver
    if method == "explicit":
        return diffrax.Dopri8()
    if method == "implicit":
        return _Kvaerno5(root_finder=diffrax.with_stepsize_controller_tols(_JacobianChord)())
    raise ValueError(
        f"lattice.simulate: method must be 'auto', 'midpoint', 'explicit', 'implicit' or "
        f"'splitting' for a rod, got {method!r}."
    )


def _diffrax(rod, state0, ts, bad_times, method, solver, rtol, atol, max_steps, dt0):
    """The explicit and implicit methods: ``(states, status, steps, messages)``
    (:func:`rbo_jax.integrate.diffeq.run`: diffrax's checks of the inputs left out where the
    host checked them)."""
    solver = _solver(method, solver)
    run_ts = jnp.where(bad_times, jnp.zeros_like(ts), ts) if is_traced(ts) else ts
    if dt0 is None:
        dt0 = (run_ts[1] - run_ts[0]) / 10.0 if is_traced(ts) else float(ts[1] - ts[0]) / 10.0
    elif is_traced(dt0):
        dt0 = jnp.where(bad_times, 1.0, jnp.asarray(dt0, dtype=ts.dtype))
    else:
        diffeq.check_start(None, dt0, ts)
        dt0 = float(dt0)
    warn_if_float32(state0.r.dtype, rtol, atol)  # a float32 rod (JAX_ENABLE_X64=0)
    args = (rod, state0, jnp.asarray(run_ts), solver, float(rtol), float(atol), int(max_steps), dt0)
    states, code, steps = diffeq.run(_solve, _solve, args, diffeq.trusted(rod, solver))
    messages = {
        n: f"the rod's solve failed: {getattr(SolveStatus, n)!r}."
        for n in ("max_steps_reached", "solver_error")
    }
    return states, enum.from_code(SolveStatus, code), steps, messages


_NONFINITE = (
    "the rod's state became non-finite (method='splitting'{}): the step is past the stability "
    "limit or the motion blew up; pass a smaller dt."
)


def _splitting(rod, state0, ts, bad_times, dt, max_steps):
    """``method="splitting"`` with concrete inputs: :func:`._rod_verlet.verlet` (the steps
    counted on the host)."""
    states, ok, steps, dt = verlet(rod, state0, ts, dt, max_steps)
    status = SolveStatus.successful if bool(ok) else SolveStatus.solver_error
    messages = {"solver_error": _NONFINITE.format(f", dt = {dt:.3g} s")}
    return states, status, jnp.asarray(steps), messages


def _splitting_traced(rod, state0, ts, bad_times, dt, max_steps):
    """``method="splitting"`` under a transformation: :func:`._rod_verlet.verlet_traced`, the
    steps and their checks in the program."""
    run_ts = jnp.where(bad_times, jnp.zeros_like(ts), ts) if is_traced(ts) else ts
    states, ok, steps, _, too_many, bad_dt = verlet_traced(rod, state0, run_ts, dt, max_steps)
    what = "dt" if dt is not None else "the default step (from the stiffnesses and masses)"
    status, messages = fixed_step_status(
        ok, too_many, bad_dt, "splitting", max_steps, _NONFINITE.format(""), what
    )
    return states, status, steps, messages
