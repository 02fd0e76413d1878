"""Strict test configuration (cf. diffrax ``test/conftest.py``): float64, no rank promotion and
strict dtype promotion (no implicit int -> float or float32 -> float64 mixing)."""

import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# the CLI's persistent compilation cache stays off in tests (tests/test_cli.py turns it on in a
# temporary directory where it is tested)
os.environ.setdefault("RBO_JAX_COMPILATION_CACHE", "off")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

import hypothesis  # noqa: E402

hypothesis.settings.register_profile(
    "rbo", max_examples=60, deadline=None, derandomize=True, print_blob=True
)
hypothesis.settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "rbo"))
