"""``rbo-jax simulate``: one trajectory of the model given by the options, as a table and a
dataset; with ``--lattice SPEC`` a chain or grid of copies of that body (:mod:`._lattice`, which
shares the initial state, the table and the solver's options with this module through
:mod:`._samples`); with ``--rod SPEC`` a rod (:mod:`._rod`)."""

from __future__ import annotations

import argparse
import time

from ._common import (
    Failure,
    check_count,
    check_number,
    check_output,
    check_state,
    check_times,
    spec_from_args,
)
from ._lattice import refuse_lattice_options, simulate_lattice
from ._memory import BYTES_PER_SAMPLE, check_memory
from ._rod import refuse_rod_options, simulate_rod_command
from ._samples import finish, initial_state, solver_options

OUT_SUFFIXES = (".nc", ".zarr", ".csv")


def check_solve_options(args) -> None:
    """The options of the solve shared by one body and a lattice (and ``demo``'s --t1,
    --samples): everything checked before anything is computed."""
    check_times(args)
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


def simulate_command(args: argparse.Namespace) -> int:
    """``rbo-jax simulate``: one trajectory of the model given by the options, as a table (with
    ``--lattice``: :func:`._lattice.simulate_lattice`; with ``--rod``:
    :func:`._rod.simulate_rod_command`)."""
    import jax.numpy as jnp
    import numpy as np

    from ... import fast_simulate, simulate

    if args.rod is None:  # the rod's own checks refuse the options of one body
        refuse_rod_options(args)
        if args.lattice is None:
            refuse_lattice_options(args)
    if args.out is not None:
        check_output(args.out, "--out", OUT_SUFFIXES)
    check_solve_options(args)
    if args.rod is not None:
        return simulate_rod_command(args)
    if args.progress and args.integrator != "simulate" and args.lattice is None:
        raise Failure("--progress needs --integrator simulate (fast_simulate has no progress bar).")
    if args.lattice is None:
        check_samples_memory(args.samples, BYTES_PER_SAMPLE)
    spec = spec_from_args(args)
    if args.lattice is not None:
        return simulate_lattice(args, spec)
    try:
        model = spec.build()
    except ValueError as e:  # e.g. --A1 1e-300: positive, but A not positive definite in floats
        inertia = "--principal" if args.principal is not None else "--A1 and --A3"
        raise Failure(
            f"{inertia} (the inertia tensor (4.39)): {' '.join(str(e).split())}"
        ) from None
    print(f"Rigid body oscillator, right form (4.55)-(4.56): {spec.describe()}")
    theta0, Omega0 = initial_state(args, model)
    ts = jnp.linspace(0.0, args.t1, args.samples)
    start = time.perf_counter()
    if args.integrator == "simulate":  # fast_simulate has no progress bar
        solve, progress = simulate, {"progress": args.progress}
    else:
        solve, progress = fast_simulate, {}
    traj = solve(model, theta0, Omega0, ts, **solver_options(args), throw=False, **progress)
    ds = traj.to_xarray(model=spec.describe(), command="rbo-jax " + " ".join(args.argv))
    elapsed = time.perf_counter() - start
    t, theta = ds["t"].values, ds["theta"].values

    def values(i):
        return [float(t[i]), float(np.linalg.norm(theta[i])), *map(float, theta[i])]

    columns = ["t", "|theta|", "theta_x", "theta_y", "theta_z"]
    return finish(args, traj, ds, ds["reached"].values, columns, values, elapsed)
