"""Strict test configuration (cf. diffrax ``test/conftest.py``): float64, no rank promotion and
strict dtype promotion (no implicit int -> float or float32 -> float64 mixing)."""

import gc
import os
import shutil
import tempfile

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# XLA's element-wise emitters for every program of the run (workers, notebook kernels and CLI
# subprocesses inherit it): the suite's time is mostly compilation, which these emitters make
# ~30 % cheaper; rbo_jax compiles its small programs this way for users too
# (rbo_jax._programs.small_program_options), and the large ones keep XLA's defaults only for
# their run time, which the benchmarks measure, not the tests.
if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=false"
    ).strip()
# (Not LLVM at -O0 as well, --xla_backend_optimization_level=0: it cut the quick tier's CPU time
# by a third, but changed results in their last bits, so the tests would check other numbers
# than users get: a guess exactly on the singular sphere stopped failing in tests/test_bautin.py.)
# One persistent compilation cache for the suite, kept from one run to the next in a per-user
# folder (``$XDG_CACHE_HOME`` or ``~/.cache``, then ``rbo_jax/test-cache``): the two xdist workers,
# the notebook kernels and the rbo-jax processes of the CLI tests compile many of the same
# programs (the DOP853 loop of fast_simulate, the fit's program, the Hopf system), and a program
# compiled by one process, or by the previous run, is loaded instead of compiled again. Entries
# are keyed on the package's sources, the JAX versions and the program (rbo_jax._cache), so an
# edit never reuses a stale one. ``RBO_JAX_TEST_COMPILATION_CACHE=DIR`` chooses the folder;
# ``=off`` gives a fresh folder removed at the end of the run (a cold run, as on a new machine).
# The workers and subprocesses inherit the variables from the controlling process. The folder
# is pruned to its newest files when it passes TEST_CACHE_LIMIT. tests/test_cli.py tests the
# command's own cache in directories of its own.
_TEST_CACHE = "RBO_JAX_TEST_COMPILATION_CACHE"
TEST_CACHE_LIMIT = 4 * 2**30  # bytes
_OWN_CACHE = False
if os.environ.get("PYTEST_XDIST_WORKER") is None:  # the controlling process (or a plain run)
    _chosen = os.environ.get(_TEST_CACHE, "").strip()
    if _chosen.lower() in ("off", "0", "no", "false", "none"):
        _OWN_CACHE = True
        os.environ[_TEST_CACHE] = tempfile.mkdtemp(prefix="rbo-jax-test-cache-")
    elif not _chosen:
        _base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        os.environ[_TEST_CACHE] = os.path.join(_base, "rbo_jax", "test-cache")
    try:
        os.makedirs(os.environ[_TEST_CACHE], exist_ok=True)
    except OSError:  # a read-only home: a fresh folder for this run
        _OWN_CACHE = True
        os.environ[_TEST_CACHE] = tempfile.mkdtemp(prefix="rbo-jax-test-cache-")
os.environ.setdefault("RBO_JAX_COMPILATION_CACHE", os.environ[_TEST_CACHE])
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", os.environ[_TEST_CACHE])


def _prune(folder: str, limit: int) -> None:
    """Delete the oldest files of ``folder`` (by modification time) until it holds at most half
    of ``limit`` bytes, when it holds more than ``limit``."""
    files = []
    for root, _, names in os.walk(folder):
        for name in names:
            path = os.path.join(root, name)
            try:
                st = os.stat(path)
            except OSError:
                continue
            files.append((st.st_mtime, st.st_size, path))
    total = sum(size for _, size, _ in files)
    if total <= limit:
        return
    for _, size, path in sorted(files):
        if total <= limit // 2:
            break
        try:
            os.remove(path)
            total -= size
        except OSError:
            pass


if not _OWN_CACHE and os.environ.get("PYTEST_XDIST_WORKER") is None:
    _prune(os.environ[_TEST_CACHE], TEST_CACHE_LIMIT)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

import equinox as eqx  # noqa: E402
import hypothesis  # noqa: E402
import pytest  # noqa: E402

hypothesis.settings.register_profile(
    "rbo", max_examples=60, deadline=None, derandomize=True, print_blob=True
)
hypothesis.settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "rbo"))


@pytest.fixture(autouse=True, scope="module")
def _free_programs_after_each_file():
    """After each test file, the compiled programs in memory are dropped (JAX's and equinox's
    caches): a worker that runs many files would otherwise keep every program it compiled
    (measured: one worker of the complete tier held 12 GB after tests/test_cli.py's
    reproduction, 19 GB used of 24 with the other worker). A later file that needs a program
    again loads it from the persistent compilation cache."""
    yield
    jax.clear_caches()
    eqx.clear_caches()
    gc.collect()


def pytest_unconfigure(config):
    if _OWN_CACHE:
        shutil.rmtree(os.environ[_TEST_CACHE], ignore_errors=True)


# The longest test files first: `make test` hands whole files to its two workers (--dist
# loadfile) in collection order, so a long file collected last keeps one worker busy while the
# other idles at the end (measured: the notebooks, ~3 min of kernels, ran last). Longest first
# is the classic greedy schedule; the order of the tests inside a file is unchanged.
# The complete tier's longest files, measured cold (a fresh machine, as CI): test_rod_hopf.py
# ~15 min of one worker, test_mechanics.py and test_devices.py ~8 min each.
_FIRST = (
    "test_rod_hopf.py",
    "test_notebooks.py",
    "test_mechanics.py",
    "test_devices.py",
    "test_benchmarks.py",
    "test_distributed_sweep.py",
    "test_lattice.py",
    "test_fitting.py",
    # then the quick tier's longest files, measured cold (`make test`, --durations=0: 23-53 s
    # each; a simulation of the two workers' queue put the last file's end ~15 s earlier than
    # in alphabetical order)
    "test_fast_simulate.py",
    "test_cli.py",
    "test_sweep.py",
    "test_simulate.py",
    "test_bifurcation.py",
    "test_rod_traced.py",
    "test_bautin.py",
    "test_kinematics.py",
    "test_physics.py",
    "test_fitting_sensors.py",
    "test_stability.py",
    "test_maps.py",
)


def pytest_collection_modifyitems(config, items):
    def rank(item):
        name = item.path.name
        return _FIRST.index(name) if name in _FIRST else len(_FIRST)

    items.sort(key=rank)  # stable: files keep their own order otherwise
