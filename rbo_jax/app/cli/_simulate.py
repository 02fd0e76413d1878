"""``rbo-jax simulate``: one trajectory of the model given by the options, as a table and a
dataset."""

from __future__ import annotations

import argparse
import time

from ._common import (
    FORMATTER,
    NEGATIVE,
    UNITS,
    Failure,
    add_model_options,
    check_suffix,
    check_vector,
    floats,
    spec_from_args,
    table,
    wrap,
)

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


def _check_options(args):
    if args.out is not None:
        check_suffix(args.out, OUT_SUFFIXES, "--out")
    if not args.t1 > 0:
        raise Failure(f"--t1 must be > 0, got {args.t1:g}.")
    if args.samples < 2:
        raise Failure(f"--samples must be >= 2, got {args.samples}.")
    if args.max_steps < 1:
        raise Failure(f"--max-steps must be >= 1, got {args.max_steps}.")
    if not (args.rtol > 0 and args.atol > 0):
        raise Failure(f"--rtol and --atol must be > 0, got {args.rtol:g}, {args.atol:g}.")


def _initial_state(args, model):
    import jax.numpy as jnp
    import numpy as np

    from ... import EquilibriumStatus, solve_equilibrium

    theta0 = check_vector(args.theta0, "theta0")
    Omega0 = check_vector(args.Omega0, "Omega0")
    if args.about_equilibrium:
        sol = solve_equilibrium(model, jnp.zeros(3))
        if not bool(sol.ok):
            raise Failure("no equilibrium for --about-equilibrium: "
                          f"{EquilibriumStatus[sol.status]}", code=1)
        print(f"equilibrium theta_eq = {np.asarray(sol.theta).tolist()} (Newton from 0, "
              f"|moment| = {float(sol.residual):.1e}); theta0 = theta_eq + --theta0")
        theta0 = sol.theta + theta0
    return theta0, Omega0


def _print_table(ds, max_rows):
    import numpy as np

    E, t, theta = ds["energy"].values, ds["t"].values, ds["theta"].values
    reached = ds["reached"].values
    relative = bool(np.isfinite(E[0]) and E[0] != 0)
    drift = (E - E[0]) / (abs(E[0]) if relative else 1.0)
    rows = [[float(t[i]), float(np.linalg.norm(theta[i])), *map(float, theta[i]), float(E[i]),
             float(drift[i])] for i in _spread(list(np.flatnonzero(reached)), max_rows)]
    if rows:
        print(table(["t", "|theta|", "theta_x", "theta_y", "theta_z", "K + U",
                     "rel. drift" if relative else "drift"], rows))
        if len(rows) < int(reached.sum()):
            print(f"   ({len(rows)} of {int(reached.sum())} samples shown; --max-rows)")
    max_drift = float(np.max(np.abs(drift[reached]))) if reached.any() else float("nan")
    where = "relative to E(0) = " + format(E[0], ".6g") if relative else "absolute"
    return f"max |energy drift| = {max_drift:.2e} ({where})"


def simulate_command(args: argparse.Namespace) -> int:
    """``rbo-jax simulate``: one trajectory of the model given by the options, as a table."""
    import jax.numpy as jnp

    from ... import simulate
    from .._io import write_dataset, write_trajectory_csv

    _check_options(args)
    spec = spec_from_args(args)
    model = spec.build()
    print(f"Rigid body oscillator, right form (4.55)-(4.56): {spec.describe()}")
    theta0, Omega0 = _initial_state(args, model)
    ts = jnp.linspace(0.0, args.t1, args.samples)
    start = time.perf_counter()
    traj = simulate(model, theta0, Omega0, ts, rtol=args.rtol, atol=args.atol,
                    max_steps=args.max_steps, throw=False, progress=args.progress)
    ds = traj.to_xarray(model=spec.describe(), command="rbo-jax " + " ".join(args.argv))
    elapsed = time.perf_counter() - start
    drift = _print_table(ds, args.max_rows)
    if args.out is not None:
        if args.out.lower().endswith(".csv"):
            write_trajectory_csv(ds, args.out)
        else:
            write_dataset(ds, args.out)
    print(f"   {int(traj.num_steps)} steps, status: {traj.status_name}, {drift}, "
          f"wall time {elapsed:.2f} s (compilation included)"
          + (f"; trajectory -> {args.out}" if args.out else ""))
    if not bool(traj.ok):
        reached = ds["reached"].values
        last = ds["t"].values[reached][-1] if reached.any() else None
        where = f" after t = {last:g} (later samples are inf)" if last is not None else ""
        raise Failure(f"the solver stopped{where}: {traj.message}", code=1)
    return 0


