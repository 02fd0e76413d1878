r"""The quantities of ``rbo-jax sweep``: functions of one parameter point, composed from library
calls on a model described as data: a :class:`~rbo_jax.app.spec.ModelSpec` (the ``[model]``
table), with a :class:`~rbo_jax.app.spec.LatticeSpec` for the Bloch quantities, or a
:class:`~rbo_jax.app.rodspec.RodSpec` (the ``[rod]`` table).

- ``final_state``: $\theta(t_1)$, $\Omega(t_1)$ of a simulation (and the number of steps);
  simulations use :func:`rbo_jax.fast_simulate` (DOP853, the batch on refilled lanes), or
  :func:`rbo_jax.simulate` (diffrax Dopri8) with ``[solver] integrator = "simulate"``;
- ``energy_drift``: $\max_t |E(t) - E(0)|/|E(0)|$ over ``samples`` times;
- ``max_deviation``: $\max_t |\theta(t) - \theta(0)|$ over ``samples`` times;
- ``spectral_abscissa``: :func:`rbo_jax.equilibrium_stability` of the equilibrium found by Newton
  (max Re p, the classification and $\theta_{eq}$);
- ``bloch_growth``: the largest growth rate $\max\mathrm{Re}\,\lambda(q)$ of the Bloch waves of
  wavenumber $q$ of a lattice of the model's bodies (the ``[lattice]`` table,
  :class:`~rbo_jax.app.spec.LatticeSpec`) about the uniform equilibrium found by Newton
  (:func:`rbo_jax.lattice.dispersion`): positive where waves of that length grow (a flutter
  band over $q$ and the load);
- ``bloch_frequencies``: the three non-negative frequencies $\mathrm{Im}\,\lambda(q)$ of the
  branches (the three largest, in increasing order; at rest $\omega_k(q) \ge 0$), with
  ``bloch_growth``;
- ``rod_stability``: :func:`rbo_jax.equilibrium_stability` of the rod's equilibrium under its
  loads (Newton in ``[stability] steps`` load steps, the eigenvalues $p$ of the whole
  linearisation): ``spectral_abscissa`` $\max\mathrm{Re}\,p$, ``frequency``
  $|\mathrm{Im}\,p|$ of that eigenvalue (the flutter frequency where it grows; 0 at
  divergence), ``stable`` (an equilibrium found and no unstable root by
  :func:`rbo_jax.classify` with ``[stability] rtol``: the test of
  :func:`rbo_jax.lattice.critical_load`) and ``tip`` (the tip's position at the equilibrium);
- ``rod_critical_load``: the load factor $\lambda_{cr}$ of
  :func:`rbo_jax.lattice.critical_load`: the smallest $\lambda \in$ (``load_min``,
  ``load_max``] at which the equilibrium of the rod with every load times $\lambda$ is
  unstable; ``inf`` where it stays stable, NaN where the stable interval ends at an equilibrium
  that cannot be computed. With a unit load (``f = [0, 0, -1]``) it is the critical load
  itself: Beck's flutter load $20.05\,EI/L^2$, the Ziegler paradox of a small damping (about
  $10.94\,EI/L^2$), Pflüger's load falling with the tip mass;
- ``rod_motion``: the motion of the rod (:func:`rbo_jax.lattice.simulate`, its default method:
  under the sweep's ``jax.vmap``, the implicit midpoint rule at the step ``[solver] dt``,
  default the shorter of ``t1/1000`` and the samples' spacing) from the straight rod at rest
  with its loads applied at $t = 0$ (a suddenly applied load), sampled at ``samples`` times
  in $[0, t_1]$: ``max_deflection`` $\max_t |r_N(t) - r_N(0)|$ (for a small dead load on
  an undamped rod about twice the static deflection: the dynamic amplification of a step
  load), ``tip`` the tip's position at $t_1$ and ``num_steps``.

Every quantity returns its values and a status: the solver's
(:class:`rbo_jax.SolveStatus`) for the simulations, the equilibrium's
(:class:`rbo_jax.EquilibriumStatus`) for the others (values NaN where Newton failed;
``rod_critical_load``'s is always ``successful``, its NaN says it).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax.numpy as jnp

from ..ensemble import fast_simulate
from ..simulate import simulate
from ..stability import (
    EquilibriumStatus,
    critical_load_along,
    equilibrium_stability,
    is_unstable,
    solve_equilibrium,
)
from ._reader import resolve

# name: (what it computes, its outputs: the first one is drawn by default)
_TABLE = {
    "final_state": (
        "theta(t1) and Omega(t1) of simulate (and the number of steps)",
        ("theta", "Omega", "num_steps"),
    ),
    "energy_drift": (
        "max_t |E(t) - E(0)| / |E(0)| over `samples` times of simulate",
        ("energy_drift", "num_steps"),
    ),
    "max_deviation": (
        "max_t |theta(t) - theta(0)| over `samples` times of simulate",
        ("max_deviation", "num_steps"),
    ),
    "spectral_abscissa": (
        "max Re p of the spectrum at the equilibrium (Newton from theta_guess)",
        ("spectral_abscissa", "kind", "theta_eq"),
    ),
    "bloch_growth": (
        "max Re lambda(q) of the Bloch waves of the [lattice] at its uniform equilibrium",
        ("bloch_growth", "theta_eq"),
    ),
    "bloch_frequencies": (
        "the three non-negative frequencies Im lambda(q) of the Bloch waves of the [lattice] "
        "(and bloch_growth)",
        ("bloch_frequencies", "bloch_growth", "theta_eq"),
    ),
    "rod_stability": (
        "the spectral abscissa (and stable flag, flutter frequency, tip) of the [rod]'s "
        "equilibrium",
        ("spectral_abscissa", "stable", "frequency", "tip"),
    ),
    "rod_critical_load": (
        "the load factor at which the [rod]'s equilibrium loses stability "
        "(rbo_jax.lattice.critical_load)",
        ("critical_load",),
    ),
    "rod_motion": (
        "the tip's largest deflection (and the tip at t1) of the [rod] released straight "
        "with its loads applied at t = 0 (rbo_jax.lattice.simulate)",
        ("max_deflection", "tip", "num_steps"),
    ),
}
QUANTITIES = {name: text for name, (text, _) in _TABLE.items()}
OUTPUTS = {name: outputs for name, (_, outputs) in _TABLE.items()}
DEFAULT_PLOT = {name: outputs[0] for name, outputs in OUTPUTS.items()}
SIMULATION = ("final_state", "energy_drift", "max_deviation")
LATTICE = ("bloch_growth", "bloch_frequencies")
ROD = ("rod_stability", "rod_critical_load", "rod_motion")
INTEGRATORS = {"fast_simulate": fast_simulate, "simulate": simulate}
# the dimensions of the outputs with more than one value per point
_DIMS = {
    "theta": ("component",),
    "Omega": ("component",),
    "theta_eq": ("component",),
    "tip": ("component",),
    "bloch_frequencies": ("branch",),
}


@dataclasses.dataclass(frozen=True)
class Settings:
    """The numbers of a quantity besides the model: initial state, solver, equilibrium, and for
    the rods the ``[stability]`` table (``classify_rtol`` is its ``rtol``) or, for
    ``rod_motion``, the ``[solver]`` table (``dt`` its step; None: the method's default)."""

    theta0: tuple = (0.0, 0.0, 0.0)
    Omega0: tuple = (0.0, 0.0, 0.0)
    about_equilibrium: bool = False
    theta_guess: tuple = (0.0, 0.0, 0.0)
    classify_rtol: float = 1e-9
    t1: Any = 1.0
    rtol: float = 1e-8
    atol: float = 1e-8
    max_steps: int = 100_000
    samples: int = 101
    integrator: str = "fast_simulate"
    steps: int = 1
    load_max: float | None = None
    load_min: float = 0.0
    n_scan: int = 32
    n_bisect: int = 40
    dt: float | None = None


def _scalar(x, point):
    return jnp.asarray(resolve(x, point), dtype=jnp.result_type(float))


def _vector(xs, point):
    return jnp.stack([_scalar(x, point) for x in xs])


def _bloch(name: str, spec, s: Settings, point, lattice) -> tuple[dict, Any]:
    from ..lattice import dispersion

    lat = lattice.build(spec, point)
    sol = solve_equilibrium(lat.body, _vector(s.theta_guess, point))
    ok = sol.status == EquilibriumStatus.successful
    theta_eq = jnp.where(ok, sol.theta, 0.0)
    lam = dispersion(lat, lattice.wavenumber(point), theta_eq=theta_eq)
    lam = jnp.where(ok, lam, jnp.nan + 0j)  # sorted by Im lambda: the branches' last
    values = {"bloch_growth": jnp.max(jnp.real(lam)), "theta_eq": sol.theta}
    return values | {"bloch_frequencies": jnp.imag(lam[3:])}, sol.status


def _stability(name: str, spec, s: Settings, point, lattice=None) -> tuple[dict, Any]:
    """:func:`rbo_jax.equilibrium_stability` of one body (Newton from ``theta_guess``) or of a
    rod (from its straight state, in ``steps`` load steps, the whole eigenproblem)."""
    if name == "spectral_abscissa":
        r = equilibrium_stability(
            spec.build(point), _vector(s.theta_guess, point), rtol=s.classify_rtol
        )
        return {"spectral_abscissa": r.abscissa, "kind": r.kind, "theta_eq": r.theta}, r.status
    r = equilibrium_stability(spec.build(point), rtol=s.classify_rtol, fast=False, steps=s.steps)
    p = r.eigenvalues  # NaN where the equilibrium failed
    values = {
        "spectral_abscissa": r.abscissa,
        "stable": r.ok & ~is_unstable(r.kind),
        "frequency": jnp.abs(p.imag[jnp.argmax(p.real)]),
        "tip": jnp.where(r.ok, r.state.tip, jnp.nan),
    }
    return values, r.status


def _critical_load(name: str, spec, s: Settings, point, lattice=None) -> tuple[dict, Any]:
    lam = critical_load_along(
        lambda factor: spec.build(point, factor),
        s.load_max,
        load_min=s.load_min,
        n_scan=s.n_scan,
        n_bisect=s.n_bisect,
        rtol=s.classify_rtol,
        steps=s.steps,
    )
    return {"critical_load": lam}, EquilibriumStatus.successful


def _rod_motion(name: str, spec, s: Settings, point, lattice=None) -> tuple[dict, Any]:
    """:func:`rbo_jax.lattice.simulate` of the rod from straight and at rest (module
    docstring)."""
    from ..lattice import simulate as simulate_lattice

    rod = spec.build(point)
    ts = jnp.linspace(0.0, 1.0, s.samples) * _scalar(s.t1, point)
    traj = simulate_lattice(
        rod, rod.straight(), ts, rtol=s.rtol, atol=s.atol, max_steps=s.max_steps, dt=s.dt,
        throw=False,
    )  # fmt: skip
    tip = traj.centreline[:, -1, :]
    values = {
        "tip": tip[-1],
        "max_deflection": jnp.max(jnp.linalg.norm(tip - tip[:1], axis=-1)),
        "num_steps": traj.num_steps,
    }
    return values, traj.status


def _simulation(name: str, spec, s: Settings, point, lattice=None) -> tuple[dict, Any]:
    model = spec.build(point)
    th0 = _vector(s.theta0, point)
    if s.about_equilibrium:
        sol = solve_equilibrium(model, _vector(s.theta_guess, point))
        th0 = jnp.where(sol.ok, sol.theta + th0, jnp.nan)  # no equilibrium: nonfinite_input
    n = 2 if name == "final_state" else s.samples
    ts = jnp.linspace(0.0, 1.0, n) * _scalar(s.t1, point)
    traj = INTEGRATORS[s.integrator](
        model,
        th0,
        _vector(s.Omega0, point),
        ts,
        max_steps=s.max_steps,
        rtol=s.rtol,
        atol=s.atol,
        throw=False,
    )
    if name == "final_state":
        values = {"theta": traj.theta[-1], "Omega": traj.Omega[-1]}
    elif name == "energy_drift":
        E = traj.energy
        scale = jnp.where(jnp.abs(E[0]) > 0, jnp.abs(E[0]), 1.0)
        values = {"energy_drift": jnp.max(jnp.abs(E - E[0])) / scale}
    else:
        deviation = jnp.linalg.norm(traj.theta - traj.theta[:1], axis=1)
        values = {"max_deviation": jnp.max(deviation)}
    return values | {"num_steps": traj.num_steps}, traj.status


def make_quantity(name: str, spec, s: Settings, lattice=None):
    """``(quantity(**point), dims)`` for the sweep engine: ``spec`` the
    :class:`~rbo_jax.app.spec.ModelSpec` (with ``lattice`` for the Bloch quantities) or the
    :class:`~rbo_jax.app.rodspec.RodSpec` of the rod quantities."""
    if name in LATTICE:
        compute = _bloch
    elif name == "rod_critical_load":
        compute = _critical_load
    elif name == "rod_motion":
        compute = _rod_motion
    elif name in SIMULATION:
        compute = _simulation
    else:
        compute = _stability

    def quantity(**point):
        values, status = compute(name, spec, s, point, lattice)
        return {k: values[k] for k in OUTPUTS[name]}, status

    quantity.__name__ = name
    return quantity, {k: _DIMS[k] for k in OUTPUTS[name] if k in _DIMS}
