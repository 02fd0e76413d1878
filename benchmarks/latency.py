"""Time to a first answer (issue 21): every row is one fresh Python process, import included.

    python benchmarks/latency.py                          # every row, this checkout
    python benchmarks/latency.py --rows fit,hopf --repeat 3
    python benchmarks/latency.py --tree /path/to/checkout --json before.json

Each row runs a small snippet in a new interpreter (``python -c``, started in the timed checkout
with it on ``PYTHONPATH``: ``-c`` puts the working directory first on ``sys.path``, so a process
started elsewhere would import that directory's ``rbo_jax``; every snippet reports which
``rbo_jax`` it imported and the run stops if it is not the tree's). The snippet times its imports
and its first call separately; the call includes building the model and inputs and ends when the
result is on the host (``np.asarray``), so the time is real. The parent also times each process
from start to exit.

* **cold**: a fresh, empty cache directory. JAX rows turn on the persistent compilation cache in
  it (``rbo_jax.enable_compilation_cache(path)`` when the tree has it, which also turns on
  rbo_jax's program store; otherwise JAX's ``jax_compilation_cache_dir`` with minimum compile
  time 0 and minimum entry size 0); the CLI rows get it as ``$RBO_JAX_COMPILATION_CACHE``; numba
  gets a fresh ``$NUMBA_CACHE_DIR``.
* **warm**: a second process on the same cache directory.
* ``--no-cache``: no persistent JAX cache at all (a plain notebook or script); numba keeps its.
* ``--pin 0``: every process on core 0 only. On a loaded machine XLA's multi-threaded CPU runtime
  can make a vmapped program many times slower (the diffrax anchor: 1.2 s -> 12 s at load 2.5,
  2.4 s pinned), so compare pinned runs when others share the machine.

Rows (Nikolai problem (4.57)-(4.62), float64; the parameters of ``bench_simulate.py``): ``import
rbo_jax``; ``simulate`` and ``fast_simulate`` of one trajectory with 501 samples (their defaults:
``throw=True``); ``jax.jit(jax.vmap(fast_simulate))`` over 1,000 parameter points (final state,
``throw=False`` as in ``bench_simulate.py``); ``stability_map`` over 41 x 37 (M, c) with the
closed-form equilibrium (4.62), and the same call again in the same process with new lambdas (a
notebook cell run twice); ``fit`` of c, d by Levenberg-Marquardt to 61 samples of theta (the README
example's motion; the data are made once by SciPy in this process, not timed); ``hopf_point`` of
the damped Nikolai problem (``tests/test_bifurcation.py``) and ``jax.grad`` of its ``.value``; the
README's two ``rbo-jax`` commands, each timed end to end (the fit's input file is made once with
the cache off, not timed); and the anchors: ``import jax``, SciPy ``solve_ivp`` DOP853 (one
trajectory, 501 samples), numba DOP853 (``_numba_reference.py`` compiled with ``cache=True``, one
trajectory), diffrax ``Dopri8`` on a hand-written vector field, ``jax.jit(jax.vmap(...))`` over
1,000 points. The anchors always come from this file's ``benchmarks/`` folder, not the ``--tree``.

Targets (issue 21): import + first call <= 5 s cold and <= 2 s warm (the gradient: <= 8 s cold);
the CLI rows are judged on their process time. "met" uses the best of ``--repeat`` runs (a loaded
machine only makes timings longer). Timings on a shared machine vary with its load: compare runs
made side by side.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)  # the benchmarks' shared pieces, also when this file is loaded by path
from _common import README_FIT, README_OBSERVATIONS, README_SIMULATE  # noqa: E402

# ---------------------------------------------------------------------------------------------
# The snippets. Each is "imports" (timed as the import) and "call" (timed as the first call; it
# sets ``result``, a small NumPy array or float that the parent records as a sanity check).
# ---------------------------------------------------------------------------------------------

_HEAD = """\
import time
_t0 = time.perf_counter()
"""

# After the call: the report, written to the file named by $RBO_LATENCY_REPORT.
_TAIL = """\
import json as _json, os as _os, sys as _sys
import numpy as _np
_mod = _sys.modules.get("rbo_jax")
_rep = {"import_s": _t1 - _t0, "call_s": _t2 - _t1, "again_s": globals().get("_again"),
        "cache": globals().get("_cache"),
        "rbo_jax_file": getattr(_mod, "__file__", None) if _mod is not None else None,
        "result": _np.asarray(result, dtype=float).ravel()[:8].tolist(),
        "cores": len(_os.sched_getaffinity(0)) if hasattr(_os, "sched_getaffinity") else None}
