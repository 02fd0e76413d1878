"""Trajectories per second: ``jax.vmap(fast_simulate)`` and ``jax.vmap(simulate)`` vs a
numba-compiled DOP853 and ``scipy.integrate.solve_ivp`` (DOP853).

The Nikolai problem (4.57)–(4.62): transversely isotropic body (A1 = 1, A3 = 0.5), quadratic
foundation (4.50), follower moment M; each parameter point (c, d, M) starts 1e-3 rad off its
equilibrium θ = (M/d)k; t ∈ [0, 20], rtol = 1e-8, atol = 1e-10, final state only.

Every side uses an 8th-order Dormand–Prince method at the same tolerances:

* :func:`rbo_jax.fast_simulate` (DOP853, SciPy's steps): one ``jax.jit(jax.vmap(...))`` call
  over all points (refilled lanes), one device;
* diffrax ``Dopri8`` through :func:`rbo_jax.simulate` (``jax.jit(jax.vmap(...))`` over chunks,
  one device);
* ``_numba_reference``: a per-trajectory DOP853 compiled with numba (scipy's tableau, error
  estimator and step-size controller; scalar right-hand side), a serial loop over all points (one
  core) and a ``prange`` loop (all cores numba sees) — skipped when numba is not installed;
* ``solve_ivp(method="DOP853")`` with a plain NumPy right-hand side (run on a sample of the
  points: it is ~1000x slower).

Final states are compared (independent checks of the vector field), numba's function-evaluation
counts against scipy's (same algorithm: they should be equal), and the per-trajectory time ratios
are printed. Compilation is timed separately (JAX: the first call; numba: a first call on one
point) and not included in the per-trajectory times. The one-core rows (everything but numba's
``prange``) run in a fresh process started on core 0 (``_common.run_child``, as ``taskset -c 0``
starts one: ``import rbo_jax`` then makes one CPU device and XLA sizes its pools for one core),
when this process may use several cores; numba's ``prange`` then runs here, on all of them, side
by side with the JAX idiom for a sharded batch: ``jax.jit(jax.vmap(fast_simulate))`` on inputs
placed with a ``NamedSharding`` over every local device (``import rbo_jax`` made one per core),
in ``--rounds`` rounds of one call each, the two in turn (medians; the final states' sha1
compared with the one-core run's).
The error of each method against a tight reference (``simulate`` at rtol = atol = 1e-13) is
printed for the scipy sample.

Usage: ``python benchmarks/bench_simulate.py [--n 10000] [--scipy-sample 20] [--chunk 500]
[--rounds 5] [--no-numba-parallel]``
"""

from __future__ import annotations

import argparse
import hashlib
import os
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from _common import run_child, run_in_chunks, write_json

try:
    import _numba_reference as numba_ref
except ImportError:  # numba is optional (the "bench" extra)
    numba_ref = None

from _pinning import pinned
from _problem import DESCRIPTION, final_state, inertia, numba_final_states, scipy_final_state

import rbo_jax
from rbo_jax import fast_simulate, simulate


