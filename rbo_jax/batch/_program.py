"""The compiled program of a sweep: one chunk, split over the local devices.

Each device runs the quantity on its shard of the chunk, with no communication between devices:
``jit(shard_map(local))`` over a 1-D mesh of the devices, ``local`` the quantity batched over the
device's points. (Plain ``jit`` over a ``NamedSharding`` is avoided: GSPMD partitions the
adaptive ``while_loop`` of a vmapped solve into one loop synchronised across devices at every
step, ~80x slower, diffrax#407, jax#20968.)

**From one point's jaxpr.** The quantity is traced once, for one point (``jax.make_jaxpr``), and
the program is that jaxpr batched (``jaxpr_as_fun`` under ``vmap``) and sharded. Library code
that transforms functions while it is traced — lineax's closure conversion in a Newton solve
(:func:`rbo_jax.solve_equilibrium`), which cannot be traced inside ``shard_map`` (lineax#185) —
has then done its work before ``shard_map`` sees the program, so every quantity runs sharded
the same way (these quantities used to run as GSPMD ``jit`` with a collective in every Newton
step). A quantity that ``shard_map`` still refuses runs on one device, with a warning that says
so.

**LAPACK in blocks** (:func:`block_size`). XLA's CPU runtime runs LAPACK custom calls (``eig``,
``lu``, triangular solves, ...) on its intra-op thread pool, and jaxlib's kernels split a large
batch of matrices into tasks on that same pool and block until they finish
(``jaxlib/cpu/lapack_kernels.cc``: ``ParallelBatchMap``; a batch is split when batch × cost ≥
200 000 flop). With one device per core every pool thread can be a device's program blocked in
such a kernel, waiting for tasks that no thread is left to run: a 100 × 100 stability map on 2
or 4 CPU devices waited forever at 0 % CPU (issue 31; native stacks: every ``tf_XLAEigen``
thread in ``BlockingCounter::Wait`` under ``lapack_dgeev_ffi``). While a chunk program is traced,
the batching rules of the LAPACK primitives are therefore replaced by ones that run a batch in
blocks small enough that no kernel is ever split (:func:`lapack_in_blocks`); the rest of the
quantity stays one ``vmap`` over the device's points. A program for several devices is also
lowered under them (:func:`rbo_jax._sharding.compile_program`): lineax's linear solve traces
its batched ``lu_solve`` only then, and a Newton map's chunk of 65,536 points on 2 devices
waited forever in ``lapack_dtrsm_ffi`` when it was lowered outside.

**The same bits on any number of devices.** A point's value must not depend on where it sits in
the batch: XLA's CPU code rounds some fused expressions differently in the scalar remainder of a
vectorised loop than in its vector body. Each device's share of a chunk is therefore a multiple
of :data:`VECTOR` points, so that no point falls in a scalar remainder, whatever the number of
devices and however the points are dealt to them (the refilled lanes of
:func:`rbo_jax.fast_simulate` follow the same rule, ``ensemble/_solve.py``); LAPACK computes each
matrix alone, whatever the block.

**Every core busy.** The points of a chunk are dealt to the devices one by one
(:func:`rbo_jax._sharding.deal`: neighbouring grid points cost alike, so contiguous shares left
one device waiting for the other at every chunk), and a program for several CPU devices is
compiled without XLA's cut of its loops into tasks for the intra-op threads
(:func:`rbo_jax._sharding.compile_options`: those tasks only queue behind the other devices'
work).

Every call has the same shape (a partial chunk is padded), so one compilation serves a sweep;
programs are cached on what the quantity computes (:func:`rbo_jax._callables.callable_key`: its
code, closure, defaults and globals, so a new but identical lambda is the same quantity), the
parameter names, the devices and the chunk size, so repeated sweeps of the same quantity compile
once. With the program store on (:func:`rbo_jax.enable_compilation_cache`) the per-device program
is exported there (``jax.export``) with its output structure and layout, keyed on
:func:`rbo_jax._callables.stable_text` of the quantity and the number of devices, so a second
process loads it instead of tracing it (the loaded program runs under ``shard_map`` like a traced
one); a quantity that cannot be named across processes (a closure over an object of no covered
module), or one that cannot be exported (a host callback), is traced as usual.
"""

from __future__ import annotations

import ast
import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from .. import _programs
from .._callables import callable_key, stable_text
from .._sharding import (
    BATCH_AXIS,
    VECTOR,
    Layout,
    compile_program,
    lapack_in_blocks,
    point_layout,
    sharded,
)
from ._output import describe_output, encode_output, split_output

