"""Subprocess worker of tests/test_sweep.py (run as ``python tests/_sweep_worker.py MODE ...``).

Modes:
- ``devices OUT``: with XLA_FLAGS=--xla_force_host_platform_device_count=4 set by the parent,
  sweeps on 4 devices and on 1 and writes a JSON report to OUT.
- ``kill STORE``: a slow sweep into STORE (the parent kills it midway).
- ``distributed PORT NPROC PID STORE OUT``: one process of a jax.distributed sweep on localhost.
"""

from __future__ import annotations

import json
import pickle
import sys

import jax

jax.config.update("jax_enable_x64", True)


def devices(out):
    import numpy as np
    from sweep_quantities import NIKOLAI_AXES, NIKOLAI_DIMS, nikolai_abscissa

    from rbo_jax.batch import sweep
    from rbo_jax.batch._chunks import Chunks
    from rbo_jax.batch._space import make_space

    n_dev = jax.local_device_count()
    # Chunks of 6 points, padded to 8 on 4 devices, and chunks of 2 on one device: the same
    # per-device batch (2 points), so the results must be bitwise equal.
    on4 = sweep(nikolai_abscissa, NIKOLAI_AXES, chunk_size=6, dims=NIKOLAI_DIMS, progress=False)
    on1 = sweep(
        nikolai_abscissa, NIKOLAI_AXES, chunk_size=2, dims=NIKOLAI_DIMS, progress=False, devices=1
    )
    # Where do the shards of one chunk live? (Same shape as above: no new compilation.)
    space = make_space(NIKOLAI_AXES, None, 6)
    chunks = Chunks(nikolai_abscissa, space, tuple(jax.local_devices()), NIKOLAI_DIMS)
    values, _ = chunks.launch(0)[4]
    report = {
        "local_devices": n_dev,
        "batch": chunks.batch,
        "strategy": chunks.program.strategy,
        "shard_devices": len(values["abscissa"].sharding.device_set),
        "shard_shapes": [list(s.data.shape) for s in values["abscissa"].addressable_shards],
        "identical": bool(
            all(np.array_equal(on4[v].values, on1[v].values, equal_nan=True) for v in on4.data_vars)
        ),
        "status_counts": on4.attrs["status_counts"],
    }
    with open(out, "w") as f:
        json.dump(report, f)


def kill(store):
    from sweep_quantities import KILL_AXES, KILL_CHUNK, NIKOLAI_DIMS, nikolai_abscissa

    from rbo_jax.batch import sweep

    sweep(
        nikolai_abscissa,
        KILL_AXES,
        chunk_size=KILL_CHUNK,
        dims=NIKOLAI_DIMS,
        store=store,
        progress=False,
    )


def distributed(port, nproc, pid, store, out):
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=f"127.0.0.1:{port}",
        num_processes=int(nproc),
        process_id=int(pid),
        initialization_timeout=60,
    )
    from sweep_quantities import DIST_AXES, DIST_CHUNK, NIKOLAI_DIMS, nikolai_abscissa

    from rbo_jax.batch import sweep

    assert jax.process_count() == int(nproc)
    in_memory = sweep(
        nikolai_abscissa, DIST_AXES, chunk_size=DIST_CHUNK, dims=NIKOLAI_DIMS, progress=False
    )
    stored = sweep(
        nikolai_abscissa,
        DIST_AXES,
        chunk_size=DIST_CHUNK,
        dims=NIKOLAI_DIMS,
        store=store,
        progress=False,
    ).load()
    with open(out, "wb") as f:
        pickle.dump(
            {"in_memory": in_memory, "stored": stored, "process_count": jax.process_count()}, f
        )
    jax.distributed.shutdown()


if __name__ == "__main__":
    mode, *args = sys.argv[1:]
    {"devices": devices, "kill": kill, "distributed": distributed}[mode](*args)
