"""Child process of tests/test_devices.py: ``python _devices_worker.py WHAT OUT.json``. It imports
rbo_jax first (which chooses the number of CPU devices before JAX starts, unless the
environment says otherwise), runs WHAT and writes a JSON report."""

import json
import os
import sys
import time
import warnings


def devices():
    import jax

    import rbo_jax  # noqa: F401  (before any JAX computation; importing jax starts nothing)

    return {
        "devices": len(jax.devices()),
        "platform": jax.devices()[0].platform,
        "cores": len(os.sched_getaffinity(0)),
    }


def started_first():
    """JAX computes before rbo_jax is imported: one device, and the first sweep says so."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    jnp.ones(2).block_until_ready()
    import rbo_jax

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rbo_jax.sweep(lambda x: x * 2.0, {"x": np.arange(4.0)}, progress=False)
        rbo_jax.sweep(lambda x: x * 3.0, {"x": np.arange(4.0)}, progress=False)
    return {"devices": len(jax.devices()), "warnings": [str(w.message) for w in caught]}


def newton_map():
    """The issue's stability map (Newton equilibria, LAPACK eigenvalues) on every local device
    and on one: it must end, and give the same bits."""
    import jax
    import numpy as np

    import rbo_jax as rbo

    axes = {"M": np.linspace(-0.8, 0.8, 40), "c": np.linspace(0.5, 2.0, 40)}

    def model_fn(M, c):
        return rbo.nikolai_model(M, c, 2.0, A3=0.6)

    start = time.perf_counter()
    many = rbo.stability_map(model_fn, axes)
    elapsed = time.perf_counter() - start
    one = rbo.stability_map(model_fn, axes, devices=1)
    return {
        "devices": len(jax.devices()),
        "seconds": elapsed,
        "counts": many.attrs["status_counts"],
        "identical": all(
            np.array_equal(many[v].values, one[v].values, equal_nan=True) for v in many.data_vars
        ),
    }


def chosen_sweep():
    """A sweep after ``import rbo_jax``, whatever RBO_JAX_CPU_DEVICES asked for: the warnings
    it gives."""
    import jax
    import numpy as np

    import rbo_jax

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rbo_jax.sweep(lambda x: x * 2.0, {"x": np.arange(4.0)}, progress=False)
    return {"devices": len(jax.devices()), "warnings": [str(w.message) for w in caught]}


def newton_map_large_chunks():
    """The Newton map in one chunk of 65,536 points over every device (32,768 a device on two):
    lineax's ``lu_solve``, traced only when the program is lowered, held triangular solves of a
    whole share, which jaxlib split over XLA's pool and waited forever. Compared with the
    default chunks on one device."""
    import jax
    import numpy as np

    import rbo_jax as rbo

    axes = {"M": np.linspace(-0.8, 0.8, 256), "c": np.linspace(0.5, 2.0, 256)}

    def model_fn(M, c):
        return rbo.nikolai_model(M, c, 2.0, A3=0.6)

    many = rbo.stability_map(model_fn, axes, chunk_size=65536)
    one = rbo.stability_map(model_fn, axes, devices=1)
    return {
        "devices": len(jax.devices()),
        "counts": many.attrs["status_counts"],
        "identical": all(
            np.array_equal(many[v].values, one[v].values, equal_nan=True) for v in many.data_vars
        ),
    }


def inner_eig():
    """A quantity with a ``vmap`` inside one point (32 eigenproblems of 60 x 60, as the spectra
    of a scan of loads in ``rbo_jax.lattice.critical_load``): jaxlib splits such a call over the
    intra-op pool, which waited forever on every device of the process. It must end, and give
    the one-device bits."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import rbo_jax as rbo

    grid = jnp.arange(60.0)

    def abscissa(x):
        k = jnp.arange(32.0)[:, None, None]
        A = jnp.eye(60) * x + jnp.sin(k + grid[None, :, None] * grid[None, None, :] + x)
        return jnp.max(jax.vmap(jnp.linalg.eigvals)(A).real, axis=-1)

    axes = {"x": np.linspace(0.0, 1.0, 64)}
    many = rbo.sweep(abscissa, axes, progress=False)
    one = rbo.sweep(abscissa, axes, progress=False, devices=1)
    name = next(iter(many.data_vars))
    return {
        "devices": len(jax.devices()),
        "identical": bool(np.array_equal(many[name].values, one[name].values)),
        "finite": bool(np.isfinite(many[name].values).all()),
    }


