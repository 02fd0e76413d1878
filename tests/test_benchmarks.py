"""A smoke run of every benchmark at a tiny size (`benchmarks/run.py --smoke`).

Timings are not asserted (speed is measured by the benchmarks themselves, not by tests). What is
asserted is what the benchmarks' tables rely on: every script runs, the three independent
integrators of the Nikolai problem (4.57)-(4.62) — rbo_jax's Dopri8, the numba DOP853 reference
and scipy's DOP853 — agree on the final states to the tolerance level (rtol = atol = 1e-8), the
numba reference takes exactly scipy's steps, the stability map matches (4.69), the fit converges,
and the summary table of ratios and compile times is printed.
"""

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def smoke_output():
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, os.path.join(ROOT, "benchmarks", "run.py"), "--smoke"],
        capture_output=True,
        text=True,
        timeout=900,
        env=env,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


def _floats(pattern, text):
    found = re.findall(pattern, text)
    assert found, f"no match for {pattern!r} in the benchmark output"
    return [float(x) for x in found]


@pytest.mark.slow  # integration: the benchmarks' smoke runs
def test_every_benchmark_runs_and_prints_the_summary(smoke_output):
    for marker in [
        "=== sweep ===",
        "=== simulate ===",
        "=== stability ===",
        "=== fitting ===",
        "=== lattice ===",
        "=== rod ===",
        "=== snake ===",
        "=== dask ===",
        "=== cores ===",
        "speed-up over one core",
        "speed-up per trajectory",
        "max |p - (4.69)|",
        "first fit",
        "shard_map over",
        "=== summary ===",
        "compile [s]",
    ]:
        assert marker in smoke_output, marker


@pytest.mark.slow  # integration: the benchmarks' smoke runs
def test_dask_workers_give_the_process_results(smoke_output):
    """The sweeps on one and two Dask workers equal the in-process sweep bit for bit."""
    part = smoke_output.split("=== dask ===")[1].split("===")[0]
    if "distributed not installed" in part:
        pytest.skip("distributed (the `dask` extra) is not installed")
    assert "results bit for bit equal to the process's: True" in part


@pytest.mark.slow  # integration: the benchmarks' smoke runs
def test_the_lattice_takes_the_numba_stencils_steps(smoke_output):
    """The lattice DOP853 and the hand-written numba DOP853 of the same chain take the same
    steps and end in the same state (the same system, SciPy's algorithm on all 6N scalars)."""
    if "numba not installed" in smoke_output.split("=== lattice ===")[1]:
        pytest.skip("numba not installed")
    assert "accepted steps equal on every N: True" in smoke_output
    rel = _floats(r"max \|f_jax - f_numba\| / max \|f_jax\| = ([0-9.e+-]+)", smoke_output)
    assert rel[0] < 1e-13


@pytest.mark.slow  # integration: the benchmarks' smoke runs
def test_the_rod_benchmark_matches_the_beam_theories(smoke_output):
    """bench_rod: the equilibrium of PyElastica's Timoshenko beam (n = 100) is within 1e-3 of
    the closed form, and the spectrum's first two frequencies of the cantilever (n = 10) are
    within 5e-3 of the Timoshenko beam's (3.4e-4: mostly the geometric nonlinearity that the
    linear closed form leaves out; 2.7e-3: second order in 1/n)."""
    part = smoke_output.split("=== rod ===")[1].split("=== ")[0]
    (err,) = _floats(r"rbo_jax equilibrium, n = 100: [^\n]*?error ([0-9.e+-]+)\)", part)
    assert abs(err) < 1e-3
    m = re.search(r"rbo_jax spectrum +10 +\S+ +\S+ +- +([0-9.e+-]+) ([0-9.e+-]+)", part)
    assert m, "no spectrum row"
    assert max(abs(float(m.group(1))), abs(float(m.group(2)))) < 5e-3
    if "pyelastica not installed" in part:
        pytest.skip("pyelastica (the `bench` extra) is not installed: its rows were skipped")
    assert "PyElastica run 1:" in part and "PyElastica PositionVerlet" in part


