"""``rbo-jax fit``: foundation (and friction) parameters from a trajectory, by least squares
through the ODE solver (:func:`rbo_jax.fit`), with Gauss-Newton standard errors."""

from __future__ import annotations

import argparse

from .._io import DATASET_SUFFIXES, read_trajectory_file, write_dataset
from ._common import (
    Failure,
    check_count,
    check_number,
    check_output,
    check_state,
    check_suffix,
    check_times,
    check_vector,
    load_index,
    model_spec,
    model_table,
)
from ._memory import BYTES_PER_FIT_SAMPLE, check_memory

PARAMS = ("c", "d", "alpha", "beta", "b")
_SYNTHETIC_STATE = ((0.8, -0.3, 0.5), (0.2, 1.1, -0.7))


def _read_data(path: str, theta0, Omega0, sigma_theta, sigma_Omega):
    """A :class:`rbo_jax.TrajectoryData` from a file (format in ``rbo-jax fit --help``)."""
    from ... import TrajectoryData

    check_suffix(path, DATASET_SUFFIXES + (".npz",), "--data")
    try:
        arrays = read_trajectory_file(path)
    except (OSError, ValueError) as e:
        raise Failure(f"--data {path}: {str(e).rstrip('.')}.") from None
    if "t" not in arrays:
        raise Failure(
            f"--data {path}: missing array 't' (the sample times, shape (n,); 'ts' "
            f"is accepted too); the file has {sorted(arrays) or 'no arrays'}."
        )
    observed = {name: arrays[name] for name in ("theta", "Q", "Omega", "omega") if name in arrays}
    if not observed:
        raise Failure(
            f"--data {path}: missing array 'theta' (the turn-vectors, shape (n, 3)); "
            "or give the attitude as 'Q' (n, 3, 3) or angular velocities 'Omega' / "
            f"'omega' (n, 3); the file has {sorted(arrays)}."
        )
    if "theta" in observed or "Q" in observed:
        observed.pop("omega", None)  # a trajectory dataset holds both; Omega is the state
    theta0 = arrays.get("theta0") if theta0 is None else theta0
    Omega0 = arrays.get("Omega0") if Omega0 is None else Omega0
    try:
        data = TrajectoryData(
            arrays["t"],
            **observed,
            theta0=theta0,
            Omega0=Omega0,
            sigma_theta=sigma_theta if ("theta" in observed or "Q" in observed) else None,
            sigma_Omega=sigma_Omega if "Omega" in observed else None,
        )
    except (ValueError, TypeError) as e:
        hint = (
            " Give the initial state with --theta0/--Omega0, or as arrays 'theta0'/'Omega0' "
            "(3,) in the file."
            if " is needed" in str(e)
            else ""
        )
        raise Failure(f"--data {path}: {e}{hint}") from None
    return data, sorted(observed)


def _check_options(args, names, table):
    bad = [x for x in names if x not in PARAMS]
    if not names or bad or len(set(names)) != len(names):
        raise Failure(
            f"--params must be distinct names among {', '.join(PARAMS)}, got {args.params!r}."
        )
    for name in names:
        if name in ("alpha", "beta") and args.foundation != "barrier":
            raise Failure(f"--params {name} needs --foundation barrier (4.49).")
        if name == "b" and args.friction is None:
            raise Failure("--params b needs --friction (its starting value).")
        if name in ("c", "d") and name not in table["foundation"]:
            raise Failure(
                f"--params {name}: --foundation {args.foundation} has no parameter {name}."
            )
        v = args.friction if name == "b" else table["foundation"][name]
        if not (v > 0 and v < float("inf")):
            option = "--friction" if name == "b" else f"--{name}"
            raise Failure(
                f"{option} {v:g}: {name} is fitted (--params), so its starting value "
                f"must be finite and > 0 (the fit works with log {name})."
            )
    for option in ("max_steps", "solver_max_steps"):
        check_count(getattr(args, option), f"--{option.replace('_', '-')}")
    for option in ("tol", "rtol", "atol"):
        check_number(getattr(args, option), f"--{option}", above=0)
    for option in ("sigma_theta", "sigma_Omega"):
        if getattr(args, option) is not None:
            if args.synthetic:
                raise Failure(
                    f"--{option.replace('_', '-')} is the noise of --data; with "
                    "--synthetic the noise level is --noise."
                )
            check_number(getattr(args, option), f"--{option.replace('_', '-')}", above=0)
    check_state(args.theta0, "--theta0")
    check_state(args.Omega0, "--Omega0")
    if args.out is not None:
        check_output(args.out, "--out", DATASET_SUFFIXES)


