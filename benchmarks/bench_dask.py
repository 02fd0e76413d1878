"""Sweeps on Dask (issue 26): what a chunk costs as a Dask task, and 2 workers against 1 process.

1. **Overhead per chunk.** A cheap quantity (a few arithmetic operations per point, so a chunk's
   computation is well under a millisecond) in chunks of ``--chunk`` points (4096, the default of
   :func:`rbo_jax.sweep`): seconds per chunk of ``sweep(..., client=client)`` on one Dask worker
   against the same sweep in this process (one device). The difference is what a task costs:
   submitting it, sending its points, the worker's call, the result back, assembling it here.
2. **2 workers vs 1 process.** A moderate quantity, the final state of the Nikolai problem
   (4.57)–(4.62) of ``bench_sweep.py`` (:func:`rbo_jax.fast_simulate`, DOP853, t in [0, 20],
   rtol 1e-8, atol 1e-10) at ``--n`` random points: in this process, on one Dask worker and on
   two (local processes of one thread each: ``distributed.LocalCluster``).

Compilation is excluded: each configuration first runs a warm-up sweep of the same chunk size
(the workers trace and compile there, once per process). Results are in memory (no store), and
each Dask result is checked bit for bit against the in-process one. The machine is shared by the
client (and the scheduler, in this process) and the workers: on 2 cores, two workers use both.

Usage: ``python benchmarks/bench_dask.py [--n 131072] [--chunk 4096] [--cheap-chunks 64]
[--repeat 3] [--json out.json]``; ``--smoke`` runs tiny sizes (``benchmarks/run.py --smoke``).
"""

from __future__ import annotations

import argparse
import os
import platform
import time

from _common import write_json


def _parse(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=131_072, help="points of the moderate sweep")
    parser.add_argument("--chunk", type=int, default=4096, help="points per chunk")
    parser.add_argument(
        "--cheap-chunks",
        type=int,
        default=64,
        help="chunks of the cheap sweep (overhead per chunk)",
    )
    parser.add_argument("--repeat", type=int, default=3, help="timed runs (the best is kept)")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes, for tests")
    parser.add_argument("--json", default=None, help="also write the figures to this file")
    args = parser.parse_args(argv)
    if args.smoke:
        args.n, args.chunk, args.cheap_chunks, args.repeat = 512, 128, 4, 1
    if min(args.n, args.chunk, args.cheap_chunks, args.repeat) < 1:
        parser.error("--n, --chunk, --cheap-chunks and --repeat must be >= 1")
    return args


def _quantities():
    """The two quantities, as closures (cloudpickle sends them to the workers by value, so the
    workers need not import this file)."""
    import jax.numpy as jnp

    from rbo_jax import (
        FollowerMoment,
        QuadraticFoundation,
        RigidBodyOscillator,
        fast_simulate,
        transversely_isotropic_inertia,
    )

    k = (0.0, 0.0, 1.0)
    perturbation = (1e-3, -5e-4, 2e-4)

    def cheap(c, M):
        return {"x": c * M + jnp.sin(c) - M * M}

    def final_state(c, d, M):
        axis = jnp.asarray(k)
        model = RigidBodyOscillator(
            transversely_isotropic_inertia(1.0, 0.5, axis),
            QuadraticFoundation(c, d, axis),
            FollowerMoment(M, axis),
        )
        traj = fast_simulate(
            model,
            (M / d) * axis + jnp.asarray(perturbation),
            jnp.zeros(3),
            jnp.array([0.0, 20.0]),
            rtol=1e-8,
            atol=1e-10,
            throw=False,
        )
        return {"y": jnp.concatenate([traj.theta[-1], traj.Omega[-1]])}, traj.status

    return cheap, final_state