@pytest.mark.slow  # integration: the benchmarks' smoke runs
def test_the_three_integrators_agree_to_the_tolerance(smoke_output):
    """rbo_jax vs scipy, numba vs scipy and numba vs rbo_jax final states differ at the level of
    rtol = atol = 1e-8 (different step sequences), not more."""
    jax_scipy = _floats(
        r"max \|final state difference\| jax vs scipy on the sample: ([0-9.e+-]+)", smoke_output
    )
    sweep_scipy = _floats(
        r"/ scipy: \d+x per trajectory; max \|final state difference\| on the "
        r"sample: ([0-9.e+-]+)",
        smoke_output,
    )
    assert max(jax_scipy + sweep_scipy) < 1e-6
    if "numba not installed" in smoke_output:
        pytest.skip("numba (the `bench` extra) is not installed: its rows were skipped")
    vs_scipy = _floats(
        r"numba check: max \|final state difference\| vs (?:the sweep [0-9.e+-]+, "
        r"vs )?scipy \(sample\) ([0-9.e+-]+)",
        smoke_output,
    )
    assert max(vs_scipy) < 1e-10  # same tableau, same controller: the same steps as scipy
    nfev = _floats(r"max \|nfev numba - nfev scipy\| = (\d+)", smoke_output)
    assert max(nfev) == 0
    vs_jax = _floats(r"vs jax \(all points\) ([0-9.e+-]+)", smoke_output)
    assert max(vs_jax) < 1e-6


@pytest.mark.slow  # integration: the benchmarks' smoke runs
def test_stability_map_and_fit_are_accurate(smoke_output):
    errors = _floats(
        r"rbo_jax\.stability_map \(block fast path\)\s+[0-9.]+\s+[0-9.]+\s+"
        r"([0-9.e+-]+)",
        smoke_output,
    )
    assert max(errors) < 1e-12  # against the closed-form roots (4.69)
    assert "converged: True" in smoke_output


@pytest.mark.slow  # integration: the benchmarks' smoke runs
def test_fast_simulate_takes_scipys_steps(smoke_output):
    """fast_simulate is DOP853 with SciPy's controller: on the benchmark's points it takes the
    steps of the numba reference (which takes SciPy's), and the final states agree to rounding;
    against a tight reference it is as accurate as SciPy."""
    assert "=== simulate ===" in smoke_output
    if "numba not installed" in smoke_output:
        pytest.skip("numba (the `bench` extra) is not installed")
    m = re.search(
        r"accepted steps equal on ([0-9.]+)% of all points, max \|final state "
        r"difference\| ([0-9.e+-]+)",
        smoke_output,
    )
    assert m, "no fast_simulate vs numba line"
    assert float(m.group(1)) == 100.0
    assert float(m.group(2)) < 1e-10
    acc = _floats(r"fast_simulate ([0-9.e+-]+), simulate", smoke_output)
    assert max(acc) < 1e-6


@pytest.mark.slow  # integration: the benchmarks' smoke runs
def test_the_sharded_vmap_row_gives_the_one_core_bits(smoke_output):
    """``jit(vmap(fast_simulate))`` on a ``NamedSharding`` over every device, timed beside
    numba's ``prange``, ends with the final states of the one-core process, bit for bit."""
    part = smoke_output.split("=== simulate ===")[1].split("===")[0]
    if "on a NamedSharding" not in part:
        pytest.skip("one core, or numba (the `bench` extra) not installed: no such row")
    assert "final states the one-core run's bits: True" in part


