"""What ``rbo-jax simulate`` does alike for one body (:mod:`._simulate`), a lattice
(:mod:`._lattice`) and a rod (:mod:`._rod`): the initial state of the options, the solver's
options, and the end of every run (:func:`finish`): the printed table of the samples with the
energy drift, the output file, the summary line and the failure of a solve that stopped early.
The command modules import it; none imports another's helpers."""

from __future__ import annotations

from ._common import Failure, check_vector, table


def spread(indices: list[int], n: int) -> list[int]:
    """At most ``n`` of ``indices``, evenly spread, first and last kept."""
    import numpy as np

    if n <= 0:
        return []
    if len(indices) <= n:
        return indices
    pick = np.unique(np.round(np.linspace(0, len(indices) - 1, n)).astype(int))
    return [indices[i] for i in pick]


def equilibrium(model, option: str, guess=None, **kwargs):
    """:func:`rbo_jax.solve_equilibrium` of ``model``, or exit status 1 naming ``option``."""
    from ... import EquilibriumStatus, solve_equilibrium

    sol = solve_equilibrium(model, guess, **kwargs)
    if not bool(sol.ok):
        raise Failure(f"no equilibrium for {option}: {EquilibriumStatus[sol.status]}", code=1)
    return sol


def initial_state(args, model):
    """``(theta0, Omega0)`` of --theta0 and --Omega0 (with --about-equilibrium: theta0 about the
    equilibrium Newton finds from 0)."""
    import jax.numpy as jnp
    import numpy as np

    theta0 = check_vector(args.theta0, "theta0")
    Omega0 = check_vector(args.Omega0, "Omega0")
    if args.about_equilibrium:
        sol = equilibrium(model, "--about-equilibrium", jnp.zeros(3))
        print(
            f"equilibrium theta_eq = {np.asarray(sol.theta).tolist()} (Newton from 0, "
            f"|moment| = {float(sol.residual):.1e}); theta0 = theta_eq + --theta0"
        )
        theta0 = sol.theta + theta0
    return theta0, Omega0


def solver_options(args) -> dict:
    """--rtol, --atol and --max-steps as the keyword arguments of the library's solvers."""
    return {"rtol": args.rtol, "atol": args.atol, "max_steps": args.max_steps}


def print_samples(ds, reached, columns, values, max_rows) -> str:
    """Print at most ``max_rows`` of the ``reached`` samples of ``ds``: the ``columns`` with
    their ``values(i)`` at sample ``i``, then the energy and its drift from E(0) (relative
    where E(0) is finite and not 0); returns the line of the largest drift."""
    import numpy as np

    E = ds["energy"].values
    relative = bool(np.isfinite(E[0]) and E[0] != 0)
    drift = (E - E[0]) / (abs(E[0]) if relative else 1.0)
    rows = [
        [*values(i), float(E[i]), float(drift[i])]
        for i in spread(list(np.flatnonzero(reached)), max_rows)
    ]
    if rows:
        print(table([*columns, "K + U", "rel. drift" if relative else "drift"], rows))
        if len(rows) < int(reached.sum()):
            print(f"   ({len(rows)} of {int(reached.sum())} samples shown; --max-rows)")
    max_drift = float(np.max(np.abs(drift[reached]))) if reached.any() else float("nan")
    where = "relative to E(0) = " + format(E[0], ".6g") if relative else "absolute"
    return f"max |energy drift| = {max_drift:.2e} ({where})"


def finish(args, traj, ds, reached, columns, values, elapsed: float, counted: str = "") -> int:
    """The end of ``rbo-jax simulate``: the table of the ``reached`` samples of ``ds``
    (:func:`print_samples`), ``ds`` written to ``--out`` (CSV or a dataset, by the suffix), one
    line with the steps (and ``counted``), the status, the energy drift and the wall time
    ``elapsed``; exit status 1 with the solver's message when the solve stopped before the last
    sample."""
    from .._io import write_dataset, write_trajectory_csv

    drift = print_samples(ds, reached, columns, values, args.max_rows)
    if args.out is not None:
        if args.out.lower().rstrip("/").endswith(".csv"):
            write_trajectory_csv(ds, args.out)
        else:
            write_dataset(ds, args.out)
    print(
        f"   {int(traj.num_steps)} steps, {counted}status: {traj.status_name}, {drift}, wall "
        f"time {elapsed:.2f} s (compilation included)"
        + (f"; trajectory -> {args.out}" if args.out else "")
    )
    if not bool(traj.ok):
        last = ds["t"].values[reached][-1] if reached.any() else None
        where = f" after t = {last:g} (later samples are inf)" if last is not None else ""
        raise Failure(f"the solver stopped{where}: {traj.message}", code=1)
    return 0