def check_fit_memory(args, samples: int, n_params: int, what: str) -> None:
    """Refuse a fit whose residuals and Jacobian do not fit in memory (exit status 2)."""
    directions = n_params + (6 if args.fit_initial_state else 0)
    check_memory(
        samples * (1 + directions) * BYTES_PER_FIT_SAMPLE,
        what,
        "fit fewer samples (--samples, or a shorter record in --data)",
    )


def _set(table, name, value):
    """Set a fitted parameter in the model table."""
    if name == "b":
        next(t for t in table["loads"] if t["type"] == "friction")["b"] = value
    else:
        table["foundation"][name] = value


def _get(table, name):
    if name == "b":
        return next(t for t in table["loads"] if t["type"] == "friction")["b"]
    return table["foundation"][name]


def _synthetic(args, table, options, names, theta0, Omega0):
    """Data simulated from the model options (the truth); the table then holds the start."""
    import jax.numpy as jnp
    import numpy as np

    from ... import TrajectoryData, simulate

    check_times(args)
    check_number(args.noise, "--noise", minimum=0)
    check_number(args.offset, "--offset", above=-1)
    if args.seed < 0:
        raise Failure(f"--seed must be >= 0, got {args.seed}.")
    check_fit_memory(args, args.samples, len(names), "--samples")
    true_model = model_spec(table, options).build()
    th0 = jnp.asarray(_SYNTHETIC_STATE[0]) if theta0 is None else theta0
    Om0 = jnp.asarray(_SYNTHETIC_STATE[1]) if Omega0 is None else Omega0
    ts = jnp.linspace(0.0, args.t1, args.samples)
    traj = simulate(true_model, th0, Om0, ts, rtol=args.rtol, atol=args.atol, throw=False)
    if not bool(traj.ok):
        raise Failure(f"the synthetic trajectory failed: {traj.message}", code=1)
    theta, Omega = np.asarray(traj.theta), np.asarray(traj.Omega)
    if args.noise > 0:
        rng = np.random.default_rng(args.seed)
        theta = theta + args.noise * rng.standard_normal(theta.shape)
        Omega = Omega + args.noise * rng.standard_normal(Omega.shape)
    sigma = args.noise if args.noise > 0 else None
    data = TrajectoryData(
        ts, theta=theta, Omega=Omega, theta0=th0, Omega0=Om0, sigma_theta=sigma, sigma_Omega=sigma
    )
    truth = {name: _get(table, name) for name in names}
    for name in names:
        _set(table, name, truth[name] * (1.0 + args.offset))
    source = (
        f"a synthetic trajectory (t1 = {args.t1:g}, {args.samples} samples, noise "
        f"{args.noise:g}) of the model with " + ", ".join(f"{n} = {v:g}" for n, v in truth.items())
    )
    return data, ["Omega", "theta"], truth, source


