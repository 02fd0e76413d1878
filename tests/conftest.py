"""Strict test configuration (cf. diffrax ``test/conftest.py``): float64, no rank promotion and
strict dtype promotion (no implicit int -> float or float32 -> float64 mixing)."""

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
# One persistent compilation cache for the whole run: the two xdist workers, the notebook kernels
# and the rbo-jax processes of the CLI tests compile many of the same programs (the DOP853 loop of
# fast_simulate, the fit's program, the Hopf system), and a program compiled by one process is
# loaded by the next. A fresh directory per run, made by the controlling process (the workers
# and subprocesses inherit the variables) and removed at its end, so nothing is carried from one
# run to the next. tests/test_cli.py tests the command's own cache in directories of its own.
_TEST_CACHE = "RBO_JAX_TEST_COMPILATION_CACHE"
_OWN_CACHE = _TEST_CACHE not in os.environ
if _OWN_CACHE:
    os.environ[_TEST_CACHE] = tempfile.mkdtemp(prefix="rbo-jax-test-cache-")
os.environ.setdefault("RBO_JAX_COMPILATION_CACHE", os.environ[_TEST_CACHE])
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", os.environ[_TEST_CACHE])

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

import hypothesis  # noqa: E402

hypothesis.settings.register_profile(
    "rbo", max_examples=60, deadline=None, derandomize=True, print_blob=True
)
hypothesis.settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "rbo"))


def pytest_unconfigure(config):
    if _OWN_CACHE:
        shutil.rmtree(os.environ[_TEST_CACHE], ignore_errors=True)


# The longest test files first: `make test` hands whole files to its two workers (--dist
# loadfile) in collection order, so a long file collected last keeps one worker busy while the
# other idles at the end (measured: the notebooks, ~3 min of kernels, ran last). Longest first
# is the classic greedy schedule; the order of the tests inside a file is unchanged.
_FIRST = ("test_notebooks.py", "test_benchmarks.py", "test_lattice.py", "test_fitting.py")


def pytest_collection_modifyitems(config, items):
    def rank(item):
        name = item.path.name
        return _FIRST.index(name) if name in _FIRST else len(_FIRST)

    items.sort(key=rank)  # stable: files keep their own order otherwise
