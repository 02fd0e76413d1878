"""The whole machine (issue 31): the same batch work in fresh processes started three ways, side
by side in one run.

- **all cores**: a fresh process with nothing set, as a user starts it (``import rbo_jax`` asks
  for one CPU device per core of the affinity);
- **one core**: the same, pinned to one core (``taskset -c C``: one core, one device);
- **1 device, XLA threads** (``RBO_JAX_CPU_DEVICES=off``): JAX's own default, one CPU device
  whose programs XLA spreads over the cores with its intra-op threads (what a user got before).

Rows:

- ``cli sweep``: ``rbo-jax sweep`` of the Nikolai ``final_state`` (the body 1e-3 rad off its
  equilibrium, found by Newton; ``fast_simulate``, t1 = ``--t1``, rtol 1e-9, atol 1e-10) over
  ``--sweep-n`` points (M, A3), the whole command's wall time (import and compilation included,
  as the user waits for it), and its CPU time;
- ``stability_map``: the map of issue 31 (Newton equilibria, eigenvalues) over ``--map-n`` points
  of (M, c); the first call (compilation included), then ``--repeat`` calls whose median is
  the figure;
- ``sweep of fast_simulate``: :func:`rbo_jax.sweep` of the same final states over ``--sim-n``
  points in the library; first call, then the median of ``--repeat`` calls, the figure.
- ``lanes`` (a profile, with ``--rows lanes``): one pinned core, ``jax.jit(jax.vmap(
  fast_simulate))`` of N of those trajectories per call for N = 1000 … 16000: the time per
  trajectory against N shows what the refilled lanes lose at the end of a call, waiting for
  the slowest trajectories (a device's share of a chunk is such a call).

Each row runs ``--rounds`` rounds (the CLI row one: it takes minutes), and every round starts
the modes one after the other, so that a machine whose speed drifts within the run (±30 % here,
issue 31) drifts alike for all of them; a mode's time is its median over the rounds, and the
speed-up is the median of the rounds' own speed-ups, printed with their range.

CPU time is the child's user + system time (``resource``): a ratio of CPU to wall near the number
of cores means every core was busy, above it threads waited for each other. The persistent caches
are off in every child, so each compiles what it runs. Speed-ups are the one-core time over the
others' (> 1: faster than one core).

Usage: ``python benchmarks/bench_cores.py [--sweep-n 6000] [--t1 600] [--map-n 1000000]
[--sim-n 40000] [--rounds 3] [--repeat 3] [--core C] [--json PATH] [--smoke]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time

from _common import write_json

HERE = os.path.dirname(os.path.abspath(__file__))

CONFIG = """\
[sweep]
quantity = "final_state"
output = "{out}"
[axes]
M = {{ start = 0.05, stop = 0.8, num = {n_m} }}
A3 = {{ start = 0.2, stop = 2.0, num = {n_a} }}
[model]
inertia = {{ A1 = 1.0, A3 = "A3" }}
foundation = {{ type = "quadratic", c = 1.0, d = 2.0 }}
loads = [{{ type = "follower", M = "M" }}]
[initial]
about_equilibrium = true
theta0 = [1e-3, 0.0, 0.0]
Omega0 = [0.0, 0.0, 0.0]
[solver]
t1 = {t1}
rtol = 1e-9
atol = 1e-10
max_steps = 1000000
"""

CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    import numpy as np
    import rbo_jax as rbo
    import jax, jax.numpy as jnp

    what, n, t1, repeat = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
    k = jnp.array([0.0, 0.0, 1.0])
    side = int(round(np.sqrt(n)))

    def final(M, c):
        model = rbo.nikolai_model(M, c, 2.0, A3=0.5)
        theta0 = (M / 2.0) * k + jnp.array([1e-3, 0.0, 0.0])
        traj = rbo.fast_simulate(model, theta0, jnp.zeros(3), jnp.array([0.0, t1]),
                                 rtol=1e-9, atol=1e-10, max_steps=10**6, throw=False)
        return {"theta": traj.theta[-1]}, traj.status

    def model_fn(M, c):
        return rbo.nikolai_model(M, c, 2.0, A3=0.6)

    if what == "lanes":
        M = np.random.default_rng(0).uniform(0.05, 0.8, n)
        c = np.random.default_rng(1).uniform(0.5, 2.0, n)
        f = jax.jit(jax.vmap(final))
        jax.block_until_ready(f(M, c))
        t = time.perf_counter()
        jax.block_until_ready(f(M, c))
        print(json.dumps({"n": n, "us_per_traj": (time.perf_counter() - t) / n * 1e6}))
        sys.exit(0)
    if what == "map":
        axes = {"M": np.linspace(-0.8, 0.8, side), "c": np.linspace(0.5, 2.0, side)}
        run = lambda: rbo.stability_map(model_fn, axes)
    else:
        axes = {"M": np.linspace(0.05, 0.8, side), "c": np.linspace(0.5, 2.0, side)}
        run = lambda: rbo.sweep(final, axes, progress=False)
    times = []
    for _ in range(1 + repeat):
        r0 = resource.getrusage(resource.RUSAGE_SELF)
        t = time.perf_counter()
        ds = run()
        wall = time.perf_counter() - t
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        cpu = r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime
        times.append((wall, cpu))
    v = next(iter(ds.data_vars.values())).values
    print(json.dumps({"devices": len(jax.devices()), "first": times[0], "timed": times[1:],
                      "points": int(np.prod(list(ds.sizes[d] for d in ("M", "c")))),
                      "checksum": float(np.nansum(np.abs(np.real(v))))}))
    """
)

