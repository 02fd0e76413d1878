r"""Linear stability and motion of a rod (:mod:`._rod`).

**Linearisation.** About an equilibrium $(\theta^*, r^*)$ the state is perturbed by turn
increments $\delta_i$ in the bodies' frames and displacements $d_i$ (:mod:`._rod_field`), with
the first-order system

$$\dot\delta = Z^T(\delta)\cdot\Omega, \quad \dot d = v, \quad
  A\cdot\dot\Omega = M - \Omega\times A\cdot\Omega, \quad m\,\dot v = F,$$

whose Jacobian at zero (forward-mode autodiff, the held coordinates of the base left out)
holds the mass, the Kelvin–Voigt damping, the gyroscopic terms and the stiffness, non-symmetric
under a follower load (circulatory forces): the eigenvalues $p$ of :func:`spectrum` decide
stability by Lyapunov's first method as (4.69) does for one body. :func:`critical_load` finds
the smallest load at which an eigenvalue crosses into $\mathrm{Re}\,p > 0$: divergence
(Euler's buckling) or flutter (Beck's column, Ziegler's pendulum).

**Motion.** :func:`simulate` integrates the rod's equations (:func:`._rod_field.rates`) with
diffrax: an explicit Runge–Kutta method (``Dopri8``, default) or, for the stiff stretch and
shear waves of a slender rod, an implicit one (``Kvaerno5``); or, with
``method="splitting"``, the fixed-step Lie-group position Verlet of :mod:`._rod_verlet` (one
force evaluation per step: the fast one where the stiffest mode holds every explicit step).

**Compilation** of the diffrax solve (issue 32; the vibrating cantilever of
benchmarks/bench_rod.py, one pinned core, first call less the best warm call, fresh processes,
before and after side by side): Kvaerno5 31.2 -> 10.8 s (n = 5) and 31.3 -> 11.6 s (n = 10),
its warm calls 1.88 -> 1.61 s and 1.48 -> 1.20 s; Dopri8 4.8 -> 2.6 s and 4.9 -> 2.7 s, warm
1.89 -> 1.40 s and 2.04 -> 1.55 s. Before, Kvaerno5's program (n = 5) took 10.6 s to trace
(diffrax traces its step three times and re-evaluates the closure-converted vector field and
the linearisations of its root finder), 0.7 s to lower and 19.5 s to compile (59.5k lines of
compiled HLO); now 1.7 s, 0.4 s and 8.4 s (47.2k lines). The changes, each measured on top of
the ones before it:

- the vector field is one jitted call (``_rates``): re-tracing it binds one equation, and its
  derivatives are cached with it (Kvaerno5's tracing 10.6 -> 4.3 s, Dopri8's 1.15 -> 0.72 s);
- the program is compiled with :func:`rbo_jax._programs.small_program_options` (XLA's
  element-wise emitters): Kvaerno5 19.4 -> 13.3 s, Dopri8 3.6 -> 2.2 s to compile, their runs
  1.85 s either way and 1.89 -> 1.76 s. LLVM -O0 (``fast_compile_options``, as :func:`spectrum`
  and :func:`rbo_jax.lattice.equilibrium`) compiled Kvaerno5 in 5.6 s but ran 2.3x slower
  (1.86 -> 4.24 s), Dopri8 2.5x (1.84 -> 4.72 s); -O1 without XLA's while-loop passes: 7.9
  instead of 9.0 s for Kvaerno5, but Dopri8's run 1.38 -> 1.95 s. Not taken;
- :func:`._rod_field.rates` evaluates the forces by :func:`._rod_field.forces_tangent`
  (Kvaerno5 19.2 -> 14.2 s, Dopri8 3.2 -> 2.7 s, first call less warm call);
- the stages' Newton matrix is built by ``jax.jacfwd`` and kept as a matrix
  (:class:`_JacobianChord`): Kvaerno5 14.2 -> 11.9 s; its tracing 1.9 s (4.3 s with diffrax's
  root finder and the first change only).

diffrax's ``scan_kind="lax"`` and ``"bounded"`` (its stages are one traced copy already, in a
loop) changed nothing (XLA's compilation 19.2 and 20.3 s against 19.5 s). Kvaerno5's program
held two dense Jacobians of the field, each a 72-lane ``jvp`` (n = 5) that XLA compiles in
~3.3 s (9.0 s with both, 2.4 s with neither; XLA's HLO passes 2.7 s of the 9.0, its code
generation 6.3 s): one before the stages, which diffrax builds from the stage relation at a
zero diagonal (the identity, for the explicit first stage; Kvaerno5 replaces it at its second
stage), and the one of the second stage. The first is now the identity itself
(:class:`_JacobianChord`, :class:`_Kvaerno5`): measured on 2026-11-28 on a machine 1.6x
slower than the day before, alternating with the tree before it, first call less warm call
18.3-18.4 -> 12.6-12.8 s (n = 5) and 17.2-19.3 -> 12.8-13.1 s (n = 10), and the warm calls
faster too, since every step computed both: 0.66-0.72 -> 0.40 s and 0.61-0.63 -> 0.32-0.35 s.
What is left is the second stage's Jacobian (the program's XLA compilation 8.6 s that day):
``jax.lax.map`` of the linearised field over the columns, or ``jax.vmap`` of it, instead of
``jax.jacfwd`` compiled alike (12.2 and 12.4 s against 13.4 s, first call less warm call).
Without any Jacobian (the Newton matrix the identity: the wrong solver, built only to time the
build) the program (n = 5) still takes 2.0 s to trace, 0.3 s to lower and 3.5 s to compile,
5.8 s: diffrax's step and one copy of the field are above the 5 s target by themselves
(measured 2026-11-28, issue 32). Also measured that day, alternating with this tree, and not
taken: the Jacobian's columns from 36 directional derivatives by the band of the rod (bodies
$i \equiv k \pmod 3$ seeded together; the same matrix to the bit where taken one lane at a
time): the compilation within the noise (n = 5: 9.6-11.6 against 11.3-12.3 s), the warm calls
faster (0.41-0.54 against 0.79-0.90 s at n = 10); forward differences of the field: 2-3 s
less to compile, but states that move by 2e-6; XLA's ``xla_llvm_disable_expensive_passes``,
one code-generation split, no inlining before the split: 7.2-8.0 s against 6.9-7.4 s.
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
from .._validation import _is_traced
from ..kinematics import Turn
from ..maps import critical_value
from ..trajectory import SolveStatus, _AbstractSolved, times_ok, warn_if_float32
from ._rod import Rod, RodState
from ._rod_field import body_forces, energy, kinetic_moment, rates
from ._rod_statics import checked_parameters, solve_equilibrium, valid_parameters
from ._rod_verlet import verlet, verlet_traced

__all__ = ["RodTrajectory", "critical_load", "linearize", "simulate_rod", "spectrum"]


def _free_index(rod: Rod):
    turn, pos = rod.free_masks()
    return np.flatnonzero(turn), np.flatnonzero(pos)


def linearize(rod: Rod, state: RodState):
    r"""The Jacobian of the first-order system at the equilibrium ``state`` (module docstring):
    a square matrix over ``[delta, d, Omega, v]`` of the bodies that move (the base's held
    coordinates left out)."""
    it, ip = _free_index(rod)
    theta, r = jnp.asarray(state.theta), jnp.asarray(state.r)
    nt, npos = 3 * len(it), 3 * len(ip)
    A = jnp.asarray(rod.inertia)
    m = jnp.asarray(rod.mass)

    def field(x):
        delta = jnp.zeros_like(theta).at[it].set(x[:nt].reshape(-1, 3))
        d = jnp.zeros_like(r).at[ip].set(x[nt : nt + npos].reshape(-1, 3))
        Om = jnp.zeros_like(theta).at[it].set(x[nt + npos : 2 * nt + npos].reshape(-1, 3))
        v = jnp.zeros_like(r).at[ip].set(x[2 * nt + npos :].reshape(-1, 3))
        M, F = body_forces(rod, theta, r, delta, d, Om, v)
        AOm = jnp.einsum("bij,bj->bi", A, Om)
        Om_dot = jnp.linalg.solve(A, (M - jnp.cross(Om, AOm))[..., None])[..., 0]
        delta_dot = jax.vmap(lambda de, w: Turn(de).ZT(w))(delta, Om)
        v_dot = F / m[:, None]
        return jnp.concatenate(
            [
                delta_dot[it].ravel(),
                v[ip].ravel(),
                Om_dot[it].ravel(),
                v_dot[ip].ravel(),
            ]
        )

    return jax.jacfwd(field)(jnp.zeros(2 * (nt + npos), theta.dtype))


def _sorted_spectrum(rod, state):
    """The sorted eigenvalues and whether the rod's parameters pass their checks (computed in
    this program: checked eagerly, op by op, they cost 0.6-0.9 s of small compilations)."""
    p = jnp.linalg.eigvals(linearize(rod, state))
    return p[jnp.lexsort((p.imag, p.real))], rod.parameter_status()[0]


_spectrum = _programs.jit(_sorted_spectrum, fast_compile=True)


def spectrum(rod: Rod, state: RodState | None = None, **equilibrium_kwargs):
    r"""The eigenvalues of the linearisation at the equilibrium ``state`` (solved by
    :func:`rbo_jax.lattice.equilibrium` when ``None``, with ``equilibrium_kwargs``), sorted by
    real then imaginary part: $2\cdot 6N$ of them for a clamped rod of $N$ bodies past the base.
    Mass, damping, gyroscopic and circulatory (follower) terms included. A rod whose
    parameters were traced at construction is checked here: an invalid one raises, naming the
    parameter (:meth:`Rod.parameter_status`)."""
    if not isinstance(rod, Rod):
        raise TypeError(f"spectrum: expected a Rod, got {type(rod).__name__}.")
    if state is None:
        sol = solve_equilibrium(rod, **equilibrium_kwargs)
        theta = checked_parameters(rod, sol.state.theta, "lattice.spectrum", valid_parameters(sol))
        state = RodState.at_rest(
            eqx.error_if(theta, ~sol.ok, "lattice.spectrum: no equilibrium found."), sol.state.r
        )
    p, ok = _spectrum(rod, state)
    return checked_parameters(rod, p, "lattice.spectrum", ok)


def _abscissa_ratio(p):
    return jnp.max(p.real) / jnp.maximum(jnp.max(jnp.abs(p)), 1.0)


def critical_load(
    rod_fn,
    load_max: float,
    *,
    load_min: float = 0.0,
    guess: RodState | None = None,
    n_scan: int = 32,
    n_bisect: int = 40,
    rtol: float = 1e-9,
    steps: int = 1,
):
    r"""The smallest load $P \in (P_{min}, P_{max}]$ at which the equilibrium of ``rod_fn(P)``
    (a :class:`Rod` for every load value, traced) loses stability: the spectral abscissa of
    :func:`spectrum` exceeds ``rtol`` × the largest $|p|$ (flutter or divergence). The largest
    $|p|$ of a rod is a stiff stretch or shear mode, many times the bending frequencies, and
    the rounding of the eigenvalues grows with it: the default ``rtol`` = 1e-9 stays clear of
    it on undamped rods (Euler's, Beck's and Pflüger's columns, tested). A small damping makes
    the growth near its boundary slow, and ``rtol`` must be smaller to see it: Ziegler's
    pendulum with hinge dampers b = 0.01 c·s needs 1e-14 (its rounding was 1.3e-16 of
    max |p|; tested). Kelvin–Voigt damping on a stiff shear or stretch with a small rotary
    inertia gives modes as fast as $\eta\kappa GA/(\rho I h^2)$, whose rounding hides the slow
    ones (Beck's column with $\eta = 10^{-3}$ on every resultant, $\kappa GA = EA = 10^6$,
    $\rho I = 10^{-8}$: 18.85 instead of 11.05): damp bending only there
    (``shear_damping=0`` in :func:`rod`). A scan at
    ``n_scan`` loads, then ``n_bisect`` bisections (:func:`rbo_jax.critical_value`); ``inf`` if
    the rod stays stable. Equilibria by Newton from ``guess`` (the straight rod) in ``steps``
    load steps; a load whose equilibrium fails counts as unstable. NaN if the rod's parameters
    are invalid at ``load_min`` or ``load_max`` (values traced at construction, e.g. a
    negative stiffness in a ``jax.vmap``: :meth:`Rod.parameter_status`)."""

    def run(lo, hi):
        def unstable(P):
            rod = rod_fn(P)
            sol = solve_equilibrium(rod, guess, steps=steps)
            ratio = _abscissa_ratio(jnp.linalg.eigvals(linearize(rod, sol.state)))
            return (ratio > rtol) | ~sol.ok

        value = critical_value(unstable, lo, hi, n_scan=n_scan, n_bisect=n_bisect)
        return jnp.where(valid_between(rod_fn, lo, hi), value, jnp.nan)

    if not load_max > load_min:
        raise ValueError(f"critical_load: load_max ({load_max}) must exceed load_min ({load_min}).")
    return _programs.jit(run, fast_compile=True)(
        jnp.asarray(float(load_min)), jnp.asarray(float(load_max))
    )


def valid_between(rod_fn, lo, hi):
    """Whether the rods ``rod_fn(lo)`` and ``rod_fn(hi)`` pass their parameter checks
    (:meth:`Rod.parameter_status`; the bounds of a critical load's search)."""
    return rod_fn(lo).parameter_status()[0] & rod_fn(hi).parameter_status()[0]


class RodTrajectory(_AbstractSolved):
    r"""Samples of a rod's motion (:func:`rbo_jax.lattice.simulate` of a :class:`Rod`): ``ts``
    (T,), ``states`` (a :class:`RodState` with a leading axis T), ``rod``, ``status`` (a
    :class:`rbo_jax.SolveStatus`), ``num_steps``. Derived: ``centreline`` (T, N+1, 3),
    ``energy`` (T,) (conserved without damping, follower loads and dead moments),
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
        return jax.vmap(lambda s: energy(self.rod, s))(self.states)

    @property
    def kinetic_moment(self):
        return jax.vmap(lambda s: kinetic_moment(self.rod, s))(self.states)


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
    traced again where it is used: the same matrix to rounding, a larger program (module
    docstring, Compilation). Tested against diffrax's ``Kvaerno5`` (1.5e-11 of the largest
    state at rtol 1e-10); ``jax.grad`` through it equals diffrax's (the matrix is held constant,
    as diffrax's is).

    The first matrix of a step (diffrax asks for it before the stages, at $\gamma = 0$ for
    the explicit first stage, where $J = I$ exactly; ``Kvaerno5`` replaces it at its second
    stage) is the identity, without the field's Jacobian: diffrax's ``runge_kutta.py`` builds
    it from the relation at a zero diagonal, which cost a second dense Jacobian in the
    compiled program (module docstring, Compilation)."""

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
    """The diffrax solve: ``(states at ts, code, accepted steps)``; ``adjoint``: diffrax's
    (``diffrax.ForwardMode()`` for ``jax.jacfwd``, as :func:`rbo_jax.lattice.fit_trajectory`)."""
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
    term = diffrax.ODETerm(lambda t, y, args: _rates(rod, y))
    sol = diffrax.diffeqsolve(
        term,
        solver,
        ts[0],
        ts[-1],
        dt0,
        state0,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps,
        throw=False,
        adjoint=adjoint,
    )
    ok = sol.result == diffrax.RESULTS.successful
    steps = sol.result == diffrax.RESULTS.max_steps_reached
    code = jnp.where(ok, 0, jnp.where(steps, 1, 2))
    return sol.ys, code, sol.stats["num_accepted_steps"]


_solve = _programs.jit(_solve_program, small=True)


# keyword arguments named as rbo_jax.simulate's: each public solver spells out its own signature
def simulate_rod(
    rod: Rod,
    state0: RodState,
    ts,
    *,
    method: str = "explicit",
    solver: diffrax.AbstractSolver | None = None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    dt0: float | None = None,
    dt: float | None = None,
    throw: bool = True,
) -> RodTrajectory:
    r"""The motion of ``rod`` from ``state0`` sampled at ``ts`` (module docstring).

    ``method``: ``"explicit"`` (diffrax ``Dopri8``, default), ``"implicit"`` (``Kvaerno5``,
    for stiff stretch and shear), or ``"splitting"``: the Lie-group position Verlet of
    :mod:`._rod_verlet` (fixed steps of at most ``dt``, default its stable step from the
    stiffnesses and masses; one force evaluation per step; symplectic on a conservative rod);
    or any diffrax ``solver``. ``rtol``, ``atol``: the step-size controller's tolerances;
    ``max_steps``: the most steps (``"splitting"``: checked before the run). A failed solve
    (``"splitting"``: a non-finite state, the step too long for stability) raises with
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
    if any(_is_traced(x) for x in jax.tree_util.tree_leaves((rod, state0, ts, dt, dt0))):
        return _simulate_traced(
            rod, state0, ts, method, solver, rtol, atol, max_steps, dt0, dt, throw
        )
    ts = jnp.asarray(ts, dtype=jnp.result_type(float))
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(_TIMES)
    increasing = jnp.all(jnp.diff(ts) > 0)
    if _is_traced(increasing):  # inside jax.jit with concrete inputs: every operation is staged
        return _simulate_traced(
            rod, state0, ts, method, solver, rtol, atol, max_steps, dt0, dt, throw
        )
    if not bool(increasing):
        raise ValueError(_TIMES)
    if method == "splitting" and solver is None:
        return _splitting(rod, state0, ts, dt, max_steps, throw)
    solver = _solver(method, solver)
    dt0 = float(ts[1] - ts[0]) / 10.0 if dt0 is None else float(dt0)
    state0 = jax.tree_util.tree_map(jnp.asarray, state0)
    warn_if_float32(state0.r.dtype, rtol, atol)  # a float32 rod (JAX_ENABLE_X64=0)
    ys, code, steps = _solve(rod, state0, ts, solver, float(rtol), float(atol), int(max_steps), dt0)
    status = _DIFFRAX_STATUS
    code = int(code)
    if throw and code != 0:
        raise RuntimeError(f"lattice.simulate: the rod's solve failed: {status[code]!r}.")
    return RodTrajectory(ts, ys, rod, status[code], steps)


_TIMES = "lattice.simulate: ts must be a strictly increasing 1-D array of >= 2 times."
# the codes of _solve
_DIFFRAX_STATUS = [SolveStatus.successful, SolveStatus.max_steps_reached, SolveStatus.solver_error]


def _solver(method, solver):
    """The diffrax solver of ``method`` (``solver`` when given)."""
    if solver is not None:
        return solver
    if method == "explicit":
        return diffrax.Dopri8()
    if method == "implicit":
        return _Kvaerno5(root_finder=diffrax.with_stepsize_controller_tols(_JacobianChord)())
    raise ValueError(
        f"lattice.simulate: method must be 'explicit', 'implicit' or 'splitting' for a "
        f"rod, got {method!r}."
    )


def _splitting(rod, state0, ts, dt, max_steps, throw):
    """``simulate_rod(..., method="splitting")``: :func:`._rod_verlet.verlet`."""
    if max_steps == 100_000:  # the adaptive methods' default; fixed steps are cheap: more room
        max_steps = 10_000_000
    state0 = jax.tree_util.tree_map(jnp.asarray, state0)
    states, ok, steps, dt = verlet(rod, state0, ts, dt, max_steps)
    if throw and not bool(ok):
        raise RuntimeError(
            f"lattice.simulate: the rod's state became non-finite (method='splitting', dt = "
            f"{dt:.3g} s): the step is past the stability limit or the motion blew up; pass a "
            f"smaller dt."
        )
    status = SolveStatus.successful if bool(ok) else SolveStatus.solver_error
    return RodTrajectory(ts, states, rod, status, jnp.asarray(steps))


# --------------------------------------------------------------------------------------------
# Under a transformation: the convention of rbo_jax.simulate (rbo_jax.trajectory.finish).
# --------------------------------------------------------------------------------------------


def _traced_times(ts, throw):
    """``(ts, bad)``: concrete ``ts`` checked now as :func:`simulate_rod` does (a NumPy array:
    the splitting counts its steps on the host); traced ones with :func:`equinox.error_if`
    when ``throw``, else flagged by ``bad`` (not finite and strictly increasing)."""
    dtype = jnp.result_type(float)
    if not _is_traced(ts):
        ts = np.asarray(ts, dtype=dtype)
        if ts.ndim != 1 or ts.shape[0] < 2 or not np.all(np.diff(ts) > 0):
            raise ValueError(_TIMES)
        return ts, np.bool_(False)
    ts = jnp.asarray(ts, dtype=dtype)
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(_TIMES)
    bad = ~times_ok(ts)
    if throw:
        ts = eqx.error_if(ts, bad, _TIMES)
    return ts, bad


def _raise_failed(x, status, messages):
    """``x`` with :func:`equinox.branched_error_if` on a failed (traced) ``status``: the message
    of its name in ``messages``, else the status's own."""
    names = enum.names(SolveStatus)
    msgs = [
        "lattice.simulate: " + (messages.get(n) or SolveStatus[getattr(SolveStatus, n)])
        for n in names
    ]
    return eqx.branched_error_if(x, status != SolveStatus.successful, enum.code(status), msgs)


def _simulate_traced(rod, state0, ts, method, solver, rtol, atol, max_steps, dt0, dt, throw):
    """:func:`simulate_rod` with a traced input: statuses in the program, no host check."""
    ts, bad_times = _traced_times(ts, throw)
    traced_ts = _is_traced(ts)
    run_ts = jnp.where(bad_times, jnp.zeros_like(ts), ts) if traced_ts else ts
    state0 = jax.tree_util.tree_map(jnp.asarray, state0)
    if method == "splitting" and solver is None:
        if max_steps == 100_000:  # as _splitting
            max_steps = 10_000_000
        states, ok, steps, _, too_many, bad_dt = verlet_traced(rod, state0, run_ts, dt, max_steps)
        status = SolveStatus.where(ok, SolveStatus.successful, SolveStatus.solver_error)
        status = SolveStatus.where(too_many, SolveStatus.max_steps_reached, status)
        status = SolveStatus.where(bad_dt, SolveStatus.invalid_parameters, status)
        what = "dt" if dt is not None else "the default step (from the stiffnesses and masses)"
        messages = {
            "max_steps_reached": (
                f"method='splitting' needs more steps of dt for ts than max_steps = "
                f"{max_steps}: raise max_steps or dt."
            ),
            "solver_error": (
                "the rod's state became non-finite (method='splitting'): the step is past the "
                "stability limit or the motion blew up; pass a smaller dt."
            ),
            "invalid_parameters": f"{what} must be finite and > 0 (method='splitting').",
        }
    else:
        solver = _solver(method, solver)
        if dt0 is None:
            dt0 = (
                (run_ts[1] - run_ts[0]) / 10.0
                if traced_ts
                else float(ts[1] - ts[0]) / 10.0  # as the eager call
            )
        elif not _is_traced(dt0):
            dt0 = float(dt0)
        if _is_traced(dt0):
            dt0 = jnp.where(bad_times, 1.0, jnp.asarray(dt0, dtype=ts.dtype))
        warn_if_float32(state0.r.dtype, rtol, atol)
        states, code, steps = _solve(
            rod, state0, jnp.asarray(run_ts), solver, float(rtol), float(atol), int(max_steps), dt0
        )
        status = SolveStatus.where(
            code == 0,
            SolveStatus.successful,
            SolveStatus.where(code == 1, SolveStatus.max_steps_reached, SolveStatus.solver_error),
        )
        messages = {
            n: f"the rod's solve failed: {getattr(SolveStatus, n)!r}."
            for n in ("max_steps_reached", "solver_error")
        }
    if traced_ts:
        status = SolveStatus.where(bad_times, SolveStatus.invalid_times, status)
        states = jax.tree_util.tree_map(lambda x: jnp.where(bad_times, jnp.nan, x), states)
        messages["invalid_times"] = _TIMES.removeprefix("lattice.simulate: ")
    # the rod's parameters that were traced at construction, checked now (Rod.parameter_checks)
    ok = rod.parameter_status()[0]
    status = SolveStatus.where(ok, status, SolveStatus.invalid_parameters)
    states = jax.tree_util.tree_map(lambda x: jnp.where(ok, x, jnp.nan), states)
    if throw:
        states = checked_parameters(rod, states, "lattice.simulate", ok)
        states = _raise_failed(states, status, messages)
    return RodTrajectory(jnp.asarray(ts), states, rod, status, steps)