def parameter_points(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    c = rng.uniform(0.5, 2.0, n)
    d = rng.uniform(0.5, 2.0, n)
    M = rng.uniform(0.05, 0.6, n)
    return np.stack([c, d, M], axis=1)


# ---------------------------------------------------------------------------------------------
# JAX side.
# ---------------------------------------------------------------------------------------------


def jax_final_state(p, solver=simulate, **tolerances):
    y, steps, _ = final_state(p[0], p[1], p[2], solver, **tolerances)
    return y, steps


def fast_final_state(p):
    return jax_final_state(p, solver=fast_simulate)


def run_fast(points: np.ndarray):
    """One jit(vmap(fast_simulate)) call over all points (first call: compilation + run)."""
    fn = jax.jit(jax.vmap(fast_final_state))
    x = jnp.asarray(points)
    t0 = time.perf_counter()
    jax.block_until_ready(fn(x))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    y, steps = jax.block_until_ready(fn(x))
    elapsed = time.perf_counter() - t0
    return np.asarray(y), np.asarray(steps), elapsed, first - elapsed


def sha1(y) -> str:
    """The first 12 hex digits of the sha1 of an array's bytes (C order)."""
    return hashlib.sha1(np.ascontiguousarray(y).tobytes()).hexdigest()[:12]


def sharded_program(points: np.ndarray):
    """``jax.jit(jax.vmap(fast_simulate))`` and the points placed with a ``NamedSharding`` over
    every local device (padded with copies of the last point to a multiple of the devices)."""
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    devices = jax.devices()
    pad = (-len(points)) % len(devices)
    padded = np.concatenate([points, np.repeat(points[-1:], pad, axis=0)])
    mesh = Mesh(np.array(devices), ("batch",))
    x = jax.device_put(padded, NamedSharding(mesh, P("batch")))
    return jax.jit(jax.vmap(fast_final_state)), x


def prange_and_sharded(points: np.ndarray, rounds: int) -> dict:
    """numba's ``prange`` and the sharded ``jit(vmap(fast_simulate))``, one call each per
    round, in turn: their median seconds per call, the sharded call's first (compilation), its
    final states' sha1, and numba's last result."""
    fn, x = sharded_program(points)
    t0 = time.perf_counter()
    jax.block_until_ready(fn(x))
    first = time.perf_counter() - t0
    par, nb_times, jax_times = None, [], []
    for _ in range(max(1, rounds)):
        par = run_numba(points, parallel=True)
        nb_times.append(par["seconds"])
        t0 = time.perf_counter()
        y, _ = jax.block_until_ready(fn(x))
        jax_times.append(time.perf_counter() - t0)
    y = np.asarray(y)[: len(points)]
    return {
        "numba": par,
        "prange": float(np.median(nb_times)),
        "sharded": float(np.median(jax_times)),
        "sharded_rounds": jax_times,
        "prange_rounds": nb_times,
        "first": first - min(jax_times),
        "devices": len(jax.devices()),
        "sha1": sha1(y),
        "finite": bool(np.isfinite(y).all()),
    }


def tight_reference(points: np.ndarray) -> np.ndarray:
    fn = jax.jit(jax.vmap(lambda p: jax_final_state(p, rtol=1e-13, atol=1e-13)[0]))
    return np.asarray(fn(jnp.asarray(points)))


def run_jax(points: np.ndarray, chunk: int):
    (y, steps), elapsed, t_compile = run_in_chunks(
        jax.jit(jax.vmap(jax_final_state)), points, chunk
    )
    return y, steps, elapsed, t_compile


# ---------------------------------------------------------------------------------------------
# NumPy / scipy side: an independent plain-NumPy right-hand side of (4.55)-(4.56).
# ---------------------------------------------------------------------------------------------


def run_scipy(points: np.ndarray):
    A, A_inv = inertia()
    outs, nfev, steps = [], [], []
    start = time.perf_counter()
    for c, d, M in points:
        sol = scipy_final_state(c, d, M, A, A_inv)
        outs.append(sol.y[:, -1])
        nfev.append(sol.nfev)
        steps.append(sol.t.size - 1)  # accepted steps
    elapsed = time.perf_counter() - start
    return np.array(outs), np.array(nfev), np.array(steps), elapsed


def run_numba(points: np.ndarray, parallel: bool) -> dict:
    return numba_final_states(points, parallel)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=4_000, help="parameter points (JAX, numba)")
    parser.add_argument("--scipy-sample", type=int, default=20, help="points run with scipy")
    parser.add_argument("--chunk", type=int, default=500, help="vmap chunk size")
    parser.add_argument(
        "--no-numba-parallel", action="store_true", help="skip the numba prange run (all cores)"
    )
    parser.add_argument(
        "--rounds", type=int, default=5, help="rounds of numba prange vs the sharded jit(vmap)"
    )

    parser.add_argument("--json", default=None, help="also write the figures to this file")
    args = parser.parse_args(argv)
    if len(os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else [0]) > 1:
        return _one_core_child_and_prange(args, list(sys.argv[1:] if argv is None else argv))

    points = parameter_points(args.n)
    ns = args.scipy_sample
    sample = points[:ns]
    nb = {}
    with pinned((0,)) as is_pinned:
        y_fast, steps_fast, t_fast, compile_fast = run_fast(points)
        y_jax, steps, t_jax, t_compile = run_jax(points, min(args.chunk, args.n))
        if numba_ref is not None:
            nb["serial"] = run_numba(points, parallel=False)
        y_sp, nfev, steps_sp, t_sp = run_scipy(sample)
    if numba_ref is not None and not args.no_numba_parallel:
        nb["prange"] = run_numba(points, parallel=True)
    err = np.max(np.abs(y_jax[:ns] - y_sp))
    tight = tight_reference(sample) if ns else np.zeros((0, 6))
    acc = {
        name: float(np.max(np.abs(y[:ns] - tight))) if ns else float("nan")
        for name, y in [("fast_simulate", y_fast), ("simulate", y_jax), ("scipy", y_sp)]
        + ([("numba", nb["serial"]["y"])] if nb else [])
    }
    per_fast = t_fast / args.n
    per_jax = t_jax / args.n
    per_sp = t_sp / ns
    per_nb = {k: r["seconds"] / args.n for k, r in nb.items()}

    print(
        f"rbo_jax {rbo_jax.__version__}, jax {jax.__version__}, "
        f"{platform.processor() or platform.machine()}, {jax.device_count()} "
        f"{jax.default_backend()} device(s); "
        + (
            f"numba {numba_ref.NUMBA_VERSION} ({nb['prange']['threads'] if 'prange' in nb else 1}"
            " threads for prange)"
            if numba_ref is not None
            else "numba not installed, skipped"
        )
    )
    print(
        f"{DESCRIPTION}, {args.n} points (scipy: {ns}); one-core rows pinned to core 0: {is_pinned}"
    )
    header = (
        f"{'method':<42}{'s / trajectory':>16}{'traj / s':>12}{'steps (mean)':>14}"
        f"{'compile [s]':>13}"
    )
    print(header)
    print("-" * len(header))
    rows = [
        (
            "jax.vmap(fast_simulate), DOP853, 1 core",
            per_fast,
            steps_fast.mean(),
            f"{compile_fast:.1f}",
        ),
        ("jax.vmap(simulate), Dopri8, 1 core", per_jax, steps.mean(), f"{t_compile:.1f}"),
    ]
    labels = {
        "serial": "numba DOP853, serial loop (1 core)",
        "prange": "numba DOP853, prange (all cores)",
    }
    for key, r in nb.items():
        comp = "(earlier)" if r["already_compiled"] else f"{r['compile_s']:.1f}"
        rows.append((labels[key], per_nb[key], r["steps"].mean(), comp))
    rows.append(("scipy solve_ivp DOP853, NumPy RHS", per_sp, steps_sp.mean(), "-"))
    for name, per, st, comp in rows:
        print(f"{name:<42}{per:>16.3e}{1 / per:>12.1f}{st:>14.1f}{comp:>13}")
    print(
        "(steps: accepted steps; compile: first call incl. JIT, not in the per-trajectory "
        "times; numba's serial compile includes the shared integrator, prange reuses it; "
        "'(earlier)': compiled by an earlier benchmark in this process)"
    )
    print("ratios below: time per trajectory of the other method / jax's (> 1: jax faster)")
    print(
        f"speed-up per trajectory: {per_sp / per_jax:.0f}x   (jax vs scipy; compile once: "
        f"{t_compile:.1f} s, not included)"
    )
    steps_equal = float(np.mean(steps_fast[:ns] == steps_sp)) if ns else float("nan")
    print(
        f"fast_simulate: {per_sp / per_fast:.0f}x scipy, {per_jax / per_fast:.1f}x "
        f"vmap(simulate) per trajectory; accepted steps equal to scipy's on {steps_equal:.0%} "
        f"of the sample; compile {compile_fast:.1f} s"
    )
    print(
        "max |final state - tight reference| (simulate at 1e-13) on the sample: "
        + ", ".join(f"{k} {v:.1e}" for k, v in acc.items())
    )
    out = {
        "per_jax": per_jax,
        "per_scipy": per_sp,
        "ratio": per_sp / per_jax,
        "max_diff": err,
        "compile_jax": t_compile,
        "steps_jax": float(steps.mean()),
        "steps_scipy": float(steps_sp.mean()),
        "numba": None,
        "pinned": is_pinned,
        "fast": {
            "per": per_fast,
            "compile": compile_fast,
            "ratio_scipy": per_sp / per_fast,
            "ratio_simulate": per_jax / per_fast,
            "steps_equal_scipy": steps_equal,
            "max_diff_scipy": float(np.max(np.abs(y_fast[:ns] - y_sp))) if ns else float("nan"),
            "steps": float(steps_fast.mean()),
            "sha1": sha1(y_fast),
        },
        "accuracy": acc,
    }
    if nb:
        ser = nb["serial"]
        r_ser = per_nb["serial"] / per_jax
        print(
            f"jax vs numba serial (one core each): {r_ser:.2f}x per trajectory"
            + (f" -- numba is {1 / r_ser:.1f}x faster than jax" if r_ser < 1 else "")
        )
        if "prange" in nb:
            r_par = per_nb["prange"] / per_jax
            print(
                f"jax (1 device) vs numba prange ({nb['prange']['threads']} threads): "
                f"{r_par:.2f}x per trajectory; numba prange / serial speed-up "
                f"{per_nb['serial'] / per_nb['prange']:.2f}x"
            )
        print(f"numba serial vs scipy: {per_sp / per_nb['serial']:.0f}x per trajectory")
        d_sp = float(np.max(np.abs(ser["y"][:ns] - y_sp)))
        d_jax = float(np.max(np.abs(ser["y"] - y_jax)))
        r_fast = per_nb["serial"] / per_fast
        print(
            f"fast_simulate vs numba serial (one core each): {r_fast:.2f}x per trajectory; "
            f"accepted steps equal on {np.mean(ser['steps'] == steps_fast):.1%} of all points, "
            f"max |final state difference| {np.max(np.abs(ser['y'] - y_fast)):.1e}"
        )
        if "prange" in nb:
            print(
                f"fast_simulate (1 core) vs numba prange ({nb['prange']['threads']} threads): "
                f"{per_nb['prange'] / per_fast:.2f}x"
            )
        out["fast"].update(
            ratio_numba_serial=r_fast,
            ratio_numba_prange=per_nb["prange"] / per_fast if "prange" in nb else None,
            steps_equal_numba=float(np.mean(ser["steps"] == steps_fast)),
            max_diff_numba=float(np.max(np.abs(ser["y"] - y_fast))),
        )
        d_par = (
            float(np.max(np.abs(nb["prange"]["y"] - ser["y"]))) if "prange" in nb else float("nan")
        )
        nfev_diff = int(np.max(np.abs(ser["nfev"][:ns] - nfev))) if ns else 0
        print(
            f"numba check: max |final state difference| vs scipy (sample) {d_sp:.2e}, vs jax "
            f"(all points) {d_jax:.2e}, prange vs serial {d_par:.1e}; max |nfev numba - nfev "
            f"scipy| = {nfev_diff} (mean nfev {ser['nfev'][:ns].mean():.1f}); failed: "
            f"{int((ser['status'] != 0).sum())}"
        )
        out["numba"] = {
            "version": numba_ref.NUMBA_VERSION,
            "per_serial": per_nb["serial"],
            "compile_serial": ser["compile_s"],
            "already_compiled": ser["already_compiled"],
            "per_prange": per_nb.get("prange"),
            "compile_prange": nb["prange"]["compile_s"] if "prange" in nb else None,
            "threads": nb["prange"]["threads"] if "prange" in nb else 1,
            "steps": float(ser["steps"].mean()),
            # speed-up of jax over numba per trajectory (t_numba / t_jax; < 1: numba faster)
            "ratio_serial": per_nb["serial"] / per_jax,
            "ratio_prange": per_nb["prange"] / per_jax if "prange" in nb else None,
            "scipy_over_numba_serial": per_sp / per_nb["serial"],
            "max_diff_scipy": d_sp,
            "max_diff_jax": d_jax,
            "nfev_diff_scipy": nfev_diff,
        }
    else:
        print("numba not installed, skipped (pip install numba, or the 'bench' extra)")
    print(f"max |final state difference| jax vs scipy on the sample: {err:.2e}")
    write_json(args.json, out, indent=2, default=float)
    return out


