"""On a GPU (issue 31 D): ``fast_simulate`` ensembles and lattices in float32 and float64, against
the device's measured memory bandwidth, in one budgeted run (a lent GPU's time is short).

Rows, in the order they run (each item is skipped, with the reason, when the time left in
``--budget`` is less than what the sizes before it predict):

- **bandwidth**: a streaming kernel (``y = 2 x`` over ``--bw-gib`` GiB), bytes read plus written
  over the median time: the ceiling of every memory-bound row below.
- **ensemble**: ``jax.jit(jax.vmap(fast_simulate))`` of the benchmark problem of
  ``bench_simulate.py`` (Nikolai, t in [0, ``--t1``], final state) over N trajectories
  (``--ensemble``, e.g. 10⁵ … 10⁷), float64 at rtol 1e-8 / atol 1e-10 and float32 at rtol 1e-5 /
  atol 1e-6 (float32's parameters, state and times). Compilation (``lower().compile()``) and one
  run are timed apart; trajectories/s and trajectory-steps/s (accepted steps summed over the
  ensemble per second); the float32 final states against float64's.
- **lanes**: the same at one N for other lane counts (``--lanes``; the default is
  :data:`rbo_jax.ensemble.ACCELERATOR_LANES`), and a run of ``--tiny`` trajectories whose time
  per loop iteration is the loop's fixed cost (launches and the host's test of the loop
  condition), since their arithmetic is negligible.
- **lattice**: ``lattice.simulate`` (DOP853) of the chain of ``bench_lattice.py`` for N bodies
  (``--lattice``, e.g. 10⁶ … 10⁸), float64 and float32, final state only: body-steps/s, and the
  bandwidth bound ``BW / (2 · 6 · itemsize)`` (the state read and written once per step, the
  least any step can move), the bytes per body-step that the measured time would move at the
  measured bandwidth, and the kernels of the compiled program (``fusion`` / ``custom-call``
  instructions in its HLO: each one a launch per loop iteration or stage).
- **sweep**: ``rbo_jax.sweep`` of the ensemble's final states over ``--sweep-n`` points on the
  GPU (the same engine as on CPUs: one chunk program over the local devices).

Prints one table at the end and writes every figure to ``--json``. ``--smoke`` runs a tiny size of
each on whatever JAX has (the test suite runs it on the CPU).

Usage: ``python benchmarks/bench_gpu.py [--ensemble 100000,1000000,10000000]
[--lattice 1000000,10000000,100000000] [--lanes 65536,1048576] [--budget 420] [--json PATH]
[--smoke]``
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import rbo_jax
from rbo_jax import ensemble
from rbo_jax import lattice as L
from rbo_jax.integrate import dop853 as D

try:
    from _problem import A1, A3, PERTURBATION, K
    from bench_lattice import build_lattice, initial_state
except ImportError:  # run from the repository root
    from benchmarks._problem import A1, A3, PERTURBATION, K
    from benchmarks.bench_lattice import build_lattice, initial_state

SETTINGS = {"float64": (jnp.float64, 1e-8, 1e-10), "float32": (jnp.float32, 1e-5, 2e-6)}


class Budget:
    """The time left of ``seconds``, and a guess of an item's cost from the last of its kind: its
    fixed part (compilation, set-up) as it was, its run time (counted twice: a first call and a
    timed one) scaled with the size."""

    def __init__(self, seconds: float):
        self.end = time.perf_counter() + seconds
        self.last: dict[str, tuple[float, float, float]] = {}  # kind -> (size, fixed, run)

    def left(self) -> float:
        return self.end - time.perf_counter()

    def allows(self, kind: str, size: float, fixed: float = 0.0) -> tuple[bool, str]:
        if kind not in self.last:
            return self.left() > fixed, f"{self.left():.0f} s left"
        n0, fixed0, run0 = self.last[kind]
        guess = fixed0 + 2 * run0 * size / n0
        return guess < self.left(), f"predicted {guess:.0f} s, {self.left():.0f} s left"

    def spent(self, kind: str, size: float, seconds: float, run: float) -> None:
        self.last[kind] = (size, max(0.0, seconds - 2 * run), run)


def use_stages(variant: str) -> None:
    """The stage loop of DOP853 as a loop or unrolled (:data:`rbo_jax.integrate.dop853.UNROLL`),
    with JAX's caches cleared so that every program is traced again under it."""
    value = {"loop": False, "unrolled": True, "default": False}[variant]
    if D.UNROLL is not value:
        D.UNROLL = value
        jax.clear_caches()