MODES = {
    "all cores": ([], {}),
    "one core": (None, {}),  # taskset prefix filled in
    "1 device, XLA threads": ([], {"RBO_JAX_CPU_DEVICES": "off"}),
}


def _env(extra):
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("XLA_FLAGS", "JAX_NUM_CPU_DEVICES", "RBO_JAX_CPU_DEVICES")
    }
    env.update(RBO_JAX_COMPILATION_CACHE="off", JAX_PLATFORMS="cpu", PYTHONUNBUFFERED="1")
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    env.update(extra)
    return env


def _prefix(mode, core):
    pre, extra = MODES[mode]
    return (["taskset", "-c", str(core)] if pre is None else pre), extra


def _timed(cmd, env):
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    res = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr[-2000:]}")
    return wall, r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime, res.stdout


def cli_sweep(mode, core, n, t1, tmp):
    pre, extra = _prefix(mode, core)
    side = int(round(n**0.5))
    out = os.path.join(tmp, f"sweep-{len(os.listdir(tmp))}.zarr")
    cfg = os.path.join(tmp, f"sweep-{len(os.listdir(tmp))}.toml")
    with open(cfg, "w") as f:
        f.write(CONFIG.format(out=out, n_m=side, n_a=side, t1=t1))
    rbo = os.path.join(os.path.dirname(sys.executable), "rbo-jax")
    wall, cpu, _ = _timed(pre + [rbo, "sweep", cfg, "--quiet", "--no-plot"], _env(extra))
    return {"wall": wall, "cpu": cpu, "points": side * side}


