"""``rbo-jax demo``, ``rbo-jax reproduce`` and ``rbo-jax sweep CONFIG.toml``."""

from __future__ import annotations

import argparse
import sys
import time

from ._common import table


def demo(args: argparse.Namespace) -> int:
    """Two short simulations printed as tables: (1) a conservative oscillator whose energy
    K + U stays constant, (2) the Nikolai problem (4.57)-(4.62): a body displaced by 1e-6 rad
    from the equilibrium theta = (M/d)k under a follower moment, whose bending deviation grows
    although the linear theory (4.74) predicts none."""
    import jax.numpy as jnp
    import numpy as np

    from ._common import check_times
    from ._memory import BYTES_PER_SAMPLE
    from ._simulate import check_samples_memory

    check_times(args)
    check_samples_memory(args.samples, 2 * BYTES_PER_SAMPLE)  # two trajectories

    from ... import (
        BarrierFoundation,
        RigidBodyOscillator,
        nikolai_equilibrium,
        nikolai_model,
        simulate,
        transversely_isotropic_inertia,
    )

    k = jnp.array([0.0, 0.0, 1.0])
    n = args.samples
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(1.0, 0.6, k),
        BarrierFoundation(c=1.0, d=2.0, alpha=2.0, beta=1.5, k=k),
    )
    start = time.perf_counter()
    traj = simulate(
        model,
        jnp.array([0.8, -0.3, 0.5]),
        jnp.array([0.2, 1.1, -0.7]),
        jnp.linspace(0.0, args.t1, n),
    )
    elapsed = time.perf_counter() - start
    E = np.asarray(traj.energy)
    rows = [
        [float(t), float(np.linalg.norm(th)), float(th[2]), float(e), float((e - E[0]) / E[0])]
        for t, th, e in zip(np.asarray(traj.ts), np.asarray(traj.theta), E)
    ]
    print("1) Rigid body oscillator on the barrier foundation (4.49), A1 = 1, A3 = 0.6,")
    print("   c = 1, d = 2, alpha = 2, beta = 1.5; right form (4.55)-(4.56), Dopri8, rtol 1e-10")
    print(table(["t", "|theta|", "k.theta", "K + U", "rel. drift"], rows))
    print(
        f"   {int(traj.num_steps)} steps, {elapsed:.2f} s including compilation; "
        f"max |energy drift| = {np.max(np.abs((E - E[0]) / E[0])):.2e}\n"
    )

    c, d, M = 1.0, 2.0, 0.4
    theta_eq = nikolai_equilibrium(M, d, k)
    traj = simulate(
        nikolai_model(M, c, d, A1=1.0, A3=0.6, k=k),
        theta_eq + jnp.array([1e-6, 0.0, 0.0]),
        jnp.zeros(3),
        jnp.linspace(0.0, 4 * args.t1, n),
    )
    dev = np.asarray(traj.theta) - np.asarray(theta_eq)
    rows = [
        [float(t), float(np.linalg.norm(dv[:2])), float(dv[2])]
        for t, dv in zip(np.asarray(traj.ts), dev)
    ]
    print(f"2) Nikolai problem (4.57)-(4.62): follower moment M = {M}, c = {c}, d = {d};")
    print("   start 1e-6 rad off the equilibrium theta = (M/d) k. The bending deviation grows,")
    print("   although the linearised theory (4.74) predicts bounded oscillations.")
    print(table(["t", "|bending dev.|", "torsion dev."], rows))
    return 0


def reproduce_command(args: argparse.Namespace) -> int:
    """``rbo-jax reproduce``: every check of the paper, written to OUT/report.md with figures."""
    from .. import reproduce
    from ._common import check_output

    check_output(args.out, "--out", directory=True, make_parents=True)
    checks = reproduce.run_reproduction(args.out, quick=args.quick, figures=not args.no_figures)
    failed = [c for c in checks if not c.passed]
    width = max(len(c.section) for c in checks)
    print()
    for c in checks:
        print(f"  {'pass' if c.passed else 'FAIL'}  {c.section:<{width}}  {c.quantity}  [{c.ours}]")
    print(
        f"\n{len(checks) - len(failed)} of {len(checks)} checks passed; report: "
        f"{args.out}/report.md"
    )
    return 1 if failed else 0


def sweep_command(args: argparse.Namespace) -> int:
    """``rbo-jax sweep CONFIG.toml``: run a declarative sweep (see ``examples/*.toml`` and
    :func:`rbo_jax.app.config.load_config`), write its zarr store and a PNG of the map."""
    import jax

    from ...batch import SweepError, status_counts
    from ..config import ConfigError, load_config, run_config
    from . import _distributed
    from ._cluster import check_cluster_options
    from ._common import Failure, check_devices
    from ._sweep_store import check_paths, report_on_interrupt

    check_cluster_options(args)  # --scheduler / --workers (Dask): exit 2 before anything starts
    multi_process = _distributed.check_options(args)  # jax.distributed: the same
    # on Dask, --devices counts each worker's devices, which this process cannot see
    check_devices(args.devices, local=args.scheduler is None and args.workers is None)
    try:
        cfg = load_config(args.config)
    except ConfigError as e:
        raise Failure(str(e)) from None
    try:
        import matplotlib

        matplotlib.use("Agg")
        plot = not args.no_plot
    except ImportError:
        print(
            "rbo-jax sweep: matplotlib is not installed, no PNG (pip install 'rbo_jax[plot]').",
            file=sys.stderr,
        )
        plot = False
    store = check_paths(args, cfg, plot)  # store and PNG writable
    if multi_process and not _distributed.supervised():
        return _distributed.supervise(args, store)  # this command again, in a watched child
    report_on_interrupt(args, store)  # Ctrl-C says what was kept
    if multi_process:
        _distributed.initialize(args)
    try:
        ds, png = run_config(
            cfg,
            resume=args.resume or args.retry_errors,
            overwrite=args.overwrite,
            progress=not args.quiet,
            output=args.output,
            plot=plot,
            retry_errors=args.retry_errors,
            scheduler=args.scheduler,
            workers=args.workers,
            devices=args.devices,
        )
    except (FileExistsError, SweepError) as e:
        raise Failure(str(e)) from None
    out = args.output or cfg.output
    counts = status_counts(ds)
    failed = {k: v for k, v in counts.items() if v and k != "successful"}
    if jax.process_index() == 0 and (not args.quiet or failed):
        print(
            f"{cfg.quantity_name}: {sum(counts.values())} points -> {out}"
            + (f", map {png}" if png else "")
        )
        print("  status: " + ", ".join(f"{k} {v}" for k, v in counts.items() if v))
    return 0
