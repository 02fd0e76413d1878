"""The ``rbo-jax`` command.

``rbo-jax reproduce`` (run by ``make demo``) reproduces the paper into ``out/report.md``.
``rbo-jax demo`` prints two short simulations as tables,
(1) a conservative oscillator whose energy K + U stays constant, and (2) the Nikolai problem
(4.57)–(4.62): a body displaced by 1e-6 rad from the equilibrium θ = (M/d)k under a follower
moment, whose bending deviation grows although the linear theory (4.74) predicts none.
``rbo-jax sweep CONFIG.toml`` runs a declarative parameter sweep.

``rbo-jax simulate`` integrates one oscillator given on the command line (inertia (4.39)/(4.40),
foundation (4.49)/(4.50), loads (4.57), (4.75), (4.84)) and prints a table with its energy;
``rbo-jax stability-map`` draws the Nikolai map (4.57)–(4.62), (4.69) over a grid of M, c, d, A3;
``rbo-jax fit`` fits foundation parameters to a recorded (or synthetic) trajectory.

Exit codes: 0 success; 1 the computation failed (a solver status, a fit that did not converge);
2 invalid input (options, parameters, files), with a message naming it.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import rbo_jax  # noqa: F401  (enables float64 before any array is made)


class _Failure(Exception):
    """A command ends with ``message`` on stderr and exit status ``code``."""

    def __init__(self, message: str, code: int = 2):
        super().__init__(message)
        self.code = code


# ---------------------------------------------------------------------------------------------
# Option parsing shared by simulate, stability-map and fit
# ---------------------------------------------------------------------------------------------


def _floats(text: str) -> tuple[float, ...]:
    """``"x,y,z"`` -> floats (any count: the package checks the shape and names the parameter)."""
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers such as 0.1,0,-0.2, got {text!r}") from None


def _horizons(text: str) -> tuple[float, ...]:
    """``"0.2,0.5,1"`` -> increasing fractions in (0, 1] (staged fitting of :func:`rbo_jax.fit`)."""
    values = _floats(text)
    if any(not 0.0 < h <= 1.0 for h in values) or list(values) != sorted(values):
        raise argparse.ArgumentTypeError(
            f"expected increasing fractions in (0, 1] such as 0.2,0.5,1, got {text!r}")
    return values


def _grid(text: str):
    """``"start:stop:num"`` (inclusive linspace), ``"a,b,c"`` or ``"a"`` -> 1-D float array."""
    import numpy as np

    try:
        if ":" in text:
            start, stop, num = text.split(":")
            n = int(num)
            if n < 1:
                raise ValueError
            values = np.linspace(float(start), float(stop), n)
        else:
            values = np.asarray([float(x) for x in text.split(",")])
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a value (0.5), a list (0.1,0.2,0.5) or start:stop:num with num >= 1 "
            f"(-0.8:0.8:41), got {text!r}") from None
    if not np.all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"values must be finite, got {text!r}")
    return values


def _wrap(text: str) -> str:
    """A description paragraph wrapped to 88 columns (the raw formatter keeps it as is)."""
    import textwrap

    return textwrap.fill(text, width=88)


_UNITS = ("Units: any consistent set, e.g. inertia kg m^2, stiffnesses N m/rad, moments N m, "
          "friction N m s, time s, angles rad.")
_NEGATIVE = ("Write a value starting with a minus sign as --opt=-0.3,1,0 (with '='), so that it "
             "is not read as an option.")


def _add_model_options(p: argparse.ArgumentParser, role: str) -> None:
    """The model options of ``simulate`` and ``fit``; ``role`` says what the values are."""
    g = p.add_argument_group("model", _wrap(
        f"The rigid body oscillator (4.55)-(4.56) with symmetry axis k; {role}"))
    g.add_argument("--A1", type=float, default=None, metavar="A1",
                   help="transverse principal moment of inertia A1 = A2 > 0 of the transversely "
                   "isotropic inertia tensor A = A1 (E - k k) + A3 k k, eq. (4.40) (default 1)")
    g.add_argument("--A3", type=float, default=None, metavar="A3",
                   help="axial principal moment of inertia A3 > 0 about k, eq. (4.40) "
                   "(default 0.6)")
    g.add_argument("--principal", type=_floats, default=None, metavar="A1,A2,A3",
                   help="instead of --A1/--A3: three principal moments of inertia (all > 0) "
                   "about the reference basis vectors e1, e2, e3, A = sum A_i e_i e_i, eq. (4.39)")
    g.add_argument("--axis", type=_floats, default=(0.0, 0.0, 1.0), metavar="X,Y,Z",
                   help="the axis k (normalised) of the foundation, the moments and the "
                   "inertia (4.40) (default 0,0,1)")
    g.add_argument("--foundation", choices=("quadratic", "barrier"), default="quadratic",
                   help="elastic foundation: 'quadratic' U = c/2 (theta^2 - (k.theta)^2) + "
                   "d/2 (k.theta)^2, eq. (4.50); 'barrier' the energy (4.49) with barriers "
                   "alpha, beta (default quadratic)")
    g.add_argument("--c", type=float, default=1.0,
                   help="bending stiffness c > 0 of (4.49)/(4.50) (default 1)")
    g.add_argument("--d", type=float, default=2.0,
                   help="torsional stiffness d > 0 of (4.49)/(4.50) (default 2)")
    g.add_argument("--alpha", type=float, default=None,
                   help="bending barrier alpha > 0 (rad) of (4.49): the domain is "
                   "|theta - (k.theta)k| < alpha; 'inf' switches it off (required by "
                   "--foundation barrier)")
    g.add_argument("--beta", type=float, default=None,
                   help="torsion barrier beta > 0 (rad) of (4.49): |k.theta| < beta; 'inf' "
                   "switches it off (required by --foundation barrier)")
    g = p.add_argument_group("loads", "External moments; any combination, they add up.")
    g.add_argument("--follower", type=float, default=None, metavar="M",
                   help="follower moment M_ex = M P.k turning with the body, eq. (4.57) (the "
                   "Nikolai problem; non-conservative) (default: none)")
    g.add_argument("--dead", type=float, default=None, metavar="M",
                   help="dead moment M_ex = M k of fixed direction, eq. (4.75) with l1 = 1, "
                   "l2 = 0 (default: none)")
    g.add_argument("--friction", type=float, default=None, metavar="b",
                   help="viscous friction M_ex = -b omega, b >= 0, omega the left angular "
                   "velocity, eq. (4.84) (default: none)")


def _model_spec(args: argparse.Namespace) -> dict:
    """The model options as keyword arguments of :func:`_make_model` (checks their combination;
    the values themselves are checked by the package's constructors)."""
    spec = {"k": tuple(args.axis), "foundation": args.foundation, "c": args.c, "d": args.d}
    if args.principal is not None:
        if args.A1 is not None or args.A3 is not None:
            raise _Failure("--principal replaces --A1 and --A3: give one or the other.")
        spec["principal"] = tuple(args.principal)
    else:
        spec["A1"] = 1.0 if args.A1 is None else args.A1
        spec["A3"] = 0.6 if args.A3 is None else args.A3
    if args.foundation == "barrier":
        if args.alpha is None or args.beta is None:
            raise _Failure("--foundation barrier needs --alpha and --beta (the barriers of "
                           "(4.49); 'inf' switches one off).")
        spec["alpha"], spec["beta"] = args.alpha, args.beta
    elif args.alpha is not None or args.beta is not None:
        raise _Failure("--alpha and --beta belong to --foundation barrier (4.49); the quadratic "
                       "foundation (4.50) has no barriers.")
    for name in ("follower", "dead", "friction"):
        if getattr(args, name) is not None:
            spec[name] = getattr(args, name)
    return spec


def _make_model(*, k, foundation="quadratic", c, d, alpha=None, beta=None, A1=None, A3=None,
                principal=None, follower=None, dead=None, friction=None):
    """A :class:`rbo_jax.RigidBodyOscillator` from plain parameters (traced values allowed, so
    the stability map builds it inside ``vmap``). Loads in the order follower, dead, friction."""
    import jax.numpy as jnp

    from rbo_jax import (
        BarrierFoundation,
        DeadMoment,
        FollowerMoment,
        Friction,
        QuadraticFoundation,
        RigidBodyOscillator,
        principal_inertia,
        transversely_isotropic_inertia,
    )

    k = jnp.asarray(k, dtype=float)
    if principal is not None:
        A = principal_inertia(jnp.asarray(principal, dtype=float), jnp.eye(3))
    else:
        A = transversely_isotropic_inertia(A1, A3, k)
    if foundation == "barrier":
        U = BarrierFoundation(c, d, alpha, beta, k)
    else:
        U = QuadraticFoundation(c, d, k)
    loads = []
    if follower is not None:
        loads.append(FollowerMoment(follower, k))
    if dead is not None:
        loads.append(DeadMoment(dead, k))
    if friction is not None:
        loads.append(Friction(friction))
    return RigidBodyOscillator(A, U, loads)


def _build_model(spec: dict):
    """:func:`_make_model` with the package's ``ValueError``/``TypeError`` as exit status 2."""
    try:
        return _make_model(**spec)
    except (ValueError, TypeError) as e:
        raise _Failure(str(e)) from None


def _describe(spec: dict) -> str:
    def g(x):
        return ",".join(f"{v:g}" for v in x) if isinstance(x, (tuple, list)) else f"{x:g}"

    if "principal" in spec:
        parts = [f"A = diag({g(spec['principal'])}) (4.39)"]
    else:
        parts = [f"A1 = {g(spec['A1'])}, A3 = {g(spec['A3'])} (4.40)"]
    parts.append(f"k = ({g(spec['k'])})")
    if spec["foundation"] == "barrier":
        parts.append(f"barrier foundation (4.49) c = {g(spec['c'])}, d = {g(spec['d'])}, "
                     f"alpha = {g(spec['alpha'])}, beta = {g(spec['beta'])}")
    else:
        parts.append(f"quadratic foundation (4.50) c = {g(spec['c'])}, d = {g(spec['d'])}")
    loads = [f"{name} {'b' if name == 'friction' else 'M'} = {g(spec[name])}"
             for name in ("follower", "dead", "friction") if name in spec]
    parts.append("loads: " + (", ".join(loads) if loads else "none"))
    return "; ".join(parts)


def _check_vector(x, name: str):
    """A (3,) vector, or exit status 2 with the package's message naming ``name``."""
    from rbo_jax.kinematics import _as_vector

    try:
        return _as_vector(x, name)
    except (ValueError, TypeError) as e:
        raise _Failure(str(e)) from None


def _suffix(path: str, allowed: tuple[str, ...], option: str) -> str:
    ext = os.path.splitext(path.rstrip("/"))[1].lower()
    if ext not in allowed:
        raise _Failure(f"{option} {path}: unknown format {ext or '(no suffix)'!r}; use "
                       + " or ".join(allowed) + ".")
    return ext


def _table(header: list[str], rows: list[list[float]]) -> str:
    widths = [max(12, len(h)) for h in header]
    out = ["  ".join(h.rjust(w) for h, w in zip(header, widths))]
    out.append("  ".join("-" * w for w in widths))
    for r in rows:
        out.append("  ".join(f"{v:{w}.4e}" if isinstance(v, float) else str(v).rjust(w)
                             for v, w in zip(r, widths)))
    return "\n".join(out)


def demo(args: argparse.Namespace) -> int:
    import jax.numpy as jnp
    import numpy as np

    from rbo_jax import (
        BarrierFoundation,
        FollowerMoment,
        QuadraticFoundation,
        RigidBodyOscillator,
        simulate,
        transversely_isotropic_inertia,
    )

    k = jnp.array([0.0, 0.0, 1.0])
    A = transversely_isotropic_inertia(1.0, 0.6, k)
    n = args.samples

    # (1) Conservative oscillator on the barrier foundation (4.49): energy is conserved.
    model = RigidBodyOscillator(A, BarrierFoundation(c=1.0, d=2.0, alpha=2.0, beta=1.5, k=k))
    ts = jnp.linspace(0.0, args.t1, n)
    start = time.perf_counter()
    traj = simulate(model, jnp.array([0.8, -0.3, 0.5]), jnp.array([0.2, 1.1, -0.7]), ts)
    elapsed = time.perf_counter() - start
    E = np.asarray(traj.energy)
    rows = [
        [float(t), float(np.linalg.norm(th)), float(th[2]), float(e), float((e - E[0]) / E[0])]
        for t, th, e in zip(np.asarray(traj.ts), np.asarray(traj.theta), E)
    ]
    print("1) Rigid body oscillator on the barrier foundation (4.49), A1 = 1, A3 = 0.6,")
    print("   c = 1, d = 2, alpha = 2, beta = 1.5; right form (4.55)-(4.56), Dopri8, rtol 1e-10")
    print(_table(["t", "|theta|", "k.theta", "K + U", "rel. drift"], rows))
    print(f"   {int(traj.num_steps)} steps, {elapsed:.2f} s including compilation; "
          f"max |energy drift| = {np.max(np.abs((E - E[0]) / E[0])):.2e}\n")

    # (2) The Nikolai paradox: follower moment, equilibrium theta = (M/d) k (4.62).
    c, d, M = 1.0, 2.0, 0.4
    model = RigidBodyOscillator(A, QuadraticFoundation(c=c, d=d, k=k), FollowerMoment(M, k))
    theta_eq = (M / d) * k
    ts = jnp.linspace(0.0, 4 * args.t1, n)
    traj = simulate(model, theta_eq + jnp.array([1e-6, 0.0, 0.0]), jnp.zeros(3), ts)
    dev = np.asarray(traj.theta) - np.asarray(theta_eq)
    rows = [
        [float(t), float(np.linalg.norm(dv[:2])), float(dv[2])]
        for t, dv in zip(np.asarray(traj.ts), dev)
    ]
    print(f"2) Nikolai problem (4.57)-(4.62): follower moment M = {M}, c = {c}, d = {d};")
    print("   start 1e-6 rad off the equilibrium theta = (M/d) k. The bending deviation grows,")
    print("   although the linearised theory (4.74) predicts bounded oscillations.")
    print(_table(["t", "|bending dev.|", "torsion dev."], rows))
    return 0


def sweep_command(args: argparse.Namespace) -> int:
    """``rbo-jax sweep CONFIG.toml``: run a declarative sweep (see ``examples/*.toml`` and
    :func:`rbo_jax.sweep_config.load_config`), write its zarr store and a PNG of the map."""
    import jax

    from rbo_jax.sweep import SweepError, status_counts
    from rbo_jax.sweep_config import ConfigError, load_config, run_config

    distributed = (args.coordinator, args.num_processes, args.process_id)
    if any(x is not None for x in distributed):
        if args.coordinator is None or args.num_processes is None or args.process_id is None:
            print("rbo-jax sweep: error: --coordinator, --num-processes and --process-id go "
                  "together.", file=sys.stderr)
            return 2
        jax.distributed.initialize(coordinator_address=args.coordinator,
                                   num_processes=args.num_processes, process_id=args.process_id)
    try:
        cfg = load_config(args.config)
    except ConfigError as e:
        print(f"rbo-jax sweep: error: {e}", file=sys.stderr)
        return 2
    try:
        import matplotlib

        matplotlib.use("Agg")
        plot = not args.no_plot
    except ImportError:
        print("rbo-jax sweep: matplotlib is not installed, no PNG (pip install 'rbo_jax[plot]').",
              file=sys.stderr)
        plot = False
    try:
        ds, png = run_config(cfg, resume=args.resume, overwrite=args.overwrite,
                             progress=not args.quiet, output=args.output, plot=plot)
    except (FileExistsError, SweepError) as e:
        print(f"rbo-jax sweep: error: {e}", file=sys.stderr)
        return 2
    out = args.output or cfg.output
    counts = status_counts(ds)
    failed = {k: v for k, v in counts.items() if v and k != "successful"}
    if jax.process_index() == 0 and (not args.quiet or failed):
        print(f"{cfg.quantity_name}: {sum(counts.values())} points -> {out}"
              + (f", map {png}" if png else ""))
        print("  status: " + ", ".join(f"{k} {v}" for k, v in counts.items() if v))
    return 0


def reproduce_command(args: argparse.Namespace) -> int:
    """``rbo-jax reproduce``: every check of the paper, written to OUT/report.md with figures."""
    from rbo_jax.reproduce import run_reproduction

    checks = run_reproduction(args.out, quick=args.quick, figures=not args.no_figures)
    failed = [c for c in checks if not c.passed]
    width = max(len(c.section) for c in checks)
    print()
    for c in checks:
        print(f"  {'pass' if c.passed else 'FAIL'}  {c.section:<{width}}  {c.quantity}  [{c.ours}]")
    print(f"\n{len(checks) - len(failed)} of {len(checks)} checks passed; report: "
          f"{args.out}/report.md")
    return 1 if failed else 0


# ---------------------------------------------------------------------------------------------
# rbo-jax simulate
# ---------------------------------------------------------------------------------------------


def _spread(indices: list[int], n: int) -> list[int]:
    """At most ``n`` of ``indices``, evenly spread, first and last kept."""
    import numpy as np

    if n <= 0:
        return []
    if len(indices) <= n:
        return indices
    pick = np.unique(np.round(np.linspace(0, len(indices) - 1, n)).astype(int))
    return [indices[i] for i in pick]


def simulate_command(args: argparse.Namespace) -> int:
    """``rbo-jax simulate``: one trajectory of the model given by the options, as a table."""
    import jax.numpy as jnp
    import numpy as np

    from rbo_jax import EquilibriumStatus, simulate, solve_equilibrium

    if args.out is not None:
        out_kind = _suffix(args.out, (".npz", ".csv"), "--out")
    if not args.t1 > 0:
        raise _Failure(f"--t1 must be > 0, got {args.t1:g}.")
    if args.samples < 2:
        raise _Failure(f"--samples must be >= 2, got {args.samples}.")
    if args.max_steps < 1:
        raise _Failure(f"--max-steps must be >= 1, got {args.max_steps}.")
    if not (args.rtol > 0 and args.atol > 0):
        raise _Failure(f"--rtol and --atol must be > 0, got {args.rtol:g}, {args.atol:g}.")
    spec = _model_spec(args)
    model = _build_model(spec)
    theta0 = _check_vector(args.theta0, "theta0")
    Omega0 = _check_vector(args.Omega0, "Omega0")
    print(f"Rigid body oscillator, right form (4.55)-(4.56): {_describe(spec)}")
    if args.about_equilibrium:
        sol = solve_equilibrium(model, jnp.zeros(3))
        if not bool(sol.ok):
            raise _Failure("no equilibrium for --about-equilibrium: "
                           f"{EquilibriumStatus[sol.status]}", code=1)
        print(f"equilibrium theta_eq = {np.asarray(sol.theta).tolist()} (Newton from 0, "
              f"|moment| = {float(sol.residual):.1e}); theta0 = theta_eq + --theta0")
        theta0 = sol.theta + theta0
    ts = jnp.linspace(0.0, args.t1, args.samples)
    start = time.perf_counter()
    traj = simulate(model, theta0, Omega0, ts, rtol=args.rtol, atol=args.atol,
                    max_steps=args.max_steps, throw=False, progress=args.progress)
    theta, Omega = np.asarray(traj.theta), np.asarray(traj.Omega)
    elapsed = time.perf_counter() - start
    E = np.asarray(traj.energy)
    t = np.asarray(traj.ts)
    ok = bool(traj.ok)
    reached = np.all(np.isfinite(theta), axis=1) & np.all(np.isfinite(Omega), axis=1)
    relative = bool(np.isfinite(E[0]) and E[0] != 0)
    scale = abs(E[0]) if relative else 1.0
    drift = (E - E[0]) / scale
    max_drift = float(np.max(np.abs(drift[reached]))) if reached.any() else float("nan")

    rows = [[float(t[i]), float(np.linalg.norm(theta[i])), *map(float, theta[i]), float(E[i]),
             float(drift[i])] for i in _spread(list(np.flatnonzero(reached)), args.max_rows)]
    if rows:
        print(_table(["t", "|theta|", "theta_x", "theta_y", "theta_z", "K + U",
                      "rel. drift" if relative else "drift"], rows))
        shown = int(reached.sum())
        if len(rows) < shown:
            print(f"   ({len(rows)} of {shown} samples shown; --max-rows)")
    if args.out is not None:
        _write_trajectory(args.out, out_kind, t, theta, Omega, E, traj, spec)
    status = traj.status_name
    print(f"   {int(traj.num_steps)} steps, status: {status}, "
          f"max |energy drift| = {max_drift:.2e} "
          f"({'relative to E(0) = ' + format(E[0], '.6g') if relative else 'absolute'}), "
          f"wall time {elapsed:.2f} s (compilation included)"
          + (f"; trajectory -> {args.out}" if args.out else ""))
    if not ok:
        last = t[reached][-1] if reached.any() else None
        where = f" after t = {last:g} (later samples are inf)" if last is not None else ""
        raise _Failure(f"the solver stopped{where}: {traj.message}", code=1)
    return 0


def _write_trajectory(path, kind, t, theta, Omega, E, traj, spec):
    import numpy as np

    if kind == ".npz":
        np.savez(path, ts=t, theta=theta, Omega=Omega, energy=E,
                 num_steps=np.asarray(int(traj.num_steps)),
                 status=np.asarray(traj.message), model=np.asarray(_describe(spec)))
    else:
        header = ("t,theta_x,theta_y,theta_z,Omega_x,Omega_y,Omega_z,energy")
        np.savetxt(path, np.column_stack([t, theta, Omega, E]), delimiter=",", header=header,
                   comments="", fmt="%.17g")


# ---------------------------------------------------------------------------------------------
# rbo-jax stability-map
# ---------------------------------------------------------------------------------------------

_MAP_AXES = ("M", "c", "d", "A3")


def _netcdf_engine() -> str | None:
    import xarray as xr

    engines = xr.backends.list_engines()
    return next((e for e in ("netcdf4", "h5netcdf", "scipy") if e in engines), None)


def _pyplot_or_fail(command: str):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise _Failure(f"--plot needs matplotlib, which is not installed (pip install "
                       f"'rbo_jax[plot]'); run {command} without --plot.") from None
    return plt


def stability_map_command(args: argparse.Namespace) -> int:
    """``rbo-jax stability-map``: the Nikolai map (4.57)-(4.62), (4.69) over a grid."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from rbo_jax import nikolai_spectrum, stability_map
    from rbo_jax.maps import STABILITY_KIND_NAMES

    axes = {name: getattr(args, name) for name in _MAP_AXES}
    ranged = [n for n, v in axes.items() if v.size > 1]
    if args.out is not None:
        out_kind = _suffix(args.out, (".npz", ".nc", ".zarr"), "--out")
        if out_kind == ".nc" and _netcdf_engine() is None:
            raise _Failure("--out .nc needs a NetCDF engine for xarray (pip install netCDF4, "
                           "h5netcdf or scipy); or write .npz or .zarr.")
        if out_kind == ".zarr":
            import importlib.util

            if importlib.util.find_spec("zarr") is None:
                raise _Failure("--out .zarr needs zarr (pip install 'zarr>=3'); or write .npz.")
    plt = None
    if args.plot is not None:
        _suffix(args.plot, (".png", ".pdf", ".svg"), "--plot")
        if len(ranged) < 2:
            raise _Failure("--plot draws a map over two axes: give at least two of --M, --c, "
                           "--d, --A3 as ranges start:stop:num.")
        plt = _pyplot_or_fail("rbo-jax stability-map")
    if args.chunk_size < 1:
        raise _Failure(f"--chunk-size must be >= 1, got {args.chunk_size}.")
    if not args.rtol > 0:
        raise _Failure(f"--rtol must be > 0, got {args.rtol:g}.")
    k = (0.0, 0.0, 1.0)
    A1, b = args.A1, args.friction

    def model_fn(M, c, d, A3):
        return _make_model(k=k, A1=A1, A3=A3, c=c, d=d, follower=M, friction=b)

    def theta_eq_fn(M, c, d, A3):
        return (M / d) * jnp.asarray(k)  # (4.62); friction vanishes at rest

    # The package validates every parameter; on the host, the smallest value of each axis is
    # decisive (A1, A3, c, d > 0; b >= 0).
    _build_model(dict(k=k, A1=A1, A3=float(axes["A3"].min()), c=float(axes["c"].min()),
                      d=float(axes["d"].min()), follower=float(axes["M"].min()), friction=b))

    n = int(np.prod([v.size for v in axes.values()]))
    fixed = ", ".join(f"{name} = {axes[name][0]:g}" for name in _MAP_AXES if name not in ranged)
    print("Nikolai problem (4.57)-(4.62): follower moment M, quadratic foundation (4.50), "
          f"A1 = {A1:g}" + (f", friction b = {b:g} (4.84)" if b is not None else "")
          + "; equilibrium theta = (M/d) k (4.62), spectrum of (4.63)-(4.67)")
    grid = " x ".join(f"{name} ({axes[name].size})" for name in ranged)
    print(f"grid: {grid + f' = {n} points' if grid else 'a single point'}"
          + (f"; fixed {fixed}" if fixed else ""))
    start = time.perf_counter()
    try:
        ds = stability_map(model_fn, axes, theta_eq_fn=theta_eq_fn, chunk_size=args.chunk_size,
                           rtol=args.rtol, progress=args.progress)
    except ValueError as e:
        raise _Failure(str(e)) from None
    elapsed = time.perf_counter() - start
    ds = ds.squeeze([name for name in _MAP_AXES if name not in ranged])
    ds.attrs.update(
        description="Nikolai problem (4.57)-(4.62): spectra of the equilibrium theta = (M/d) k "
        "under a follower moment M on the quadratic foundation (4.50)",
        A1=A1, command="rbo-jax " + " ".join(args.argv),
    )
    if b is not None:
        ds.attrs["friction_b"] = b

    kind = np.asarray(ds["kind"].values).ravel()
    counts = {name: int(np.sum(kind == i)) for i, name in enumerate(STABILITY_KIND_NAMES)}
    print("classification (Lyapunov's first method, rbo_jax.classify, rtol "
          f"{args.rtol:g}): " + ", ".join(f"{name} {c}" for name, c in counts.items() if c))
    a = np.asarray(ds["spectral_abscissa"].values)
    finite = a[np.isfinite(a)]
    if finite.size:
        print(f"spectral abscissa max Re p: min {finite.min():.6e}, max {finite.max():.6e}")
    if b is None:
        grids = [jnp.asarray(g.ravel()) for g in np.meshgrid(*axes.values(), indexing="ij")]
        roots = jax.vmap(lambda M, c, d, A3: nikolai_spectrum(A1, A3, c, d, M))(*grids)
        closed = np.max(np.real(np.asarray(roots)), axis=1)
        dev = np.max(np.abs(closed - a.ravel()))
        print(f"closed form (4.69): max |max Re p - max Re (4.69) roots| = {dev:.1e}")
    print(f"wall time {elapsed:.2f} s (compilation included)")

    if args.out is not None:
        _write_map(ds, args.out, out_kind)
        print(f"map -> {args.out}")
    if plt is not None:
        from rbo_jax.plotting import plot_stability_map

        x, y = ranged[:2]
        select = {name: float(axes[name][axes[name].size // 2]) for name in ranged[2:]}
        where = ", ".join(f"{name} = {v:g}" for name, v in select.items())
        ax = plot_stability_map(ds, x, y, select=select or None,
                                title=f"Nikolai problem: max Re p over ({x}, {y})"
                                + (f" at {where}" if where else ""))
        ax.figure.savefig(args.plot, dpi=120, bbox_inches="tight")
        plt.close(ax.figure)
        print(f"figure -> {args.plot}")
    return 0


def _write_map(ds, path: str, kind: str) -> None:
    """The map dataset as .npz (always), NetCDF (complex eigenvalues split into real and
    imaginary parts; NetCDF has no complex type) or zarr."""
    import numpy as np

    if kind == ".npz":
        arrays = {name: np.asarray(ds[name].values) for name in ds.variables}
        arrays["dims"] = np.asarray(list(ds["spectral_abscissa"].dims), dtype=str)
        arrays["kind_names"] = np.asarray(ds["kind"].attrs["flag_meanings"].split())
        arrays["equilibrium_status_names"] = np.asarray(
            ds["equilibrium_status"].attrs["flag_meanings"].split())
        np.savez(path, **arrays)
    elif kind == ".nc":
        p = ds["eigenvalues"]
        ds = ds.drop_vars("eigenvalues").assign(eigenvalues_real=p.real, eigenvalues_imag=p.imag)
        ds.to_netcdf(path, engine=_netcdf_engine())
    else:
        # zarr v3 has no specification for fixed-length strings: drop the labels x, y, z.
        ds = ds.drop_vars("component")
        ds.attrs["component"] = "x y z"
        ds.to_zarr(path, mode="w", zarr_format=3, consolidated=False)


# ---------------------------------------------------------------------------------------------
# rbo-jax fit
# ---------------------------------------------------------------------------------------------

_FIT_PARAMS = ("c", "d", "alpha", "beta", "b")
_SYNTHETIC_STATE = ((0.8, -0.3, 0.5), (0.2, 1.1, -0.7))


def _read_data(path: str, theta0, Omega0, sigma_theta, sigma_Omega):
    """A :class:`rbo_jax.TrajectoryData` from an .npz file (format in ``rbo-jax fit --help``)."""
    import numpy as np

    from rbo_jax import TrajectoryData

    if _suffix(path, (".npz",), "--data") and not os.path.isfile(path):
        raise _Failure(f"--data {path}: no such file.")
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {name: f[name] for name in f.files}
    except (OSError, ValueError) as e:
        raise _Failure(f"--data {path}: not a readable .npz file ({e}).") from None
    t = arrays.get("t", arrays.get("ts"))
    if t is None:
        raise _Failure(f"--data {path}: missing array 't' (the sample times, shape (n,); 'ts' "
                       f"is accepted too); the file has {sorted(arrays) or 'no arrays'}.")
    observed = {name: arrays[name] for name in ("theta", "Q", "Omega", "omega") if name in arrays}
    if not observed:
        raise _Failure(f"--data {path}: missing array 'theta' (the turn-vectors, shape (n, 3)); "
                       "or give the attitude as 'Q' (n, 3, 3) or angular velocities 'Omega' / "
                       f"'omega' (n, 3); the file has {sorted(arrays)}.")
    theta0 = arrays.get("theta0") if theta0 is None else theta0
    Omega0 = arrays.get("Omega0") if Omega0 is None else Omega0
    try:
        data = TrajectoryData(t, **observed, theta0=theta0, Omega0=Omega0,
                              sigma_theta=sigma_theta if ("theta" in observed or "Q" in observed)
                              else None,
                              sigma_Omega=sigma_Omega if "Omega" in observed else None)
    except (ValueError, TypeError) as e:
        hint = (" Give the initial state with --theta0/--Omega0, or as arrays 'theta0'/'Omega0' "
                "(3,) in the file." if " is needed" in str(e) else "")
        raise _Failure(f"--data {path}: {e}{hint}") from None
    return data, sorted(observed)


def fit_command(args: argparse.Namespace) -> int:
    """``rbo-jax fit``: foundation parameters from a trajectory, by least squares through the
    ODE solver (:func:`rbo_jax.fit`), with Gauss-Newton standard errors."""
    import jax.numpy as jnp
    import numpy as np

    from rbo_jax import TrajectoryData, fit, simulate

    names = [x.strip() for x in args.params.split(",") if x.strip()]
    bad = [x for x in names if x not in _FIT_PARAMS]
    if not names or bad or len(set(names)) != len(names):
        raise _Failure(f"--params must be distinct names among {', '.join(_FIT_PARAMS)}, got "
                       f"{args.params!r}.")
    spec = _model_spec(args)
    for name in names:
        if name in ("alpha", "beta") and spec["foundation"] != "barrier":
            raise _Failure(f"--params {name} needs --foundation barrier (4.49).")
        if name == "b" and "friction" not in spec:
            raise _Failure("--params b needs --friction (its starting value).")
    key = {"b": "friction"}
    for name in names:
        v = spec[key.get(name, name)]
        if not (np.isfinite(v) and v > 0):
            raise _Failure(f"--params {name}: the starting value must be finite and > 0 (the fit "
                           f"works with log {name}), got {v:g}.")
    for option in ("max_steps", "samples", "solver_max_steps"):
        if getattr(args, option) < 1:
            raise _Failure(f"--{option.replace('_', '-')} must be >= 1.")
    if not (args.tol > 0 and args.rtol > 0 and args.atol > 0):
        raise _Failure("--tol, --rtol and --atol must be > 0.")
    theta0 = None if args.theta0 is None else _check_vector(args.theta0, "theta0")
    Omega0 = None if args.Omega0 is None else _check_vector(args.Omega0, "Omega0")

    truth = None
    if args.synthetic:
        if not args.t1 > 0 or args.samples < 2 or not args.noise >= 0:
            raise _Failure("--synthetic needs --t1 > 0, --samples >= 2 and --noise >= 0.")
        if not args.offset > -1:
            raise _Failure(f"--offset must be > -1, got {args.offset:g}.")
        true_model = _build_model(spec)
        th0 = jnp.asarray(_SYNTHETIC_STATE[0]) if theta0 is None else theta0
        Om0 = jnp.asarray(_SYNTHETIC_STATE[1]) if Omega0 is None else Omega0
        ts = jnp.linspace(0.0, args.t1, args.samples)
        traj = simulate(true_model, th0, Om0, ts, rtol=args.rtol, atol=args.atol, throw=False)
        if not bool(traj.ok):
            raise _Failure(f"the synthetic trajectory failed: {traj.message}", code=1)
        theta, Omega = np.asarray(traj.theta), np.asarray(traj.Omega)
        if args.noise > 0:
            rng = np.random.default_rng(args.seed)
            theta = theta + args.noise * rng.standard_normal(theta.shape)
            Omega = Omega + args.noise * rng.standard_normal(Omega.shape)
        sigma = args.noise if args.noise > 0 else None
        data = TrajectoryData(ts, theta=theta, Omega=Omega, theta0=th0, Omega0=Om0,
                              sigma_theta=sigma, sigma_Omega=sigma)
        observed = ["Omega", "theta"]
        truth = {name: spec[key.get(name, name)] for name in names}
        for name in names:
            spec[key.get(name, name)] *= 1.0 + args.offset
        source = (f"a synthetic trajectory (t1 = {args.t1:g}, {args.samples} samples, noise "
                  f"{args.noise:g}) of the model with " + ", ".join(
                      f"{n} = {v:g}" for n, v in truth.items()))
    else:
        data, observed = _read_data(args.data, theta0, Omega0, args.sigma_theta,
                                    args.sigma_Omega)
        source = args.data
    model = _build_model(spec)
    print(f"Model: {_describe(spec)} (starting values)")
    print(f"Fitting {', '.join(names)} to {source}: {data.num_samples} samples of "
          f"{', '.join(observed)}; Levenberg-Marquardt through the ODE solver")

    friction_index = sum(1 for name in ("follower", "dead") if name in spec)

    def selector(m):
        return tuple(m.loads[friction_index].b if name == "b" else getattr(m.foundation, name)
                     for name in names)

    try:
        res = fit(model, data, selector, fit_initial_state=args.fit_initial_state,
                  max_steps=args.max_steps, tol=args.tol, solve_rtol=args.rtol,
                  solve_atol=args.atol, solve_max_steps=args.solver_max_steps,
                  progress=args.progress, horizons=args.horizons)
    except FloatingPointError as e:
        raise _Failure(f"the fit could not start: {e}", code=1) from None
    for name, value, se in zip(names, res.params, res.stderr):
        line = f"  {name:>5} = {float(value):.12g} +/- {float(se):.2e}"
        line += f"   (start {spec[key.get(name, name)]:g}"
        if truth is not None:
            line += f", truth {truth[name]:g}, relative error " \
                    f"{abs(float(value) / truth[name] - 1):.1e}"
        print(line + ")")
    if args.fit_initial_state:
        th, Om = res.initial_states[0]
        print(f"  theta0 = {np.asarray(th).tolist()}, Omega0 = {np.asarray(Om).tolist()}")
    print(f"  {res.num_steps} iterations, final loss {res.loss_history[-1]:.3e}, residual rms "
          f"{res.residual_rms:.3e}, {res.message}, wall time {res.wall_time:.2f} s "
          "(compilation included)")
    if not res.converged:
        raise _Failure(f"the fit did not converge: {res.message}", code=1)
    # whitened residuals (rms ~ 1 at the right answer) when the noise is given, else in rad, rad/s
    whitened = any(getattr(data, name) is not None
                   for name in ("sigma_theta", "sigma_omega", "sigma_Omega"))
    if res.residual_rms > (3.0 if whitened else 1e-2):
        print(f"  note: the residual rms {res.residual_rms:.3g} is large "
              f"({'> 3 noise standard deviations' if whitened else '> 1e-2 rad or rad/s'}): the "
              "fit may have stopped in a local minimum (or the model does not describe the data), "
              "and the standard errors are then meaningless; try staged horizons "
              "(--horizons 0.2,0.5,1) or starting values closer to the answer.")
    return 0


# ---------------------------------------------------------------------------------------------
# The parser
# ---------------------------------------------------------------------------------------------

_FORMATTER = argparse.RawDescriptionHelpFormatter  # the epilogs are laid out by hand


def _add_simulate(sub) -> None:
    p = sub.add_parser(
        "simulate", formatter_class=_FORMATTER,
        help="Simulate one oscillator and print t, |theta|, theta, energy K + U and its drift.",
        description=_wrap(
        "Integrate the rigid body oscillator (right form (4.55)-(4.56), Dopri8 with adaptive "
        "steps) from (theta0, Omega0) and print a table of the turn-vector theta, the "
        "energy K + U (4.124) and its drift relative to E(0), then a summary line (solver "
        "steps, status, max |energy drift|, wall time). Without friction and external moments "
        "K + U is conserved, so the drift measures the accuracy; follower/dead moments and "
        "friction change it physically. Exit status 1 when the solver stops early (a singular "
        "point |theta| = 2 pi of Z (4.11), a barrier of (4.49) crossed, the step budget, a "
        "step-size collapse), with the reason; 2 for invalid options or parameters. "
        + _UNITS),
        epilog="examples:\n"
        "  rbo-jax simulate --foundation barrier --c 1 --d 2 --alpha 2 --beta 1.5 \\\n"
        "      --theta0 0.8,-0.3,0.5 --Omega0 0.2,1.1,-0.7 --t1 20 --out run.npz\n"
        "  rbo-jax simulate --follower 0.4 --about-equilibrium --theta0 1e-6,0,0 --t1 60\n\n"
        + _wrap(_NEGATIVE),
    )
    _add_model_options(p, "its parameters.")
    g = p.add_argument_group("initial state and solver")
    g.add_argument("--theta0", type=_floats, default=(0.0, 0.0, 0.0), metavar="X,Y,Z",
                   help="initial turn-vector theta0 (rad; |theta0| is the turn angle about the "
                   "axis theta0/|theta0|, eq. (4.3)) (default 0,0,0)")
    g.add_argument("--Omega0", type=_floats, default=(0.0, 0.0, 0.0), metavar="X,Y,Z",
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
                   help="write the whole trajectory: FILE.npz (arrays ts (n,), theta (n, 3), "
                   "Omega (n, 3), energy (n,), plus num_steps, status, model) or FILE.csv "
                   "(columns t, theta_x..z, Omega_x..z, energy); written also when the solver "
                   "fails (later samples are inf). A FILE.npz is valid input of 'rbo-jax fit "
                   "--data'")
    g.add_argument("--progress", action="store_true",
                   help="show a progress bar of the solve (tqdm)")
    p.set_defaults(func=simulate_command)


def _add_stability_map(sub) -> None:
    p = sub.add_parser(
        "stability-map", formatter_class=_FORMATTER,
        help="Stability map of the Nikolai problem over a grid of M, c, d, A3.",
        description=_wrap("The Nikolai problem (4.57)-(4.62): a transversely isotropic body (4.40) "
        "on the quadratic foundation (4.50) under a follower moment M k turning with the body "
        "(4.57) has the equilibrium theta = (M/d) k (4.62). Its linearization (4.63)-(4.67) "
        "has the roots (4.69): bending (A1 p^2 + K)^2 + M^2/4 = 0 and torsion A3 p^2 + d = 0; "
        "every M != 0 gives a root with Re p > 0 (flutter). This command evaluates the 6 "
        "eigenvalues at every point of the grid of --M, --c, --d, --A3 (each a single value, a "
        "list or a range start:stop:num) with rbo_jax.stability_map (jit + vmap in chunks), "
        "classifies them (rbo_jax.classify: asymptotically_stable, marginally_stable, "
        "divergence, flutter, undefined), and prints the counts, the range of the spectral "
        "abscissa max Re p and, without friction, its largest deviation from the closed form "
        "(4.69). " + _UNITS),
        epilog="examples:\n"
        "  rbo-jax stability-map --M=-0.8:0.8:41 --c 0.2:2:37 --plot map.png --out map.npz\n"
        "  rbo-jax stability-map --M 0:1:101 --A3 0.2:2:50 --c 1 --friction 0.05\n\n"
        "output formats (--out, by suffix):\n"
        "  .npz   always available: the axis values (M, c, d, A3; scalars for fixed ones), "
        "mode,\n"
        "         component, eigenvalues (complex, grid x 6, sorted by Re then Im),\n"
        "         spectral_abscissa, kind (codes; names in kind_names), equilibrium_status\n"
        "         (names in equilibrium_status_names), theta_eq (grid x 3), dims (the grid "
        "axes)\n"
        "  .nc    the xarray Dataset as NetCDF, if netCDF4, h5netcdf or scipy is installed;\n"
        "         eigenvalues split into eigenvalues_real / eigenvalues_imag (NetCDF has no\n"
        "         complex type)\n"
        "  .zarr  the xarray Dataset as a zarr v3 store (zarr is installed with rbo_jax on\n"
        "         Python >= 3.11); the component labels x, y, z are in the attribute 'component'"
        "\n\n" + _wrap(_NEGATIVE),
    )
    g = p.add_argument_group("grid", _wrap(
        "Each of these is a value (0.5), a list (0.1,0.2,0.5) or an inclusive range "
        "start:stop:num (numpy.linspace); the grid is their Cartesian product."))
    g.add_argument("--M", type=_grid, default=_grid("-0.8:0.8:41"), metavar="SPEC",
                   help="follower moment M of (4.57) (default -0.8:0.8:41)")
    g.add_argument("--c", type=_grid, default=_grid("0.2:2:37"), metavar="SPEC",
                   help="bending stiffness c > 0 of (4.50) (default 0.2:2:37)")
    g.add_argument("--d", type=_grid, default=_grid("1"), metavar="SPEC",
                   help="torsional stiffness d > 0 of (4.50) (default 1)")
    g.add_argument("--A3", type=_grid, default=_grid("0.6"), metavar="SPEC",
                   help="axial moment of inertia A3 > 0 of (4.40) (default 0.6)")
    g = p.add_argument_group("fixed parameters and output")
    g.add_argument("--A1", type=float, default=1.0,
                   help="transverse moment of inertia A1 > 0 of (4.40) (default 1)")
    g.add_argument("--friction", type=float, default=None, metavar="b",
                   help="add viscous friction -b omega, b >= 0, eq. (4.84) (the equilibrium is "
                   "unchanged; the closed form (4.69) does not apply then) (default: none)")
    g.add_argument("--rtol", type=float, default=1e-9,
                   help="classification tolerance, relative to max|p|: real parts within "
                   "+-rtol max|p| count as zero (default 1e-9)")
    g.add_argument("--chunk-size", type=int, default=16_384,
                   help="grid points per compiled jit+vmap call; memory grows with it "
                   "(default 16384)")
    g.add_argument("--out", default=None, metavar="FILE",
                   help="write the map: FILE.npz, FILE.nc or FILE.zarr (formats below)")
    g.add_argument("--plot", default=None, metavar="FILE",
                   help="draw max Re p over the first two ranged axes (in the order M, c, d, "
                   "A3; further ranged axes at their middle value) with the stability boundary "
                   "into FILE.png/.pdf/.svg (needs matplotlib: pip install 'rbo_jax[plot]')")
    g.add_argument("--progress", action="store_true",
                   help="show a progress bar over the grid points (tqdm)")
    p.set_defaults(func=stability_map_command)


def _add_fit(sub) -> None:
    p = sub.add_parser(
        "fit", formatter_class=_FORMATTER,
        help="Fit foundation parameters (c, d, alpha, beta) to a trajectory.",
        description=_wrap("Fit parameters of the foundation (4.49)/(4.50) (and the friction b of "
        "(4.84)) so that simulated trajectories match observed ones: Levenberg-Marquardt on "
        "the whitened residuals (the rotation angle between observed and simulated attitude, "
        "and angular velocity differences), with forward-mode derivatives through the ODE "
        "solver (rbo_jax.fit). Prints the estimates +/- Gauss-Newton standard errors, the "
        "iterations and the final loss (1/2 sum r^2). The model options give the starting "
        "values of the fitted parameters and the fixed values of all others; with --synthetic "
        "they are the truth instead. Exit status 1 if the fit does not converge, 2 for invalid "
        "options or a bad data file. " + _UNITS),
        epilog="data file (--data FILE.npz), arrays:\n"
        "  t       sample times, shape (n,), strictly increasing ('ts' is accepted too)\n"
        "  theta   observed turn-vectors, shape (n, 3)  (or Q: attitudes, shape (n, 3, 3))\n"
        "  Omega   optional: right angular velocities, shape (n, 3)\n"
        "  omega   optional: left angular velocities, shape (n, 3)\n"
        "  theta0, Omega0  optional initial state (3,) at t[0]; default the first samples\n"
        "  (other arrays are ignored; 'rbo-jax simulate --out FILE.npz' writes this format)\n\n"
        "examples:\n"
        "  rbo-jax fit --synthetic --c 1 --d 2 --params c,d --noise 1e-3\n"
        "  rbo-jax simulate --c 1 --d 2 --theta0 0.8,-0.3,0.5 --Omega0 0.2,1.1,-0.7 --t1 6 \\\n"
        "      --samples 61 --out obs.npz && rbo-jax fit --data obs.npz --c 1.3 --d 1.5\n\n"
        + _wrap(_NEGATIVE),
    )
    src = p.add_argument_group("data").add_mutually_exclusive_group(required=True)
    src.add_argument("--data", default=None, metavar="FILE.npz",
                     help="the observed trajectory (format below)")
    src.add_argument("--synthetic", action="store_true",
                     help="fit a trajectory simulated here from the model options (the truth), "
                     "starting from the truth times (1 + --offset)")
    _add_model_options(p, "starting values of the fitted parameters (with --synthetic: "
                       "the true values), fixed values of the others.")
    g = p.add_argument_group("fit")
    g.add_argument("--params", default="c,d", metavar="NAMES",
                   help="comma-separated parameters to fit, among c, d, alpha, beta "
                   "(--foundation barrier) and b (--friction); fitted as logarithms, so they "
                   "stay > 0 (default c,d)")
    g.add_argument("--fit-initial-state", action="store_true",
                   help="also fit theta0 and Omega0 (starting from the data's)")
    g.add_argument("--theta0", type=_floats, default=None, metavar="X,Y,Z",
                   help="initial turn-vector (rad): with --data it replaces the data's, with "
                   "--synthetic it is the true one (default: the data's; synthetic 0.8,-0.3,0.5)")
    g.add_argument("--Omega0", type=_floats, default=None, metavar="X,Y,Z",
                   help="initial right angular velocity (rad/s), as --theta0 (default: the "
                   "data's; synthetic 0.2,1.1,-0.7)")
    g.add_argument("--horizons", type=_horizons, default=(1.0,), metavar="F1,F2,...",
                   help="staged fitting: fit on the first fractions F1 < F2 < ... <= 1 of the "
                   "record in turn, each stage starting from the previous estimate; helps long "
                   "or unstable records, where the loss over the whole record has many local "
                   "minima (default 1: the whole record at once)")
    g.add_argument("--max-steps", type=int, default=100,
                   help="maximum number of Levenberg-Marquardt iterations per stage (default "
                   "100)")
    g.add_argument("--tol", type=float, default=1e-8,
                   help="convergence tolerance: relative step size and relative decrease of the "
                   "loss (default 1e-8)")
    g.add_argument("--rtol", type=float, default=1e-10,
                   help="relative tolerance of the ODE solves (default 1e-10)")
    g.add_argument("--solver-max-steps", type=int, default=100_000,
                   help="step budget of each ODE solve inside the fit; a solve that exhausts it "
                   "counts as a failed trial step (default 100000)")
    g.add_argument("--atol", type=float, default=1e-10,
                   help="absolute tolerance of the ODE solves (default 1e-10)")
    g.add_argument("--sigma-theta", type=float, default=None,
                   help="noise standard deviation of the attitude (rad), if known: standard "
                   "errors then use it (default: estimated from the residuals)")
    g.add_argument("--sigma-Omega", type=float, default=None,
                   help="noise standard deviation of Omega (rad/s), if known (default: "
                   "estimated from the residuals)")
    g.add_argument("--progress", action="store_true",
                   help="show a progress bar over the iterations (tqdm)")
    g = p.add_argument_group("synthetic data (with --synthetic)")
    g.add_argument("--t1", type=float, default=6.0,
                   help="length of the synthetic record, from t = 0 (default 6)")
    g.add_argument("--samples", type=int, default=61,
                   help="number of equally spaced synthetic samples (default 61)")
    g.add_argument("--noise", type=float, default=0.0,
                   help="standard deviation of Gaussian noise added to every component of theta "
                   "(rad) and Omega (rad/s); also passed to the fit as the known noise level "
                   "(default 0)")
    g.add_argument("--seed", type=int, default=0, help="seed of the noise (default 0)")
    g.add_argument("--offset", type=float, default=0.3,
                   help="the fit starts from the true values times (1 + offset) (default 0.3)")
    p.set_defaults(func=fit_command)


def build_parser() -> argparse.ArgumentParser:
    """The ``rbo-jax`` argument parser (all subcommands)."""
    parser = argparse.ArgumentParser(
        prog="rbo-jax",
        description="Rigid body oscillator in JAX: simulation and analysis of the turn-vector "
        "model.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("demo", help="Run two short simulations and print them as tables.")
    p.add_argument("--t1", type=float, default=20.0,
                   help="final time of the first run (default 20)")
    p.add_argument("--samples", type=int, default=11, help="number of printed rows (default 11)")
    p.set_defaults(func=demo)
    p = sub.add_parser(
        "reproduce",
        help="Reproduce the paper's results: a table of checks and figures in OUT/report.md.",
        description="Reproduce every result of the paper (kinematics identities, the Nikolai "
        "paradox and its stability maps, the balance (4.78), energy conservation, the integrals "
        "of the simplest oscillator, the Euler-angle comparison of 4.6.3, regular precession and "
        "its stability, a stiffness fit). Exits non-zero if any check fails.",
    )
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--quick", action="store_true",
                   help="smaller maps and samples (the version run by the tests)")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.set_defaults(func=reproduce_command)
    p = sub.add_parser(
        "sweep",
        help="Run a parameter sweep described by a TOML file (see examples/*.toml).",
        description="Run a declarative parameter sweep: write the results to a zarr store chunk "
        "by chunk and draw a PNG of the map.",
    )
    p.add_argument("config", help="the sweep configuration (TOML)")
    p.add_argument("--resume", action="store_true",
                   help="finish an interrupted sweep: compute only the chunks not in the store")
    p.add_argument("--overwrite", action="store_true", help="delete an existing store first")
    p.add_argument("--output", default=None,
                   help="store path (overrides [sweep] output; the PNG goes beside it)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-plot", action="store_true", help="do not draw the PNG")
    p.add_argument("--coordinator", default=None,
                   help="multi-process run: address host:port of process 0 (jax.distributed)")
    p.add_argument("--num-processes", type=int, default=None, help="multi-process run: count")
    p.add_argument("--process-id", type=int, default=None, help="multi-process run: this index")
    p.set_defaults(func=sweep_command)
    _add_simulate(sub)
    _add_stability_map(sub)
    _add_fit(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    args.argv = argv
    try:
        return args.func(args)
    except _Failure as e:
        print(f"rbo-jax {args.command}: error: {e}", file=sys.stderr)
        return e.code


if __name__ == "__main__":
    sys.exit(main())