def _report(res, names, table, truth, data, args) -> str:
    """Print the estimates; returns the local-minimum note ("" if none)."""
    import numpy as np

    for name, value, se in zip(names, res.params, res.stderr):
        line = (
            f"  {name:>5} = {float(value):.12g} +/- {float(se):.2e}   (start {_get(table, name):g}"
        )
        if truth is not None:
            line += (
                f", truth {truth[name]:g}, relative error {abs(float(value) / truth[name] - 1):.1e}"
            )
        print(line + ")")
    if args.fit_initial_state:
        th, Om = res.initial_states[0]
        print(f"  theta0 = {np.asarray(th).tolist()}, Omega0 = {np.asarray(Om).tolist()}")
    print(
        f"  {res.num_steps} iterations, final loss {res.loss_history[-1]:.3e}, residual rms "
        f"{res.residual_rms:.3e}, {res.message}, wall time {res.wall_time:.2f} s "
        "(compilation included)"
    )
    # whitened residuals (rms ~ 1 at the right answer) when the noise is given, else in rad, rad/s
    whitened = any(
        getattr(data, name) is not None for name in ("sigma_theta", "sigma_omega", "sigma_Omega")
    )
    note = ""
    if res.converged and res.residual_rms > (3.0 if whitened else 1e-2):
        note = (
            f"the residual rms {res.residual_rms:.3g} is large "
            f"({'> 3 noise standard deviations' if whitened else '> 1e-2 rad or rad/s'}): "
            "the fit may have stopped in a local minimum (or the model does not describe the "
            "data), and the standard errors are then meaningless; try staged horizons "
            "(--horizons 0.2,0.5,1) or starting values closer to the answer."
        )
        print(f"  note: {note}")
    return note


def fit_command(args: argparse.Namespace) -> int:
    """``rbo-jax fit``: foundation parameters from a trajectory, by least squares through the
    ODE solver (:func:`rbo_jax.fit`), with Gauss-Newton standard errors."""
    from ... import fit

    names = [x.strip() for x in args.params.split(",") if x.strip()]
    table, options = model_table(args)
    _check_options(args, names, table)
    model_spec(table, options)  # the values given are valid
    theta0 = None if args.theta0 is None else check_vector(args.theta0, "theta0")
    Omega0 = None if args.Omega0 is None else check_vector(args.Omega0, "Omega0")
    truth = None
    if args.synthetic:
        data, observed, truth, source = _synthetic(args, table, options, names, theta0, Omega0)
    else:
        data, observed = _read_data(args.data, theta0, Omega0, args.sigma_theta, args.sigma_Omega)
        source = args.data
        if data.num_samples < 2:
            raise Failure(
                f"--data {args.data}: {data.num_samples} sample; a fit needs at least "
                "2 (the first is the initial state)."
            )
        check_fit_memory(
            args, data.num_samples, len(names), f"--data {args.data} ({data.num_samples:,} samples)"
        )
    spec = model_spec(table, options)
    print(f"Model: {spec.describe()} (starting values)")
    print(
        f"Fitting {', '.join(names)} to {source}: {data.num_samples} samples of "
        f"{', '.join(observed)}; Levenberg-Marquardt through the ODE solver "
        f"({args.integrator})"
    )
    friction = load_index(spec, "friction") if "b" in names else None

    def selector(m):
        return tuple(
            m.loads[friction].b if name == "b" else getattr(m.foundation, name) for name in names
        )

    try:
        res = fit(
            spec.build(),
            data,
            selector,
            fit_initial_state=args.fit_initial_state,
            max_steps=args.max_steps,
            tol=args.tol,
            solve_rtol=args.rtol,
            solve_atol=args.atol,
            solve_max_steps=args.solver_max_steps,
            integrator=args.integrator,
            progress=args.progress,
            horizons=args.horizons,
        )
    except FloatingPointError as e:
        raise Failure(f"the fit could not start: {e}", code=1) from None
    note = _report(res, names, table, truth, data, args)
    if args.out is not None:
        attrs = {
            "model": spec.describe(),
            "data": str(source),
            "note": note,
            "command": "rbo-jax " + " ".join(args.argv),
            "num_samples": data.num_samples,
            "observed": " ".join(observed),
        }
        if truth is not None:
            attrs["truth"] = " ".join(f"{n}={v:.17g}" for n, v in truth.items())
        write_dataset(res.to_xarray(names, **attrs), args.out)
        print(f"  result -> {args.out}")
    if not res.converged:
        raise Failure(f"the fit did not converge: {res.message}", code=1)
    return 0
