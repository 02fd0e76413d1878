"""Concrete inputs are checked in NumPy, not by small eager JAX programs (each compiled on its
own, 5-50 ms): building models and observed data and checking a solve's inputs compile
nothing, a trajectory's derived quantities compile one program each and its status none.
Compilations are counted in a fresh interpreter (this process has compiled the small programs
of other tests already, and JAX keeps them) with ``jax_log_compiles``."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

from rbo_jax import TrajectoryData, nikolai_model, simulate
from rbo_jax.trajectory import Trajectory, check_times

PRELUDE = """
import json, logging, sys
import jax
import numpy as np

compiled = []

class Count(logging.Handler):
    def emit(self, record):
        if record.getMessage().startswith("Compiling "):
            compiled.append(record.getMessage().split(" with ")[0])

logging.getLogger("jax").addHandler(Count())
logging.getLogger("jax").setLevel(logging.WARNING)
jax.config.update("jax_log_compiles", True)
import rbo_jax
K = np.array([0.0, 0.0, 1.0])
"""


def _compiled_by(code: str) -> list[str]:
    """The programs compiled while ``code`` runs in a fresh interpreter (after the prelude)."""
    script = PRELUDE + textwrap.dedent(code) + "\nprint(json.dumps(compiled))\n"
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300, check=False
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_constructors_and_input_checks_compile_nothing():
    compiled = _compiled_by("""
        from rbo_jax.trajectory import prepare_inputs
        A = rbo_jax.transversely_isotropic_inertia(1.0, 0.6, K)
        model = rbo_jax.RigidBodyOscillator(
            A, rbo_jax.BarrierFoundation(1.0, 2.0, 1.5, 1.2, K),
            [rbo_jax.SemiTangentialMoment(0.3, K), rbo_jax.FollowerMoment(0.2, K),
             rbo_jax.Friction(0.1)])
        ts = np.linspace(0.0, 2.0, 23)
        data = rbo_jax.TrajectoryData(ts, theta=np.zeros((23, 3)), Omega=np.ones((23, 3)))
        x0 = jax.device_put(np.array([0.1, 0.2, 0.3]))
        inputs = prepare_inputs(model, x0, x0, ts, 1e-8, 1e-8, True)
        assert not bool(inputs.invalid) and inputs.ts.dtype == np.float64
    """)
    assert compiled == []


def test_concrete_times_are_checked_on_the_host():
    ts = check_times(np.arange(5))  # integer times become floats
    assert isinstance(ts, jax.Array) and ts.dtype == np.float64
    np.testing.assert_array_equal(ts, np.arange(5.0))
    given = jax.device_put(np.linspace(0.0, 1.0, 4))
    assert check_times(given) is given
    for bad, match in [
        ([0.0, 1.0, 1.0], "strictly increasing"),
        ([0.0, np.inf], "finite"),
        (np.zeros((2, 2)), "1-D"),
        ([], "non-empty"),
    ]:
        with pytest.raises(ValueError, match=match):
            check_times(bad)


def test_derived_quantities_compile_one_program_each():
    compiled = _compiled_by("""
        ts = np.linspace(0.0, 1.0, 7)
        x0 = np.array([0.3, -0.2, 0.5])
        traj = rbo_jax.fast_simulate(rbo_jax.nikolai_model(0.3, 1.0, 2.0), x0, x0, ts)
        jax.block_until_ready(traj.theta)
        compiled.clear()
        names = ("omega", "turn_tensor", "kinetic_moment", "kinetic_energy",
                 "potential_energy", "energy")
        for name in names:
            getattr(traj, name)
        assert bool(traj.ok)  # compared on the host
        first = list(compiled)
        other = rbo_jax.fast_simulate(rbo_jax.nikolai_model(0.1, 1.5, 2.5), x0, x0, ts)
        jax.block_until_ready(other.theta)
        compiled.clear()
        for name in names:
            getattr(other, name)  # a model of the same structure: nothing new
        compiled[:] = [first, list(compiled)]
    """)
    first, again = compiled
    assert len(first) == 6, first
    assert again == []


def test_derived_quantities_match_the_model_per_sample():
    model = nikolai_model(0.3, 1.0, 2.0, friction=0.05)
    ts = np.linspace(0.0, 1.0, 5)
    traj = simulate(model, np.array([0.3, -0.2, 0.5]), np.array([0.1, 0.4, -0.3]), ts)
    for name, f, args in [
        ("omega", model.omega, (traj.theta, traj.Omega)),
        ("energy", model.energy, (traj.theta, traj.Omega)),
        ("kinetic_energy", model.kinetic_energy, (traj.Omega,)),
        ("potential_energy", model.potential_energy, (traj.theta,)),
    ]:
        expected = np.stack([np.asarray(f(*(a[i] for a in args))) for i in range(len(ts))])
        np.testing.assert_allclose(
            getattr(traj, name), expected, rtol=1e-14, atol=1e-15, err_msg=name
        )
    # inside a transformation the quantities are traced with the rest
    energy = jax.jit(lambda t: t.energy)(traj)
    np.testing.assert_allclose(energy, traj.energy, rtol=1e-14)
    assert isinstance(traj, Trajectory)


def test_observed_data_stay_float64_on_the_device():
    data = TrajectoryData(
        np.linspace(0.0, 1.0, 3), theta=np.zeros((3, 3)), Omega0=np.ones(3), t0=-0.5
    )
    for x in (data.ts, data.theta, data.theta0, data.t0):
        assert isinstance(x, jax.Array) and x.dtype == np.float64
    assert float(data.t0) == -0.5
