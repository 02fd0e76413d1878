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
from .._validation import common_float_dtype, is_traced
from ..integrate import diffeq
from ..kinematics import distance_to_singularity
from ..models.lattice import Lattice, rates, right_forms
from ..models.rod import Rod
from ..trajectory import SolveStatus, check_times, flag, raise_failure, warn_if_float32
from ._halo import BLOCK, HALO, Halo, Whole
from ._integrate import Config, Problem, solve
from ._recentre import transverse
from ._rod_dynamics import RodTrajectory, simulate_rod
from ._splitting import split
from ._trajectory import LatticeTrajectory

__all__ = ["simulate"]

METHODS = ("dop853", "diffrax", "splitting")


def _state(x, lattice: Lattice, name: str, dtype):
    """``x`` (``(N, 3)`` or ``(*shape, 3)``) as a component-major ``(3, N)`` array."""
    traced = is_traced(x)
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


def _in_precision(lattice: Lattice, theta0, Omega0, ts, dtype):
    """``(lattice, theta0, Omega0, ts, dtype)`` in the solve's precision: ``dtype``, by default
    the inputs' and parameters' (the lattice's float leaves cast; integers, the edges, kept);
    the states component-major (:func:`_state`)."""
    if dtype is None:
        params = jax.tree_util.tree_leaves(eqx.filter(lattice, eqx.is_inexact_array))
        states = (x for x in (theta0, Omega0) if hasattr(x, "dtype"))
        dtype = common_float_dtype(ts, *params, *states)
    dtype = jax.dtypes.canonicalize_dtype(dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"lattice.simulate: dtype must be a float type, got {dtype}.")
    lattice = jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if eqx.is_inexact_array(x) and x.dtype != dtype else x, lattice
    )
    theta0 = _state(theta0, lattice, "theta0", dtype)
    Omega0 = _state(Omega0, lattice, "Omega0", dtype)
    return lattice, theta0, Omega0, ts.astype(dtype), dtype


def _parameters_ok(lattice: Lattice):
    """Whether every parameter is valid (bodies and coupling): a NumPy bool for concrete ones
    (the constructors checked them), else a traced bool (:meth:`Lattice.parameter_status`)."""
    if not any(is_traced(x) for x in jax.tree_util.tree_leaves(lattice)):
        return np.bool_(True)
    return lattice.parameter_status()[0]


class Layout(NamedTuple):
    """Where and how a DOP853 solve runs (static): on the local devices with these ids (one:
    the plain program; several: a chain split over them, :func:`_sharded`), the step made in
    blocks (``halo``: :class:`._halo.Halo`) or on whole arrays (:class:`._halo.Whole`)."""

    devices: tuple[int, ...]
    halo: bool
    block: int = BLOCK


class Options(NamedTuple):
    """The static settings of a lattice's solve, every method's (:func:`simulate`): the
    adaptive methods' :class:`._integrate.Config`, DOP853's :class:`Layout`, diffrax's solver
    and adjoint."""

    cfg: Config
    layout: Layout | None
    solver: diffrax.AbstractSolver | None
    adjoint: diffrax.AbstractAdjoint | None


# The methods: (lattice, theta0, Omega0 (3, N), ts, step (the splitting's dt, diffrax's dt0, or
# None), options) -> (theta, Omega, turns, status code, steps, bodies re-centred).


def _dop853(lattice, theta0, Omega0, ts, dt, o: Options):
    problem = Problem.of(lattice)
    y0 = tuple(theta0) + tuple(Omega0)
    n = lattice.size
    if len(o.layout.devices) > 1:
        out = _sharded(problem, y0, ts, o.cfg, o.layout)
    else:
        plan = Halo(n, n, lattice.periodic[0], o.layout.block) if o.layout.halo else Whole(n)
        out = solve(problem, y0, ts, o.cfg, plan)
    return _split(out["samples"]) + (
        out["turns"],
        out["status"],
        out["num_steps"],
        out["num_recentred"],
    )


def _split(samples):
    """``(theta, Omega)`` of the ``(T, N, 6)`` samples, in the program (not two more slices
    after it)."""
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


def _diffrax(lattice, theta0, Omega0, ts, dt, o: Options):
    forms = right_forms(lattice)

    def field(t, y, args):
        return rates(lattice, forms, t, *y)

    cond = jax.tree_util.Partial(_near_singular, lattice, jnp.asarray(o.cfg.singular_tol, ts.dtype))
    (theta, Omega), status, steps = diffeq.solve(
        field,
        o.solver,
        (theta0, Omega0),
        ts,
        dt0=dt,
        rtol=o.cfg.rtol,
        atol=o.cfg.atol,
        events=[("singular_point", cond)],
        adjoint=o.adjoint,
        max_steps=o.cfg.max_steps,
    )
    samples = jnp.concatenate([theta, Omega], axis=1).transpose(0, 2, 1)
    samples = jnp.where(jnp.isfinite(samples), samples, jnp.inf)
    turns = jnp.zeros((ts.shape[0], theta0.shape[1]), jnp.int32)
    return _split(samples) + (turns, enum.code(status), steps, jnp.asarray(0, jnp.int32))