def partitions():
    """XLA's cuts of a chunk program's loops into tasks (``outer_dimension_partitions``), for
    every device and for one: the cut counts found in each compiled program's text."""
    import re

    import jax
    import jax.numpy as jnp

    from rbo_jax._sharding import compile_program, point_program

    def point(x):  # a loop over a large fusion, per device: 4096 points each
        return jax.lax.fori_loop(0, 3, lambda i, y: jnp.tanh(y * y + x[0]), x[0] * jnp.ones(64))

    found = {}
    for n in (len(jax.devices()), 1):
        traced, layout = point_program(point, 1, jax.devices()[:n], 4096 * n)
        text = compile_program(traced, layout).as_text()
        found[str(n)] = sorted(set(re.findall(r'outer_dimension_partitions":\[([^]]*)\]', text)))
    return {"devices": len(jax.devices()), "found": found}


def fast_sweep():
    """Final states of fast_simulate (refilled lanes) over the device counts of
    ``RBO_TEST_DEVICE_COUNTS`` (default 1, 2 and all local devices) and two chunk sizes: the
    same bits. The tail of a share is compacted from 256 trajectories on here (the default is
    2048), so that some of these sweeps compact and others do not. Each device's share of a
    chunk is recorded (the layout's, every device the same)."""
    import importlib

    import jax
    import jax.numpy as jnp
    import numpy as np

    import rbo_jax as rbo
    from rbo_jax import _sharding

    importlib.import_module("rbo_jax.ensemble._solve").COMPACT_FROM = 256

    k = jnp.array([0.0, 0.0, 1.0])

    def final(M, c):
        model = rbo.nikolai_model(M, c, 2.0, A3=0.5)
        theta0 = (M / 2.0) * k + jnp.array([1e-3, 0.0, 0.0])
        traj = rbo.fast_simulate(
            model, theta0, jnp.zeros(3), jnp.array([0.0, 30.0]), rtol=1e-9, atol=1e-10, throw=False
        )
        return {"theta": traj.theta[-1], "Omega": traj.Omega[-1]}, traj.status

    axes = {"M": np.linspace(0.05, 0.8, 30), "c": np.linspace(0.5, 2.0, 41)}
    counts = os.environ.get("RBO_TEST_DEVICE_COUNTS")
    counts = [int(c) for c in counts.split(",")] if counts else [1, 2, len(jax.devices())]
    runs, shares = {}, {}
    for devices in sorted(set(counts)):
        for chunk in (1230, 500):
            ds = rbo.sweep(final, axes, chunk_size=chunk, devices=devices, progress=False)
            runs[f"{devices}/{chunk}"] = np.concatenate(
                [ds["theta"].values.ravel(), ds["Omega"].values.ravel()]
            )
            layout = _sharding.Layout(jax.local_devices()[:devices], 0, chunk)
            shares[f"{devices}/{chunk}"] = layout.batch // devices
    first = next(iter(runs.values()))
    return {
        "devices": len(jax.devices()),
        "shares": shares,
        "runs": sorted(runs),
        "differ": sorted(k for k, v in runs.items() if not np.array_equal(v, first)),
        "finite": bool(np.isfinite(first).all()),
    }


COLLECTIVE = r"\b(all-to-all|all-gather|all-reduce|collective-permute|reduce-scatter)(-start)?\("


def collectives(hlo: str) -> dict:
    """The collectives of a compiled program's HLO text: how many in all, and how many inside
    a loop (in a ``while``'s body or condition, or a computation they call)."""
    import re

    computations, name = {}, None
    for line in hlo.splitlines():
        head = re.match(r"^(?:ENTRY )?%(\S+) .*\{$", line)
        if head:
            name = head.group(1)
            computations[name] = []
        elif name is not None:
            computations[name].append(line)

    def called(lines, keys="body|condition|calls|to_apply"):
        out = set()
        for line in lines:
            out.update(re.findall(rf"(?:{keys})=%([\w.\-]+)", line))
            for group in re.findall(r"branch_computations=\{([^}]*)\}", line):
                out.update(x.strip().lstrip("%") for x in group.split(","))
        return out

    loops = set()
    stack = list(
        called(
            [ln for lines in computations.values() for ln in lines if " while(" in ln],
            "body|condition",
        )
    )
    while stack:
        name = stack.pop()
        if name in computations and name not in loops:
            loops.add(name)
            stack.extend(called(computations[name]))
    return {
        "all": len(re.findall(COLLECTIVE, hlo)),
        "in_loops": sum(len(re.findall(COLLECTIVE, "\n".join(computations[c]))) for c in loops),
        "loops": len(loops),
    }


