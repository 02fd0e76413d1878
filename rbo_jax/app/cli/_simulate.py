"""``rbo-jax simulate``: one trajectory of the model given by the options, as a table and a
dataset; with ``--lattice SPEC`` a chain or grid of copies of that body (:mod:`._lattice`)."""

from __future__ import annotations

import argparse
import time

from ._common import (
    Failure,
    check_count,
    check_number,
    check_output,
    check_state,
    check_vector,
    spec_from_args,
    table,
)
from ._memory import BYTES_PER_SAMPLE, check_memory

OUT_SUFFIXES = (".nc", ".zarr", ".csv")


def _spread(indices: list[int], n: int) -> list[int]:
    """At most ``n`` of ``indices``, evenly spread, first and last kept."""
    import numpy as np

    if n <= 0:
        return []
    if len(indices) <= n:
        return indices
    pick = np.unique(np.round(np.linspace(0, len(indices) - 1, n)).astype(int))
    return [indices[i] for i in pick]


def check_solve_options(args) -> None:
    """The options of the solve shared by one body and a lattice (and ``demo``'s --t1,
    --samples): everything checked before anything is computed."""
    check_number(args.t1, "--t1", above=0)
    if args.samples < 2:
        raise Failure(f"--samples must be >= 2, got {args.samples}.")
    check_count(args.max_steps, "--max-steps")
    if args.max_rows < 0:
        raise Failure(f"--max-rows must be >= 0, got {args.max_rows}.")
    check_number(args.rtol, "--rtol", above=0)
    check_number(args.atol, "--atol", above=0)
    check_state(args.theta0, "--theta0")
    check_state(args.Omega0, "--Omega0")


def check_samples_memory(samples: int, per_sample: float, fixed: float = 0.0) -> None:
    """Refuse a number of samples whose trajectory does not fit in memory (exit status 2)."""
    check_memory(
        fixed + samples * per_sample,
        f"--samples {samples}",
        "give fewer samples (--samples N: the printed and written times; the solver's "
        "accuracy does not depend on them)",
    )


def _check_options(args):
    if args.out is not None:
        check_output(args.out, "--out", OUT_SUFFIXES)
    check_solve_options(args)
    if args.progress and args.integrator != "simulate" and args.lattice is None:
        raise Failure("--progress needs --integrator simulate (fast_simulate has no progress bar).")
    if args.lattice is None:
        check_samples_memory(args.samples, BYTES_PER_SAMPLE)


def _initial_state(args, model):
    import jax.numpy as jnp
    import numpy as np

    from ... import EquilibriumStatus, solve_equilibrium

    theta0 = check_vector(args.theta0, "theta0")
    Omega0 = check_vector(args.Omega0, "Omega0")
    if args.about_equilibrium:
        sol = solve_equilibrium(model, jnp.zeros(3))
        if not bool(sol.ok):
            raise Failure(
                f"no equilibrium for --about-equilibrium: {EquilibriumStatus[sol.status]}", code=1
            )
        print(
            f"equilibrium theta_eq = {np.asarray(sol.theta).tolist()} (Newton from 0, "
            f"|moment| = {float(sol.residual):.1e}); theta0 = theta_eq + --theta0"
        )
        theta0 = sol.theta + theta0
    return theta0, Omega0


def _print_table(ds, max_rows):
    import numpy as np

    E, t, theta = ds["energy"].values, ds["t"].values, ds["theta"].values
    reached = ds["reached"].values
    relative = bool(np.isfinite(E[0]) and E[0] != 0)
    drift = (E - E[0]) / (abs(E[0]) if relative else 1.0)
    rows = [
        [
            float(t[i]),
            float(np.linalg.norm(theta[i])),
            *map(float, theta[i]),
            float(E[i]),
            float(drift[i]),
        ]
        for i in _spread(list(np.flatnonzero(reached)), max_rows)
    ]
    if rows:
        print(
            table(
                [
                    "t",
                    "|theta|",
                    "theta_x",
                    "theta_y",
                    "theta_z",
                    "K + U",
                    "rel. drift" if relative else "drift",
                ],
                rows,
            )
        )
        if len(rows) < int(reached.sum()):
            print(f"   ({len(rows)} of {int(reached.sum())} samples shown; --max-rows)")
    max_drift = float(np.max(np.abs(drift[reached]))) if reached.any() else float("nan")
    where = "relative to E(0) = " + format(E[0], ".6g") if relative else "absolute"
    return f"max |energy drift| = {max_drift:.2e} ({where})"


def simulate_command(args: argparse.Namespace) -> int:
    """``rbo-jax simulate``: one trajectory of the model given by the options, as a table (with
    ``--lattice``: :func:`._lattice.simulate_lattice`)."""
    import jax.numpy as jnp

    from ... import fast_simulate, simulate
    from .._io import write_dataset, write_trajectory_csv
    from ._lattice import refuse_lattice_options, simulate_lattice

    if args.lattice is None:
        refuse_lattice_options(args)
    _check_options(args)
    spec = spec_from_args(args)
    if args.lattice is not None:
        return simulate_lattice(args, spec)
    model = spec.build()
    print(f"Rigid body oscillator, right form (4.55)-(4.56): {spec.describe()}")
    theta0, Omega0 = _initial_state(args, model)
    ts = jnp.linspace(0.0, args.t1, args.samples)
    start = time.perf_counter()
    if args.integrator == "simulate":
        traj = simulate(
            model,
            theta0,
            Omega0,
            ts,
            rtol=args.rtol,
            atol=args.atol,
            max_steps=args.max_steps,
            throw=False,
            progress=args.progress,
        )
    else:
        traj = fast_simulate(
            model,
            theta0,
            Omega0,
            ts,
            rtol=args.rtol,
            atol=args.atol,
            max_steps=args.max_steps,
            throw=False,
        )
    ds = traj.to_xarray(model=spec.describe(), command="rbo-jax " + " ".join(args.argv))
    elapsed = time.perf_counter() - start
    drift = _print_table(ds, args.max_rows)
    if args.out is not None:
        if args.out.lower().rstrip("/").endswith(".csv"):
            write_trajectory_csv(ds, args.out)
        else:
            write_dataset(ds, args.out)
    print(
        f"   {int(traj.num_steps)} steps, status: {traj.status_name}, {drift}, "
        f"wall time {elapsed:.2f} s (compilation included)"
        + (f"; trajectory -> {args.out}" if args.out else "")
    )
    if not bool(traj.ok):
        reached = ds["reached"].values
        last = ds["t"].values[reached][-1] if reached.any() else None
        where = f" after t = {last:g} (later samples are inf)" if last is not None else ""
        raise Failure(f"the solver stopped{where}: {traj.message}", code=1)
    return 0
