"""Trajectories per second of a simulation sweep (:func:`rbo_jax.sweep`) against the number of
local devices, and against ``scipy.integrate.solve_ivp`` on a sample, in the same run.

The problem is that of ``bench_simulate.py``: the Nikolai problem (4.57)–(4.62), transversely
isotropic body (A1 = 1, A3 = 0.5), quadratic foundation (4.50), follower moment M; each point
(c, d, M) starts 1e-3 rad off its equilibrium θ = (M/d)k; t ∈ [0, 20], rtol = 1e-8,
atol = 1e-10, :func:`rbo_jax.fast_simulate` (DOP853; ``--integrator simulate``: diffrax Dopri8)
against DOP853 (scipy, plain NumPy right-hand side, on a sample) and against
the numba-compiled DOP853 of ``_numba_reference.py`` (all points; a serial loop on one core and a
``prange`` loop on all cores numba sees; skipped when numba is not installed); the final state is
kept.

The CPU is split into ``max(--devices)`` XLA devices (``jax_num_cpu_devices``, set before JAX
starts; on a GPU machine the GPUs are the devices); each sweep shards its chunks over the first
k of them with ``shard_map``. Compilation
is excluded (one warm-up chunk per device count; numba: a first call on one point) and printed
in its own column. The jax/jaxlib versions, the machine and its
load average are printed with the figures: the CPU runtime's speed changes between versions.

Usage: ``python benchmarks/bench_sweep.py [--n 100000] [--devices 1,2] [--chunk 4096]
[--scipy-sample 20] [--no-numba] [--integrator fast_simulate|simulate] [--json out.json]``
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time


def _parse(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=100_000, help="points of the sweep")
    parser.add_argument(
        "--devices",
        default=f"1,{len(os.sched_getaffinity(0))}",
        help="device counts to time (default: 1 and one per core of the affinity)",
    )
    parser.add_argument("--chunk", type=int, default=4096, help="chunk size (points per call)")
    parser.add_argument("--scipy-sample", type=int, default=20, help="points run with scipy")
    parser.add_argument("--no-numba", action="store_true", help="skip the numba runs")
    parser.add_argument("--json", default=None, help="also write the figures to this file")
    parser.add_argument(
        "--integrator",
        default="fast_simulate",
        choices=["fast_simulate", "simulate"],
        help="the sweep's solver",
    )
    args = parser.parse_args(argv)
    try:
        args.devices = sorted({int(x) for x in args.devices.split(",")})
    except ValueError:
        parser.error(f"--devices must be a comma-separated list of integers, got {args.devices!r}")
    if min(args.devices) < 1 or args.n < 1 or args.chunk < 1 or args.scipy_sample < 0:
        parser.error("--n, --chunk and the device counts must be >= 1, --scipy-sample >= 0")
    return args


def main(argv=None) -> dict:
    args = _parse(argv)
    import jax

    # Before any computation: split the CPU into as many XLA devices as the largest count asked.
    # (Run after other benchmarks in one process, JAX has started already: the devices it has
    # are used and larger counts skipped.)
    try:
        jax.config.update("jax_num_cpu_devices", max(args.devices))
    except RuntimeError:
        pass
    import numpy as np

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import _problem as problem
    from _common import write_json

    numba_ref = None
    if not args.no_numba:
        try:
            import _numba_reference as numba_ref
        except ImportError:  # numba is optional (the "bench" extra)
            pass

    import rbo_jax
    from rbo_jax import fast_simulate, simulate, sweep
    from rbo_jax.batch._space import make_space

    solver = fast_simulate if args.integrator == "fast_simulate" else simulate

    def quantities(c, d, M):
        y, steps, status = problem.final_state(c, d, M, solver)
        return {"y": y, "num_steps": steps}, status

    rng = np.random.default_rng(0)
    points = {
        "c": rng.uniform(0.5, 2.0, args.n),
        "d": rng.uniform(0.5, 2.0, args.n),
        "M": rng.uniform(0.05, 0.6, args.n),
    }
    n_local = jax.local_device_count()
    counts = [k for k in args.devices if k <= n_local]
    batch = make_space(None, points, args.chunk).chunk_shape[0]
    warm = {name: v[:batch] for name, v in points.items()}

    results, reference = [], None
    for k in counts:
        t0 = time.perf_counter()
        sweep(quantities, points=warm, chunk_size=args.chunk, devices=k, progress=False)
        t_compile = time.perf_counter() - t0
        t0 = time.perf_counter()
        ds = sweep(quantities, points=points, chunk_size=args.chunk, devices=k, progress=False)
        ds["y"].values  # noqa: B018 - all results on the host
        elapsed = time.perf_counter() - t0
        ok = int((ds["status"].values == 0).sum())
        if reference is None:
            reference = ds
        diff_1 = float(np.max(np.abs(ds["y"].values - reference["y"].values)))
        results.append(
            {
                "devices": k,
                "seconds": elapsed,
                "traj_per_s": args.n / elapsed,
                "compile_s": t_compile,
                "successful": ok,
                "steps_mean": float(ds["num_steps"].values.mean()),
                "max_diff_to_first": diff_1,
            }
        )

    # scipy on a sample of the same points.
    A, A_inv = problem.inertia()
    ys, nfev_sp = [], []
    t0 = time.perf_counter()
    for i in range(args.scipy_sample):
        sol = problem.scipy_final_state(points["c"][i], points["d"][i], points["M"][i], A, A_inv)
        ys.append(sol.y[:, -1])
        nfev_sp.append(sol.nfev)
    t_scipy = time.perf_counter() - t0
    per_scipy = t_scipy / args.scipy_sample if args.scipy_sample else float("nan")
    diff = (
        float(np.max(np.abs(np.array(ys) - reference["y"].values[: args.scipy_sample])))
        if args.scipy_sample
        else float("nan")
    )

    # numba on all points, serial (one core) and prange (all cores numba sees).
    nb = {}
    if numba_ref is not None:
        pts = np.stack([points["c"], points["d"], points["M"]], axis=1)
        for key, par in [("serial", False), ("prange", True)]:
            r = problem.numba_final_states(pts, par)
            nb[key] = {
                "seconds": r["seconds"],
                "traj_per_s": args.n / r["seconds"],
                "compile_s": r["compile_s"],
                "threads": r["threads"],
                "successful": int((r["status"] == 0).sum()),
                "steps_mean": float(r["steps"].mean()),
                "max_diff_to_sweep": float(np.max(np.abs(r["y"] - reference["y"].values)))
                if reference is not None
                else float("nan"),
                "max_diff_to_scipy": float(
                    np.max(np.abs(r["y"][: args.scipy_sample] - np.array(ys)))
                )
                if args.scipy_sample
                else float("nan"),
                "nfev_diff_to_scipy": int(
                    np.max(np.abs(r["nfev"][: args.scipy_sample] - np.array(nfev_sp)))
                )
                if args.scipy_sample
                else 0,
            }

    env = {
        "rbo_jax": rbo_jax.__version__,
        "jax": jax.__version__,
        "jaxlib": __import__("jaxlib").__version__,
        "python": platform.python_version(),
        "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0],
        "backend": jax.default_backend(),
        "local_devices": n_local,
        "numba": numba_ref.NUMBA_VERSION if numba_ref is not None else None,
    }
    print(
        f"rbo_jax {env['rbo_jax']}, jax {env['jax']}, jaxlib {env['jaxlib']}, Python "
        f"{env['python']}, {env['machine']}, {env['cpu_count']} CPUs, load average "
        f"{env['load_average_1min']:.2f}, {n_local} {env['backend']} device(s); "
        + (f"numba {env['numba']}" if env["numba"] else "numba not installed, skipped")
    )
    print(
        f"{problem.DESCRIPTION}, {args.n} points, "
        f"chunks of {batch} (scipy: {args.scipy_sample} points); sweep solver "
        f"{args.integrator}"
    )
    header = f"{'method':<42}{'traj / s':>12}{'s / traj':>12}{'compile s':>11}{'steps':>8}{'ok':>9}"
    print(header)
    print("-" * len(header))
    for r in results:
        name = f"sweep, shard_map over {r['devices']} device(s)"
        print(
            f"{name:<42}{r['traj_per_s']:>12.1f}{1 / r['traj_per_s']:>12.3e}"
            f"{r['compile_s']:>11.1f}{r['steps_mean']:>8.1f}{r['successful']:>9d}"
        )
    labels = {
        "serial": "numba DOP853, serial loop (1 core)",
        "prange": "numba DOP853, prange ({} threads)",
    }
    for key, r in nb.items():
        name = labels[key].format(r["threads"])
        print(
            f"{name:<42}{r['traj_per_s']:>12.1f}{1 / r['traj_per_s']:>12.3e}"
            f"{r['compile_s']:>11.1f}{r['steps_mean']:>8.1f}{r['successful']:>9d}"
        )
    if args.scipy_sample:
        print(f"{'scipy solve_ivp DOP853, NumPy RHS':<42}{1 / per_scipy:>12.1f}{per_scipy:>12.3e}")
    print(
        "(steps: mean accepted steps; compile: first call incl. JIT, not in the rates; numba's "
        "serial compile includes the shared integrator, prange reuses it)"
    )
    base = results[0]["traj_per_s"] if results else float("nan")
    for r in results[1:]:
        print(
            f"{r['devices']} devices / {results[0]['devices']}: {r['traj_per_s'] / base:.2f}x; "
            f"max |final state difference| {r['max_diff_to_first']:.1e} (another per-device "
            "batch size may round differently)"
        )
    if results and args.scipy_sample:
        print(
            f"sweep on {results[-1]['devices']} device(s) / scipy: "
            f"{results[-1]['traj_per_s'] * per_scipy:.0f}x per trajectory; max |final state "
            f"difference| on the sample: {diff:.2e}"
        )
    if results and nb:
        last = results[-1]
        for key, r in nb.items():
            ratio = last["traj_per_s"] / r["traj_per_s"]
            print(
                f"sweep on {last['devices']} device(s) / numba {key}: {ratio:.2f}x per "
                "trajectory" + (f" -- numba {key} is {1 / ratio:.1f}x faster" if ratio < 1 else "")
            )
        r = nb["serial"]
        par = nb["prange"]["traj_per_s"] / r["traj_per_s"]
        print(
            f"numba check: max |final state difference| vs the sweep {r['max_diff_to_sweep']:.2e}"
            f", vs scipy (sample) {r['max_diff_to_scipy']:.2e}; max |nfev numba - nfev scipy| "
            f"= {r['nfev_diff_to_scipy']}; prange / serial {par:.2f}x"
        )
    if len(counts) < len(args.devices):
        print(f"(skipped device counts above the {n_local} local devices)")
    out = {
        "env": env,
        "integrator": args.integrator,
        "n": args.n,
        "chunk": batch,
        "sweep": results,
        "scipy": {"sample": args.scipy_sample, "s_per_traj": per_scipy, "max_diff": diff},
        "numba": nb or None,
    }
    write_json(args.json, out, indent=2)
    return out


if __name__ == "__main__":
    main()
