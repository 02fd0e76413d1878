r"""The quantities of ``rbo-jax sweep``: functions of one parameter point, composed from library
calls on a :class:`~rbo_jax.app.spec.ModelSpec`.

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
- ``rod_stability``, ``rod_critical_load``: of a ``[rod]`` (:mod:`rbo_jax.app._rod_sweep`), the
  stability of its equilibrium and its critical load factor.

Every quantity returns its values and a status: the solver's
(:class:`rbo_jax.SolveStatus`) for the simulations, the equilibrium's
(:class:`rbo_jax.EquilibriumStatus`) for the others (values NaN where Newton failed).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax.numpy as jnp

from ..ensemble import fast_simulate
from ..maps import equilibrium_stability
from ..simulate import simulate
from ..stability import EquilibriumStatus, solve_equilibrium
from ._reader import Ref
from ._rod_sweep import ROD_DEFAULT_PLOT, ROD_OUTPUTS, ROD_QUANTITIES
from .spec import LatticeSpec, ModelSpec

QUANTITIES = {
    "final_state": "theta(t1) and Omega(t1) of simulate (and the number of steps)",
    "energy_drift": "max_t |E(t) - E(0)| / |E(0)| over `samples` times of simulate",
    "max_deviation": "max_t |theta(t) - theta(0)| over `samples` times of simulate",
    "spectral_abscissa": "max Re p of the spectrum at the equilibrium (Newton from theta_guess)",
    "bloch_growth": "max Re lambda(q) of the Bloch waves of the [lattice] at its uniform "
    "equilibrium",
    "bloch_frequencies": "the three non-negative frequencies Im lambda(q) of the Bloch waves of "
    "the [lattice] (and bloch_growth)",
    **ROD_QUANTITIES,
}
OUTPUTS = {
    "final_state": ("theta", "Omega", "num_steps"),
    "energy_drift": ("energy_drift", "num_steps"),
    "max_deviation": ("max_deviation", "num_steps"),
    "spectral_abscissa": ("spectral_abscissa", "kind", "theta_eq"),
    "bloch_growth": ("bloch_growth", "theta_eq"),
    "bloch_frequencies": ("bloch_frequencies", "bloch_growth", "theta_eq"),
    **ROD_OUTPUTS,
}
DEFAULT_PLOT = {
    "final_state": "theta",
    "energy_drift": "energy_drift",
    "max_deviation": "max_deviation",
    "spectral_abscissa": "spectral_abscissa",
    "bloch_growth": "bloch_growth",
    "bloch_frequencies": "bloch_frequencies",
    **ROD_DEFAULT_PLOT,
}
SIMULATION = ("final_state", "energy_drift", "max_deviation")
LATTICE = ("bloch_growth", "bloch_frequencies")
INTEGRATORS = {"fast_simulate": fast_simulate, "simulate": simulate}


@dataclasses.dataclass(frozen=True)
class Settings:
    """The numbers of a quantity besides the model: initial state, solver, equilibrium."""

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


def _vector(xs, point):
    return jnp.stack(
        [
            jnp.asarray(point[x.name] if isinstance(x, Ref) else x, dtype=jnp.result_type(float))
            for x in xs
        ]
    )


def _scalar(x, point):
    return jnp.asarray(point[x.name] if isinstance(x, Ref) else x, dtype=jnp.result_type(float))


def _bloch_quantity(name: str, spec: ModelSpec, lattice: LatticeSpec, s: Settings):
    from ..lattice import dispersion

    def bloch(**point):
        lat = lattice.build(spec, point)
        sol = solve_equilibrium(lat.body, _vector(s.theta_guess, point))
        ok = sol.status == EquilibriumStatus.successful
        theta_eq = jnp.where(ok, sol.theta, 0.0)
        lam = dispersion(lat, lattice.wavenumber(point), theta_eq=theta_eq)
        lam = jnp.where(ok, lam, jnp.nan + 0j)  # sorted by Im lambda: the branches' last
        values = {"bloch_growth": jnp.max(jnp.real(lam)), "theta_eq": sol.theta}
        if name == "bloch_frequencies":
            values = {"bloch_frequencies": jnp.imag(lam[3:])} | values
        return values, sol.status

    bloch.__name__ = name
    dims = {"theta_eq": ("component",)}
    return bloch, dims | ({"bloch_frequencies": ("branch",)} if name == "bloch_frequencies" else {})


def make_quantity(name: str, spec: ModelSpec, s: Settings, lattice: LatticeSpec | None = None):
    """``(quantity(**point), dims)`` for the sweep engine; ``lattice`` for the Bloch
    quantities."""
    if name in LATTICE:
        return _bloch_quantity(name, spec, lattice, s)
    if name == "spectral_abscissa":

        def spectral_abscissa(**point):
            r = equilibrium_stability(
                spec.build(point), _vector(s.theta_guess, point), rtol=s.classify_rtol
            )
            return {"spectral_abscissa": r.abscissa, "kind": r.kind, "theta_eq": r.theta}, r.status

        return spectral_abscissa, {"theta_eq": ("component",)}

    def quantity(**point):
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
        values["num_steps"] = traj.num_steps
        return values, traj.status

    quantity.__name__ = name
    dims = {"theta": ("component",), "Omega": ("component",)} if name == "final_state" else {}
    return quantity, dims
