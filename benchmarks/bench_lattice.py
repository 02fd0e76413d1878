"""Time per body and step of a lattice solve: ``rbo_jax.lattice.simulate(method="dop853")``
against a hand-written numba DOP853 of the same chain (``_numba_lattice.py``), one core each.

The problem: a periodic chain of N transversely isotropic bodies (A1 = 1, A3 = 0.6, axis k = e_z)
on the quadratic foundation (4.50) (c = 1, d = 2) with a follower moment M = 0.2 k (4.57),
neighbours coupled by the quadratic energy of their relative turn (κ_b = 0.7, κ_t = 0.3). The
start is a smooth wave with noise: θ_n = 0.3 (sin 6πn/N, cos 6πn/N, 0.1) + 1e-3 ξ_n,
Ω_n = 1e-2 η_n (ξ, η standard normal, seed 0); t ∈ [0, t1], rtol = 1e-8, atol = 1e-10, final
state only (``ts = [0, t1]``).

Both sides are SciPy's DOP853 on the whole 6N system (one step size, the error norm over all 6N
scalars), so they take the same steps: the accepted steps of both are printed and compared, and
the final states (max |difference| over θ and Ω). The right-hand sides are compared on the
initial state of the smallest N (rbo_jax's ``lattice._integrate.Problem.f``).

Timing: JAX's first call (tracing, compilation and one run) is timed alone; "compile" is it
less the best run. Then ``--repeat`` rounds of one call of each side, alternating so that a
change of the machine's load hits both, the best of each kept (JAX: ``simulate`` from NumPy
inputs to ``jax.block_until_ready(traj.theta)``; numba: the compiled solver from the flat state,
compiled once on a tiny chain first). JAX's fixed cost of a call (checks, dispatch, the loop's
iterations) is printed as the best call on a chain of 8 bodies: it weighs on small N. The
per-core table runs in a fresh process started on one core (``--core``, default the first core
this process may use; ``_common.run_child``), as ``taskset -c`` would start it: a process
started on every core and pinned afterwards keeps XLA's thread pools sized for all of them
(its tasks then queue on the one core), which is not what a user who pins a run gets. A
body-step is one accepted step of one body: µs per body-step = time / (N × accepted steps).
The ratio is numba's time / JAX's (> 1: JAX faster).

**All cores** (``--all-n``, default 10⁶ bodies; 0 skips it): this process asks JAX for one CPU
device per core it may use (``jax_num_cpu_devices``, before JAX starts; ``--devices`` chooses
another number). The row is the chain split over all devices (``lattice.simulate(...,
devices=None)``: a shard per device, halos of the neighbours, one error norm), unpinned, best of
``--repeat``, against the same chain's row of the per-core table; the final states of the split
and of one device are compared.

Usage: ``python benchmarks/bench_lattice.py [--n 1000,10000,100000,1000000] [--t1 2]
[--rtol 1e-8] [--atol 1e-10] [--repeat 3] [--core C] [--all-n 1000000] [--devices D]
[--json PATH] [--smoke]``
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import equinox as eqx
import jax
import numpy as np
from _common import run_child, write_json
from _pinning import pinned

import rbo_jax
from rbo_jax import lattice as L

try:
    import _numba_lattice as numba_lattice
except ImportError:  # numba is optional (the "bench" extra)
    numba_lattice = None


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def _ask_devices(argv) -> None:
    """One CPU device per core (or ``--devices D``), before JAX's backend starts."""
    argv = list(argv) if argv is not None else __import__("sys").argv[1:]
    d = _cores()
    for i, a in enumerate(argv):
        if a == "--devices" and i + 1 < len(argv):
            d = int(argv[i + 1])
        elif a.startswith("--devices="):
            d = int(a.split("=", 1)[1])
    try:
        jax.config.update("jax_num_cpu_devices", max(1, d))
    except RuntimeError:  # the backend started already (imported as a module): keep its devices
        pass


K = np.array([0.0, 0.0, 1.0])
A1, A3, C, D, KB, KT, M = 1.0, 0.6, 1.0, 2.0, 0.7, 0.3, 0.2


