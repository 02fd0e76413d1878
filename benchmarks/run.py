"""Run every benchmark, each in a fresh process, and print their tables (``make bench``), then
one summary table of the headline ratios and compile times collected from the benchmarks'
results, and write that table, with the machine, the commit and the date, at the top of
``benchmarks/README.md`` (between its ``current table`` markers; the dated history below it is
left as it is).

``--smoke`` runs each at a tiny size (used by the test suite to keep the scripts working) and
writes nothing; ``--no-write`` prints only.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from _common import cpu_name, run_child  # noqa: E402

import rbo_jax  # noqa: E402,F401  (float64 on before anything else)

SMOKE_ARGS = {
    "sweep": ["--n", "60", "--chunk", "30", "--scipy-sample", "2"],
    "simulate": ["--n", "40", "--chunk", "20", "--scipy-sample", "2"],  # one-core rows pinned
    "stability": ["--n-per-axis", "4", "--numpy-sample", "5", "--chunk", "32"],
    "fitting": ["--samples", "20", "--trajectories", "1"],
    "lattice": ["--smoke"],
    "rod": ["--smoke"],  # PyElastica's rows skipped without it (the `bench` extra)
    "snake": ["--smoke"],  # likewise
    "dask": ["--smoke"],  # skipped without distributed (the `dask` extra)
    "cores": ["--smoke", "--rows", "map"],  # three fresh processes
}
# run in a process started on one core (the first this process may use)
PINNED = {"rod", "snake"}
ONE_CORE = min(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 0
README = os.path.join(os.path.dirname(os.path.abspath(__file__)), "README.md")
BEGIN, END = "<!-- current table: begin (make bench) -->", "<!-- current table: end -->"


def _fmt(x, spec):
    return "-" if x is None or x != x else format(x, spec)  # None / NaN -> "-"


def summary_rows(results: dict) -> list[tuple[str, str, str, str]]:
    """(benchmark, comparison, value, compile [s]) rows from the benchmarks' result dicts.
    Ratios are the other method's time per item / rbo_jax's (> 1: rbo_jax faster)."""
    rows = []
    sim = results.get("simulate")
    if sim and sim.get("fast"):
        fa = sim["fast"]
        rows.append(
            (
                "simulate",
                "jax.vmap(fast_simulate) vs scipy DOP853 (1 core each)",
                _fmt(fa["ratio_scipy"], ".0f") + "x",
                f"jax {fa['compile']:.1f}",
            )
        )
        if fa.get("ratio_numba_serial") is not None:
            rows.append(
                (
                    "simulate",
                    "jax.vmap(fast_simulate) vs numba DOP853 serial (1 core each)",
                    _fmt(fa["ratio_numba_serial"], ".2f") + "x",
                    "",
                )
            )
            rows.append(
                (
                    "simulate",
                    "jax.vmap(fast_simulate) (1 core) vs numba prange",
                    _fmt(fa.get("ratio_numba_prange"), ".2f") + "x",
                    "",
                )
            )
    sh = (sim or {}).get("sharded")
    if sh:
        rows.append(
            (
                "simulate",
                f"jit(vmap(fast_simulate)) on a NamedSharding ({sh['devices']} devices) "
                "vs numba prange (side by side)",
                _fmt(sh["ratio_numba_prange"], ".2f") + "x",
                f"{sh['per'] * 1e6:.1f} us; same bits as 1 core: {sh['same_bits_as_one_core']}",
            )
        )
    if sim:
        rows.append(
            (
                "simulate",
                "jax.vmap(simulate) vs scipy DOP853 (1 core each)",
                _fmt(sim["ratio"], ".0f") + "x",
                f"jax {sim['compile_jax']:.1f}",
            )
        )
        nb = sim.get("numba")
        if nb:
            pre = nb.get("already_compiled")
            rows.append(
                (
                    "simulate",
                    "jax.vmap(simulate) vs numba DOP853 serial (1 core each)",
                    _fmt(nb["ratio_serial"], ".2f") + "x",
                    "numba: compiled in sweep" if pre else f"numba {nb['compile_serial']:.1f}",
                )
            )
            if nb.get("ratio_prange") is not None:
                rows.append(
                    (
                        "simulate",
                        f"jax.vmap (1 device) vs numba prange ({nb['threads']} threads)",
                        _fmt(nb["ratio_prange"], ".2f") + "x",
                        "" if pre else f"numba prange {nb['compile_prange']:.1f}",
                    )
                )
        else:
            rows.append(("simulate", "numba not installed, skipped", "-", ""))
    sw = results.get("sweep")
    if sw and sw["sweep"]:
        last = sw["sweep"][-1]
        k = last["devices"]
        compiles = ", ".join(f"{r['devices']} dev {r['compile_s']:.1f}" for r in sw["sweep"])
        if sw["scipy"]["sample"]:
            rows.append(
                (
                    "sweep",
                    f"sweep on {k} device(s) vs scipy DOP853 (1 core)",
                    _fmt(last["traj_per_s"] * sw["scipy"]["s_per_traj"], ".0f") + "x",
                    f"sweep {compiles}",
                )
            )
        nb = sw.get("numba")
        if nb:
            for key, r in nb.items():
                who = "1 core" if key == "serial" else f"{r['threads']} threads"
                rows.append(
                    (
                        "sweep",
                        f"sweep on {k} device(s) vs numba {key} ({who})",
                        _fmt(last["traj_per_s"] / r["traj_per_s"], ".2f") + "x",
                        f"numba {key} {r['compile_s']:.1f}",
                    )
                )
        else:
            rows.append(("sweep", "numba not installed, skipped", "-", ""))
    st = results.get("stability")
    if st:
        rows.append(
            (
                "stability",
                "stability_map vs vmap(eigvals(jacfwd))",
                _fmt(st["ratio"]["plain"], ".1f") + "x",
                f"map ~{st['compile_map_estimate']:.1f}, plain {st['compile_plain']:.1f}",
            )
        )
        rows.append(
            (
                "stability",
                "stability_map vs NumPy loop (FD + eigvals)",
                _fmt(st["ratio"]["numpy"], ".0f") + "x",
                "",
            )
        )
    fi = results.get("fitting")
    if fi:
        rows.append(
            (
                "fitting",
                "first fit, wall incl. compilation [s]",
                f"{fi['first']:.1f}",
                f"~{fi['compile_estimate']:.1f}",
            )
        )
        rows.append(
            ("fitting", "second fit, compiled program reused [s]", f"{fi['second']:.1f}", "")
        )
    la = results.get("lattice")
    if la:
        for r in la["rows"]:
            nb = r.get("numba")
            rows.append(
                (
                    "lattice",
                    f"lattice.simulate (DOP853, N = {r['n']}) vs numba DOP853 "
                    "stencil (1 core each)",
                    _fmt(r.get("ratio"), ".2f") + "x" if nb else "numba not installed",
                    f"jax {r['compile_jax']:.1f}",
                )
            )
        every = la.get("all_cores")
        if every:
            rows.append(
                (
                    "lattice",
                    f"lattice.simulate (DOP853, N = {every['n']}) on {every['shards']} devices "
                    "(all cores) vs one core",
                    _fmt(every["ratio"], ".2f") + "x",
                    f"max diff {every['max_diff']:.1e}",
                )
            )
    ro = results.get("rod")
    if ro:
        st = ro["statics"]
        rj = st["rbo_jax"]
        if st.get("pyelastica"):
            rows.append(
                (
                    "rod",
                    f"lattice.equilibrium (n = {st['n']}) vs PyElastica's Timoshenko example "
                    f"(damped dynamics to t = {st['final_time']:g}; 1 core each)",
                    _fmt(st["ratio"], ".0f") + "x",
                    f"jax {rj['compile']:.1f}",
                )
            )
            rows.append(
                (
                    "rod",
                    "lattice.equilibrium vs PyElastica until its deflection settles (0.1 %)",
                    _fmt(st["ratio_settled"], ".0f") + "x",
                    "",
                )
            )
        else:
            rows.append(("rod", "pyelastica not installed, skipped", "-", ""))
        compiles = {
            (r["code"], r["n"]): r["first"] - r["seconds"]
            for r in ro["vibration"]["rows"]
            if r["first"] is not None
        }
        for e in ro["vibration"]["equal_accuracy"]:
            what = (
                "per simulated second"
                if e["per_sim"]
                else f"vs its whole run ({ro['vibration']['T']:g} s simulated)"
            )
            rows.append(
                (
                    "rod",
                    f"{e['code']} (n = {e['n']}) vs PyElastica PositionVerlet (n = {e['pe_n']}), "
                    f"{what}, at equal accuracy of the first two frequencies",
                    _fmt(e["ratio"], ".2f") + "x",
                    f"jax {compiles.get((e['code'], e['n']), float('nan')):.1f}",
                )
            )
        for e in ro["vibration"].get("same_n", []):
            if "midpoint" not in e["code"]:
                continue
            rows.append(
                (
                    "rod",
                    f"{e['code']} vs PyElastica PositionVerlet at the same n = {e['n']}, per "
                    f"simulated second (ω1 vs Euler-Bernoulli {e['error_eb']:+.1e} against "
                    f"{e['pe_error_eb']:+.1e}; energy drift {e['drift'] or float('nan'):.0e} "
                    f"against {e['pe_drift'] or float('nan'):.0e})",
                    _fmt(e["ratio"], ".2f") + "x",
                    f"jax {compiles.get((e['code'], e['n']), float('nan')):.1f}",
                )
            )
        mo = ro.get("motion", [])
        if len(mo) > 1:
            rows.append(
                (
                    "rod",
                    f"lattice.simulate (midpoint): time a step per body, n = {mo[-1]['n']} / "
                    f"n = {mo[0]['n']} (1: O(n))",
                    _fmt(mo[-1]["per_body"] / mo[0]["per_body"], ".2f"),
                    "",
                )
            )
        sc = ro["scaling"]
        if len(sc) > 1:
            rows.append(
                (
                    "rod",
                    f"lattice.equilibrium: us per body, n = {sc[0]['n']} / n = {sc[-1]['n']} "
                    "(1: O(n))",
                    _fmt(sc[0]["us_per_body"] / sc[-1]["us_per_body"], ".2f"),
                    "",
                )
            )
    sn = results.get("snake")
    if sn:
        rj, pe = sn["snake"][0], (sn["snake"][1:] or [None])[0]
        if pe is not None:
            rows.append(
                (
                    "snake",
                    f"continuum snake (n = {sn['n']}, {sn['simulated_s']:.1f} s): midpoint "
                    f"(dt = {rj['dt']:g}) vs PyElastica PositionVerlet (dt = {pe['dt']:g}), wall; "
                    f"forward speed {rj['forward'] / pe['forward'] - 1:+.1%}",
                    _fmt(pe["wall"] / rj["wall"], ".2f") + "x",
                    f"jax {rj['first'] - rj['wall']:.1f}",
                )
            )
        else:
            rows.append(("snake", "pyelastica not installed, skipped", "-", ""))
    co = results.get("cores")
    if co:
        for r in co["rows"]:
            if r["mode"] == "one core":
                continue
            rows.append(
                (
                    "cores",
                    f"{r['label']}: {r['mode']} vs pinned to one core (wall, fresh processes)",
                    _fmt(r["speedup"], ".2f") + "x",
                    f"CPU/wall {r['cpu_per_wall']:.2f}"
                    + (
                        f"; median of {r['rounds']} rounds, "
                        f"{r['speedups'][0]:.2f}-{r['speedups'][-1]:.2f}x"
                        if r.get("rounds", 1) > 1
                        else ""
                    ),
                )
            )
    da = results.get("dask")
    if da:
        rows.append(
            (
                "dask",
                f"a chunk of {da['chunk']} points as a Dask task: overhead [ms]",
                f"{da['overhead_ms']:.2f}",
                "",
            )
        )
        rows.append(
            (
                "dask",
                "sweep on 2 Dask workers vs 1 process",
                _fmt(da["speedup_2_workers"], ".2f") + "x",
                "",
            )
        )
    return rows


def print_summary(results: dict) -> None:
    rows = summary_rows(results)
    if not rows:
        return
    print("\n=== summary ===")
    print(
        "ratio: the other method's time per trajectory / point over rbo_jax's (> 1: rbo_jax "
        "faster, < 1: the other is faster); compile [s]: first call incl. compilation, not in "
        "the ratios (~: first run minus second run)"
    )
    w = [max(len(r[i]) for r in rows) for i in range(4)]
    w = [max(a, len(h)) for a, h in zip(w, ["benchmark", "comparison", "ratio", "compile [s]"])]
    header = (
        f"{'benchmark':<{w[0]}}  {'comparison':<{w[1]}}  {'ratio':>{w[2]}}  {'compile [s]':<{w[3]}}"
    )
    print(header.rstrip())
    print("-" * len(header))
    for b, c, v, comp in rows:
        print(f"{b:<{w[0]}}  {c:<{w[1]}}  {v:>{w[2]}}  {comp}".rstrip())


def _machine() -> str:
    cpu = cpu_name()
    try:
        mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        mem = float("nan")
    import jax

    return (
        f"{cpu}, {len(os.sched_getaffinity(0))} cores, {mem:.1f} GiB; "
        f"{platform.platform()}; Python {platform.python_version()}, jax {jax.__version__}"
    )


def _commit() -> str:
    try:
        out = subprocess.run(
            ["git", "-C", os.path.dirname(README), "describe", "--always", "--dirty"],
            capture_output=True,
            text=True,
            timeout=10,
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def markdown_table(results: dict, started: str, loads: tuple[float, float]) -> str:
    """The current table for benchmarks/README.md."""
    lines = [
        BEGIN,
        "",
        f"Regenerated by `make bench` on {started} (commit {_commit()}), load average "
        f"{loads[0]:.2f} at the start, {loads[1]:.2f} at the end. Machine: {_machine()}.",
        "Ratios: the other side's time per item over rbo_jax's, or the speed-up stated, measured "
        "side by side in this one run (> 1: rbo_jax faster).",
        "",
        "| benchmark | comparison | ratio | note |",
        "|---|---|---|---|",
    ]
    lines += [f"| {b} | {c} | {v} | {n} |" for b, c, v, n in summary_rows(results)]
    lines += ["", END]
    return "\n".join(lines)


def write_readme(table: str, path: str = README) -> None:
    """Put ``table`` between the markers of ``path`` (after its first heading if it has none)."""
    with open(path) as f:
        text = f.read()
    if BEGIN in text and END in text:
        head, rest = text.split(BEGIN, 1)
        tail = rest.split(END, 1)[1]
        text = head + table + tail
    else:
        first, _, rest = text.partition("\n")
        text = first + "\n\n" + table + "\n" + rest
    with open(path, "w") as f:
        f.write(text)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--smoke", action="store_true", help="tiny sizes, for tests")
    parser.add_argument(
        "--only",
        nargs="*",
        default=None,
        help="subset of: sweep simulate stability fitting lattice rod snake dask cores",
    )
    parser.add_argument("--no-write", action="store_true", help="do not write README.md")
    args = parser.parse_args(argv)
    import jax

    # every benchmark in a fresh process (_common.run_child), started as a user starts one:
    # on every core, or on one core for the per-core figures (bench_simulate and bench_lattice
    # start their own one-core processes; the rods' benchmark is one core throughout)
    modules = {
        "sweep": "bench_sweep",
        "simulate": "bench_simulate",
        "stability": "bench_stability",
        "fitting": "bench_fitting",
        "lattice": "bench_lattice",
        "rod": "bench_rod",
        "snake": "bench_snake",
        "dask": "bench_dask",
        "cores": "bench_cores",
    }
    started = time.strftime("%Y-%m-%d %H:%M")
    load_start = os.getloadavg()[0]
    print(
        f"{time.strftime('%Y-%m-%d')}  {platform.platform()}  {os.cpu_count()} CPUs  "
        f"jax {jax.__version__}  python {platform.python_version()}  load average "
        f"{os.getloadavg()[0]:.2f}",
        flush=True,
    )
    results = {}
    for name, module in modules.items():
        if args.only and name not in args.only:
            continue
        print(f"\n=== {name} ===", flush=True)
        fargs = SMOKE_ARGS[name] if args.smoke else []
        results[name] = run_child(module, fargs, core=ONE_CORE if name in PINNED else None)
    print_summary(results)
    load_end = os.getloadavg()[0]
    print(f"load average at the end: {load_end:.2f}")
    if not args.smoke and not args.no_write and args.only is None:
        write_readme(markdown_table(results, started, (load_start, load_end)))
        print(f"the current table written to {README}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