def _latency_module(monkeypatch):
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "_latency_benchmark", os.path.join(ROOT, "benchmarks", "latency.py")
    )
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)  # dataclasses look the module up
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow  # integration: the benchmarks' smoke runs (fresh processes)
def test_latency_smoke_run(tmp_path):
    """`benchmarks/latency.py` with two cheap rows (a few seconds): every process ran (cold and
    warm), imported this checkout's rbo_jax, and the table and JSON carry the machine and the
    rows. SciPy's answer is the same in both processes."""
    out = tmp_path / "latency.json"
    proc = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "benchmarks", "latency.py"),
            "--rows",
            "import,scipy",
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "| `import rbo_jax` |" in proc.stdout and "anchor: SciPy" in proc.stdout
    report = json.loads(out.read_text())
    assert report["machine"]["cores"] >= 1 and len(report["machine"]["load_start"]) == 3
    for key in ("import", "scipy"):
        for which in ("cold", "warm"):
            (run,) = report["runs"][key][which]
            assert "error" not in run, run
            assert 0 < run["import_s"] < run["process_s"]
    for which in ("cold", "warm"):
        imported = report["runs"]["import"][which][0]["rbo_jax_file"]
        assert os.path.realpath(imported).startswith(os.path.realpath(ROOT) + os.sep)
    y_cold, y_warm = (report["runs"]["scipy"][w][0]["result"] for w in ("cold", "warm"))
    assert len(y_cold) == 3 and np.all(np.isfinite(y_cold)) and y_cold == y_warm


def test_latency_refuses_unknown_rows(capsys, monkeypatch):
    latency = _latency_module(monkeypatch)
    with pytest.raises(SystemExit) as e:
        latency.main(["--rows", "import,nonsense"])
    assert e.value.code == 2
    assert "nonsense" in capsys.readouterr().err


def test_latency_snippets_compile(monkeypatch):
    """Every row's program is valid Python (the heavy rows are not run by the tests)."""
    latency = _latency_module(monkeypatch)
    keys = [row.key for row in latency.rows()]
    assert len(set(keys)) == len(keys)
    for row in latency.rows():
        compile(latency.snippet(row), f"<latency {row.key}>", "exec")


def test_the_current_table_goes_between_the_markers(tmp_path):
    """make bench writes the summary, machine, commit and date between the README's markers and
    leaves the history below them as it was."""
    sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
    import run

    readme = tmp_path / "README.md"
    readme.write_text("# Benchmarks\n\n## History\n\nold figures\n")
    results = {"dask": {"chunk": 64, "overhead_ms": 7.5, "speedup_2_workers": 1.5}}
    run.write_readme(run.markdown_table(results, "2026-11-26 12:00", (0.5, 0.7)), str(readme))
    first = readme.read_text()
    assert first.startswith("# Benchmarks\n\n" + run.BEGIN)
    assert "| dask | sweep on 2 Dask workers vs 1 process | 1.50x |" in first
    assert "2026-11-26 12:00" in first and "## History\n\nold figures" in first
    results["dask"]["speedup_2_workers"] = 1.8
    run.write_readme(run.markdown_table(results, "2026-11-27 12:00", (0.5, 0.7)), str(readme))
    second = readme.read_text()
    assert "1.80x" in second and "1.50x" not in second and second.count(run.BEGIN) == 1
    assert second.endswith("## History\n\nold figures\n")


@pytest.mark.slow  # integration: ~2 min, ten small programs compiled
def test_the_gpu_benchmark_runs_on_whatever_jax_has(tmp_path):
    """``benchmarks/bench_gpu.py --smoke`` (issue 31 D) on the CPU: every row runs without an
    error, the loop and the unrolled stages take the same steps, float32's final states are
    float64's to its tolerance, and the table is printed."""
    out = tmp_path / "gpu.json"
    proc = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "benchmarks", "bench_gpu.py"),
            "--smoke",
            "--stages",
            "loop,unrolled",
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=900,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
        cwd=os.path.join(ROOT, "benchmarks"),
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "| ensemble | stages |" in proc.stdout and "| lattice | stages |" in proc.stdout
    result = json.loads(out.read_text())
    assert result["errors"] == [] and result["skipped"] == []
    rows = {(r["dtype"], r["n"], r["lanes"], r["stages"]): r for r in result["ensemble"]}
    for (dtype, n, lanes, stages), r in rows.items():
        assert r["successful"] == 1.0
        if stages == "unrolled":
            assert r["steps_mean"] == rows[(dtype, n, lanes, "loop")]["steps_mean"]
    assert all(r["finite"] and r["status"] == "successful" for r in result["lattice"])
    assert result["sweep"]["finite"] == 1.0
    assert 0 < result["float32_vs_float64"]["64"] < 1e-3
