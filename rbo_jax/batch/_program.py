"""The compiled program of a sweep: ``jit(shard_map(vmap(quantity)))`` over one chunk.

Each device runs the vmapped quantity on its shard of the chunk with no communication. (Plain
``jit`` over a ``NamedSharding`` is avoided on purpose: the adaptive ``while_loop`` of a vmapped
ODE solve is then partitioned by GSPMD into one loop synchronised across shards at every step,
reported ~80x slower — diffrax#407, jax#20968.) One exception: a quantity that lineax cannot solve
inside ``shard_map`` (lineax#185; e.g. the Newton solve of :func:`rbo_jax.solve_equilibrium`) is
compiled as ``jit`` over the sharded batch instead; its few Newton steps then run in lock-step
across devices, which costs little.

Every call has the same shape (a partial chunk is padded), so one compilation serves a sweep;
programs are cached on the quantity, the parameter names, the devices and the batch size, so
repeated sweeps of the same quantity compile once.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from ._output import describe_output, encode_output, split_output

BATCH_AXIS = "batch"


def point_function(quantity, names, record: dict):
    """``point(x) -> (values as arrays, int32 status code)``; records the output structure in
    ``record`` when traced."""

    def point(x):
        values, status = split_output(quantity(**{n: x[i] for i, n in enumerate(names)}))
        record.update(describe_output(values, status))
        return encode_output(values, status)

    return point


class Program:
    """One chunk program: ``call(points sharded over the batch) -> (values, status)``. Traced at
    once (which gives the output ``structure``), compiled on the first call (a sweep with nothing
    left to compute compiles nothing)."""

    def __init__(self, traced, sharding: NamedSharding, batch: int, structure: dict,
                 strategy: str):
        self.traced, self.sharding, self.batch = traced, sharding, batch
        self.structure = structure  # the output structure recorded while tracing
        self.strategy = strategy  # "shard_map", or "jit" for what shard_map cannot trace
        self._compiled = None

    def call(self, x):
        if self._compiled is None:
            self._compiled = self.traced.lower().compile()
        return self._compiled(x)


def _compile_program(quantity, names, devices, batch) -> Program:
    mesh = jax.sharding.Mesh(np.array(devices, dtype=object), (BATCH_AXIS,))
    sharding = NamedSharding(mesh, P(BATCH_AXIS))
    x = jax.ShapeDtypeStruct((batch, len(names)), jnp.result_type(float), sharding=sharding)
    record: dict = {}
    batched = jax.vmap(point_function(quantity, names, record))
    # check_vma=False: the body has no collectives, and user quantities may hold callbacks or
    # custom rules that the varying-manual-axes checker does not know.
    sharded = jax.shard_map(batched, mesh=mesh, in_specs=P(BATCH_AXIS),
                            out_specs=P(BATCH_AXIS), check_vma=False)
    try:
        traced, strategy = jax.jit(sharded).trace(x), "shard_map"
    except Exception:
        # lineax cannot yet be traced inside shard_map (patrick-kidger/lineax#185): plain jit
        # over the sharded batch. A user error raises again here, unchanged.
        record.clear()
        fn = jax.jit(batched, in_shardings=sharding, out_shardings=sharding)
        traced, strategy = fn.trace(x), "jit"
    return Program(traced, sharding, batch, dict(record), strategy)


_cached_program = functools.lru_cache(maxsize=32)(_compile_program)


def program(quantity, names, devices, batch) -> Program:
    """The program of ``quantity`` (cached when the quantity is hashable)."""
    try:
        hash(quantity)
    except TypeError:
        return _compile_program(quantity, names, devices, batch)
    return _cached_program(quantity, names, devices, batch)


def local_devices(devices) -> tuple:
    """All local devices (``None``), the first ``n`` of them, or the given ones."""
    local = jax.local_devices()
    if devices is None:
        return tuple(local)
    if isinstance(devices, (int, np.integer)) and not isinstance(devices, bool):
        if not 1 <= devices <= len(local):
            raise ValueError(f"devices={devices}: this process has {len(local)} local device(s).")
        return tuple(local[:devices])
    devices = tuple(devices)
    if not devices or any(d not in local for d in devices):
        raise ValueError("devices must be a non-empty subset of jax.local_devices().")
    return devices