def add_simulate(sub) -> None:
    p = sub.add_parser(
        "simulate", formatter_class=FORMATTER,
        help="Simulate one oscillator and print t, |theta|, theta, energy K + U and its drift.",
        description=wrap(
            "Integrate the rigid body oscillator (right form (4.55)-(4.56), Dopri8 with adaptive "
            "steps) from (theta0, Omega0) and print a table of the turn-vector theta, the "
            "energy K + U (4.124) and its drift relative to E(0), then a summary line (solver "
            "steps, status, max |energy drift|, wall time). Without friction and external "
            "moments K + U is conserved, so the drift measures the accuracy; follower/dead "
            "moments and friction change it physically. Exit status 1 when the solver stops "
            "early (a singular point |theta| = 2 pi of Z (4.11), a barrier of (4.49) crossed, "
            "the step budget, a step-size collapse), with the reason; 2 for invalid options or "
            "parameters. " + UNITS),
        epilog="examples:\n"
        "  rbo-jax simulate --foundation barrier --c 1 --d 2 --alpha 2 --beta 1.5 \\\n"
        "      --theta0 0.8,-0.3,0.5 --Omega0 0.2,1.1,-0.7 --t1 20 --out run.nc\n"
        "  rbo-jax simulate --follower 0.4 --about-equilibrium --theta0 1e-6,0,0 --t1 60\n\n"
        + wrap(NEGATIVE),
    )
    add_model_options(p, "its parameters.")
    g = p.add_argument_group("initial state and solver")
    g.add_argument("--theta0", type=floats, default=(0.0, 0.0, 0.0), metavar="X,Y,Z",
                   help="initial turn-vector theta0 (rad; |theta0| is the turn angle about the "
                   "axis theta0/|theta0|, eq. (4.3)) (default 0,0,0)")
    g.add_argument("--Omega0", type=floats, default=(0.0, 0.0, 0.0), metavar="X,Y,Z",
                   help="initial right (body-frame) angular velocity Omega0 (rad/s), "
                   "omega = P.Omega (default 0,0,0)")
    g.add_argument("--about-equilibrium", action="store_true",
                   help="start at theta_eq + theta0, theta_eq the equilibrium (zero moment at "
                   "rest, (4.61)) found by Newton from 0; under a follower moment with the "
                   "quadratic foundation theta_eq = (M/d) k, eq. (4.62)")
    g.add_argument("--t1", type=float, default=10.0,
                   help="final time; the solve runs from t = 0 (default 10)")
    g.add_argument("--samples", type=int, default=11,
                   help="number of equally spaced output times in [0, t1], both ends included "
                   "(default 11)")
    g.add_argument("--max-rows", type=int, default=101,
                   help="print at most this many of the samples, evenly spread (0: only the "
                   "summary; --out always gets all) (default 101)")
    g.add_argument("--rtol", type=float, default=1e-10,
                   help="relative tolerance of the step-size controller (default 1e-10)")
    g.add_argument("--atol", type=float, default=1e-10,
                   help="absolute tolerance of the step-size controller (default 1e-10)")
    g.add_argument("--max-steps", type=int, default=100_000,
                   help="solver step budget; exhausting it stops the solve with exit status 1 "
                   "(default 100000)")
    g.add_argument("--out", default=None, metavar="FILE",
                   help="write the whole trajectory: FILE.nc (netCDF) or FILE.zarr, the xarray "
                   "Dataset of Trajectory.to_xarray() (variables theta, Omega, omega, energy, "
                   "reached over t and component; attributes status, message, num_steps, "
                   "model), or FILE.csv (columns t, theta_x..z, Omega_x..z, energy); written also "
                   "when the solver fails (later samples are inf). FILE.nc and FILE.zarr are "
                   "valid input of 'rbo-jax fit --data'")
    g.add_argument("--progress", action="store_true",
                   help="show a progress bar of the solve (tqdm)")
    p.set_defaults(func=simulate_command)