def _one_core_child_and_prange(args, argv) -> dict:
    """The one-core rows in a fresh process started on core 0, numba's prange here (all
    cores) side by side with the sharded ``jit(vmap(fast_simulate))`` (every device), both
    compared with the child's per-trajectory times."""
    child = [a for a in argv if a != "--no-numba-parallel"] + ["--no-numba-parallel"]
    if "--json" in child:
        i = child.index("--json")
        del child[i : i + 2]
    out = run_child("bench_simulate", child, core=0)
    if numba_ref is not None and not args.no_numba_parallel and out["numba"]:
        both = prange_and_sharded(parameter_points(args.n), args.rounds)
        par = both["numba"]
        per = both["prange"] / args.n
        out["numba"].update(
            per_prange=per,
            compile_prange=par["compile_s"],
            threads=par["threads"],
            ratio_prange=per / out["per_jax"],
        )
        out["fast"]["ratio_numba_prange"] = per / out["fast"]["per"]
        per_sharded = both["sharded"] / args.n
        out["sharded"] = {
            "per": per_sharded,
            "devices": both["devices"],
            "compile": both["first"],
            "ratio_numba_prange": per / per_sharded,
            "speedup_one_core": out["fast"]["per"] / per_sharded,
            "rounds_us": [t / args.n * 1e6 for t in both["sharded_rounds"]],
            "prange_rounds_us": [t / args.n * 1e6 for t in both["prange_rounds"]],
            "same_bits_as_one_core": both["sha1"] == out["fast"].get("sha1"),
            "sha1": both["sha1"],
        }
        print(
            f"numba DOP853, prange ({par['threads']} threads, this process): {per:.3e} s per "
            f"trajectory; fast_simulate (1 core) vs numba prange: "
            f"{out['fast']['ratio_numba_prange']:.2f}x; vmap(simulate) (1 core) vs numba "
            f"prange: {out['numba']['ratio_prange']:.2f}x"
        )
        sh = out["sharded"]
        print(f"side by side, {args.rounds} rounds in turn (us per trajectory, median):")
        header = f"{'method':<62}{'us / traj':>10}{'vs prange':>11}"
        print(header)
        print("-" * len(header))
        for name, us, ratio in [
            (f"numba DOP853, prange ({par['threads']} threads)", per * 1e6, 1.0),
            (
                f"jit(vmap(fast_simulate)) on a NamedSharding ({sh['devices']} devices)",
                per_sharded * 1e6,
                sh["ratio_numba_prange"],
            ),
            ("jax.vmap(fast_simulate), 1 core (child process)", out["fast"]["per"] * 1e6, None),
        ]:
            r = f"{ratio:.2f}x" if ratio is not None else f"{per / out['fast']['per']:.2f}x"
            print(f"{name:<62}{us:>10.1f}{r:>11}")
        print(
            f"rounds: sharded {', '.join(f'{t:.1f}' for t in sh['rounds_us'])}; prange "
            f"{', '.join(f'{t:.1f}' for t in sh['prange_rounds_us'])} us per trajectory; the "
            f"sharded call {sh['speedup_one_core']:.2f}x one core; its first call "
            f"{sh['compile']:.1f} s more; final states the one-core run's bits: "
            f"{sh['same_bits_as_one_core']} (sha1 {sh['sha1']}); load average "
            f"{os.getloadavg()[0]:.2f}"
        )
    write_json(args.json, out, indent=2, default=float)
    return out


if __name__ == "__main__":
    main()