__all__ = ["BATCH_AXIS", "VECTOR", "Program", "local_devices", "point_function", "program"]


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
    left to compute compiles nothing). ``traced`` is a traced jitted function, or the jitted
    ``shard_map`` of a program from the program store (:mod:`rbo_jax._programs`), traced and
    compiled on the first call. ``strategy``: ``"shard_map"``, or ``"one device"`` for a quantity
    that ``shard_map`` refused."""

    def __init__(
        self, traced, layout: Layout, structure: dict, strategy: str, x=None, options=None
    ):
        self.traced, self.layout = traced, layout
        self.sharding, self.batch, self.block = layout.sharding, layout.batch, layout.block
        self.devices = layout.devices
        self.structure = structure  # the output structure recorded while tracing
        self.strategy = strategy
        self._x = x  # the argument's shape, dtype and sharding, for a stored program
        self.options = options  # XLA's options (_compile_options)
        self._compiled = None

    def call(self, x):
        if self._compiled is None:
            traced = self.traced if self._x is None else self.traced.trace(self._x)
            self._compiled = compile_program(traced, self.layout, self.options)
        return self._compiled(x)


def _store_key(quantity, names, devices, chunk_points) -> str | None:
    """The program store's key of a chunk program (``None``: store off, or a quantity that
    cannot be named across processes)."""
    if _programs.program_store() is None:
        return None
    text = stable_text(quantity)
    if text is None:
        return None
    return _programs.program_key(
        repr(
            (
                # 3: traced with LAPACK in blocks inside the point too; 4: each call's own block;
                # 5: fast_simulate's lanes from the batch's size (ensemble._solve.lane_count)
                "rbo_jax.batch chunk 5",
                text,
                names,
                chunk_points,
                len(devices),
                str(jnp.result_type(float)),
                devices[0].platform,
            )
        )
    )


def _stored_program(key, quantity, names, devices, chunk_points) -> Program | None:
    """The chunk program from the store, exported there first if missing (``None``: it cannot
    be exported, e.g. a host callback in the quantity)."""
    found = _programs.load(key)
    if found is None and not _programs.unexportable(key):
        local, layout, record = _point_layout(quantity, names, devices, chunk_points)
        try:
            with lapack_in_blocks(layout.block):
                exported = jax.export.export(jax.jit(local))(layout.local_x(len(names)))
        except Exception:  # not exportable: the caller traces it
            _programs.unexportable(key, mark=True)
            return None
        meta = repr((dict(record), layout.block))
        _programs.save(key, exported, meta)
        found = exported, meta
    if found is None:
        return None
    exported, meta = found
    structure, block = ast.literal_eval(meta)
    layout = Layout(devices, block, chunk_points)

    def chunk_program(xs):  # the name in JAX's logs and persistent cache
        return exported.call(xs)

    call = sharded(chunk_program, layout.mesh)
    options = _compile_options(quantity)
    return Program(call, layout, structure, "shard_map", layout.x(len(names)), options)


def _point_layout(quantity, names, devices, chunk_points):
    """:func:`point_layout` of the quantity, and the output structure recorded in tracing it."""
    record: dict = {}
    point = point_function(quantity, names, record)
    return (*point_layout(point, len(names), devices, chunk_points), record)


def _compile_options(quantity) -> dict | None:
    """XLA's options for the chunk program of ``quantity``: :func:`rbo_jax._programs.
    small_program_options` for a quantity marked ``small_program`` (a critical load's Newton
    loops and eigenproblems, :mod:`._maps`: they compile faster and run as fast), XLA's
    defaults otherwise (a vmapped DOP853 runs slower with the former; a stability map's
    eigenvalues on several devices differed from one device's by rounding)."""
    return _programs.small_program_options() if getattr(quantity, "small_program", False) else None


def _compile_program(quantity, names, devices, chunk_points) -> Program:
    key = _store_key(quantity, names, devices, chunk_points)
    if key is not None:
        found = _stored_program(key, quantity, names, devices, chunk_points)
        if found is not None:
            return found
    local, layout, record = _point_layout(quantity, names, devices, chunk_points)
    try:
        with lapack_in_blocks(layout.block):
            traced = sharded(local, layout.mesh).trace(layout.x(len(names)))
        return Program(traced, layout, dict(record), "shard_map", None, _compile_options(quantity))
    except Exception as e:  # shard_map refused the quantity: one device, said so
        if len(devices) == 1:
            raise
        warnings.warn(
            f"rbo_jax.sweep: this quantity cannot run under shard_map over {len(devices)} "
            f"devices ({type(e).__name__}: {str(e)[:200]}); its chunks run on one device, "
            f"{devices[0]}.",
            RuntimeWarning,
            stacklevel=2,
        )
        layout = Layout(devices[:1], layout.block, chunk_points)
        traced = jax.jit(local, in_shardings=layout.sharding, out_shardings=layout.sharding)
        with lapack_in_blocks(layout.block):
            traced = traced.trace(layout.x(len(names)))
        return Program(traced, layout, dict(record), "one device", None, _compile_options(quantity))


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
def _cached_program(quantity: _Quantity, names, devices, chunk_points) -> Program:
    return _compile_program(quantity.fn, names, devices, chunk_points)


def program(quantity, names, devices, chunk_points) -> Program:
    """The program of ``quantity`` for chunks of ``chunk_points`` points over ``devices``
    (its ``batch`` is the padded chunk), cached on what the quantity computes, not on the
    object: a new but identical lambda (a notebook cell run again) reuses the compiled program.
    With the program store on, a second process loads it instead of tracing it."""
    return _cached_program(_Quantity(quantity), tuple(names), tuple(devices), int(chunk_points))


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
