r"""Rods in float32 (``JAX_ENABLE_X64=0``, rbo_jax._precision): the equilibrium, the spectrum and
the motion of a cantilever agree with float64 to float32's accuracy, and stay in float32.

The same script (tests/_rod_float32_worker.py) runs in two fresh interpreters, float64 (the
default) and float32. Tolerances, from float32's machine epsilon $\varepsilon = 1.2\times
10^{-7}$:

- equilibrium: Newton stops at $100\varepsilon$ (:func:`rbo_jax.lattice.solve_equilibrium`'s
  floor), the tip then agrees to $10^{-5} L$;
- spectrum: a dense eigenvalue problem's rounding is about $\varepsilon\,\max|p|$ (the stiff
  shear and rotary modes, $\max|p| \approx 1000$ here), so the lowest frequencies agree to
  $30\,\varepsilon\max|p|$ in absolute terms (measured: $10\,\varepsilon\max|p|$,
  $3.6\times10^{-4}$ of the lowest frequency: the two planes' equal frequencies split by that
  much);
- motion: the solver's tolerances $10^{-5}$ (float32 warns below $10\varepsilon$): the tip
  agrees to $10^{-5} L$ over half a period (measured $2.3\times10^{-7}$).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

WORKER = os.path.join(os.path.dirname(__file__), "_rod_float32_worker.py")


def _env(x64: str | None):
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "XLA_FLAGS"))}
    env["JAX_PLATFORMS"] = "cpu"
    env["OPENBLAS_NUM_THREADS"] = "1"
    if x64 is not None:
        env["JAX_ENABLE_X64"] = x64
    return env


def _run(procs):
    out = {}
    for key, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=1800)
        assert proc.returncode == 0, stderr[-3000:]
        line = [s for s in stdout.splitlines() if s.startswith("RESULT ")][-1]
        out[key] = json.loads(line[len("RESULT ") :])
    return out


def _start(which, x64):
    return subprocess.Popen(
        [sys.executable, "-W", "error", WORKER, which],
        env=_env(x64),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_a_float32_rod_is_built_in_float32():
    """With x64 off the rod's constants and its straight state are float32 (no compile)."""
    code = (
        "import rbo_jax; from rbo_jax import lattice;"
        "b = lattice.rod(4, 1.0, bending=1.0, torsion=1.0, shear=1e3, stretch=1e3, mass=1.0,"
        " rotary=1e-3); s = b.straight();"
        "print(rbo_jax.float64_enabled(), b.mass.dtype, b.turn_stiffness.dtype, s.r.dtype)"
    )
    out = subprocess.run(
        [sys.executable, "-W", "error", "-c", code],
        env=_env("0"),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split() == ["False", "float32", "float32", "float32"]


@pytest.mark.slow  # two fresh interpreters, each compiling a Newton solve, a spectrum, a motion
def test_equilibrium_spectrum_and_motion_agree_with_float64():
    res = _run({"32": _start("all", "0"), "64": _start("all", None)})
    f32, f64 = res["32"], res["64"]
    print(json.dumps(res))  # shown when an assertion fails
    assert f32["x64"] is False and f64["x64"] is True
    # no silent upcast (float32 stays float32) and no downcast of the float64 run
    for key, want32, want64 in [
        ("rod_dtype", "float32", "float64"),
        ("state_dtype", "float32", "float64"),
        ("spectrum_dtype", "complex64", "complex128"),
        ("trajectory_dtype", "float32", "float64"),
    ]:
        assert (f32[key], f64[key]) == (want32, want64), key
    assert f32["ok"] and f64["ok"]
    np.testing.assert_allclose(f32["tip"], f64["tip"], atol=1e-5)
    np.testing.assert_allclose(f32["tip_turn"], f64["tip_turn"], atol=1e-5)
    eps = float(np.finfo(np.float32).eps)
    w_tol = 30 * eps * f64["max_abs_p"]
    np.testing.assert_allclose(f32["frequencies"], f64["frequencies"], atol=w_tol)
    assert w_tol < 0.002 * f64["frequencies"][0]  # a meaningful check of the lowest mode
    np.testing.assert_allclose(f32["tip_x"], f64["tip_x"], atol=1e-5)
    assert f32["energy_drift"] < 1e-5 and f64["energy_drift"] < 1e-6
