"""Float64 by default (rbo_jax._precision), checked in fresh interpreters.

The test session itself has x64 switched on by conftest.py, so the behaviour of a plain
``import rbo_jax`` can only be observed in a subprocess with a controlled environment.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

SCRIPT = """
import rbo_jax
import jax.numpy as jnp
print(jnp.zeros(1).dtype)
print(rbo_jax.float64_enabled())
import jax
@jax.jit
def f(theta):
    Q = rbo_jax.turn_tensor(theta)
    return Q, jnp.abs(Q @ Q.T - jnp.eye(3)).max()
Q, err = f(jnp.asarray([0.1, -0.2, 0.3]))
print(Q.dtype)
print(float(err))
"""

# JAX_ENABLE_X64 value in the child's environment (None: unset) -> expected default dtype
CASES = {
    "unset": (None, "float64"),
    "opt-out-0": ("0", "float32"),
    "opt-out-false": ("false", "float32"),
}


@pytest.fixture(scope="module")
def children():
    """Run every case in its own fresh interpreter, concurrently (each takes ~1 s to import jax)."""
    procs = {}
    for case, (value, _) in CASES.items():
        env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "XLA_FLAGS"))}
        env["JAX_PLATFORMS"] = "cpu"
        if value is not None:
            env["JAX_ENABLE_X64"] = value
        procs[case] = subprocess.Popen(
            [sys.executable, "-c", SCRIPT],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
    out = {}
    for case, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=300)
        out[case] = (proc.returncode, stdout.split(), stderr)
    return out


@pytest.mark.parametrize("case", CASES)
def test_default_dtype_in_fresh_interpreter(children, case):
    """``import rbo_jax`` turns float64 on unless JAX_ENABLE_X64 is explicitly false, in which case
    the user's choice is respected (float32, float64_enabled() is False) and the kinematics still
    work in float32 (Q of (4.3) orthogonal, (4.27), to float32 accuracy)."""
    returncode, lines, stderr = children[case]
    assert returncode == 0, stderr
    dtype, enabled, q_dtype, orth_err = lines
    expected = CASES[case][1]
    assert dtype == expected
    assert enabled == str(expected == "float64")
    assert q_dtype == expected
    assert float(orth_err) <= (1e-15 if expected == "float64" else 1e-6)