def _parse(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--n", default="1000,10000,100000,1000000", help="chain sizes, e.g. 1000,10000"
    )
    parser.add_argument(
        "--all-n", type=int, default=1_000_000, help="chain of the all-cores row (0: none)"
    )
    parser.add_argument("--devices", type=int, default=None, help="CPU devices (default: cores)")
    parser.add_argument("--t1", type=float, default=2.0, help="end time")
    parser.add_argument("--rtol", type=float, default=1e-8)
    parser.add_argument("--atol", type=float, default=1e-10)
    parser.add_argument("--repeat", type=int, default=3, help="timed calls per side (best kept)")
    parser.add_argument(
        "--core",
        type=int,
        default=None,
        help="the core to pin to (default: the first this process may use)",
    )
    parser.add_argument("--json", default=None, help="also write the figures to this file")
    parser.add_argument("--smoke", action="store_true", help="a tiny run (N = 50, t1 = 0.2)")
    args = parser.parse_args(argv)
    try:
        args.n = [int(x) for x in args.n.split(",")]
    except ValueError:
        parser.error(f"--n must be a comma-separated list of integers, got {args.n!r}")
    if args.smoke:
        args.n, args.t1, args.repeat = [50], 0.2, 1
        args.all_n = 64 if jax.local_device_count() > 1 else 0
    if min(args.n) < 2 or args.repeat < 1 or not args.t1 > 0:
        parser.error("need chain sizes >= 2, --repeat >= 1 and --t1 > 0")
    if args.core is None:
        args.core = min(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 0
    return args


def initial_state(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    x = 2.0 * np.pi * 3.0 * np.arange(n) / n
    wave = np.stack([np.sin(x), np.cos(x), np.full(n, 0.1)], axis=1)
    theta0 = 0.3 * wave + 1e-3 * rng.standard_normal((n, 3))
    Omega0 = 1e-2 * rng.standard_normal((n, 3))
    return theta0, Omega0


def build_lattice(n: int):
    body = rbo_jax.RigidBodyOscillator(
        rbo_jax.transversely_isotropic_inertia(A1, A3, K),
        rbo_jax.QuadraticFoundation(C, D, K),
        [rbo_jax.FollowerMoment(M, K)] if M else [],
    )
    return L.chain(n, body, rbo_jax.QuadraticFoundation(KB, KT, K)), body


def numba_params(body) -> dict:
    return dict(c=C, d=D, M=M, kb=KB, kt=KT, A=np.asarray(body.inertia), k=K)


def jax_call(lat, theta0, Omega0, args, devices=1):
    """One ``lattice.simulate`` call, to the final state on the host side of JAX's dispatch."""
    traj = L.simulate(
        lat,
        theta0,
        Omega0,
        np.array([0.0, args.t1]),
        rtol=args.rtol,
        atol=args.atol,
        devices=devices,
    )
    jax.block_until_ready(traj.theta)
    return traj


def all_cores(args, one_core_seconds: float) -> dict:
    """The chain of ``args.all_n`` bodies split over all devices, unpinned (best of
    ``args.repeat``), against ``one_core_seconds``: the same chain's best call in a process
    started on one core (the per-core table's row, :func:`main`). The final states of the split
    and of one device (this process, not timed) are compared."""
    n = args.all_n
    lat, _ = build_lattice(n)
    theta0, Omega0 = initial_state(n)
    d = jax.local_device_count()
    split = d if n % d == 0 and n // d >= 16 else None  # None: the default's choice
    one = jax_call(lat, theta0, Omega0, args)
    many = lambda: jax_call(lat, theta0, Omega0, args, devices=split)  # noqa: E731
    t_many = many()
    best_many = min(timed(many)[1] for _ in range(args.repeat))
    shards = len(t_many.theta.sharding.device_set)
    diff = max(
        float(np.max(np.abs(np.asarray(one.theta) - np.asarray(t_many.theta)))),
        float(np.max(np.abs(np.asarray(one.Omega) - np.asarray(t_many.Omega)))),
    )
    steps = int(one.num_steps)
    return {
        "n": n,
        "devices": d,
        "shards": shards,
        "steps": [steps, int(t_many.num_steps)],
        "seconds_one_core": one_core_seconds,
        "seconds_all": best_many,
        "us_per_body_step_one_core": one_core_seconds / (n * steps) * 1e6,
        "us_per_body_step_all": best_many / (n * steps) * 1e6,
        "ratio": one_core_seconds / best_many,
        "max_diff": diff,
    }


def timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def run_pair(lat, theta0, Omega0, params, args) -> dict:
    """JAX's first call alone, then ``args.repeat`` rounds of one JAX call and one numba call
    (alternating, so that a change of the machine's load hits both sides); the best of each."""
    traj, first = timed(lambda: jax_call(lat, theta0, Omega0, args))
    best_jax, best_nb = np.inf, None
    for _ in range(args.repeat):
        traj, seconds = timed(lambda: jax_call(lat, theta0, Omega0, args))
        best_jax = min(best_jax, seconds)
        if numba_lattice is not None:
            r = numba_lattice.solve_chain(theta0, Omega0, args.t1, args.rtol, args.atol, params)
            if r["status"] != 0:
                raise RuntimeError(f"numba DOP853 failed (status {r['status']})")
            if best_nb is None or r["seconds"] < best_nb["seconds"]:
                best_nb = r
    return {
        "theta": np.asarray(traj.theta[-1]),
        "Omega": np.asarray(traj.Omega[-1]),
        "steps": int(traj.num_steps),
        "seconds": best_jax,
        "first": first,
        "numba": best_nb,
    }


def jax_overhead(args) -> float:
    """The best of ``args.repeat`` calls on a chain of 8 bodies (after a first call): the fixed
    cost of a call (checks, dispatch, the loop's steps) that the time per body-step of small
    chains includes."""
    lat, _ = build_lattice(8)
    theta0, Omega0 = initial_state(8)
    jax_call(lat, theta0, Omega0, args)
    return min(timed(lambda: jax_call(lat, theta0, Omega0, args))[1] for _ in range(args.repeat))


def compile_numba(params, args) -> float:
    theta0, Omega0 = initial_state(4)
    start = time.perf_counter()
    numba_lattice.solve_chain(theta0, Omega0, 1e-3, args.rtol, args.atol, params)
    numba_lattice.rhs(theta0, Omega0, params)
    return time.perf_counter() - start


def rhs_difference(lat, theta0, Omega0, params) -> float:
    """max |f_jax − f_numba| / max |f_jax| at the initial state."""
    from rbo_jax.lattice._integrate import Problem

    y = tuple(np.concatenate([theta0.T, Omega0.T]))
    f = eqx.filter_jit(lambda p, y: p.f(0.0, y))(Problem.of(lat), y)
    fj = np.stack([np.asarray(v) for v in f])
    fn = numba_lattice.rhs(theta0, Omega0, params)
    return float(np.max(np.abs(fj - fn)) / np.max(np.abs(fj)))


def header(args, is_pinned, numba_compile):
    try:
        load = f"load average {os.getloadavg()[0]:.2f}"
    except OSError:
        load = "load average unknown"
    print(
        f"rbo_jax {rbo_jax.__version__}, jax {jax.__version__}, "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"{jax.device_count()} {jax.default_backend()} device(s); "
        + (
            f"numba {numba_lattice.NUMBA_VERSION} (compile {numba_compile:.1f} s)"
            if numba_lattice is not None
            else "numba not installed, skipped"
        )
        + f"; {load}"
    )
    print(
        f"periodic chain, t in [0, {args.t1:g}], rtol = {args.rtol:g}, atol = {args.atol:g}, "
        f"DOP853 on the 6N system; best of {args.repeat}; every thread pinned to core "
        f"{args.core}: {is_pinned}"
    )


COLUMNS = (
    f"{'N':>9}{'steps jax/numba':>17}{'jax us/body-step':>18}"
    f"{'numba us/body-step':>20}{'numba/jax':>11}{'jax compile [s]':>17}"
    f"{'max |diff|':>12}"
)


def row_text(r) -> str:
    nb = r.get("numba")
    steps = f"{r['steps_jax']}/{nb['steps'] if nb else '-'}"
    nb_us = f"{nb['us_per_body_step']:.3f}" if nb else "-"
    ratio = f"{nb['us_per_body_step'] / r['us_per_body_step']:.2f}" if nb else "-"
    diff = f"{r['max_diff']:.1e}" if nb else "-"
    return (
        f"{r['n']:>9}{steps:>17}{r['us_per_body_step']:>18.3f}{nb_us:>20}{ratio:>11}"
        f"{r['compile_jax']:>17.1f}{diff:>12}"
    )


def per_core(args, extra_n=()) -> dict:
    """The per-core table: every N of ``args.n`` and ``extra_n`` (the all-cores row's chain)
    against numba, every thread pinned to ``args.core``."""
    rows = []
    numba_compile = None
    rhs_diff = None
    with pinned((args.core,)) as is_pinned:
        if numba_lattice is not None:
            numba_compile = compile_numba(numba_params(build_lattice(4)[1]), args)
        header(args, is_pinned, numba_compile)
        print(COLUMNS)
        print("-" * len(COLUMNS))
        for n in list(args.n) + list(extra_n):
            lat, body = build_lattice(n)
            params = numba_params(body)
            theta0, Omega0 = initial_state(n)
            if numba_lattice is not None and rhs_diff is None:
                rhs_diff = rhs_difference(lat, theta0, Omega0, params)
            res = run_pair(lat, theta0, Omega0, params, args)
            steps_j, t_jax, nb = res["steps"], res["seconds"], res["numba"]
            r = {
                "n": n,
                "steps_jax": steps_j,
                "seconds_jax": t_jax,
                "us_per_body_step": t_jax / (n * steps_j) * 1e6,
                "first_call_jax": res["first"],
                "compile_jax": res["first"] - t_jax,
                "numba": None,
                "max_diff": None,
            }
            if nb is not None:
                r["numba"] = {
                    "steps": nb["steps"],
                    "rejected": nb["rejected"],
                    "nfev": nb["nfev"],
                    "seconds": nb["seconds"],
                    "us_per_body_step": nb["seconds"] / (n * nb["steps"]) * 1e6,
                }
                r["max_diff"] = float(
                    max(
                        np.max(np.abs(res["theta"] - nb["theta"])),
                        np.max(np.abs(res["Omega"] - nb["Omega"])),
                    )
                )
                r["steps_equal"] = steps_j == nb["steps"]
                r["ratio"] = r["numba"]["us_per_body_step"] / r["us_per_body_step"]
            rows.append(r)
            print(row_text(r), flush=True)
        overhead = None if args.smoke else jax_overhead(args)
    print(
        "(steps: accepted; us/body-step: best call time / (N x accepted steps); numba/jax > 1: "
        "jax faster; jax compile: first call less the best call; max |diff|: final state, "
        "jax vs numba, over theta and Omega)"
    )
    if numba_lattice is not None:
        equal = all(r["steps_equal"] for r in rows)
        print(
            f"accepted steps equal on every N: {equal}; numba rejected steps: "
            + ", ".join(str(r["numba"]["rejected"]) for r in rows)
            + f"; right-hand sides at the initial state (N = {args.n[0]}): max |f_jax - "
            f"f_numba| / max |f_jax| = {rhs_diff:.1e}"
        )
    else:
        print("numba not installed, skipped (pip install numba, or the 'bench' extra)")
    if overhead is not None:
        print(
            f"jax fixed cost of a call (best call on a chain of 8 bodies, same t1 and "
            f"tolerances): {overhead * 1e3:.2f} ms"
        )
    return {
        "t1": args.t1,
        "rtol": args.rtol,
        "atol": args.atol,
        "repeat": args.repeat,
        "jax_overhead": overhead,
        "core": args.core,
        "pinned": is_pinned,
        "numba_compile": numba_compile,
        "rhs_rel_diff": rhs_diff,
        "rows": rows,
        "versions": {
            "rbo_jax": rbo_jax.__version__,
            "jax": jax.__version__,
            "numba": numba_lattice.NUMBA_VERSION if numba_lattice else None,
        },
    }


def main(argv=None) -> dict:
    _ask_devices(argv)
    args = _parse(argv)
    n_all = [args.all_n] if args.all_n and args.all_n not in args.n else []
    if _cores() > 1 and not args.smoke:
        # the per-core table in a fresh process started on the core (_common.run_child)
        child = ["--n", ",".join(str(n) for n in args.n + n_all), "--all-n", "0"]
        for name in ("t1", "rtol", "atol", "repeat", "core"):
            child += [f"--{name}", str(getattr(args, name))]
        out = run_child("bench_lattice", child, core=args.core)
    else:
        out = per_core(args, n_all)
    rows = {r["n"]: r for r in out["rows"]}
    every = all_cores(args, rows[args.all_n]["seconds_jax"]) if args.all_n else None
    if every is not None:
        print(
            f"all cores: N = {every['n']}, {every['shards']} shard(s) on {every['devices']} "
            f"CPU device(s), unpinned: {every['us_per_body_step_all']:.3f} us/body-step; one "
            f"device in a process started on core {args.core}: "
            f"{every['us_per_body_step_one_core']:.3f}; all/one = {every['ratio']:.2f}x; steps "
            f"{every['steps'][0]}/{every['steps'][1]}; max |diff| {every['max_diff']:.1e}",
            flush=True,
        )
    out["all_cores"] = every
    write_json(args.json, out, indent=2, default=float)
    return out


if __name__ == "__main__":
    main()
