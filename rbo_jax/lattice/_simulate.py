r"""``lattice.simulate``: the motion of a lattice, by three integrators.

- ``method="dop853"`` (default): the whole lattice as one system of $6N$ equations, DOP853 with
  SciPy's steps, error norm and dense output (:mod:`._integrate`): the fast path for large N,
  with re-centred turn-vectors off the plane near the singular spheres.
- ``method="diffrax"``: :func:`diffrax.diffeqsolve` with any solver (default ``Dopri8``) and
  adjoint (reverse-mode gradients); stops with ``singular_point`` where a body nears a singular
  sphere off the plane.
- ``method="splitting"``: the Lie-group splitting of :mod:`._splitting` with fixed steps of at
  most ``dt``, for lattices without loads: symplectic, its energy error bounded over any number
  of steps.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from .._programs import jit, program
from .._validation import (
    _common_float_dtype,
    _is_traced,
    checked_inputs_trusted,
)
from ..kinematics import distance_to_singularity
from ..simulate import _solve_sampled, _status_from_solution
from ..simulate import _trusted as _trusted_solve
from ..trajectory import SolveStatus, check_times, warn_if_float32
from ._field import rates, right_forms, transverse
from ._halo import BLOCK, HALO, Halo, Whole
from ._integrate import Config, Problem, solve
from ._lattice import Lattice
from ._rod import Rod
from ._rod_dynamics import RodTrajectory, simulate_rod
from ._splitting import split
from ._trajectory import LatticeTrajectory

__all__ = ["simulate"]

METHODS = ("dop853", "diffrax", "splitting")


def _state(x, lattice: Lattice, name: str, dtype):
    """``x`` (``(N, 3)`` or ``(*shape, 3)``) as a component-major ``(3, N)`` array."""
    traced = _is_traced(x)
    # a JAX array stays where it is (a GPU's input is not copied to the host and back)
    on_device = isinstance(x, jax.Array) and not traced
    a = x if traced or on_device else np.asarray(x)
    n = lattice.size
    if tuple(a.shape) not in ((n, 3), tuple(lattice.shape) + (3,)):
        raise ValueError(
            f"lattice.simulate: {name} must have shape ({n}, 3) or "
            f"{tuple(lattice.shape) + (3,)} (one vector per body), got "
            f"{tuple(a.shape)}."
        )
    if not traced:
        if np.iscomplexobj(a):
            raise TypeError(f"lattice.simulate: {name} must be real.")
        xp = jnp if on_device else np
        if not bool(xp.all(xp.isfinite(a))):
            raise ValueError(f"lattice.simulate: {name} must be finite.")
        if not on_device:
            return jax.device_put(np.ascontiguousarray(a.reshape(n, 3).T.astype(dtype)))
    return jnp.reshape(a, (n, 3)).T.astype(dtype)


def _cast(lattice: Lattice, dtype):
    """The lattice with its float leaves in ``dtype`` (integers, the edges, kept)."""
    return jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if eqx.is_inexact_array(x) and x.dtype != dtype else x, lattice
    )


def _parameters_ok(lattice: Lattice):
    """Whether every parameter is valid (bodies and coupling): a NumPy bool for concrete ones
    (the constructors checked them), else a traced bool (:meth:`parameter_status`)."""
    leaves = jax.tree_util.tree_leaves(lattice)
    if not any(_is_traced(x) for x in leaves):
        return np.bool_(True)
    if lattice.per_site:
        ok = jax.vmap(lambda b: b.parameter_status()[0], in_axes=(lattice.body_axes(),))(
            lattice.site_bodies()
        )
        ok = jnp.all(ok)
    else:
        ok = lattice.body.parameter_status()[0]
    for valid, _ in lattice.coupling.parameter_checks():
        ok = ok & jnp.all(jnp.asarray(valid))
    return ok


class Layout(NamedTuple):
    """Where and how a DOP853 solve runs (static): on the local devices with these ids (one:
    the plain program; several: a chain split over them, :func:`_sharded`), the step made in
    blocks (``halo``: :class:`._halo.Halo`) or on whole arrays (:class:`._halo.Whole`)."""

    devices: tuple[int, ...]
    halo: bool
    block: int = BLOCK


def _dop853(lattice, theta0, Omega0, ts, cfg: Config, layout: Layout):
    problem = Problem.of(lattice)
    y0 = tuple(theta0) + tuple(Omega0)
    n = lattice.size
    if len(layout.devices) > 1:
        out = _sharded(problem, y0, ts, cfg, layout)
    else:
        plan = Halo(n, n, lattice.periodic[0], layout.block) if layout.halo else Whole(n)
        out = solve(problem, y0, ts, cfg, plan)
    return _split(out["samples"]) + (
        out["turns"],
        out["status"],
        out["num_steps"],
        out["num_recentred"],
    )


def _split(samples):
    """``(theta, Omega)`` of the ``(T, N, 6)`` samples, in the program (two slices after it
    were ~0.2 ms of a call's fixed cost)."""
    return samples[..., :3], samples[..., 3:]


AXIS = "lattice"


def _sharded(problem, y0, ts, cfg: Config, layout: Layout):
    """:func:`._integrate.solve` of a chain split over ``layout.devices`` (``jax.shard_map``
    over a 1-D mesh): every device integrates its N/d bodies with halos from its neighbours and
    the shards' error norms summed (:class:`._halo.Halo`), so that all take the same steps. The
    right forms ($A^{-1}$, by cofactors) are made before ``shard_map``: the devices' program,
    whose devices wait on each other in its collectives, holds no LAPACK call."""
    by_id = {d.id: d for d in jax.devices()}
    devices = [by_id[i] for i in layout.devices]
    d, n = len(devices), problem.lattice.size
    mesh = jax.sharding.Mesh(np.array(devices), (AXIS,))
    plan = Halo(n, n // d, problem.lattice.periodic[0], layout.block, d, AXIS)
    P = jax.sharding.PartitionSpec

    def local(problem, y0, ts):
        out = solve(problem, tuple(y0), ts, cfg, plan)
        return out["samples"], out["turns"], out["status"], out["num_steps"], out["num_recentred"]

    run = jax.shard_map(
        local,
        mesh=mesh,
        in_specs=(P(), P(None, AXIS), P()),
        out_specs=(P(None, AXIS, None), P(None, AXIS), P(), P(), P()),
        check_vma=False,
    )
    samples, turns, status, steps, nrec = run(problem, jnp.stack(y0), ts)
    return dict(samples=samples, turns=turns, status=status, num_steps=steps, num_recentred=nrec)


def _near_singular(lattice, singular_tol, t, y, args, **kwargs):
    theta, Omega = y
    near = jax.vmap(distance_to_singularity, in_axes=1)(theta) < singular_tol
    return jnp.any(near & transverse(theta, Omega))


def _diffrax(lattice, theta0, Omega0, ts, solver, rtol, atol, max_steps, singular_tol, adjoint):
    forms = right_forms(lattice)

    def field(t, y, args):
        return rates(lattice, forms, t, *y)

    cond = jax.tree_util.Partial(_near_singular, lattice, jnp.asarray(singular_tol, ts.dtype))
    sol = _solve_sampled(
        field, (theta0, Omega0), ts, [cond], solver, rtol, atol, max_steps, adjoint
    )
    status = _status_from_solution(sol, ("singular_point",))
    theta, Omega = sol.ys
    samples = jnp.concatenate([theta, Omega], axis=1).transpose(0, 2, 1)
    samples = jnp.where(jnp.isfinite(samples), samples, jnp.inf)
    turns = jnp.zeros((ts.shape[0], theta0.shape[1]), jnp.int32)
    return _split(samples) + (
        turns,
        enum.code(status),
        sol.stats["num_accepted_steps"],
        jnp.asarray(0, jnp.int32),
    )


def _splitting(lattice, theta0, Omega0, ts, dt, recenter, recenter_margin):
    samples, turns, steps = split(lattice, theta0, Omega0, ts, dt, recenter, recenter_margin)
    finite = jnp.all(jnp.isfinite(samples))
    status = jnp.where(
        finite, enum.code(SolveStatus.successful), enum.code(SolveStatus.nonfinite_state)
    )
    return _split(samples) + (turns, status.astype(jnp.int32), steps, jnp.sum(turns[-1] > 0))


_TRACED = {"dop853": _dop853, "diffrax": _diffrax, "splitting": _splitting}
# Lattices of fewer bodies compile with XLA's options for small programs (their run time is
# dominated by per-operation costs; measured on one core for a chain of 8: compilation 4.7 ->
# 3.4 s, the same run time; of 10 000: 5.5 -> 4.0 s but +15 % run time). Larger ones keep
# XLA's defaults: best call with the small options / with the defaults, one pinned core,
# alternating (benchmark chain, t1 = 2): 64 bodies 1.58 / 1.42 ms, 256: 3.14 / 2.36 ms,
# 1000: 9.37 / 6.50 ms.
SMALL = 64
_PROGRAMS = {
    (name, small): program(fn, small=small)
    for name, fn in _TRACED.items()
    for small in (False, True)
}
# A solve split over devices is not stored (an exported program is bound to its number of
# devices and their shardings): plain jit.
_SHARDED = jit(_dop853)


def _config(
    lattice, method, rtol, atol, max_steps, singular_tol, recenter, recenter_margin, dt
) -> Config:
    """The checked settings of :func:`simulate` (a clear error naming the bad one)."""
    if not isinstance(lattice, Lattice):
        raise TypeError(
            f"lattice.simulate: lattice must be a rbo_jax.lattice.Lattice, got "
            f"{type(lattice).__name__}."
        )
    if method not in METHODS:
        raise ValueError(f"lattice.simulate: method must be one of {METHODS}, got {method!r}.")
    try:
        cfg = Config(
            float(rtol),
            float(atol),
            int(max_steps),
            float(singular_tol),
            bool(recenter),
            float(recenter_margin),
        )
    except (TypeError, jax.errors.ConcretizationTypeError):
        raise TypeError(
            "lattice.simulate: rtol, atol, max_steps, singular_tol and "
            "recenter_margin must be Python numbers (they are compiled in)."
        ) from None
    if not (
        cfg.rtol > 0
        and cfg.atol > 0
        and cfg.max_steps >= 1
        and cfg.singular_tol > 0
        and 0 < cfg.recenter_margin < math.pi
    ):
        raise ValueError(
            f"lattice.simulate: need rtol, atol, singular_tol > 0, max_steps >= 1 "
            f"and 0 < recenter_margin < pi, got {cfg}."
        )
    if method == "splitting":
        if dt is None or _is_traced(dt) or not (float(dt) > 0 and math.isfinite(float(dt))):
            raise ValueError(
                f"lattice.simulate: method='splitting' needs a step dt > 0 (a number), got {dt!r}."
            )
        if lattice.body.loads:
            raise ValueError(
                "lattice.simulate: method='splitting' integrates conservative "
                "lattices (no loads: its kicks are the gradient of the foundations "
                "and couplings); use method='dop853' or 'diffrax' with loads."
            )
    return cfg


# The step in blocks (:mod:`._halo`) against whole arrays, µs per body-step on one pinned core,
# alternating (benchmark chain, loaded 2-core machine): 10⁴ bodies 1.46 / 1.39, 3·10⁴ 1.30 /
# 1.27, 10⁵ 1.66 / 2.07, 2·10⁵ 1.19 / 1.59: blocks from HALO_MIN bodies on (the 16 slopes of
# 5·10⁴ bodies, 38 MB, exceed the 32 MiB L3). A chain is split over the local devices by default
# from SHARD_MIN bodies on.
HALO_MIN = 50_000
SHARD_MIN = 100_000


def _chain_like(lattice: Lattice) -> bool:
    """Whether the halo and shard plans serve ``lattice``: a chain (one axis, nearest
    neighbours), one body for every site."""
    return lattice.is_grid and lattice.ndim == 1 and not lattice.per_site


def _layout(lattice: Lattice, devices, traced: bool) -> Layout:
    """The :class:`Layout` of a DOP853 solve for ``devices`` (:func:`simulate`)."""
    n = lattice.size
    chain = _chain_like(lattice)
    if devices is None:
        chosen = [jax.local_devices()[0]]
        local = jax.local_devices()
        if chain and not traced and n >= SHARD_MIN and len(local) > 1:
            # the most local devices that split the chain evenly
            d = max(k for k in range(1, len(local) + 1) if n % k == 0 and n // k >= HALO)
            chosen = local[:d]
    else:
        if isinstance(devices, (int, np.integer)) and not isinstance(devices, bool):
            local = jax.local_devices()
            if not 1 <= devices <= len(local):
                raise ValueError(
                    f"lattice.simulate: devices must be between 1 and the {len(local)} local "
                    f"device(s), got {devices}."
                )
            chosen = local[: int(devices)]
        else:
            chosen = list(devices)
            if not chosen or not all(isinstance(d, jax.Device) for d in chosen):
                raise TypeError(
                    "lattice.simulate: devices must be None, a number of local devices or a "
                    f"list of jax devices, got {devices!r}."
                )
        if len(chosen) > 1:
            if not chain:
                raise ValueError(
                    "lattice.simulate: only a chain with one body for every site is split "
                    "over devices (method='dop853'); use devices=1 for this lattice."
                )
            if n % len(chosen) or n // len(chosen) < HALO:
                raise ValueError(
                    f"lattice.simulate: a chain of {n} bodies splits over {len(chosen)} "
                    f"devices only if they divide it evenly with at least {HALO} bodies "
                    f"each; choose another number of devices."
                )
    # blocks that fit a CPU's cache; a GPU steps whole arrays (its kernels stream them)
    cpu = all(d.platform == "cpu" for d in chosen)
    halo = chain and (len(chosen) > 1 or (cpu and n >= HALO_MIN))
    return Layout(tuple(d.id for d in chosen), halo, BLOCK if cpu else n)


def _method_args(method, lattice, theta0, Omega0, ts, cfg, solver, adjoint, dt, dtype, layout):
    """The arguments of the method's program."""
    if method == "dop853":
        args = (lattice, theta0, Omega0, ts, cfg, layout)
    elif method == "diffrax":
        args = (
            lattice,
            theta0,
            Omega0,
            ts,
            solver,
            cfg.rtol,
            cfg.atol,
            cfg.max_steps,
            cfg.singular_tol,
            adjoint,
        )
    else:
        # dt traced: one program for every step size
        args = (
            lattice,
            theta0,
            Omega0,
            ts,
            jnp.asarray(dt, dtype),
            cfg.recenter,
            cfg.recenter_margin,
        )
    return args


def _trusted(lattice, method, solver, adjoint) -> bool:
    """Whether diffrax's own input checks may be left out (rbo_jax checked the inputs; the
    lattice, solver and adjoint are library code): the rule of :func:`rbo_jax.simulate`."""
    return method == "diffrax" and _trusted_solve(lattice, solver, adjoint)


def _simulate_rod(rod, state0, ts, extra, method, solver, rtol, atol, max_steps, dt, throw):
    """``simulate(rod, state0, ts)``: the rod's arguments sit where a lattice's ``theta0`` and
    ``Omega0`` do (``ts`` may also be given by name)."""
    if ts is not None and extra is not None:
        raise TypeError("lattice.simulate of a rod takes (rod, state0, ts).")
    ts = extra if ts is None else ts
    if ts is None:
        raise TypeError("lattice.simulate(rod, state0, ts): ts is missing.")
    method = "explicit" if method == "dop853" else method
    return simulate_rod(
        rod,
        state0,
        ts,
        method=method,
        solver=solver,
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
        dt=dt,
        throw=throw,
    )


def simulate(
    lattice: Lattice,
    theta0,
    Omega0=None,
    ts=None,
    *,
    method: str = "dop853",
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    singular_tol: float = 1e-3,
    recenter: bool = True,
    recenter_margin: float = 0.5,
    solver: diffrax.AbstractSolver | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    dt: float | None = None,
    dtype=None,
    devices=None,
    throw: bool = True,
) -> LatticeTrajectory | RodTrajectory:
    r"""Integrate a lattice (every body's (4.55)–(4.56) with the gradient of the total energy)
    from ``(theta0, Omega0)`` at ``ts[0]`` and sample it at ``ts``.

    **Arguments:**

    - `lattice`: a :class:`rbo_jax.lattice.Lattice` (:func:`rbo_jax.lattice.chain`, ...).
    - `theta0`, `Omega0`: the turn-vectors and right angular velocities of the bodies,
      ``(N, 3)`` or ``(*shape, 3)``.
    - `ts`: strictly increasing sample times.
    - `method`: ``"dop853"`` (default; SciPy's DOP853 on the whole lattice, re-centring),
      ``"diffrax"`` (any ``solver``, default ``Dopri8``, and ``adjoint``: reverse-mode
      gradients), or ``"splitting"`` (symplectic Lie-group splitting with steps of at most
      ``dt``; lattices without loads only). See :mod:`rbo_jax.lattice._simulate`.
    - `rtol`, `atol` (default 1e-8, 1e-10), `max_steps` (step attempts), `singular_tol`: the
      adaptive methods' settings (Python numbers, compiled in).
    - `recenter`, `recenter_margin`: re-centre the turn-vector of a body that comes within
      ``recenter_margin`` rad of a singular sphere $|\theta| = 2\pi k$ off the plane (DOP853
      and splitting); with ``recenter=False`` the solve stops there with ``singular_point``.
    - `dtype`: ``jnp.float32`` runs the solve in single precision (for GPUs: see
      ``benchmarks/README.md`` for its accuracy); default: the inputs' and parameters' precision
      (float64 with rbo_jax's default).
    - `devices`: where a ``"dop853"`` solve runs. ``None`` (default): a chain of at least
      ``SHARD_MIN`` (10⁵) bodies, one body for every site, is split over all local devices
      that divide it evenly (domain decomposition, :mod:`._halo`: halos of the neighbours'
      states, one error norm for the whole chain, SciPy's steps), anything else runs on one
      device; an int ``d`` (the first ``d`` local devices) or a list of devices chooses;
      ``1``: the single-device program. Several devices give the one device's steps and
      states to rounding (the error norm is summed in another order).
    - `throw`: raise on failure (default) or return the status.

    **Returns** a :class:`rbo_jax.lattice.LatticeTrajectory`: ``theta``, ``Omega`` (T, N, 3),
    ``turns`` (T, N), ``energy`` (T,), ``status``. jit-, vmap- (ensembles of lattices) and
    forward-mode differentiable (all methods; ``"diffrax"`` also reverse mode).

    **A rod** (:class:`rbo_jax.lattice.Rod`): ``simulate(rod, state0, ts, method="explicit" |
    "implicit" | "splitting", solver=..., rtol=..., atol=..., max_steps=..., dt=...,
    throw=...)`` (``"splitting"``: the Lie-group position Verlet of
    :mod:`rbo_jax.lattice._rod_verlet`, fixed steps of at most ``dt``) with a
    :class:`rbo_jax.lattice.RodState` returns a :class:`rbo_jax.lattice.RodTrajectory`
    (:func:`rbo_jax.lattice._rod_dynamics.simulate_rod`), inside ``jax.jit``, ``jax.vmap``
    and ``jax.grad`` too (a rod built from traced parameters; the failures as statuses or
    :func:`equinox.error_if`).
    """
    if isinstance(lattice, Rod):
        return _simulate_rod(
            lattice, theta0, Omega0, ts, method, solver, rtol, atol, max_steps, dt, throw
        )
    if ts is None or Omega0 is None:
        raise TypeError("lattice.simulate(lattice, theta0, Omega0, ts): Omega0 and ts are needed.")
    cfg = _config(
        lattice, method, rtol, atol, max_steps, singular_tol, recenter, recenter_margin, dt
    )
    ts = check_times(ts, throw)
    params = jax.tree_util.tree_leaves(eqx.filter(lattice, eqx.is_inexact_array))
    if dtype is None:
        dtype = _common_float_dtype(
            ts, *params, *(x for x in (theta0, Omega0) if hasattr(x, "dtype"))
        )
    dtype = jax.dtypes.canonicalize_dtype(dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"lattice.simulate: dtype must be a float type, got {dtype}.")
    lattice = _cast(lattice, dtype)
    theta0 = _state(theta0, lattice, "theta0", dtype)
    Omega0 = _state(Omega0, lattice, "Omega0", dtype)
    ts = ts.astype(dtype)
    warn_if_float32(dtype, rtol, atol)
    ok = _parameters_ok(lattice)

    traced = any(_is_traced(x) for x in jax.tree_util.tree_leaves((lattice, theta0, Omega0, ts)))
    layout = _layout(lattice, devices, traced) if method == "dop853" else None
    args = _method_args(
        method, lattice, theta0, Omega0, ts, cfg, solver, adjoint, dt, dtype, layout
    )
    if traced:
        out = _TRACED[method](*args)
    else:
        with checked_inputs_trusted(_trusted(lattice, method, solver, adjoint)):
            if layout is not None and len(layout.devices) > 1:
                out = _SHARDED(*args)
            else:
                out = _PROGRAMS[method, lattice.size < SMALL](*args)
    theta, Omega, turns, code, num_steps, num_recentred = out
    status = enum.from_code(SolveStatus, code)
    if not (isinstance(ok, np.bool_) and ok):
        status = SolveStatus.where(ok, status, SolveStatus.invalid_parameters)
        theta, Omega = jnp.where(ok, theta, jnp.nan), jnp.where(ok, Omega, jnp.nan)
    if throw and (_is_traced(enum.code(status)) or enum.name(status) != "successful"):
        theta = status.error_if(theta, status != SolveStatus.successful)
    return LatticeTrajectory(
        ts=ts,
        theta=theta,
        Omega=Omega,
        turns=turns,
        lattice=lattice,
        status=status,
        num_steps=num_steps,
        num_recentred=num_recentred,
    )