def device_line() -> dict:
    d = jax.devices()[0]
    info = {
        "platform": d.platform,
        "device": getattr(d, "device_kind", str(d)),
        "devices": len(jax.devices()),
        "jax": jax.__version__,
        "python": platform.python_version(),
    }
    stats = d.memory_stats() if hasattr(d, "memory_stats") else None
    if stats:
        info["memory_gib"] = round(stats.get("bytes_limit", 0) / 2**30, 1)
    return info


def bandwidth(gib: float) -> float:
    """Bytes read plus written per second by ``y = 2 x`` over ``gib`` GiB of float32 (median of
    ten, after a warm-up)."""
    n = int(gib * 2**30 / 4)
    x = jnp.ones(n, jnp.float32)
    f = jax.jit(lambda x: x * 2.0)
    jax.block_until_ready(f(x))
    times = []
    for _ in range(10):
        t = time.perf_counter()
        jax.block_until_ready(f(x))
        times.append(time.perf_counter() - t)
    return 2 * n * 4 / float(np.median(times))


def trajectory(dtype, rtol, atol, t1):
    """The benchmark problem of ``bench_simulate.py`` at (c, d, M), in ``dtype``: its
    ``fast_simulate`` trajectory to ``t1``, final state only."""

    def solve(c, d, M):
        k = jnp.asarray(K, dtype)
        model = rbo_jax.RigidBodyOscillator(
            rbo_jax.transversely_isotropic_inertia(dtype(A1), dtype(A3), k),
            rbo_jax.QuadraticFoundation(c, d, k),
            rbo_jax.FollowerMoment(M, k),
        )
        theta0 = (M / d) * k + jnp.asarray(PERTURBATION, dtype)
        ts = jnp.asarray([0.0, t1], dtype)
        return rbo_jax.fast_simulate(
            model, theta0, jnp.zeros(3, dtype), ts, rtol=rtol, atol=atol, throw=False
        )

    return solve


def final_state(dtype, rtol, atol, t1):
    """``p = (c, d, M) -> (final state (6,), accepted steps, successful)``."""
    solve = trajectory(dtype, rtol, atol, t1)

    def final(p):
        traj = solve(p[0], p[1], p[2])
        ok = traj.status == rbo_jax.SolveStatus.successful
        return jnp.concatenate([traj.theta[-1], traj.Omega[-1]]), traj.num_steps, ok

    return final


