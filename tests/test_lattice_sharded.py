"""A chain's DOP853 step on halo-extended segments (rbo_jax/lattice/_halo.py): in blocks on one
device and split over several CPU devices (a child process that asks JAX for them before it
starts), against the plain program on whole arrays: the same accepted steps, the same states to
rounding."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import rbo_jax
from rbo_jax import lattice as L
from rbo_jax.lattice._halo import Halo, Whole
from rbo_jax.lattice._integrate import Config, Problem, solve

K = np.array([0.0, 0.0, 1.0])
CFG = Config(1e-8, 1e-10, 10_000, 1e-3, True, 0.5)


def chain(n, periodic):
    body = rbo_jax.RigidBodyOscillator(
        rbo_jax.transversely_isotropic_inertia(1.0, 0.6, K),
        rbo_jax.QuadraticFoundation(1.0, 2.0, K),
        [rbo_jax.FollowerMoment(0.2, K)],
    )
    return L.chain(n, body, rbo_jax.QuadraticFoundation(0.7, 0.3, K), periodic=periodic)


def start(n, seed=0):
    rng = np.random.default_rng(seed)
    x = 6.0 * np.pi * np.arange(n) / n
    theta = 0.3 * np.stack([np.sin(x), np.cos(x), np.full(n, 0.1)], 1)
    theta = theta + 1e-3 * rng.standard_normal((n, 3))
    return theta, 1e-2 * rng.standard_normal((n, 3))


@pytest.mark.slow  # large size: cache blocks of a large chain
@pytest.mark.parametrize("periodic", [True, False])
def test_blocks_match_whole_arrays(periodic):
    """Blocks of 24 bodies (the last overlapping its neighbour) on a chain of 100, with
    samples (the dense output's stages) against the whole-array program."""
    n = 100
    lat = chain(n, periodic)
    theta, Omega = start(n)
    y0 = tuple(jnp.asarray(np.concatenate([theta.T, Omega.T])))
    ts = jnp.linspace(0.0, 1.5, 4)
    run = eqx.filter_jit(lambda p, y, ts, plan: solve(p, y, ts, CFG, plan))
    a = run(Problem.of(lat), y0, ts, Whole(n))
    b = run(Problem.of(lat), y0, ts, Halo(n, n, periodic, 24))
    assert int(a["status"]) == int(b["status"]) == 0
    assert int(a["num_steps"]) == int(b["num_steps"])
    np.testing.assert_allclose(b["samples"], a["samples"], rtol=0, atol=1e-14)


W = 2.0


def spinning(n, seed=3):
    """A Kelvin chain (no foundation) spinning at W about e_x, transverse to its turn-vectors
    near 0, with noise: its bodies come near |θ| = 2π off the plane at different steps."""
    site = rbo_jax.RigidBodyOscillator(
        rbo_jax.transversely_isotropic_inertia(1.0, 0.6, K), rbo_jax.ZeroFoundation()
    )
    lat = L.chain(n, site, rbo_jax.QuadraticFoundation(0.9, 0.4, K))
    rng = np.random.default_rng(seed)
    theta = np.tile([0.0, 2e-4, 0.0], (n, 1)) + 1e-5 * rng.standard_normal((n, 3))
    Omega = np.tile([W, 0.0, 0.0], (n, 1)) + 1e-3 * rng.standard_normal((n, 3))
    return lat, theta, Omega


@pytest.mark.slow  # cost: ~14-19 s, the whole-array and the blocked programs compiled
def test_blocks_recentre_as_whole_arrays():
    """Re-centring (the re-centred turn-vector of a body off the plane near |θ| = 2π, the
    integrators' module docstring) decided in blocks: a uniform spin transverse to θ (every body
    alike, the couplings idle) with noise so that the bodies cross the sphere at different
    steps; blocks of 15 on a periodic chain of 40 (the last overlapping its neighbour) re-centre
    the same bodies at the same steps as the whole-array program, and a body's turn-tensor
    stays near the free rotation's (to 1e-2: the noise, 1e-3 in Ω, sets the couplings to work)."""
    n, w = 40, W
    lat, theta, Omega = spinning(n)
    y0 = tuple(jnp.asarray(np.concatenate([theta.T, Omega.T])))
    ts = jnp.linspace(0.0, 6.0, 5)
    cfg = Config(1e-10, 1e-12, 10_000, 1e-3, True, 0.5)
    run = eqx.filter_jit(lambda p, y, ts, plan: solve(p, y, ts, cfg, plan))
    a = run(Problem.of(lat), y0, ts, Whole(n))
    b = run(Problem.of(lat), y0, ts, Halo(n, n, True, 15))
    assert int(a["status"]) == int(b["status"]) == 0
    assert int(a["num_steps"]) == int(b["num_steps"])
    assert int(a["num_recentred"]) == int(b["num_recentred"]) >= n
    np.testing.assert_array_equal(b["turns"], a["turns"])
    np.testing.assert_allclose(b["samples"], a["samples"], rtol=0, atol=1e-12)
    exact = rbo_jax.turn_tensor(theta[0]) @ rbo_jax.turn_tensor(w * 6.0 * np.eye(3)[0])
    np.testing.assert_allclose(rbo_jax.turn_tensor(b["samples"][-1, 0, :3]), exact, atol=1e-2)


def test_devices_are_checked():
    lat = chain(64, True)
    theta, Omega = start(64)
    ts = np.array([0.0, 0.1])
    with pytest.raises(ValueError, match="devices"):
        L.simulate(lat, theta, Omega, ts, devices=0)
    grid = L.grid((8, 8), lat.body, lat.coupling)
    if len(__import__("jax").local_devices()) > 1:
        with pytest.raises(ValueError, match="chain"):
            L.simulate(grid, theta.reshape(8, 8, 3), Omega.reshape(8, 8, 3), ts, devices=2)
    # one device is always fine
    assert L.simulate(lat, theta, Omega, ts, devices=1).ok


CHILD = textwrap.dedent(
    """
    import json, sys
    import jax
    jax.config.update("jax_num_cpu_devices", {d})
    import numpy as np
    sys.path.insert(0, {here!r})
    from test_lattice_sharded import chain, spinning, start
    from rbo_jax import lattice as L
    out = {{"devices": len(jax.local_devices())}}
    for periodic in (True, False):
        lat = chain(64, periodic)
        theta, Omega = start(64)
        ts = np.linspace(0.0, 1.5, 4)
        one = L.simulate(lat, theta, Omega, ts, devices=1)
        many = L.simulate(lat, theta, Omega, ts, devices={d})
        out[str(periodic)] = dict(
            steps=[int(one.num_steps), int(many.num_steps)],
            ok=[bool(one.ok), bool(many.ok)],
            diff=max(float(np.max(np.abs(np.asarray(one.theta) - np.asarray(many.theta)))),
                     float(np.max(np.abs(np.asarray(one.Omega) - np.asarray(many.Omega))))),
            scale=float(np.max(np.abs(one.theta))),
            shards=len(many.theta.sharding.device_set),
        )
    lat, theta, Omega = spinning(64)
    ts = np.linspace(0.0, 6.0, 5)
    one = L.simulate(lat, theta, Omega, ts, rtol=1e-10, atol=1e-12, devices=1)
    many = L.simulate(lat, theta, Omega, ts, rtol=1e-10, atol=1e-12, devices={d})
    out["recentred"] = dict(
        count=[int(one.num_recentred), int(many.num_recentred)],
        steps=[int(one.num_steps), int(many.num_steps)],
        turns=bool(np.array_equal(np.asarray(one.turns), np.asarray(many.turns))),
        diff=float(np.max(np.abs(np.asarray(one.theta) - np.asarray(many.theta)))),
    )
    print(json.dumps(out))
    """
)


@pytest.mark.slow  # cost: ~15 s a process, a chain split over devices
@pytest.mark.parametrize("d", [2, 4])
def test_split_over_devices(d):
    """A chain of 64 bodies, periodic and open, on ``d`` CPU devices against one device: the
    same steps, the states to 1e-13 relative (the error norm is summed in another order)."""
    here = os.path.dirname(os.path.abspath(__file__))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [os.path.dirname(here)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    )
    proc = subprocess.run(
        [sys.executable, "-c", CHILD.format(d=d, here=here)],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["devices"] == d
    for periodic in ("True", "False"):
        r = out[periodic]
        assert r["ok"] == [True, True]
        assert r["steps"][0] == r["steps"][1]
        assert r["shards"] == d
        assert r["diff"] <= 1e-13 * r["scale"]
    r = out["recentred"]  # re-centring decided on the shards: the same bodies at the same steps
    assert r["count"][0] == r["count"][1] >= 64 and r["steps"][0] == r["steps"][1]
    assert r["turns"] and r["diff"] <= 1e-11