def _best(run, repeat):
    """(best seconds of ``repeat`` runs, the last result)."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = run()
        best = min(best, time.perf_counter() - t0)
    return best, out


def _same_bits(a, b) -> bool:
    return all(a[v].values.tobytes() == b[v].values.tobytes() for v in b.data_vars)


def main(argv=None) -> dict:
    args = _parse(argv)
    try:
        import distributed
    except ImportError:
        print("distributed not installed, skipped (pip install 'rbo_jax[dask]')")
        return {}
    import jax
    import numpy as np

    import rbo_jax
    from rbo_jax import sweep

    cheap, final_state = _quantities()
    rng = np.random.default_rng(0)
    n_cheap = args.cheap_chunks * args.chunk
    cheap_pts = {"c": rng.uniform(0.5, 2.0, n_cheap), "M": rng.uniform(-1.0, 1.0, n_cheap)}
    moderate = {
        "c": rng.uniform(0.5, 2.0, args.n),
        "d": rng.uniform(0.5, 2.0, args.n),
        "M": rng.uniform(0.05, 0.6, args.n),
    }

    def warm(pts, chunks=4):
        return {k: v[: chunks * args.chunk] for k, v in pts.items()}

    def run(q, pts, client=None):
        return sweep(q, points=pts, chunk_size=args.chunk, devices=1, progress=False, client=client)

    # in this process (one device, as each worker)
    rows = {}
    for name, q, pts in (("cheap", cheap, cheap_pts), ("moderate", final_state, moderate)):
        run(q, warm(pts))
        rows[name] = {"process": _best(lambda q=q, pts=pts: run(q, pts), args.repeat)}

    cluster = distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0"
    )
    client = distributed.Client(cluster)
    try:
        for workers in (1, 2):
            if workers == 2:
                cluster.scale(2)
                client.wait_for_workers(2, timeout=120)
            for name, q, pts in (("cheap", cheap, cheap_pts), ("moderate", final_state, moderate)):
                for _ in range(workers):  # every worker traces and compiles in a warm-up
                    run(q, warm(pts, 4 * workers), client)
                rows[name][workers] = _best(lambda q=q, pts=pts: run(q, pts, client), args.repeat)
    finally:
        client.close()
        cluster.close()

    equal = {
        name: all(_same_bits(r[w][1], r["process"][1]) for w in (1, 2)) for name, r in rows.items()
    }
    n_chunks = {"cheap": args.cheap_chunks, "moderate": -(-args.n // args.chunk)}
    env = {
        "rbo_jax": rbo_jax.__version__,
        "jax": jax.__version__,
        "distributed": distributed.__version__,
        "python": platform.python_version(),
        "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0],
    }
    print(
        f"rbo_jax {env['rbo_jax']}, jax {env['jax']}, distributed {env['distributed']}, "
        f"Python {env['python']}, {env['machine']}, {env['cpu_count']} CPUs, load average "
        f"{env['load_average_1min']:.2f}; best of {args.repeat}, compilation excluded"
    )
    header = (
        f"{'sweep':<34}{'chunks':>7}{'1 process':>12}{'1 worker':>12}{'2 workers':>12}"
        f"{'1 worker/':>11}{'2 workers/':>11}"
    )
    print(header)
    print(
        f"{'(ms per chunk of ' + str(args.chunk) + ' points)':<34}{'':>7}{'':>12}{'':>12}"
        f"{'':>12}{'1 process':>11}{'1 process':>11}"
    )
    print("-" * len(header))
    out = {"env": env, "chunk": args.chunk, "rows": {}}
    for name, label in (
        ("cheap", "cheap quantity (arithmetic)"),
        ("moderate", "final state (fast_simulate, t1=20)"),
    ):
        r, m = rows[name], n_chunks[name]
        ms = {k: 1e3 * r[k][0] / m for k in ("process", 1, 2)}
        print(
            f"{label:<34}{m:>7}{ms['process']:>12.2f}{ms[1]:>12.2f}{ms[2]:>12.2f}"
            f"{ms[1] / ms['process']:>10.2f}x{ms[2] / ms['process']:>10.2f}x"
        )
        out["rows"][name] = {
            "chunks": m,
            "ms_per_chunk": {str(k): v for k, v in ms.items()},
            "bit_for_bit": equal[name],
        }
    cheap_ms = out["rows"]["cheap"]["ms_per_chunk"]
    mod = out["rows"]["moderate"]["ms_per_chunk"]
    out["overhead_ms"] = cheap_ms["1"] - cheap_ms["process"]
    out["speedup_2_workers"] = mod["process"] / mod["2"]
    print(
        f"overhead of a chunk as a Dask task (cheap quantity, 1 worker - 1 process): "
        f"{out['overhead_ms']:.2f} ms per chunk of {args.chunk} points"
    )
    print(
        f"2 workers vs 1 process on the moderate sweep: speed-up {out['speedup_2_workers']:.2f}x"
        f"; results bit for bit equal to the process's: {equal['cheap'] and equal['moderate']}"
    )
    write_json(args.json, out, indent=2)
    return out


if __name__ == "__main__":
    main()
