"""Run by tests/test_rod_float32.py in a fresh interpreter (JAX_ENABLE_X64 chosen by the test):
a rod's equilibrium, spectrum and motion, printed as JSON with the dtypes met on the way."""

from __future__ import annotations

import json
import sys

import jax.numpy as jnp
import numpy as np

import rbo_jax
from rbo_jax import lattice


def main() -> None:
    which = sys.argv[1] if len(sys.argv) > 1 else "all"
    out = {"x64": rbo_jax.float64_enabled()}
    beam = lattice.rod(
        6, 1.0, bending=1.0, torsion=1.0, shear=1e3, stretch=1e3, mass=1.0, rotary=1e-3,
        loads=lattice.TipForce(jnp.array([0.5, 0.0, 0.0])),
    )  # fmt: skip
    out["rod_dtype"] = str(beam.mass.dtype)
    if which in ("all", "equilibrium"):
        sol = lattice.solve_equilibrium(beam, steps=2)
        out["ok"] = bool(sol.ok)
        out["iterations"] = int(sol.iterations)
        out["tip"] = np.asarray(sol.state.tip, float).tolist()
        out["tip_turn"] = np.asarray(sol.state.theta[-1], float).tolist()
        out["state_dtype"] = str(sol.state.r.dtype)
    if which in ("all", "spectrum"):
        free = beam.with_loads(())
        p = lattice.spectrum(free, free.straight())
        w = np.sort(np.asarray(p.imag, float))
        out["frequencies"] = w[w > 0][:4].tolist()
        out["max_abs_p"] = float(np.max(np.abs(np.asarray(p))))
        out["spectrum_dtype"] = str(p.dtype)
    if which in ("all", "simulate"):
        state0 = lattice.equilibrium(beam, steps=2)
        ts = jnp.linspace(0.0, 1.0, 6)
        traj = lattice.simulate(beam.with_loads(()), state0, ts, rtol=1e-5, atol=1e-5)
        out["tip_x"] = np.asarray(traj.centreline[:, -1, 0], float).tolist()
        out["trajectory_dtype"] = str(traj.states.r.dtype)
        out["energy_drift"] = float(np.ptp(np.asarray(traj.energy, float)))
    print("RESULT " + json.dumps(out))


if __name__ == "__main__":
    main()