def library(mode, core, what, n, t1, repeat):
    """One fresh process: the first call, then the median (wall, its CPU) of ``repeat`` calls."""
    pre, extra = _prefix(mode, core)
    cmd = pre + [sys.executable, "-c", CHILD, what, str(n), str(t1), str(repeat)]
    _, _, out = _timed(cmd, _env(extra))
    r = json.loads(out.strip().splitlines()[-1])
    wall, cpu = sorted(r["timed"])[len(r["timed"]) // 2]
    return {
        "wall": wall,
        "cpu": cpu,
        "first": r["first"][0],
        "devices": r["devices"],
        "points": r["points"],
        "checksum": r["checksum"],
    }


def lanes_profile(core, t1, sizes=(1000, 2000, 4000, 8000, 16000)):
    """µs per trajectory of one vmapped call of N trajectories, one pinned core."""
    out = []
    print("lanes: jax.jit(jax.vmap(fast_simulate)) on one pinned core", flush=True)
    for n in sizes:
        cmd = [
            "taskset",
            "-c",
            str(core),
            sys.executable,
            "-c",
            CHILD,
            "lanes",
            str(n),
            str(t1),
            "1",
        ]
        _, _, text = _timed(cmd, _env({}))
        r = json.loads(text.strip().splitlines()[-1])
        out.append(r)
        print(f"  N = {n:6d}: {r['us_per_traj']:7.2f} us per trajectory", flush=True)
    return out


def _parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sweep-n", type=int, default=6000, help="points of the CLI sweep")
    p.add_argument("--t1", type=float, default=600.0, help="end time of the simulations")
    p.add_argument("--map-n", type=int, default=1_000_000, help="points of the stability map")
    p.add_argument("--sim-n", type=int, default=40_000, help="points of the library sweep")
    p.add_argument("--sim-t1", type=float, default=100.0, help="end time of the library sweep")
    p.add_argument("--rounds", type=int, default=3, help="rounds of the library rows")
    p.add_argument("--repeat", type=int, default=3, help="timed calls in each library process")
    p.add_argument("--core", type=int, default=None, help="the core of the one-core runs")
    p.add_argument("--rows", default="cli,map,sim", help="subset of cli,map,sim,lanes")
    p.add_argument("--json", default=None)
    p.add_argument("--smoke", action="store_true", help="tiny sizes (tests)")
    args = p.parse_args(argv)
    if args.smoke:
        args.sweep_n, args.t1, args.map_n, args.sim_n, args.sim_t1 = 16, 5.0, 64, 64, 5.0
        args.rounds, args.repeat = 1, 1
    return args


def main(argv=None) -> dict:
    args = _parse(argv)
    core = args.core if args.core is not None else min(os.sched_getaffinity(0))
    cores = len(os.sched_getaffinity(0))
    rows = args.rows.split(",")
    print(
        f"{time.strftime('%Y-%m-%d %H:%M')}  {platform.platform()}  {cores} cores in the "
        f"affinity  python {platform.python_version()}  load average {os.getloadavg()[0]:.2f}",
        flush=True,
    )
    results = {"cores": cores, "rows": []}
    if "lanes" in rows:
        rows.remove("lanes")
        results["lanes"] = lanes_profile(core, args.sim_t1)
    with tempfile.TemporaryDirectory() as tmp:
        for row in rows:
            rounds = 1 if row == "cli" else max(1, args.rounds)
            runs = {mode: [] for mode in MODES}
            for k in range(rounds):
                for mode in MODES:  # the modes of a round one after the other
                    if row == "cli":
                        r = cli_sweep(mode, core, args.sweep_n, args.t1, tmp)
                        label = f"rbo-jax sweep final_state ({r['points']} points, t1 {args.t1:g})"
                    elif row == "map":
                        r = library(mode, core, "map", args.map_n, 0.0, args.repeat)
                        label = f"stability_map, Newton ({r['points']} points)"
                    else:
                        r = library(mode, core, "sim", args.sim_n, args.sim_t1, args.repeat)
                        label = f"sweep of fast_simulate ({r['points']} points, t1 {args.sim_t1:g})"
                    runs[mode].append(r)
                    print(
                        f"{label:<50} {mode:<22} round {k + 1}/{rounds} wall {r['wall']:8.2f} s  "
                        f"cpu {r['cpu']:8.2f} s"
                        + (f"  first call {r['first']:.2f} s" if "first" in r else ""),
                        flush=True,
                    )
            base = [r["wall"] for r in runs["one core"]]
            for mode, rs in runs.items():
                ratios = sorted(b / r["wall"] for b, r in zip(base, rs))
                r = dict(sorted(rs, key=lambda r: r["wall"])[len(rs) // 2])  # the median run
                r.update(
                    row=row,
                    mode=mode,
                    label=label,
                    rounds=len(rs),
                    walls=[x["wall"] for x in rs],
                    speedup=statistics.median(ratios),
                    speedups=ratios,
                    cpu_per_wall=r["cpu"] / r["wall"],
                )
                results["rows"].append(r)
    print(
        "\nspeed-up over one core (same row, each round's own ratio; median [range]; > 1: faster)"
    )
    for r in results["rows"]:
        spread = (
            f" [{r['speedups'][0]:.2f}-{r['speedups'][-1]:.2f} over {r['rounds']} rounds]"
            if r["rounds"] > 1
            else ""
        )
        print(
            f"{r['label']:<50} {r['mode']:<22} {r['speedup']:5.2f}x{spread}  "
            f"(CPU/wall {r['cpu_per_wall']:.2f})"
        )
    print(f"load average at the end: {os.getloadavg()[0]:.2f}")
    write_json(args.json, results, indent=1)
    return results


if __name__ == "__main__":
    main()
