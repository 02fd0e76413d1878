r"""The rod quantities of ``rbo-jax sweep``: functions of one parameter point of a ``[rod]``
(:class:`~rbo_jax.app.rodspec.RodSpec`), composed from :mod:`rbo_jax.lattice`.

- ``rod_stability``: the equilibrium of the rod under its loads (Newton,
  :func:`rbo_jax.lattice.solve_equilibrium`), the eigenvalues $p$ of its linearisation
  (:func:`rbo_jax.lattice.linearize`) and Lyapunov's first method: ``spectral_abscissa``
  $\max\mathrm{Re}\,p$, ``frequency`` $|\mathrm{Im}\,p|$ of that eigenvalue (the flutter
  frequency where it grows; 0 at divergence), ``stable`` (the criterion of
  :func:`rbo_jax.lattice.critical_load`: $\max\mathrm{Re}\,p \le$ ``rtol`` $\cdot\max(|p|, 1)$,
  and an equilibrium found) and ``tip`` (the tip's position at the equilibrium); status: the
  equilibrium's (:class:`rbo_jax.lattice.RodEquilibriumStatus`), values NaN where it failed;
- ``rod_critical_load``: the load factor $\lambda_{cr}$ of
  :func:`rbo_jax.lattice.critical_load`: the smallest $\lambda \in$ (``load_min``,
  ``load_max``] at which the equilibrium of the rod with every load times $\lambda$ is unstable
  (or is not found); ``inf`` where it stays stable. With a unit load
  (``f = [0, 0, -1]``) it is the critical load itself: Beck's flutter load
  $20.05\,EI/L^2$, the Ziegler paradox of a small damping (about $10.94\,EI/L^2$), Pflüger's
  load falling with the tip mass. Its status is always ``successful``: a failed equilibrium
  counts as unstable, so $\lambda_{cr}$ always has that meaning.

The ``[stability]`` table: ``rtol`` (default 1e-9; a small damping needs a smaller one, e.g.
1e-14, see :func:`rbo_jax.lattice.critical_load`), ``steps`` (Newton's load steps, default 1);
for ``rod_critical_load`` also ``load_max`` (required), ``load_min`` (0), ``n_scan`` (32),
``n_bisect`` (40).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import jax.numpy as jnp

from .._validation import FINITE, POSITIVE
from ._reader import Reader
from .rodspec import RodSpec

__all__ = [
    "ROD",
    "ROD_DEFAULT_PLOT",
    "ROD_OUTPUTS",
    "ROD_QUANTITIES",
    "RodSettings",
    "make_rod_quantity",
    "read_rod_settings",
]

ROD_QUANTITIES = {
    "rod_stability": "the spectral abscissa (and stable flag, flutter frequency, tip) of the "
    "[rod]'s equilibrium",
    "rod_critical_load": "the load factor at which the [rod]'s equilibrium loses stability "
    "(rbo_jax.lattice.critical_load)",
}
ROD_OUTPUTS = {
    "rod_stability": ("spectral_abscissa", "stable", "frequency", "tip"),
    "rod_critical_load": ("critical_load",),
}
ROD_DEFAULT_PLOT = {"rod_stability": "spectral_abscissa", "rod_critical_load": "critical_load"}
ROD = tuple(ROD_QUANTITIES)


@dataclasses.dataclass(frozen=True)
class RodSettings:
    """The numbers of a rod quantity besides the rod (the ``[stability]`` table)."""

    rtol: float = 1e-9
    steps: int = 1
    load_max: float | None = None
    load_min: float = 0.0
    n_scan: int = 32
    n_bisect: int = 40


def read_rod_settings(r: Reader, cfg: Mapping, name: str) -> RodSettings:
    """The ``[stability]`` table of quantity ``name`` (module docstring), checked."""
    t = r.table(cfg, "stability", "config", required=name == "rod_critical_load")
    where = "[stability]"
    critical = ("load_max", "load_min", "n_scan", "n_bisect")
    if name == "rod_critical_load":
        r.keys(t, ("rtol", "steps", *critical), where, required=("load_max",))
    else:
        for k in critical:
            if k in t:
                r.fail(f"{where} {k}", "is only used by quantity 'rod_critical_load'.")
        r.keys(t, ("rtol", "steps"), where)
    s = RodSettings(
        rtol=r.number(t, "rtol", where, default=1e-9, requirement=POSITIVE, axis=False),
        steps=r.integer(t, "steps", where, default=1),
    )
    if name != "rod_critical_load":
        return s
    lo = r.number(t, "load_min", where, default=0.0, requirement=FINITE, axis=False)
    hi = r.number(t, "load_max", where, requirement=FINITE, axis=False)
    if not hi > lo:
        r.fail(f"{where} load_max", f"must exceed load_min ({lo:g}), got {hi:g}.")
    return dataclasses.replace(
        s,
        load_max=hi,
        load_min=lo,
        n_scan=r.integer(t, "n_scan", where, default=32),
        n_bisect=r.integer(t, "n_bisect", where, default=40, minimum=0),
    )


def _stability(spec: RodSpec, s: RodSettings):
    from ..lattice import linearize, solve_equilibrium

    def rod_stability(**point):
        rod = spec.build(point)
        sol = solve_equilibrium(rod, steps=s.steps)
        p = jnp.linalg.eigvals(linearize(rod, sol.state))
        k = jnp.argmax(p.real)
        abscissa = p.real[k]
        stable = sol.ok & (abscissa <= s.rtol * jnp.maximum(jnp.max(jnp.abs(p)), 1.0))
        nan = jnp.where(sol.ok, 0.0, jnp.nan)
        values = {
            "spectral_abscissa": abscissa + nan,
            "stable": stable,
            "frequency": jnp.abs(p.imag[k]) + nan,
            "tip": sol.state.tip + nan,
        }
        return values, sol.status

    return rod_stability, {"tip": ("component",)}


def _critical(spec: RodSpec, s: RodSettings):
    from ..lattice import RodEquilibriumStatus, critical_load

    def rod_critical_load(**point):
        lam = critical_load(
            lambda factor: spec.build(point, factor),
            s.load_max,
            load_min=s.load_min,
            n_scan=s.n_scan,
            n_bisect=s.n_bisect,
            rtol=s.rtol,
            steps=s.steps,
        )
        return {"critical_load": lam}, RodEquilibriumStatus.successful

    return rod_critical_load, {}


def make_rod_quantity(name: str, spec: RodSpec, s: RodSettings):
    """``(quantity(**point), dims)`` of the rod quantity ``name`` for the sweep engine."""
    return _stability(spec, s) if name == "rod_stability" else _critical(spec, s)
