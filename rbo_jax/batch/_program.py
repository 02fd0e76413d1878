"""The compiled program of a sweep: ``jit(shard_map(vmap(quantity)))`` over one chunk.

Each device runs the vmapped quantity on its shard of the chunk with no communication. (Plain
``jit`` over a ``NamedSharding`` is avoided on purpose: the adaptive ``while_loop`` of a vmapped
ODE solve is then partitioned by GSPMD into one loop synchronised across shards at every step,
reported ~80x slower — diffrax#407, jax#20968.) One exception: a quantity that lineax cannot solve
inside ``shard_map`` (lineax#185; e.g. the Newton solve of :func:`rbo_jax.solve_equilibrium`) is
compiled as ``jit`` over the sharded batch instead; its few Newton steps then run in lock-step
across devices, which costs little.

Every call has the same shape (a partial chunk is padded), so one compilation serves a sweep;
programs are cached on what the quantity computes (:func:`rbo_jax._callables.callable_key`: its
code, closure, defaults and globals, so a new but identical lambda is the same quantity), the
parameter names, the devices and the batch size, so repeated sweeps of the same quantity compile
once. With the program store on (:func:`rbo_jax.enable_compilation_cache`) a single-device
program is exported there (``jax.export``) with its output structure, keyed on
:func:`rbo_jax._callables.stable_text` of the quantity, so a second process loads it instead of
tracing it; a quantity that cannot be named across processes (a closure over an object of no
covered module), or one that cannot be exported (a host callback), is traced as usual.
"""

from __future__ import annotations

import ast
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from .. import _programs
from .._callables import callable_key, stable_text
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
    left to compute compiles nothing). ``traced`` is a traced jitted function, or the jitted call
    of a program from the program store (:mod:`rbo_jax._programs`), compiled the same way."""

    def __init__(
        self, traced, sharding: NamedSharding, batch: int, structure: dict, strategy: str, x=None
    ):
        self.traced, self.sharding, self.batch = traced, sharding, batch
        self.structure = structure  # the output structure recorded while tracing
        self.strategy = strategy  # "shard_map", or "jit" for what shard_map cannot trace
        self._x = x  # the argument's shape, dtype and sharding, for a stored program
        self._compiled = None

    def call(self, x):
        if self._compiled is None:
            traced = self.traced if self._x is None else self.traced.trace(self._x)
            self._compiled = traced.lower().compile()
        return self._compiled(x)


def _functions(quantity, names, devices, batch):
    """The argument and the two jitted chunk functions (``shard_map`` and plain ``jit``), with
    the record that their tracing fills."""
    mesh = jax.sharding.Mesh(np.array(devices, dtype=object), (BATCH_AXIS,))
    sharding = NamedSharding(mesh, P(BATCH_AXIS))
    x = jax.ShapeDtypeStruct((batch, len(names)), jnp.result_type(float), sharding=sharding)
    record: dict = {}
    batched = jax.vmap(point_function(quantity, names, record))
    # check_vma=False: the body has no collectives, and user quantities may hold callbacks or
    # custom rules that the varying-manual-axes checker does not know.
    sharded = jax.shard_map(
        batched, mesh=mesh, in_specs=P(BATCH_AXIS), out_specs=P(BATCH_AXIS), check_vma=False
    )
    functions = {
        "shard_map": jax.jit(sharded),
        "jit": jax.jit(batched, in_shardings=sharding, out_shardings=sharding),
    }
    return x, sharding, record, functions


def _trace(x, record, functions, how):
    """``how(jitted)(x)`` with the shard_map program, else (lineax cannot yet be traced inside
    shard_map, patrick-kidger/lineax#185) with plain jit over the sharded batch: ``(result,
    strategy)``. A user error raises again with the second, unchanged."""
    for strategy in ("shard_map", "jit"):
        record.clear()
        try:
            return how(functions[strategy])(x), strategy
        except Exception:
            if strategy == "jit":
                raise
    raise AssertionError("unreachable")


def _store_key(quantity, names, devices, batch) -> str | None:
    """The program store's key of a chunk program (``None``: store off, or a quantity that
    cannot be named across processes, or several devices, whose programs are not stored)."""
    if _programs.program_store() is None or len(devices) != 1:
        return None
    text = stable_text(quantity)
    if text is None:
        return None
    return _programs.program_key(
        repr(
            (
                "rbo_jax.batch chunk",
                text,
                names,
                batch,
                str(jnp.result_type(float)),
                devices[0].platform,
            )
        )
    )


def _stored_program(key, x, sharding, record, functions, batch) -> Program | None:
    """The chunk program from the store, exported there first if missing (``None``: it cannot
    be exported, e.g. a host callback in the quantity)."""
    found = _programs.load(key)
    if found is None and not _programs.unexportable(key):
        try:
            exported, strategy = _trace(x, record, functions, jax.export.export)
        except Exception:  # not exportable, or a user error: the plain trace tells them apart
            return None
        meta = repr((dict(record), strategy))
        _programs.save(key, exported, meta)
        found = exported, meta
    if found is None:
        return None
    exported, meta = found
    structure, strategy = ast.literal_eval(meta)
    call = _programs.call_of(exported, "chunk_program")
    return Program(call, sharding, batch, structure, strategy, x)


def _compile_program(quantity, names, devices, batch) -> Program:
    x, sharding, record, functions = _functions(quantity, names, devices, batch)
    key = _store_key(quantity, names, devices, batch)
    if key is not None:
        found = _stored_program(key, x, sharding, record, functions, batch)
        if found is not None:
            return found
        # new functions: jit would answer the trace of a failed export from its cache, without
        # running the quantity, which records the output structure
        x, sharding, record, functions = _functions(quantity, names, devices, batch)
    traced, strategy = _trace(x, record, functions, lambda f: f.trace)
    if key is not None and not _programs.unexportable(key):
        _programs.unexportable(key, mark=True)  # traced fine, but jax.export refused it
    return Program(traced, sharding, batch, dict(record), strategy)


class _Quantity:
    """A quantity compared by what it computes (:func:`rbo_jax._callables.callable_key`),
    carrying the first of the equal ones."""

    __slots__ = ("fn", "key")

    def __init__(self, fn):
        self.fn, self.key = fn, callable_key(fn)

    def __hash__(self):
        return hash(self.key)

    def __eq__(self, other):
        return isinstance(other, _Quantity) and self.key == other.key


@functools.lru_cache(maxsize=32)
def _cached_program(quantity: _Quantity, names, devices, batch) -> Program:
    return _compile_program(quantity.fn, names, devices, batch)


def program(quantity, names, devices, batch) -> Program:
    """The program of ``quantity``, cached on what the quantity computes, not on the object: a
    new but identical lambda (a notebook cell run again) reuses the compiled program. With the
    program store on, a second process loads it instead of tracing it."""
    return _cached_program(_Quantity(quantity), names, devices, batch)


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