with open(_os.environ["RBO_LATENCY_REPORT"], "w") as _f:
    _json.dump(_rep, _f)
"""

# Turn on the persistent caches in $RBO_LATENCY_CACHE (part of the timed call: a user does it).
_CACHE = """\
def _enable_cache():
    import os
    import jax
    path = os.environ["RBO_LATENCY_CACHE"]
    if path == "off":  # --no-cache: a plain process
        return "off"
    mod = __import__("sys").modules.get("rbo_jax")
    if mod is not None and hasattr(mod, "enable_compilation_cache"):
        mod.enable_compilation_cache(path)
        return "rbo_jax.enable_compilation_cache"
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return "jax_compilation_cache_dir"
_cache = _enable_cache()
"""

# The Nikolai problem of bench_simulate.py, with NumPy inputs (no eager JAX operations of ours).
_NIKOLAI = """\
K = np.array([0.0, 0.0, 1.0])
PERT = np.array([1e-3, -5e-4, 2e-4])
T1, RTOL, ATOL = 20.0, 1e-8, 1e-10
def nikolai(c, d, M):
    return rbo_jax.RigidBodyOscillator(rbo_jax.transversely_isotropic_inertia(1.0, 0.5, K),
                                       rbo_jax.QuadraticFoundation(c, d, K),
                                       rbo_jax.FollowerMoment(M, K))
def points(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(0.5, 2.0, n), rng.uniform(0.5, 2.0, n),
                     rng.uniform(0.05, 0.6, n)], axis=1)
c, d, M = 1.0, 1.5, 0.3
theta0 = np.array([0.0, 0.0, M / d]) + PERT
ts = np.linspace(0.0, T1, 501)
"""

_ONE_TRAJECTORY = (
    _CACHE
    + _NIKOLAI
    + """\
traj = rbo_jax.{fn}(nikolai(c, d, M), theta0, np.zeros(3), ts, rtol=RTOL, atol=ATOL)
result = np.asarray(traj.theta)[-1]
"""
)

_VMAP = (
    _CACHE
    + _NIKOLAI
    + """\
def final_state(p):
    c, d, M = p[0], p[1], p[2]
    theta0 = (M / d) * K + PERT
    traj = rbo_jax.fast_simulate(nikolai(c, d, M), theta0, jnp.zeros(3), jnp.array([0.0, T1]),
                                 rtol=RTOL, atol=ATOL, throw=False)
    return jnp.concatenate([traj.theta[-1], traj.Omega[-1]])
result = np.asarray(jax.jit(jax.vmap(final_state))(points(1000)))[:2]
"""
)

_MAP = (
    _CACHE
    + """\
K = np.array([0.0, 0.0, 1.0])
Ms, cs = np.linspace(-0.8, 0.8, 41), np.linspace(0.2, 2.0, 37)
def run_map():  # new lambdas on every call, as a notebook cell run again
    return rbo_jax.stability_map(lambda M, c: rbo_jax.nikolai_model(M, c, 2.0, A3=0.5, k=K),
                                 {"M": Ms, "c": cs},
                                 theta_eq_fn=lambda M, c: rbo_jax.nikolai_equilibrium(M, 2.0, K))
result = np.asarray(run_map()["spectral_abscissa"])[[0, 20, 40]]
"""
)
_MAP_NEWTON = (
    _CACHE
    + """\