def points(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack(
        [rng.uniform(0.5, 2.0, n), rng.uniform(0.5, 2.0, n), rng.uniform(0.05, 0.6, n)], axis=1
    )


def kernels(compiled) -> int:
    """The ``fusion`` and ``custom-call`` instructions of a compiled program's HLO (its kernels)."""
    text = compiled.as_text() or ""
    return sum(
        1
        for line in text.splitlines()
        if "=" in line and (" fusion(" in line or " custom-call(" in line)
    )


def ensemble_row(n: int, name: str, t1: float, lanes: int | None = None) -> dict:
    dtype, rtol, atol = SETTINGS[name]
    saved = ensemble.ACCELERATOR_LANES, ensemble.LANES
    if lanes is not None:
        ensemble.ACCELERATOR_LANES = ensemble.LANES = lanes
    try:
        p = jnp.asarray(points(n), dtype)
        f = jax.jit(jax.vmap(final_state(dtype.dtype.type, rtol, atol, t1)))
        t = time.perf_counter()
        compiled = f.lower(p).compile()
        t_compile = time.perf_counter() - t
    finally:
        ensemble.ACCELERATOR_LANES, ensemble.LANES = saved
    t = time.perf_counter()
    y, steps, ok = jax.block_until_ready(compiled(p))
    seconds = time.perf_counter() - t
    steps, ok = np.asarray(steps, np.int64), np.asarray(ok)
    return {
        "n": n,
        "dtype": name,
        "rtol": rtol,
        "atol": atol,
        "lanes": int(lanes if lanes is not None else ensemble.lanes()[0]),
        "compile_s": t_compile,
        "run_s": seconds,
        "trajectories_per_s": n / seconds,
        "trajectory_steps_per_s": float(steps.sum()) / seconds,
        "steps_mean": float(steps.mean()),
        "steps_max": int(steps.max()),
        "iteration_us": None,
        "successful": float(ok.mean()),
        "kernels": kernels(compiled),
        "_final": np.asarray(y[: min(n, 4096)], np.float64),
    }


def lattice_row(n: int, name: str, t1: float, bw: float | None) -> dict:
    dtype, rtol, atol = SETTINGS[name]
    lat, _ = build_lattice(n)
    # on the device before the clock starts: the rows time the integration, not the transfer
    theta0, Omega0 = (jnp.asarray(x, dtype) for x in initial_state(n))
    ts = np.array([0.0, t1])

    def run():
        traj = L.simulate(lat, theta0, Omega0, ts, rtol=rtol, atol=atol, dtype=dtype)
        jax.block_until_ready(traj.theta)
        return traj

    t = time.perf_counter()
    run()
    first = time.perf_counter() - t
    t = time.perf_counter()
    traj = run()
    seconds = time.perf_counter() - t
    steps = int(traj.num_steps)
    item = np.dtype(dtype).itemsize
    rate = n * steps / seconds
    row = {
        "n": n,
        "dtype": name,
        "steps": steps,
        "status": str(traj.message),
        "first_s": first,
        "run_s": seconds,
        "body_steps_per_s": rate,
        "finite": bool(np.all(np.isfinite(np.asarray(traj.theta[-1])))),
    }
    if bw:
        row["bound_body_steps_per_s"] = bw / (2 * 6 * item)
        row["fraction_of_bound"] = rate / row["bound_body_steps_per_s"]
        row["bytes_per_body_step_at_bw"] = bw / rate
    return row


def _sizes(text: str) -> list[int]:
    return [int(float(x)) for x in text.split(",") if x.strip()]


def parse(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ensemble", default="100000,1000000,10000000")
    ap.add_argument("--lattice", default="1000000,10000000,100000000")
    ap.add_argument(
        "--lattice-f64-max", type=float, default=2e7, help="largest float64 lattice (memory)"
    )
    ap.add_argument("--lanes", default="65536,1048576", help="other lane counts at --lanes-n")
    ap.add_argument("--lanes-n", type=int, default=1_000_000)
    ap.add_argument("--tiny", type=int, default=256, help="trajectories of the fixed-cost row")
    ap.add_argument("--t1", type=float, default=20.0, help="ensemble end time")
    ap.add_argument("--lattice-t1", type=float, default=0.5)
    ap.add_argument("--sweep-n", type=int, default=1_000_000, help="0: no sweep row")
    ap.add_argument("--bw-gib", type=float, default=4.0)
    ap.add_argument("--budget", type=float, default=420.0, help="seconds for all items")
    ap.add_argument("--json", default=None)
    ap.add_argument(
        "--stages",
        default="default",
        help="the DOP853 stage loop: default (a loop), loop, unrolled; a list compares them",
    )
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument(
        "--profile",
        default=None,
        help="instead: a profiler trace (Perfetto JSON) of one ensemble and one lattice call "
        "of the first sizes, float64, into this folder",
    )
    args = ap.parse_args(argv)
    if args.smoke:
        args.ensemble, args.lattice, args.lanes = "64", "64", "32"
        args.lanes_n, args.tiny, args.t1, args.lattice_t1 = 64, 16, 1.0, 0.1
        args.sweep_n, args.bw_gib = 64, 0.01
    args.stages = [v.strip() for v in args.stages.split(",")]
    if not set(args.stages) <= {"default", "loop", "unrolled"}:
        ap.error(f"--stages: default, loop or unrolled, got {args.stages}")
    args.ensemble, args.lattice, args.lanes = (
        _sizes(args.ensemble),
        _sizes(args.lattice),
        _sizes(args.lanes),
    )
    return args


def profile(args) -> None:
    """One ensemble call and one lattice call of the first sizes (float64), compiled first, then
    run under ``jax.profiler.trace`` (``perfetto_trace.json.gz`` in ``args.profile``)."""
    dtype, rtol, atol = SETTINGS["float64"]
    p = jnp.asarray(points(args.ensemble[0]), dtype)
    f = jax.jit(jax.vmap(final_state(np.float64, rtol, atol, args.t1)))
    jax.block_until_ready(f(p))
    n = args.lattice[0]
    lat, _ = build_lattice(n)
    theta0, Omega0 = initial_state(n)
    ts = np.array([0.0, args.lattice_t1])

    def lattice_call():
        traj = L.simulate(lat, theta0, Omega0, ts, rtol=rtol, atol=atol)
        return jax.block_until_ready(traj.theta)

    lattice_call()
    with jax.profiler.trace(args.profile, create_perfetto_trace=True):
        jax.block_until_ready(f(p))
        lattice_call()


def main(argv=None):
    args = parse(argv)
    if args.profile:
        profile(args)
        return
    budget = Budget(args.budget)
    out = {"machine": device_line(), "argv": sys.argv[1:], "skipped": [], "errors": []}
    print(json.dumps(out["machine"]), flush=True)

    def attempt(label, fn):
        try:
            return fn()
        except Exception as e:  # noqa: BLE001 (one failed item must not lose the others)
            out["errors"].append(f"{label}: {type(e).__name__}: {str(e).splitlines()[0][:300]}")
            print(f"ERROR {label}: {type(e).__name__}: {e}", flush=True)
            return None

    bw = attempt("bandwidth", lambda: bandwidth(args.bw_gib))
    out["bandwidth_bytes_per_s"] = bw
    print(f"bandwidth: {bw / 1e9 if bw else float('nan'):.0f} GB/s (read + write)", flush=True)

    def save():
        if args.json:
            with open(args.json, "w") as f:
                json.dump(out, f, indent=1, default=str)

    # the first size of each kind first (every kind measured once), then the larger ones; each
    # in every variant of the stage loop (--stages)
    ens, lat = [], []
    V = args.stages
    plan = [("ensemble", n, name, v) for n in args.ensemble[:1] for name in SETTINGS for v in V]
    plan += [("lattice", n, name, v) for n in args.lattice[:1] for name in SETTINGS for v in V]
    plan += [("tiny", args.tiny, "float64", v) for v in V]
    plan += [("ensemble", n, name, v) for n in args.ensemble[1:] for name in SETTINGS for v in V]
    plan += [
        ("lattice", n, name, v)
        for n in args.lattice[1:]
        for name in SETTINGS
        if name == "float32" or n <= args.lattice_f64_max
        for v in V
    ]
    plan += [("lanes", lanes, "float64", V[0]) for lanes in args.lanes]
    plan += [("sweep", args.sweep_n, "float64", V[0])] if args.sweep_n > 0 else []
    for kind, n, name, variant in plan:
        key = f"{kind}/{name}/{variant}"
        # a compile of ~5-15 s per new shape on a GPU: ask for that much room too
        size = args.lanes_n if kind == "lanes" else n
        ok, why = budget.allows(
            f"ensemble/{name}/{variant}" if kind == "lanes" else key, size, fixed=20.0
        )
        if not ok:
            out["skipped"].append(f"{kind} {name} {variant} N={n}: {why}")
            print(f"skip {kind} {name} {variant} N={n}: {why}", flush=True)
            continue
        use_stages(variant)
        t = time.perf_counter()
        if kind == "ensemble":
            row = attempt(key, lambda: ensemble_row(n, name, args.t1))
        elif kind == "tiny":
            row = attempt(key, lambda: ensemble_row(n, name, args.t1, lanes=n))
            if row:
                row["iteration_us"] = row["run_s"] / row["steps_max"] * 1e6
        elif kind == "lanes":
            row = attempt(key, lambda: ensemble_row(args.lanes_n, name, args.t1, lanes=n))
        elif kind == "lattice":
            row = attempt(key, lambda: lattice_row(n, name, args.lattice_t1, bw))
        else:
            row = attempt(key, lambda: sweep_row(n, args.t1))
        if row:
            row["stages"] = variant
            {"lattice": lat, "sweep": []}.get(kind, ens).append(row)
            if kind == "sweep":
                out["sweep"] = row
        spent = time.perf_counter() - t
        if row and kind in ("ensemble", "lattice"):
            budget.spent(key, n, spent, row["run_s"])
        print(f"{key} N={n}: {json.dumps(_public(row))} ({spent:.1f} s)", flush=True)
        out["ensemble"] = [_public(r) for r in ens]
        out["lattice"] = lat
        save()
    _accuracy(ens, out)
    save()
    table(out)


def _public(row):
    return None if row is None else {k: v for k, v in row.items() if not k.startswith("_")}


def _accuracy(ens, out):
    """The float32 final states against float64's, same N and points, default lanes."""
    by = {
        (r["n"], r["dtype"]): r
        for r in ens
        if r["iteration_us"] is None and r["lanes"] == ens[0]["lanes"]
    }
    for (n, name), r in by.items():
        if name == "float32" and (n, "float64") in by:
            a, b = r["_final"], by[(n, "float64")]["_final"]
            both = np.isfinite(a).all(1) & np.isfinite(b).all(1)
            out.setdefault("float32_vs_float64", {})[str(n)] = float(
                np.max(np.abs(a[both] - b[both])) if both.any() else np.nan
            )


def sweep_row(n: int, t1: float) -> dict:
    dtype, rtol, atol = SETTINGS["float64"]
    solve = trajectory(np.float64, rtol, atol, t1)
    side = int(round(n ** (1 / 3)))

    def quantity(c, d, M):
        traj = solve(c, d, M)
        final = jnp.concatenate([traj.theta[-1], traj.Omega[-1]])
        return {"final": final, "steps": traj.num_steps}, traj.status

    axes = {
        "c": np.linspace(0.5, 2.0, side),
        "d": np.linspace(0.5, 2.0, side),
        "M": np.linspace(0.05, 0.6, side),
    }
    t = time.perf_counter()
    ds = rbo_jax.sweep(quantity, axes, progress=False)
    first = time.perf_counter() - t
    t = time.perf_counter()
    ds = rbo_jax.sweep(quantity, axes, progress=False)
    seconds = time.perf_counter() - t
    return {
        "points": side**3,
        "first_s": first,
        "run_s": seconds,
        "points_per_s": side**3 / seconds,
        "finite": float(np.isfinite(ds["final"].values).all(-1).mean()),
    }


def table(out):
    m = out["machine"]
    print(
        f"\n{m['device']} ({m['platform']}, jax {m['jax']}), bandwidth "
        f"{(out.get('bandwidth_bytes_per_s') or float('nan')) / 1e9:.0f} GB/s"
    )
    print(
        "| ensemble | stages | N | lanes | compile s | run s | trajectories/s | traj-steps/s | "
        "mean steps | iteration us | ok |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in out.get("ensemble", []):
        it = "-" if r["iteration_us"] is None else f"{r['iteration_us']:.0f}"
        print(
            f"| {r['dtype']} | {r['stages']} | {r['n']:.0e} | {r['lanes']} | "
            f"{r['compile_s']:.1f} | "
            f"{r['run_s']:.2f} | {r['trajectories_per_s']:.3g} | "
            f"{r['trajectory_steps_per_s']:.3g} | {r['steps_mean']:.0f} | {it} | "
            f"{r['successful']:.3f} |"
        )
    print(
        "| lattice | stages | N | steps | first s | run s | body-steps/s | bound | of bound | "
        "B/step |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in out.get("lattice", []):
        print(
            f"| {r['dtype']} | {r['stages']} | {r['n']:.0e} | {r['steps']} | "
            f"{r['first_s']:.1f} | "
            f"{r['run_s']:.2f} | {r['body_steps_per_s']:.3g} | "
            f"{r.get('bound_body_steps_per_s', float('nan')):.3g} | "
            f"{r.get('fraction_of_bound', float('nan')):.3f} | "
            f"{r.get('bytes_per_body_step_at_bw', float('nan')):.0f} |"
        )
    if out.get("sweep"):
        print(f"sweep: {json.dumps(out['sweep'])}")
    if out.get("float32_vs_float64"):
        print(f"float32 vs float64 final states, max |diff|: {out['float32_vs_float64']}")
    for s in out["skipped"]:
        print(f"skipped: {s}")
    for e in out["errors"]:
        print(f"error: {e}")


if __name__ == "__main__":
    main()