def _splitting(lattice, theta0, Omega0, ts, dt, o: Options):
    samples, turns, steps = split(
        lattice, theta0, Omega0, ts, dt, o.cfg.recenter, o.cfg.recenter_margin
    )
    finite = jnp.all(jnp.isfinite(samples))
    status = jnp.where(
        finite, enum.code(SolveStatus.successful), enum.code(SolveStatus.nonfinite_state)
    )
    return _split(samples) + (turns, status.astype(jnp.int32), steps, jnp.sum(turns[-1] > 0))


_TRACED = {"dop853": _dop853, "diffrax": _diffrax, "splitting": _splitting}
# Lattices of fewer bodies compile with XLA's options for small programs (their run time is
# dominated by per-operation costs: they compile faster and run as fast); larger ones keep
# XLA's defaults, with which they run faster (benchmarks/README.md, History).
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
        if dt is None or is_traced(dt) or not (float(dt) > 0 and math.isfinite(float(dt))):
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


# The step in blocks (:mod:`._halo`) from HALO_MIN bodies on (the 16 slopes of 5·10⁴ bodies,
# 38 MB, exceed a 32 MiB L3; benchmarks/README.md, History). A chain is split over the local
# devices by default from SHARD_MIN bodies on.
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


def _simulate_rod(rod, state0, at, ts, **options):
    """``simulate(rod, state0, ts)``: the rod's arguments sit where a lattice's ``theta0`` and
    ``Omega0`` do (``at``; ``ts`` may also be given by name)."""
    if at is not None and ts is not None:
        raise TypeError("lattice.simulate of a rod takes (rod, state0, ts).")
    ts = at if ts is None else ts
    if ts is None:
        raise TypeError("lattice.simulate(rod, state0, ts): ts is missing.")
    if options["method"] == "dop853":  # the lattices' default: the rod's own (method="auto")
        options["method"] = "auto"
    return simulate_rod(rod, state0, ts, **options)


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
    dt0: float | None = None,
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
      gradients; ``dt0`` its first step, default diffrax's choice), or ``"splitting"``
      (symplectic Lie-group splitting with steps of at most ``dt``; lattices without loads
      only). See :mod:`rbo_jax.lattice._simulate`.
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

    **A rod** (:class:`rbo_jax.lattice.Rod`): ``simulate(rod, state0, ts, method="auto" |
    "midpoint" | "explicit" | "implicit" | "splitting", solver=..., rtol=..., atol=...,
    max_steps=..., dt0=..., dt=..., throw=...)`` (``"auto"``, the default: the implicit midpoint
    rule for a stiff rod, Dopri8 otherwise; ``"splitting"``: the Lie-group position Verlet of
    :mod:`rbo_jax.lattice._rod_verlet`, fixed steps of at most ``dt``) with a
    :class:`rbo_jax.lattice.RodState` returns a :class:`rbo_jax.lattice.RodTrajectory`
    (:func:`rbo_jax.lattice._rod_dynamics.simulate_rod`), inside ``jax.jit``, ``jax.vmap``
    and ``jax.grad`` too (a rod built from traced parameters; the failures as statuses or
    :func:`equinox.error_if`).
    """
    if isinstance(lattice, Rod):
        return _simulate_rod(
            lattice,
            theta0,
            Omega0,
            ts,
            method=method,
            solver=solver,
            rtol=rtol,
            atol=atol,
            max_steps=max_steps,
            dt0=dt0,
            dt=dt,
            throw=throw,
        )
    if ts is None or Omega0 is None:
        raise TypeError("lattice.simulate(lattice, theta0, Omega0, ts): Omega0 and ts are needed.")
    cfg = _config(
        lattice, method, rtol, atol, max_steps, singular_tol, recenter, recenter_margin, dt
    )
    ts = check_times(ts, throw)
    lattice, theta0, Omega0, ts, dtype = _in_precision(lattice, theta0, Omega0, ts, dtype)
    warn_if_float32(dtype, rtol, atol)
    ok = _parameters_ok(lattice)

    traced = any(is_traced(x) for x in jax.tree_util.tree_leaves((lattice, theta0, Omega0, ts)))
    layout = _layout(lattice, devices, traced) if method == "dop853" else None
    diffeq.check_start(None, dt0, ts)
    step = {"splitting": dt, "diffrax": dt0}.get(method)  # traced: one program for every step
    step = None if step is None else jnp.asarray(step, dtype)
    args = (lattice, theta0, Omega0, ts, step, Options(cfg, layout, solver, adjoint))
    sharded = layout is not None and len(layout.devices) > 1
    compiled = _SHARDED if sharded else _PROGRAMS[method, lattice.size < SMALL]
    checked = method == "diffrax" and diffeq.trusted(lattice, solver, adjoint)
    out = diffeq.run(compiled, _TRACED[method], args, checked)
    theta, Omega, turns, code, num_steps, num_recentred = out
    status = enum.from_code(SolveStatus, code)
    if not (isinstance(ok, np.bool_) and ok):
        status, (theta, Omega) = flag(status, (theta, Omega), ~ok, "invalid_parameters", jnp.nan)
    theta = raise_failure(theta, status, throw)
    return LatticeTrajectory(ts, theta, Omega, turns, lattice, status, num_steps, num_recentred)