Ms, cs = np.linspace(-0.8, 0.8, 41), np.linspace(0.2, 2.0, 37)
def run_map():  # equilibria by Newton (the default), new lambdas on every call
    return rbo_jax.stability_map(lambda M, c: rbo_jax.nikolai_model(M, c, 2.0, A3=0.5),
                                 {"M": Ms, "c": cs})
result = np.asarray(run_map()["spectral_abscissa"])[[0, 20, 40]]
"""
)
_MAP_AGAIN = """\
_a0 = time.perf_counter()
np.asarray(run_map()["spectral_abscissa"])
_again = time.perf_counter() - _a0
"""

_FIT = (
    _CACHE
    + """\
obs = np.load(os.environ["RBO_LATENCY_FIT_DATA"])
K = np.array([0.0, 0.0, 1.0])
data = rbo_jax.TrajectoryData(obs["ts"], theta=obs["theta"], theta0=obs["theta0"],
                              Omega0=obs["Omega0"], sigma_theta=float(obs["sigma"]))
start = rbo_jax.RigidBodyOscillator(rbo_jax.transversely_isotropic_inertia(1.0, 0.6, K),
                                    rbo_jax.QuadraticFoundation(1.3, 1.5, K))
res = rbo_jax.fit(start, data, lambda m: (m.foundation.c, m.foundation.d))
result = np.concatenate([np.asarray(res.params), [float(res.converged)]])
"""
)

_HOPF_SETUP = (
    _CACHE
    + """\
def nikolai(M, b):  # tests/test_bifurcation.py
    return rbo_jax.nikolai_model(M, 1.0, 2.0, A1=1.0, A3=0.6, k=(0.0, 0.0, 1.0), friction=b)
"""
)
_HOPF = (
    _HOPF_SETUP
    + """\
h = rbo_jax.hopf_point(nikolai, {"b": 0.1}, "M", 0.15)
result = np.array([float(h.value), float(h.frequency), float(h.first_lyapunov)])
"""
)
_HOPF_GRAD = (
    _HOPF_SETUP
    + """\
result = float(jax.grad(lambda b: rbo_jax.hopf_point(nikolai, {"b": b}, "M", 0.15).value)(0.1))
"""
)
_BAUTIN = (
    _CACHE
    + """\
def nikolai(M, b, A3):  # tests/test_bautin.py, c fixed
    return rbo_jax.nikolai_model(M, 1.0, 2.0, A1=1.0, A3=A3, friction=b)
bp = rbo_jax.bautin_point(nikolai, {"b": 0.1}, ("M", "A3"), (0.2, 1.2))
result = np.array([*np.asarray(bp.value), float(bp.second_lyapunov)])
"""
)

_SCIPY = """\
from _numpy_reference import numpy_rhs
c, d, M, A1, A3 = 1.0, 1.5, 0.3, 1.0, 0.5
K = np.array([0.0, 0.0, 1.0])
A = A1 * (np.eye(3) - np.outer(K, K)) + A3 * np.outer(K, K)
y0 = np.concatenate([np.array([0.0, 0.0, M / d]) + np.array([1e-3, -5e-4, 2e-4]), np.zeros(3)])
sol = solve_ivp(numpy_rhs, (0.0, 20.0), y0, method="DOP853", rtol=1e-8, atol=1e-10,
                t_eval=np.linspace(0.0, 20.0, 501), args=(c, d, M, A, np.linalg.inv(A), K))
result = sol.y[:3, -1]
"""

_NUMBA = """\
solve = numba.njit(cache=True)(ref._solve_points)  # the serial driver, cached in $NUMBA_CACHE_DIR
c, d, M, A1, A3 = 1.0, 1.5, 0.3, 1.0, 0.5
K = np.array([0.0, 0.0, 1.0])
A = A1 * (np.eye(3) - np.outer(K, K)) + A3 * np.outer(K, K)
y, steps, nfev, status = solve(np.array([[c, d, M]]), 20.0, 1e-8, 1e-10,
                               np.array([1e-3, -5e-4, 2e-4]), A, np.linalg.inv(A), K)