def sharded_vmap():
    """``jax.jit(jax.vmap(fast_simulate))`` on inputs sharded over every device (a
    ``NamedSharding``), and replicated on them (a batch that is not a multiple of the devices:
    padded), against the same batch on one device: the same bits, and outputs sharded like the
    inputs. The queue is ordered longest first and the tails compacted from 512 and 256
    trajectories on here (the defaults are 2048), so that one device's run and the shares of 2
    devices take those paths and the shares of 4 do not. ``RBO_TEST_EAGER=1`` also runs the
    sharded batch under ``jax.vmap`` without ``jit``, and one with a time grid a trajectory."""
    import importlib

    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    import rbo_jax as rbo

    importlib.import_module("rbo_jax.ensemble._queue").ORDER_FROM = 512
    importlib.import_module("rbo_jax.ensemble._solve").COMPACT_FROM = 256
    k = jnp.array([0.0, 0.0, 1.0])

    def final(M, c, ts):
        model = rbo.nikolai_model(M, c, 2.0, A3=0.5)
        theta0 = (M / 2.0) * k + jnp.array([1e-3, 0.0, 0.0])
        traj = rbo.fast_simulate(
            model, theta0, jnp.zeros(3), ts, rtol=1e-9, atol=1e-10, throw=False
        )
        return traj.theta, traj.Omega, traj.num_steps

    M, c = (a.ravel() for a in np.meshgrid(np.linspace(0.05, 0.8, 30), np.linspace(0.5, 2.0, 41)))
    ts = jnp.array([0.0, 7.5, 30.0])
    mesh = Mesh(np.array(jax.devices()), ("batch",))
    n = len(jax.devices())
    cut = len(M) // (16 * n) * (16 * n)  # a multiple of every device count tested
    run = jax.jit(jax.vmap(final, in_axes=(0, 0, None)))
    one = run(jnp.asarray(M), jnp.asarray(c), ts)
    spread = NamedSharding(mesh, P("batch"))
    args = (jax.device_put(M[:cut], spread), jax.device_put(c[:cut], spread), ts)
    compiled = run.lower(*args).compile()
    sharded = compiled(*args)
    everywhere = NamedSharding(mesh, P())
    padded = run(jax.device_put(M, everywhere), jax.device_put(c, everywhere), ts)
    runs = {"sharded": [a[:cut] for a in one], "padded": list(one)}
    got = {"sharded": sharded, "padded": padded}
    if os.environ.get("RBO_TEST_EAGER"):
        eager = jax.vmap(final, in_axes=(0, 0, None))
        got["eager"] = eager(jax.device_put(M[:cut], spread), jax.device_put(c[:cut], spread), ts)
        runs["eager"] = runs["sharded"]
        grids = jnp.asarray(np.linspace(0.0, 1.0, cut)[:, None] * 2.0) + ts[None, :]
        per = jax.jit(jax.vmap(final))
        got["per-trajectory times"] = per(
            jax.device_put(M[:cut], spread), jax.device_put(c[:cut], spread), grids
        )
        runs["per-trajectory times"] = per(jnp.asarray(M[:cut]), jnp.asarray(c[:cut]), grids)
    return {
        "devices": n,
        "collectives": collectives(compiled.as_text()),
        "points": [len(M), cut],
        "differ": sorted(
            name
            for name in got
            if not all(np.array_equal(a, b) for a, b in zip(got[name], runs[name]))
        ),
        "spread": {name: len(out[0].sharding.device_set) for name, out in got.items()},
        "finite": bool(np.isfinite(np.asarray(one[0])).all()),
        "steps": int(np.asarray(one[2]).sum()),
    }


if __name__ == "__main__":
    what, out = sys.argv[1], sys.argv[2]
    report = globals()[what]()
    with open(out, "w") as f:
        json.dump(report, f)