result = y[0, :3]
"""

# diffrax's Dopri8 on a hand-written vector field (_numpy_reference.numpy_rhs in jax.numpy).
_DIFFRAX = (
    """\
jax.config.update("jax_enable_x64", True)
"""
    + _CACHE
    + """\
def rhs(t, y, args):
    c, d, M = args
    k = jnp.array([0.0, 0.0, 1.0])
    A = jnp.diag(jnp.array([1.0, 1.0, 0.5]))
    theta, Omega = y[:3], y[3:]
    th2 = theta @ theta
    small = th2 < 1e-8
    th = jnp.sqrt(jnp.where(small, 1.0, th2))
    big = (1.0 - th * jnp.sin(th) / (2.0 * (1.0 - jnp.cos(th)))) / jnp.where(small, 1.0, th2)
    g = jnp.where(small, 1.0 / 12.0 + th2 / 720.0, big)
    R = jnp.array([[0.0, -theta[2], theta[1]], [theta[2], 0.0, -theta[0]],
                   [-theta[1], theta[0], 0.0]])
    Z = jnp.eye(3) - 0.5 * R + g * (jnp.outer(theta, theta) - th2 * jnp.eye(3))
    dU = c * theta + (d - c) * (k @ theta) * k
    rest = M * k - Z @ dU - jnp.cross(Omega, A @ Omega)
    return jnp.concatenate([Z.T @ Omega, jnp.linalg.solve(A, rest)])
def final_state(p):
    c, d, M = p[0], p[1], p[2]
    y0 = jnp.concatenate([(M / d) * jnp.array([0.0, 0.0, 1.0])
                          + jnp.array([1e-3, -5e-4, 2e-4]), jnp.zeros(3)])
    sol = diffrax.diffeqsolve(diffrax.ODETerm(rhs), diffrax.Dopri8(), 0.0, 20.0, None, y0,
                              args=(c, d, M), saveat=diffrax.SaveAt(t1=True), max_steps=4096,
                              stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-10))
    return sol.ys[-1]
rng = np.random.default_rng(0)
pts = np.stack([rng.uniform(0.5, 2.0, 1000), rng.uniform(0.5, 2.0, 1000),
                rng.uniform(0.05, 0.6, 1000)], axis=1)
result = np.asarray(jax.jit(jax.vmap(final_state))(pts))[:2]
"""
)

_RBO = "import rbo_jax\nimport jax\nimport jax.numpy as jnp\nimport numpy as np\n"
_BENCH_PATH = "import sys\nsys.path.insert(0, {bench!r})\n"

# The README's two commands (the fit's input file is made once per run, not timed).
CLI_SIMULATE = ["simulate", *README_SIMULATE, "--out", "{work}/run.nc"]
CLI_OBS = ["simulate", *README_OBSERVATIONS, "--out", "{data}/obs.nc"]
CLI_FIT = ["fit", "--data", "{data}/obs.nc", *README_FIT, "--out", "{work}/fit.nc"]
_CLI = """\
import sys
from rbo_jax.app.cli import main
_t1 = time.perf_counter()
_rc = main(sys.argv[1:])
_t2 = time.perf_counter()
result = float(_rc)
"""


@dataclass
class Row:
    key: str
    label: str
    imports: str = ""
    call: str = ""
    cli: list | None = None
    target: tuple | None = (5.0, 2.0)  # (cold, warm) seconds; None: an anchor
    after: str = ""
    needs: tuple = field(default_factory=tuple)


def rows() -> list[Row]:
    bench = _BENCH_PATH.format(bench=HERE)
    return [
        Row("import", "`import rbo_jax`", "import rbo_jax\n", "result = 0.0\n"),
        Row(
            "simulate",
            "`simulate`, 1 trajectory, 501 samples",
            _RBO,
            _ONE_TRAJECTORY.format(fn="simulate"),
        ),
        Row(
            "fast_simulate",
            "`fast_simulate`, 1 trajectory, 501 samples",
            _RBO,
            _ONE_TRAJECTORY.format(fn="fast_simulate"),
        ),
        Row("vmap", "`jax.jit(jax.vmap(fast_simulate))`, 1,000 points", _RBO, _VMAP),
        Row("stability_map", "`stability_map`, 41 x 37", _RBO, _MAP, after=_MAP_AGAIN),
        Row(
            "stability_map_newton",
            "`stability_map`, 41 x 37, equilibria by Newton",
            _RBO,
            _MAP_NEWTON,
            after=_MAP_AGAIN,
        ),
        Row(
            "fit",
            "`fit` of c, d (Levenberg-Marquardt, 61 samples)",
            _RBO + "import os\n",
            _FIT,
            needs=("fit_data",),
        ),
        Row("hopf", "`hopf_point` (damped Nikolai)", _RBO, _HOPF),
        Row(
            "hopf_grad",
            "`jax.grad` of `hopf_point(...).value`",
            _RBO,
            _HOPF_GRAD,
            target=(8.0, 2.0),
        ),
        Row("bautin", "`bautin_point` (damped Nikolai, (M, A3))", _RBO, _BAUTIN),
        Row("cli_simulate", "`rbo-jax simulate` (README example, process)", cli=CLI_SIMULATE),
        Row("cli_fit", "`rbo-jax fit` (README example, process)", cli=CLI_FIT, needs=("cli_obs",)),
        Row("import_jax", "anchor: `import jax`", "import jax\n", "result = 0.0\n", target=None),
        Row(
            "scipy",
            "anchor: SciPy `solve_ivp` DOP853, 1 trajectory",
            bench + "import numpy as np\nfrom scipy.integrate import solve_ivp\n",
            _SCIPY,
            target=None,
        ),
        Row(
            "numba",
            "anchor: numba DOP853 (`cache=True`), 1 trajectory",
            bench + "import numba\nimport numpy as np\nimport _numba_reference as ref\n",
            _NUMBA,
            target=None,
        ),
        Row(
            "diffrax",
            "anchor: diffrax Dopri8, hand-written field, vmap 1,000",
            "import diffrax\nimport jax\nimport jax.numpy as jnp\nimport numpy as np\n",
            _DIFFRAX,
            target=None,
        ),
    ]


def snippet(row: Row) -> str:
    """The program one process of ``row`` runs (``python -c``)."""
    if row.cli is not None:
        # as the console script ends (rbo_jax.app.cli.run: exit_process, where the tree has it)
        return (
            _HEAD + _CLI + _TAIL + "import rbo_jax.app.cli as _cli\n"
            "getattr(_cli, 'exit_process', sys.exit)(_rc)\n"
        )
    return (
        _HEAD
        + row.imports
        + "_t1 = time.perf_counter()\n"
        + row.call
        + "_t2 = time.perf_counter()\n"
        + row.after
        + _TAIL
    )


# ---------------------------------------------------------------------------------------------
# Inputs made once per run (not timed).
# ---------------------------------------------------------------------------------------------


def make_fit_data(path: str) -> str:
    """61 samples of theta on t in [0, 6] of the README's conservative motion (c = 1, d = 2,
    A1 = 1, A3 = 0.6, no load), by SciPy's DOP853 at rtol = atol = 1e-12 on the NumPy vector
    field of ``_numpy_reference`` (independent of the tree), plus noise of 1e-3 rad."""
    import numpy as np
    from scipy.integrate import solve_ivp

    sys.path.insert(0, HERE)
    from _numpy_reference import numpy_rhs

    k = np.array([0.0, 0.0, 1.0])
    A = np.eye(3) - np.outer(k, k) + 0.6 * np.outer(k, k)
    theta0, Omega0 = np.array([0.8, -0.3, 0.5]), np.array([0.2, 1.1, -0.7])
    ts = np.linspace(0.0, 6.0, 61)
    sol = solve_ivp(
        numpy_rhs,
        (0.0, 6.0),
        np.concatenate([theta0, Omega0]),
        method="DOP853",
        rtol=1e-12,
        atol=1e-12,
        t_eval=ts,
        args=(1.0, 2.0, 0.0, A, np.linalg.inv(A), k),
    )
    sigma = 1e-3
    theta = sol.y[:3].T + sigma * np.random.default_rng(7).standard_normal((61, 3))
    out = os.path.join(path, "fit_data.npz")
    np.savez(out, ts=ts, theta=theta, theta0=theta0, Omega0=Omega0, sigma=sigma)
    return out


# ---------------------------------------------------------------------------------------------
# Running the processes.
# ---------------------------------------------------------------------------------------------


def run_process(
    row: Row,
    tree: str,
    cache: str,
    work: str,
    env_extra: dict,
    timeout: float,
    jax_cache: bool = True,
    cpus: set | None = None,
):
    """One process of ``row`` on the cache directory ``cache`` (``jax_cache=False``: no
    persistent JAX cache, for the library rows and the CLI; numba's stays on): a dict with
    import_s, call_s, process_s (start to exit, measured here), again_s, result, or error.
    ``cpus``: the cores the process may run on (``--pin``; None: all)."""
    report = os.path.join(work, f"report-{row.key}-{time.monotonic_ns()}.json")
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("JAX_COMPILATION_CACHE", "RBO_LATENCY"))
    }
    env.update(env_extra)
    env.update(
        PYTHONPATH=tree,
        RBO_LATENCY_REPORT=report,
        RBO_LATENCY_CACHE=cache if jax_cache else "off",
        RBO_JAX_COMPILATION_CACHE=cache if jax_cache else "off",
        NUMBA_CACHE_DIR=os.path.join(cache, "numba"),
        XDG_CACHE_HOME=os.path.join(cache, "xdg"),
    )
    args = [
        a.format(work=work, data=env_extra.get("RBO_LATENCY_DATA_DIR", work))
        for a in (row.cli or [])
    ]
    start = time.perf_counter()
    try:
        proc = subprocess.run(
            [sys.executable, "-c", snippet(row), *args],
            env=env,
            cwd=tree,
            capture_output=True,
            text=True,
            timeout=timeout,
            preexec_fn=None if cpus is None else lambda: os.sched_setaffinity(0, cpus),
        )
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s"}
    wall = time.perf_counter() - start
    if proc.returncode != 0 or not os.path.exists(report):
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-5:]
        return {"error": f"exit {proc.returncode}: " + " | ".join(tail), "process_s": wall}
    with open(report) as f:
        out = json.load(f)
    out["process_s"] = wall
    mod = out.get("rbo_jax_file")
    if mod is not None and not os.path.realpath(mod).startswith(os.path.realpath(tree) + os.sep):
        sys.exit(f"row {row.key} imported {mod}, not the rbo_jax of {tree}")
    return out


def first_answer(run: dict, row: Row) -> float | None:
    """The figure judged against the target: import + call, the process time for the CLI."""
    if "error" in run:
        return None
    return run["process_s"] if row.cli is not None else run["import_s"] + run["call_s"]


def machine(tree: str) -> dict:
    """CPU model, cores, load average, memory, versions and the tree's commit."""
    info = {
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cores": os.cpu_count(),
        "tree": os.path.abspath(tree),
    }
    try:
        with open("/proc/cpuinfo") as f:
            info["cpu"] = next(
                line.split(":", 1)[1].strip() for line in f if line.startswith("model name")
            )
    except (OSError, StopIteration):
        info["cpu"] = platform.processor() or "unknown"
    if hasattr(os, "sched_getaffinity"):
        info["cores_usable"] = len(os.sched_getaffinity(0))
    try:
        with open("/proc/meminfo") as f:
            kib = int(next(line.split()[1] for line in f if line.startswith("MemTotal")))
        info["memory_gib"] = round(kib / 2**20, 1)
    except (OSError, StopIteration, ValueError):
        pass
    info["versions"] = {}
    for name in ("jax", "jaxlib", "equinox", "diffrax", "optimistix", "numpy", "scipy", "numba"):
        try:
            info["versions"][name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            pass
    git = ["git", "-C", tree]
    try:
        info["commit"] = subprocess.run(
            [*git, "rev-parse", "--short", "HEAD"], text=True, capture_output=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            [*git, "status", "--porcelain", "--untracked-files=no", "--", "rbo_jax"],
            text=True,
            capture_output=True,
        ).stdout.strip()
        info["rbo_jax_modified"] = bool(dirty)  # uncommitted changes under rbo_jax/
    except (OSError, subprocess.CalledProcessError):
        info["commit"] = None
    return info


def _span(values):
    values = [v for v in values if v is not None]
    if not values:
        return "failed"
    lo, hi = (_fmt(min(values)), _fmt(max(values)))
    return lo if lo == hi else f"{lo}-{hi}"


def _fmt(x: float) -> str:
    return f"{x:.2f}" if x < 1 else f"{x:.1f}"


def _cell(runs: list[dict], row: Row) -> str:
    """'import + call' (min-max over the repeats; the CLI: its import, then ``main``)."""
    ok = [r for r in runs if "error" not in r]
    if not ok:
        return "failed"
    return f"{_span([r['import_s'] for r in ok])} + {_span([r['call_s'] for r in ok])}"


def _met(result: dict, row: Row) -> str:
    if row.target is None:
        return "-"
    notes = []
    for which, target in zip(("cold", "warm"), row.target):
        best = [first_answer(r, row) for r in result[which]]
        best = [b for b in best if b is not None]
        if not best:
            notes.append(f"{which} failed")
        elif min(best) > target:
            notes.append(f"{which} +{min(best) - target:.2f} s")
    return "yes" if not notes else "no (" + ", ".join(notes) + ")"


def table(results: dict, selected: list[Row]) -> str:
    lines = [
        "| task | cold: import + call [s] | warm: import + call [s] | cold / warm process "
        "[s] | target cold / warm [s] | met? |",
        "|---|---|---|---|---|---|",
    ]
    for row in selected:
        res = results[row.key]
        proc = " / ".join(_span([r.get("process_s") for r in res[w]]) for w in ("cold", "warm"))
        target = "-" if row.target is None else f"{row.target[0]:g} / {row.target[1]:g}"
        lines.append(
            f"| {row.label} | {_cell(res['cold'], row)} | {_cell(res['warm'], row)} | "
            f"{proc} | {target} | {_met(res, row)} |"
        )
        if row.after:
            again = [
                _span([r.get("again_s") for r in res[w] if "error" not in r])
                for w in ("cold", "warm")
            ]
            lines.append(
                f"| ... the same call again, new lambdas, same process | {again[0]} | "
                f"{again[1]} | | - | - |"
            )
    return "\n".join(lines)


def main(argv=None):
    all_rows = rows()
    keys = [r.key for r in all_rows]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", default=ROOT, help="checkout to time (default: this one)")
    parser.add_argument(
        "--rows",
        default=",".join(keys),
        help=f"comma-separated rows (default: all): {','.join(keys)}",
    )
    parser.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="cold/warm pairs per row, each on a fresh cache (min-max reported)",
    )
    parser.add_argument("--json", help="write the machine, every run and the table here")
    parser.add_argument(
        "--no-cache",
        action="store_true",
        help="no persistent JAX cache in any process (a plain notebook): cold "
        "and warm then differ only by the operating system's file cache",
    )
    parser.add_argument(
        "--pin",
        help="run every process on these cores only, e.g. '0' or "
        "'0,1' (Linux): on a loaded machine XLA's multi-threaded runtime can "
        "slow a vmapped program many times over; one core is steadier",
    )
    parser.add_argument("--label", help="name of the tree in the output (e.g. 'before')")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds per process")
    args = parser.parse_args(argv)
    wanted = [k.strip() for k in args.rows.split(",") if k.strip()]
    unknown = sorted(set(wanted) - set(keys))
    if unknown or not wanted:
        parser.error(f"unknown rows {unknown}; choose from {', '.join(keys)}")
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    cpus = None
    if args.pin:
        try:
            cpus = {int(c) for c in args.pin.split(",")}
        except ValueError:
            parser.error(f"--pin takes core numbers such as 0 or 0,1, not {args.pin!r}")
        if not hasattr(os, "sched_setaffinity") or not cpus <= os.sched_getaffinity(0):
            parser.error(f"--pin {args.pin}: not cores this process may use")
    tree = os.path.abspath(args.tree)
    if not os.path.isdir(os.path.join(tree, "rbo_jax")):
        parser.error(f"{tree} holds no rbo_jax package")
    selected = [r for r in all_rows if r.key in wanted]

    info = machine(tree)
    info["label"] = args.label
    info["jax_cache"] = not args.no_cache
    info["pinned_to"] = sorted(cpus) if cpus else None
    info["load_start"] = os.getloadavg()
    print(
        f"{args.label + ': ' if args.label else ''}tree {tree} (commit {info.get('commit')}"
        f"{', rbo_jax/ modified' if info.get('rbo_jax_modified') else ''}); "
        f"{info['cpu']}, {info['cores']} cores, {info.get('memory_gib', '?')} GiB; "
        f"Python {info['python']}, " + ", ".join(f"{k} {v}" for k, v in info["versions"].items()),
        flush=True,
    )
    print(
        f"load average at start {' '.join(f'{x:.2f}' for x in info['load_start'])}"
        f"{'; processes pinned to cores ' + args.pin if cpus else ''}"
        f"{'; no persistent JAX cache' if args.no_cache else ''}",
        flush=True,
    )
    results = {r.key: {"cold": [], "warm": []} for r in selected}
    with tempfile.TemporaryDirectory(prefix="rbo-latency-") as tmp:
        extra = {}
        if any("fit_data" in r.needs for r in selected):
            extra["RBO_LATENCY_FIT_DATA"] = make_fit_data(tmp)
        if any("cli_obs" in r.needs for r in selected):
            data_dir = os.path.join(tmp, "data")
            os.makedirs(data_dir)
            extra["RBO_LATENCY_DATA_DIR"] = data_dir
            obs = Row("cli_obs", "input of the fit", cli=CLI_OBS)
            made = run_process(obs, tree, data_dir, data_dir, extra, args.timeout, jax_cache=False)
            if "error" in made:
                sys.exit(f"making the fit's input failed: {made['error']}")
        for rep in range(args.repeat):
            for row in selected:
                cache = os.path.join(tmp, f"cache-{row.key}-{rep}")
                os.makedirs(cache)
                work = os.path.join(tmp, f"work-{row.key}-{rep}")
                os.makedirs(work)
                for which in ("cold", "warm"):
                    run = run_process(
                        row,
                        tree,
                        cache,
                        work,
                        extra,
                        args.timeout,
                        jax_cache=not args.no_cache,
                        cpus=cpus,
                    )
                    run["load"] = os.getloadavg()[0]
                    results[row.key][which].append(run)
                    if "error" in run:
                        status = run["error"]
                    else:
                        status = (
                            f"import {run['import_s']:.2f} s + call {run['call_s']:.2f} s"
                            f" (process {run['process_s']:.2f} s)"
                        )
                        if run.get("again_s") is not None:
                            status += f", again {run['again_s']:.2f} s"
                    print(
                        f"[{rep + 1}/{args.repeat}] {row.key:20s} {which}: {status}; "
                        f"load {run['load']:.2f}",
                        flush=True,
                    )
                shutil.rmtree(cache, ignore_errors=True)
    info["load_end"] = os.getloadavg()
    text = table(results, selected)
    how = sorted({r["cache"] for v in results.values() for r in v["cold"] if r.get("cache")})
    print(
        f"\nload average at end {' '.join(f'{x:.2f}' for x in info['load_end'])}; JAX cache "
        f"turned on by: {', '.join(how) or '-'} (CLI rows: $RBO_JAX_COMPILATION_CACHE)\n"
    )
    print(text)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {"machine": info, "repeat": args.repeat, "runs": results, "table": text},
                f,
                indent=1,
            )
    return results


if __name__ == "__main__":
    main()
