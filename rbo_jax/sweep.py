r"""Parameter sweeps at scale: batched, memory-bounded, sharded over devices and hosts, resumable.

:func:`sweep` evaluates a user's *quantity* — any function of one parameter point, e.g. the final
state of :func:`rbo_jax.simulate`, an energy drift, the spectral abscissa of an equilibrium — on a
grid of named axes (their Cartesian product) or on a list of points, and returns a labelled
:class:`xarray.Dataset` (the container of :func:`rbo_jax.stability_map`).

How it runs:

- **Chunks.** The points are cut into chunks of at most ``chunk_size`` points (hyper-rectangular
  blocks of the grid); each chunk is one call of ``jit(shard_map(vmap(quantity)))``, so device
  memory is O(``chunk_size``). Every call has the same shape — the last, partial chunks are padded
  with a valid point, not recompiled — so one compilation serves the whole sweep.
- **Devices.** The batch axis of a chunk is split over all local devices with
  :func:`jax.shard_map`: each device runs its own vmapped program on its shard, with no
  communication. (Plain ``jit`` over a ``NamedSharding`` is avoided on purpose: the adaptive
  ``while_loop`` of a vmapped ODE solve is then partitioned by GSPMD into one loop synchronised
  across shards at every step, reported ~80x slower — diffrax#407, jax#20968.) One exception:
  a quantity that lineax cannot solve inside ``shard_map`` (lineax#185; e.g. the Newton solve of
  :func:`rbo_jax.solve_equilibrium`) is compiled as ``jit`` over the sharded batch instead; its
  few Newton steps then run in lock-step across devices, which costs little.
- **Hosts.** After ``jax.distributed.initialize(...)`` every process takes its share of the
  chunks (round robin), computes them on its local devices independently (no lock-step between
  hosts) and writes them to its own chunks of the store (which must then be on a file system all
  hosts see); without a store the results are gathered with
  :func:`jax.experimental.multihost_utils.process_allgather` (on CPU through the gloo
  collectives). Process 0 creates the store; barriers are
  :func:`jax.experimental.multihost_utils.sync_global_devices`.
- **Storage.** With ``store=PATH`` each chunk is written, as soon as it is computed, to a
  `Zarr <https://zarr.dev>`_ (format 3) store laid out as xarray writes one: one array per
  variable on the grid dimensions, zarr chunks equal to sweep chunks, so every chunk is exactly
  one file per variable (atomic writes by zarr; no two processes ever write the same file).
  A chunk counts as done once its marker in the hidden group ``_sweep`` is set, after its data.
  ``xarray.open_zarr(PATH)`` reads the result; :func:`open_sweep` checks it is complete.
  ``resume=True`` recomputes only the chunks without a marker; the store then ends byte for byte
  identical to an uninterrupted run's.
- **Bad points** never stop the sweep. Each point carries a ``status``: the quantity returns
  ``(values, status)`` with ``status`` an :class:`equinox.Enumeration` item (typically
  :class:`rbo_jax.SolveStatus` from ``simulate(..., throw=False)``: ``max_steps_reached``,
  ``singular_point``, ``domain_error``, ...; or :class:`rbo_jax.EquilibriumStatus`) or an integer
  code of :class:`rbo_jax.SolveStatus`. Points with a non-finite parameter are not evaluated at all
  (they would raise in the models' constructors); they get ``nonfinite_input`` and NaN values.
  :func:`status_counts` counts the statuses (also stored in ``ds.attrs["status_counts"]``).

The declarative front end of ``rbo-jax sweep CONFIG.toml`` is :mod:`rbo_jax.sweep_config`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from .simulate import SolveStatus

__all__ = [
    "sweep",
    "open_sweep",
    "status_counts",
    "SweepError",
    "plot_sweep",
]

_FORMAT = "rbo_jax.sweep"
_FORMAT_VERSION = 1
_META = "_sweep"  # hidden subgroup of the store (markers); xarray does not open subgroups
_POINT_DIM = "point"
_BATCH_AXIS = "batch"
_NONFINITE = "nonfinite_input"


class SweepError(RuntimeError):
    """A sweep could not be completed (a chunk raised, a store does not match, ...)."""


# ---------------------------------------------------------------------------------------------
# The parameter space: a grid (Cartesian product of axes) or a list of points, cut in chunks.
# ---------------------------------------------------------------------------------------------


def _balanced(n: int, room: int) -> int:
    """The largest block ≤ ``room`` that cuts ``n`` into equal parts (up to one point)."""
    parts = -(-n // room)
    return -(-n // parts)


def _chunk_shape(shape: tuple[int, ...], chunk_size: int) -> tuple[int, ...]:
    """Block shape of at most ``chunk_size`` points: whole trailing axes first (C order), then a
    balanced split of the next one."""
    out = [1] * len(shape)
    room = chunk_size
    for ax in reversed(range(len(shape))):
        if room <= 1:
            break
        n = shape[ax]
        if n <= room:
            out[ax] = n
            room //= n
        else:
            out[ax] = _balanced(n, room)
            room = 1
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class _Space:
    names: tuple[str, ...]  # parameter names, the quantity's keyword arguments
    values: dict  # grid: 1-D values of each axis; points: 1-D per-point values of each name
    grid: bool
    chunk_shape: tuple[int, ...]

    @property
    def dims(self) -> tuple[str, ...]:
        return self.names if self.grid else (_POINT_DIM,)

    @property
    def shape(self) -> tuple[int, ...]:
        if self.grid:
            return tuple(self.values[n].size for n in self.names)
        return (self.values[self.names[0]].size,)

    @property
    def n_points(self) -> int:
        return math.prod(self.shape)

    @property
    def chunk_grid(self) -> tuple[int, ...]:
        return tuple(-(-s // c) for s, c in zip(self.shape, self.chunk_shape))

    @property
    def n_chunks(self) -> int:
        return math.prod(self.chunk_grid)

    @property
    def chunk_points(self) -> int:
        return math.prod(self.chunk_shape)

    def slices(self, chunk_id: int) -> tuple[slice, ...]:
        idx = np.unravel_index(chunk_id, self.chunk_grid)
        return tuple(
            slice(int(i) * c, min((int(i) + 1) * c, s))
            for i, c, s in zip(idx, self.chunk_shape, self.shape)
        )

    def points(self, slices: tuple[slice, ...]) -> np.ndarray:
        """The chunk's points, (m, len(names)) in C order of the block."""
        if self.grid:
            sub = [self.values[n][sl] for n, sl in zip(self.names, slices)]
            mesh = np.meshgrid(*sub, indexing="ij")
            return np.stack([g.ravel() for g in mesh], axis=1)
        return np.stack([self.values[n][slices[0]] for n in self.names], axis=1)

    def dummy(self) -> np.ndarray | None:
        """A point with finite coordinates (used for padding and for non-finite points), or None."""
        if self.grid:
            firsts = []
            for n in self.names:
                ok = np.flatnonzero(np.isfinite(self.values[n]))
                if ok.size == 0:
                    return None
                firsts.append(self.values[n][ok[0]])
            return np.asarray(firsts)
        pts = np.stack([self.values[n] for n in self.names], axis=1)
        ok = np.flatnonzero(np.all(np.isfinite(pts), axis=1))
        return pts[ok[0]] if ok.size else None


def _as_1d(values, where: str) -> np.ndarray:
    try:
        v = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{where} must be a 1-D array of numbers.") from None
    if v.ndim != 1 or v.size == 0:
        raise ValueError(f"{where} must be a non-empty 1-D array, got shape {v.shape}.")
    return v


def _check_name(name, where: str) -> str:
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"{where}: parameter name {name!r} must be a Python identifier.")
    if name == _POINT_DIM or name == "status" or name.startswith("_"):
        raise ValueError(f"{where}: parameter name {name!r} is reserved; choose another.")
    return name


def _make_space(axes, points, chunk_size) -> _Space:
    if (axes is None) == (points is None):
        raise ValueError("give exactly one of `axes` (a grid) or `points` (a list of points).")
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)):
        raise TypeError(f"chunk_size must be an integer, got {chunk_size!r}.")
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}.")
    table, what = (axes, "axes") if axes is not None else (points, "points")
    if not isinstance(table, Mapping) or not table:
        raise ValueError(f"{what} must be a non-empty mapping {{name: 1-D array of values}}.")
    values = {}
    for name, v in table.items():
        _check_name(name, what)
        values[name] = _as_1d(v, f"{what}[{name!r}]")
    if points is not None:
        sizes = {n: v.size for n, v in values.items()}
        if len(set(sizes.values())) != 1:
            raise ValueError(
                f"points: every parameter needs the same number of values, got {sizes}."
            )
    names = tuple(values)
    grid = axes is not None
    shape = tuple(v.size for v in values.values()) if grid else (values[names[0]].size,)
    return _Space(names, values, grid, _chunk_shape(shape, int(chunk_size)))


# ---------------------------------------------------------------------------------------------
# The quantity: values and a status per point.
# ---------------------------------------------------------------------------------------------


def _is_enum_item(x) -> bool:
    return hasattr(x, "_enumeration") and hasattr(x, "_value")


def _enum_names(cls) -> tuple[str, ...]:
    items = sorted(cls._name_to_item.items(), key=lambda kv: int(np.asarray(kv[1]._value)))
    return tuple(name for name, _ in items)


def _enum_label(cls) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def _split_output(out):
    """``quantity(**point)`` → (dict of values, status or None)."""
    status = None
    if isinstance(out, tuple):
        if len(out) != 2:
            raise TypeError(
                "quantity must return values (an array or a dict {name: array}) or a pair "
                f"(values, status); got a tuple of length {len(out)}."
            )
        out, status = out
    if isinstance(out, Mapping):
        values = dict(out)
    elif isinstance(out, (list, tuple)):
        raise TypeError(
            "quantity values must be an array or a dict {name: array}; to return several "
            "arrays, return a dict."
        )
    else:
        values = {"value": out}
    for name in values:
        if not isinstance(name, str) or not name.isidentifier():
            raise TypeError(f"quantity output names must be identifiers, got {name!r}.")
    return values, status


@dataclasses.dataclass(frozen=True)
class _Variable:
    name: str
    shape: tuple[int, ...]  # per point
    dtype: str
    dims: tuple[str, ...]  # per-point dims
    flags: tuple[str, ...] | None  # names of an enumeration-valued output
    enum: str | None


@dataclasses.dataclass(frozen=True)
class _Spec:
    variables: tuple[_Variable, ...]
    status_names: tuple[str, ...]
    status_enum: str

    @property
    def nonfinite_code(self) -> int:
        return self.status_names.index(_NONFINITE)

    def describe(self) -> dict:
        return {
            "variables": [dataclasses.asdict(v) for v in self.variables],
            "status_flags": list(self.status_names),
            "status_enumeration": self.status_enum,
        }

    @classmethod
    def from_description(cls, d) -> _Spec:
        variables = tuple(
            _Variable(
                v["name"], tuple(v["shape"]), v["dtype"], tuple(v["dims"]),
                None if v["flags"] is None else tuple(v["flags"]), v["enum"],
            )
            for v in d["variables"]
        )
        return cls(variables, tuple(d["status_flags"]), d["status_enumeration"])


def _describe_output(values, status) -> dict:
    """Per-point structure of one output of the quantity (at trace time), validated."""
    out = {}
    for name, leaf in values.items():
        if _is_enum_item(leaf):
            out[name] = (tuple(leaf._value.shape), "int8", _enum_names(leaf._enumeration),
                         _enum_label(leaf._enumeration))
        elif hasattr(leaf, "shape") and hasattr(leaf, "dtype"):
            out[name] = (tuple(leaf.shape), np.dtype(leaf.dtype).name, None, None)
        else:
            raise TypeError(
                f"quantity output {name!r} must be an array, got {type(leaf).__name__}."
            )
    if status is None:
        st = (_enum_names(SolveStatus), _enum_label(SolveStatus))
    elif _is_enum_item(status):
        if status._value.shape != ():
            raise TypeError(
                f"the status must be one item per point, got shape {status._value.shape}."
            )
        st = (_enum_names(status._enumeration), _enum_label(status._enumeration))
    else:
        shape, dtype = getattr(status, "shape", None), getattr(status, "dtype", None)
        if shape != () or dtype is None or not jnp.issubdtype(dtype, jnp.integer):
            raise TypeError(
                "the status returned with the values must be an eqx.Enumeration item (e.g. the "
                "`status` of simulate(..., throw=False)) or an integer scalar code of "
                f"rbo_jax.SolveStatus; got {getattr(dtype, 'name', type(status).__name__)}"
                f"{list(shape) if shape is not None else ''}. To return several arrays, return a "
                "dict."
            )
        st = (_enum_names(SolveStatus), _enum_label(SolveStatus))
    return {"values": out, "status": st}


def _point_function(quantity, names, record: dict):
    """``point(x) -> (values as arrays, int32 status code)``; records the output structure in
    ``record`` when traced."""

    def point(x):
        values, status = _split_output(quantity(**{n: x[i] for i, n in enumerate(names)}))
        record.update(_describe_output(values, status))
        codes = {
            k: (v._value.astype(jnp.int8) if _is_enum_item(v) else jnp.asarray(v))
            for k, v in values.items()
        }
        if status is None:
            s = jnp.asarray(SolveStatus.successful._value)
        else:
            s = jnp.asarray(status._value if _is_enum_item(status) else status)
        return codes, s.astype(jnp.int32)

    return point


class _Program:
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


def _compile_program(quantity, names, devices, batch) -> _Program:
    mesh = jax.sharding.Mesh(np.array(devices, dtype=object), (_BATCH_AXIS,))
    sharding = NamedSharding(mesh, P(_BATCH_AXIS))
    x = jax.ShapeDtypeStruct((batch, len(names)), jnp.result_type(float), sharding=sharding)
    record: dict = {}
    batched = jax.vmap(_point_function(quantity, names, record))
    # Each device runs the vmapped quantity on its shard, no communication (check_vma=False: the
    # body has no collectives, and user quantities may hold callbacks or custom rules that the
    # varying-manual-axes checker does not know).
    sharded = jax.shard_map(batched, mesh=mesh, in_specs=P(_BATCH_AXIS),
                            out_specs=P(_BATCH_AXIS), check_vma=False)
    try:
        traced, strategy = jax.jit(sharded).trace(x), "shard_map"
    except Exception:
        # lineax (and so optimistix's Newton, used for equilibria) cannot yet be traced inside
        # shard_map (patrick-kidger/lineax#185). Such quantities get a plain jit over the sharded
        # batch: GSPMD runs their loops in lock-step across devices, which costs little for a few
        # Newton steps. A user error raises again here, unchanged.
        record.clear()
        fn = jax.jit(batched, in_shardings=sharding, out_shardings=sharding)
        traced, strategy = fn.trace(x), "jit"
    return _Program(traced, sharding, batch, dict(record), strategy)


_cached_program = functools.lru_cache(maxsize=32)(_compile_program)


def _program(quantity, names, devices, batch) -> _Program:
    """Compiled once per quantity, parameter names, devices and batch size (cached, so that
    repeated sweeps of the same quantity reuse it)."""
    try:
        hash(quantity)
    except TypeError:
        return _compile_program(quantity, names, devices, batch)
    return _cached_program(quantity, names, devices, batch)


def _make_spec(structure: dict, space: _Space, dims: Mapping[str, Sequence[str]] | None) -> _Spec:
    """Names the per-point dimensions of the outputs; checks names against the parameters."""
    dims = dict(dims or {})
    values = structure["values"]
    unknown = set(dims) - set(values)
    if unknown:
        raise ValueError(f"dims names outputs {sorted(unknown)} that the quantity does not return "
                         f"(it returns {sorted(values)}).")
    variables, dim_sizes = [], {}
    for name, (shape, dtype, flags, enum) in values.items():
        if name in space.names or name in space.dims or name == "status":
            raise ValueError(f"quantity output {name!r} clashes with a parameter or reserved name.")
        vdims = tuple(dims.get(name, tuple(f"{name}_dim{j}" for j in range(len(shape)))))
        if len(vdims) != len(shape):
            raise ValueError(f"dims[{name!r}] = {list(vdims)} has {len(vdims)} names for an output "
                             f"of shape {shape} per point.")
        for dname, size in zip(vdims, shape):
            if dname in space.dims or dname in space.names:
                raise ValueError(f"dims[{name!r}]: {dname!r} is already a parameter dimension.")
            if dim_sizes.setdefault(dname, size) != size:
                raise ValueError(f"dimension {dname!r} has sizes {dim_sizes[dname]} and {size} in "
                                 "different outputs.")
        variables.append(_Variable(name, shape, dtype, vdims, flags, enum))
    status_names, status_enum = structure["status"]
    if _NONFINITE not in status_names:
        status_names = status_names + (_NONFINITE,)
    return _Spec(tuple(variables), status_names, status_enum)


def _local_devices(devices) -> tuple:
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


def _fill_value(dtype: str):
    dt = np.dtype(dtype)
    if dt.kind in "fc":
        return np.nan
    if dt.kind == "b":
        return False
    return -1 if dt.kind == "i" else 0


def _error_text(e: Exception) -> str:
    """The message of a runtime error raised inside compiled code, without the host traceback
    that jax wraps around a failing callback (equinox.error_if)."""
    text = str(e)
    found = re.findall(r"EquinoxRuntimeError: (.+)", text)
    if found:
        return found[-1].strip()
    return text if len(text) <= 600 else text[:600] + " ..."


class _Chunks:
    """Runs chunks through the compiled program, one chunk in flight while the previous one is
    stored (dispatch is asynchronous)."""

    def __init__(self, quantity, space: _Space, devices, dims=None):
        n_dev = len(devices)
        self.batch = -(-space.chunk_points // n_dev) * n_dev
        self.program = _program(quantity, space.names, tuple(devices), self.batch)
        self.space = space
        self.spec = _make_spec(self.program.structure, space, dims)
        self.dummy = space.dummy()

    def launch(self, cid: int):
        slices = self.space.slices(cid)
        pts = self.space.points(slices)
        valid = np.all(np.isfinite(pts), axis=1)
        future = None
        if valid.any():
            block = np.empty((self.batch, pts.shape[1]))
            block[:] = self.dummy
            block[: pts.shape[0]][valid] = pts[valid]
            future = self.program.call(jax.device_put(block, self.program.sharding))
        return cid, slices, valid, future

    def finish(self, cid, slices, valid, future):
        m = valid.size
        block_shape = tuple(sl.stop - sl.start for sl in slices)
        spec = self.spec
        if future is not None:
            try:
                values, status = jax.device_get(future)
            except Exception as e:  # an error raised inside the compiled quantity
                raise self.error(cid, e) from e
            status = np.asarray(status)[:m]
            bad = (status < 0) | (status >= len(spec.status_names))
            if bad.any():
                raise SweepError(
                    f"the quantity returned status codes {sorted(set(status[bad].tolist()))} "
                    f"outside {spec.status_enum} (0..{len(spec.status_names) - 1})."
                )
            out = {v.name: np.asarray(values[v.name])[:m] for v in spec.variables}
        else:
            status = np.zeros(m, np.int32)
            out = {v.name: np.zeros((m,) + v.shape, v.dtype) for v in spec.variables}
        status = np.where(valid, status, spec.nonfinite_code).astype(np.int8)
        result = {}
        for v in spec.variables:
            a = out[v.name].astype(v.dtype, copy=True)
            a[~valid] = _fill_value(v.dtype)
            result[v.name] = a.reshape(block_shape + v.shape)
        result["status"] = status.reshape(block_shape)
        return cid, slices, result

    def error(self, cid: int, e: Exception) -> SweepError:
        slices = self.space.slices(cid)
        pts = self.space.points(slices)
        first = dict(zip(self.space.names, pts[0].tolist()))
        return SweepError(
            f"chunk {cid} ({pts.shape[0]} points, the first {first}) raised: {_error_text(e)}\n"
            "A sweep expects failures as statuses, not errors: call simulate with throw=False and "
            "return (values, traj.status). Chunks already written to a store are kept."
        )

    def run(self, chunk_ids, consume, bar=None):
        """Compute the chunks and hand each result to ``consume``; one chunk is computed while
        the previous one is consumed."""
        pending = None
        for cid in chunk_ids:
            try:
                launched = self.launch(cid)
            except Exception as e:  # a runtime error raised at dispatch
                if pending is not None:
                    self._consume(pending, consume, bar)
                raise self.error(cid, e) from e
            if pending is not None:
                self._consume(pending, consume, bar)
            pending = launched
        if pending is not None:
            self._consume(pending, consume, bar)

    def _consume(self, pending, consume, bar):
        cid, slices, result = self.finish(*pending)
        consume(cid, slices, result)
        if bar is not None:
            bar.update(pending[2].size)


# ---------------------------------------------------------------------------------------------
# The labelled result.
# ---------------------------------------------------------------------------------------------


def _json(x):
    return json.loads(json.dumps(x))


def _counts(status: np.ndarray, names: Sequence[str]) -> dict[str, int]:
    c = np.bincount(np.asarray(status, dtype=np.int64).ravel(), minlength=len(names))
    return {n: int(k) for n, k in zip(names, c)}


def _variable_attrs(v: _Variable) -> dict:
    if v.flags is None:
        return {}
    return {"flag_values": list(range(len(v.flags))), "flag_meanings": " ".join(v.flags),
            "enumeration": v.enum}


def _status_attrs(spec: _Spec) -> dict:
    return {
        "flag_values": list(range(len(spec.status_names))),
        "flag_meanings": " ".join(spec.status_names),
        "enumeration": spec.status_enum,
        "long_name": "outcome of the quantity at each point",
    }


def _dataset(space: _Space, spec: _Spec, arrays: dict, attrs: dict):
    import xarray as xr

    data = {
        v.name: (space.dims + v.dims, arrays[v.name], _variable_attrs(v)) for v in spec.variables
    }
    data["status"] = (space.dims, arrays["status"], _status_attrs(spec))
    if space.grid:
        coords = {n: space.values[n] for n in space.names}
    else:
        coords = {n: (_POINT_DIM, space.values[n]) for n in space.names}
    attrs = dict(attrs)
    attrs["status_counts"] = _counts(arrays["status"], spec.status_names)
    return xr.Dataset(data, coords=coords, attrs=_json(attrs))


def status_counts(ds) -> dict[str, int]:
    """Number of points with each status, ``{name: count}``, of a :func:`sweep` result."""
    names = ds["status"].attrs["flag_meanings"].split()
    return _counts(np.asarray(ds["status"].values), names)


def _summary_line(counts: Mapping[str, int]) -> str:
    total = sum(counts.values())
    parts = [f"{k} {n}" for n, k in counts.items() if k]
    return f"{total} points: " + ", ".join(parts)


# ---------------------------------------------------------------------------------------------
# Processes (jax.distributed).
# ---------------------------------------------------------------------------------------------


class _Hosts:
    def __init__(self):
        self.index, self.count = jax.process_index(), jax.process_count()

    def barrier(self, name: str):
        if self.count > 1:
            from jax.experimental import multihost_utils

            multihost_utils.sync_global_devices(f"rbo_jax.sweep:{name}")

    def any_failed(self, failed: bool) -> list[int]:
        """All processes meet here; the indices of those that report a failure."""
        if self.count == 1:
            return [0] if failed else []
        from jax.experimental import multihost_utils

        flags = np.asarray(multihost_utils.process_allgather(np.int32(failed)))
        return [int(i) for i in np.flatnonzero(flags)]


# ---------------------------------------------------------------------------------------------
# The store (zarr format 3, xarray layout).
# ---------------------------------------------------------------------------------------------

_PARTIAL = re.compile(r"\.[0-9a-f]{32}\.partial$")


def _descriptor(space: _Space, spec: _Spec) -> dict:
    return _json({
        "format": _FORMAT,
        "format_version": _FORMAT_VERSION,
        "mode": "grid" if space.grid else "points",
        "names": list(space.names),
        "dims": list(space.dims),
        "shape": list(space.shape),
        "chunk_shape": list(space.chunk_shape),
        **spec.describe(),
    })


def _zarr():
    try:
        import zarr
    except ImportError as e:  # pragma: no cover - zarr is a dependency
        raise ImportError(
            "sweep(store=...) needs zarr >= 3, which needs Python >= 3.11: pip install 'zarr>=3'"
        ) from e
    return zarr


def _open_group(path, mode):
    zarr = _zarr()
    return zarr.open_group(str(path), mode=mode, zarr_format=3)


def _read_descriptor(group, path) -> dict:
    d = group.attrs.get(_FORMAT)
    if not isinstance(d, dict) or d.get("format") != _FORMAT:
        raise SweepError(f"{path} is not an rbo_jax sweep store (no {_FORMAT!r} attribute).")
    if d.get("format_version") != _FORMAT_VERSION:
        raise SweepError(f"{path}: sweep store format {d.get('format_version')} is not supported "
                         f"(this rbo_jax writes {_FORMAT_VERSION}).")
    return d


def _space_from_store(group, d) -> _Space:
    names = tuple(d["names"])
    values = {n: np.asarray(group[n][...]) for n in names}
    return _Space(names, values, d["mode"] == "grid", tuple(d["chunk_shape"]))


def _create_store(path: Path, space: _Space, spec: _Spec, attrs: dict):
    group = _open_group(path, "w")
    config = {"write_empty_chunks": True}
    for n in space.names:
        if space.grid:
            a = group.create_array(n, shape=space.values[n].shape, dtype="float64",
                                   chunks=space.values[n].shape, dimension_names=[n],
                                   fill_value=np.nan, config=config)
        else:
            a = group.create_array(n, shape=space.shape, dtype="float64", chunks=space.chunk_shape,
                                   dimension_names=[_POINT_DIM], fill_value=np.nan, config=config)
        a[...] = space.values[n]
    point_coords = {} if space.grid else {"coordinates": " ".join(space.names)}
    for v in spec.variables:
        group.create_array(
            v.name, shape=space.shape + v.shape, dtype=v.dtype, chunks=space.chunk_shape + v.shape,
            dimension_names=list(space.dims + v.dims), fill_value=_fill_value(v.dtype),
            attributes=_json({**_variable_attrs(v), **point_coords}), config=config,
        )
    group.create_array(
        "status", shape=space.shape, dtype="int8", chunks=space.chunk_shape,
        dimension_names=list(space.dims), fill_value=-1,
        attributes=_json({**_status_attrs(spec), **point_coords}), config=config,
    )
    meta = group.create_group(_META)
    meta.create_array("chunk_done", shape=space.chunk_grid, dtype="uint8",
                      chunks=(1,) * len(space.chunk_grid), fill_value=0, compressors=None,
                      config=config)
    group.attrs.update(_json({**attrs, _FORMAT: _descriptor(space, spec)}))
    return group


def _check_compatible(group, path, space: _Space, spec: _Spec, attrs: dict) -> _Space:
    """The store's space if it was made by the same sweep (its chunk layout wins), else raise."""
    d = _read_descriptor(group, path)
    new = _descriptor(space, spec)
    diffs = [k for k in new if k != "chunk_shape" and new[k] != d.get(k)]
    if diffs:
        detail = "; ".join(f"{k}: store {d.get(k)!r}, now {new[k]!r}" for k in diffs)
        raise SweepError(f"cannot resume {path}: it was written by a different sweep ({detail}).")
    stored = _space_from_store(group, d)
    for n in space.names:
        if not np.array_equal(stored.values[n], space.values[n], equal_nan=True):
            raise SweepError(f"cannot resume {path}: the values of {n!r} differ from the store's.")
    for k, v in _json(attrs).items():
        if group.attrs.get(k) != v:
            raise SweepError(f"cannot resume {path}: attribute {k!r} differs from the store's "
                             "(e.g. a different configuration).")
    return stored


def _resumed_layout(path: Path, space: _Space) -> _Space:
    """The space with the chunk layout of an existing store (a resumed sweep keeps it)."""
    if not (path / "zarr.json").exists():
        return space
    d = _read_descriptor(_open_group(path, "r"), path)
    shape = d.get("chunk_shape")
    if not (isinstance(shape, list) and len(shape) == len(space.shape)):
        return space  # _check_compatible reports the mismatch
    return dataclasses.replace(space, chunk_shape=tuple(int(c) for c in shape))


def _missing_chunks(group, space: _Space) -> list[int]:
    done = np.asarray(group[f"{_META}/chunk_done"][...]).ravel()
    return [int(i) for i in np.flatnonzero(done == 0)]


def _remove_partial_files(path: Path):
    """Temporary files of zarr's atomic writes left by a killed writer."""
    for root, _, files in os.walk(path):
        for f in files:
            if _PARTIAL.search(f):
                Path(root, f).unlink(missing_ok=True)


def _prepare_store(path: Path, space, spec, attrs, resume, overwrite) -> tuple[_Space, list[int]]:
    if path.exists() and not (path.is_dir() and not any(path.iterdir())):
        if not (path / "zarr.json").exists():
            raise SweepError(f"{path} exists and is not a zarr store; choose another path.")
        if overwrite:
            import shutil

            shutil.rmtree(path)
        elif not resume:
            raise FileExistsError(
                f"{path} already holds a sweep: pass resume=True (CLI: --resume) to finish it, "
                "or overwrite=True to start again."
            )
        else:
            group = _open_group(path, "r+")
            space = _check_compatible(group, path, space, spec, attrs)
            _remove_partial_files(path)
            return space, _missing_chunks(group, space)
    _create_store(path, space, spec, attrs)
    return space, list(range(space.n_chunks))


class _Writer:
    def __init__(self, path: Path, spec: _Spec):
        group = _open_group(path, "r+")
        self.arrays = {v.name: group[v.name] for v in spec.variables}
        self.arrays["status"] = group["status"]
        self.done = group[f"{_META}/chunk_done"]
        self.space_chunk_grid = self.done.shape

    def __call__(self, cid, slices, result):
        for name, arr in self.arrays.items():
            arr[slices] = result[name]
        # The marker last: a chunk counts as done only once all its data is on disk.
        self.done[np.unravel_index(cid, self.space_chunk_grid)] = 1


def _finalize_store(path: Path):
    group = _open_group(path, "r+")
    d = _read_descriptor(group, path)
    status = np.asarray(group["status"][...])
    group.attrs.update(_json({"status_counts": _counts(status, d["status_flags"])}))


def open_sweep(path, *, allow_incomplete: bool = False):
    """Open a sweep store written by :func:`sweep` as a labelled :class:`xarray.Dataset` (lazily:
    values are read on access; ``.load()`` reads them all).

    Raises :class:`SweepError` if some chunks are missing (an interrupted sweep: finish it with
    ``sweep(..., store=path, resume=True)``) unless ``allow_incomplete`` (missing points then hold
    the fill values: NaN, and status -1).
    """
    import xarray as xr

    path = Path(path)
    if not (path / "zarr.json").exists():
        raise FileNotFoundError(f"{path} is not a zarr store.")
    group = _open_group(path, "r")
    d = _read_descriptor(group, path)
    space = _space_from_store(group, d)
    missing = _missing_chunks(group, space)
    if missing and not allow_incomplete:
        raise SweepError(f"{path} is incomplete: {len(missing)} of {space.n_chunks} chunks missing;"
                         " "
                         "finish it with sweep(..., store=path, resume=True).")
    ds = xr.open_zarr(str(path), consolidated=False, chunks=None, zarr_format=3)
    ds.attrs.pop(_FORMAT, None)  # the store's own layout, not a property of the result
    return ds


# ---------------------------------------------------------------------------------------------
# The sweep.
# ---------------------------------------------------------------------------------------------


def sweep(
    quantity: Callable[..., Any],
    axes: Mapping[str, Any] | None = None,
    *,
    points: Mapping[str, Any] | None = None,
    chunk_size: int = 4096,
    store: str | os.PathLike | None = None,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    devices: int | Sequence[Any] | None = None,
    dims: Mapping[str, Sequence[str]] | None = None,
    attrs: Mapping[str, Any] | None = None,
    desc: str = "sweep",
):
    r"""Evaluate ``quantity(**point)`` at every point of a grid or a list of points.

    **Arguments:**

    - `quantity`: a function of one point, called with the parameters as keyword arguments
      (float64 scalars, traced: build models from them inside). It returns the values — an array,
      or a dict ``{name: array}`` (arrays of any fixed shape per point, or enumeration items such
      as :class:`rbo_jax.StabilityKind`) — or a pair ``(values, status)``, ``status`` an
      :class:`equinox.Enumeration` item (e.g. ``traj.status`` of ``simulate(..., throw=False)``) or
      an integer code of :class:`rbo_jax.SolveStatus`. Example::

          def final_state(c, M):
              model = RigidBodyOscillator(A, QuadraticFoundation(c, 1.0, k), FollowerMoment(M, k))
              traj = simulate(model, (M / 1.0) * k + dtheta, jnp.zeros(3), jnp.array([0.0, 20.0]),
                              throw=False)
              return {"theta": traj.theta[-1], "Omega": traj.Omega[-1]}, traj.status

    - `axes`: ``{name: 1-D values}``, a grid (the Cartesian product, in this order); or
    - `points`: ``{name: 1-D values}`` of equal lengths, a list of points (dimension ``point``).
    - `chunk_size`: at most this many points per compiled call (device memory is
      O(``chunk_size``)). The chunks are blocks of the grid; every call is padded to one shape.
    - `store`: a directory for a zarr store written chunk by chunk (else results stay in memory).
    - `resume`: continue the sweep already in ``store`` (its chunk layout is kept; only chunks not
      yet written are computed). It must be the same sweep: same names, values, outputs, ``attrs``.
    - `overwrite`: delete an existing ``store`` first.
    - `progress`: a tqdm bar (points done, rate, ETA) and a summary line on stderr; ``False`` for
      quiet scripts.
    - `devices`: local devices to shard each chunk over: all (default), a number of them, or a list.
    - `dims`: names of the per-point dimensions of outputs, e.g. ``{"theta": ["component"]}``
      (default ``"{name}_dim{j}"``).
    - `attrs`: metadata stored with the result (JSON-able); a resumed sweep must pass the same.

    **Returns:** an :class:`xarray.Dataset` with coordinates the parameters (grid: one dimension
    per axis; points: dimension ``point``), one variable per output, and ``status`` (int8 codes,
    names in its ``flag_meanings``; non-finite parameters give ``nonfinite_input`` and NaN values);
    ``attrs["status_counts"]`` counts the statuses. With a store the dataset is read from it
    (lazily). The same on every process of a multi-process run.

    Multi-process (after ``jax.distributed.initialize``): every process calls ``sweep`` with the
    same arguments; the store must be on a file system that all of them see.
    """
    space = _make_space(axes, points, chunk_size)
    local = _local_devices(devices)
    attrs = _json(dict(attrs or {}))
    for k in attrs:
        if k in (_FORMAT, "status_counts"):
            raise ValueError(f"attrs: {k!r} is reserved.")
    if resume and store is None:
        raise ValueError("resume=True needs a store.")
    path = None if store is None else Path(store)
    if path is not None and resume and not overwrite:
        space = _resumed_layout(path, space)
    hosts = _Hosts()
    chunks = _Chunks(quantity, space, local, dims)  # traced here, compiled at the first chunk
    spec = chunks.spec

    if path is not None:
        error = None
        if hosts.index == 0:
            try:
                space, _ = _prepare_store(path, space, spec, attrs, resume, overwrite)
            except Exception as e:  # reported to the other processes, re-raised below
                error = e
        failed = hosts.any_failed(error is not None)
        if error is not None:
            raise error
        if failed:
            raise SweepError(f"process 0 could not prepare the store {path} (see its error).")
        group = _open_group(path, "r")
        if hosts.index != 0:
            _check_compatible(group, path, space, spec, attrs)
        missing = _missing_chunks(group, space)
        hosts.barrier("missing chunks read")  # nobody writes before everybody has read them
    else:
        missing = list(range(space.n_chunks))

    mine = missing[hosts.index :: hosts.count]
    if path is not None:
        consume = _Writer(path, spec)
        arrays = None
    else:
        arrays = {v.name: np.empty(space.shape + v.shape, v.dtype) for v in spec.variables}
        arrays["status"] = np.empty(space.shape, np.int8)
        kept = {}

        def consume(cid, slices, result):
            if hosts.count == 1:
                for name, a in result.items():
                    arrays[name][slices] = a
            else:
                kept[cid] = result

    bar = None
    if progress:
        from tqdm.auto import tqdm

        n_mine = sum(int(math.prod(s.stop - s.start for s in space.slices(c))) for c in mine)
        label = desc if hosts.count == 1 else f"{desc} [process {hosts.index}/{hosts.count}]"
        bar = tqdm(total=n_mine, desc=label, unit="pt", unit_scale=True, dynamic_ncols=True)
    error = None
    try:
        chunks.run(mine, consume, bar)
    except Exception as e:  # let every process reach the meeting point below
        error = e
        if hosts.count == 1:
            raise
    finally:
        if bar is not None:
            bar.close()
    failed = hosts.any_failed(error is not None)
    if error is not None:
        raise error
    if failed:
        raise SweepError(f"process(es) {failed} failed (see their errors); "
                         + ("resume the sweep to finish it." if path else ""))

    if path is not None:
        if hosts.index == 0:
            _finalize_store(path)
        hosts.barrier("store finalized")
        ds = open_sweep(path)
    else:
        if hosts.count > 1:
            _gather(arrays, kept, missing, space, spec, hosts)
        ds = _dataset(space, spec, arrays, attrs)
    if progress and hosts.index == 0:
        print(f"{desc}: {_summary_line(ds.attrs['status_counts'])}", file=sys.stderr)
    return ds


def _gather(arrays, kept, missing, space: _Space, spec: _Spec, hosts: _Hosts):
    """Assemble the chunks computed by every process (in-memory multi-process sweep)."""
    from jax.experimental import multihost_utils

    per_process = -(-len(missing) // hosts.count)
    names = [v.name for v in spec.variables] + ["status"]
    shapes = {v.name: v.shape for v in spec.variables} | {"status": ()}
    dtypes = {v.name: v.dtype for v in spec.variables} | {"status": "int8"}
    mine = missing[hosts.index :: hosts.count]
    local = {}
    for name in names:
        buf = np.zeros((per_process,) + space.chunk_shape + shapes[name], dtypes[name])
        for j, cid in enumerate(mine):
            r = kept[cid][name]
            buf[(j,) + tuple(slice(0, s) for s in r.shape)] = r
        local[name] = buf
    everyone = multihost_utils.process_allgather(local)
    for p in range(hosts.count):
        for j, cid in enumerate(missing[p :: hosts.count]):
            slices = space.slices(cid)
            block = tuple(slice(0, sl.stop - sl.start) for sl in slices)
            for name in names:
                arrays[name][slices] = np.asarray(everyone[name])[(p, j) + block]


# ---------------------------------------------------------------------------------------------
# Figures.
# ---------------------------------------------------------------------------------------------


def _pyplot():
    try:
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - exercised only without matplotlib
        raise ImportError("plot_sweep needs matplotlib: pip install 'rbo_jax[plot]'.") from e
    return plt


def plot_sweep(ds, variable: str | None = None, *, x: str | None = None, y: str | None = None,
               select: Mapping[str, float] | None = None, ax=None, title: str | None = None):
    """Draw one variable of a :func:`sweep` result; points whose status is not ``successful``
    are left blank (grey). Vector-valued outputs are drawn by their norm.

    Grid: a colour map over axes ``x``, ``y`` (default the first two; other axes at ``select``
    or their first value), or a curve for a one-axis grid. Points: a scatter over the first two
    parameters. Returns the Axes.
    """
    plt = _pyplot()
    if variable is None:
        variable = next(n for n in ds.data_vars if n != "status")
    if variable not in ds.data_vars:
        raise KeyError(f"no variable {variable!r}; the sweep has {sorted(ds.data_vars)}.")
    da, status = ds[variable], ds["status"]
    space_dims = list(status.dims)
    if _POINT_DIM in space_dims:
        names = [n for n in ds.coords if ds[n].dims == (_POINT_DIM,)]
    else:
        names = space_dims
    sel = {d: (select or {}).get(d) for d in space_dims if d != _POINT_DIM}
    extra = [d for d in da.dims if d not in space_dims]
    vals = np.asarray(da.values)
    label = variable
    if extra:
        vals = np.linalg.norm(np.abs(vals).reshape(vals.shape[: len(space_dims)] + (-1,)), axis=-1)
        label = f"|{variable}|"
    elif np.iscomplexobj(vals):
        vals, label = np.abs(vals), f"|{variable}|"
    flags = status.attrs["flag_meanings"].split()
    ok = np.asarray(status.values) == (flags.index("successful") if "successful" in flags else 0)
    vals = np.where(ok, vals.astype(float), np.nan)
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    counts = status_counts(ds)
    if _POINT_DIM in space_dims:
        xs = np.asarray(ds[names[0]].values)
        if len(names) >= 2:
            sc = ax.scatter(xs, np.asarray(ds[names[1]].values), c=vals, s=12, cmap="viridis")
            ax.scatter(xs[~ok], np.asarray(ds[names[1]].values)[~ok], marker="x", c="0.5", s=12)
            plt.colorbar(sc, ax=ax, label=label)
            ax.set_ylabel(names[1])
        else:
            ax.plot(xs, vals, ".")
            ax.set_ylabel(label)
        ax.set_xlabel(names[0])
    else:
        x = x or space_dims[0]
        if len(space_dims) == 1:
            ax.plot(np.asarray(ds[x].values), vals, "-o", ms=3)
            ax.set_xlabel(x)
            ax.set_ylabel(label)
        else:
            y = y or next(d for d in space_dims if d != x)
            for d in (x, y):
                if d not in space_dims:
                    raise ValueError(f"{d!r} is not an axis of the sweep ({space_dims}).")
            index = []
            for d in space_dims:
                if d in (x, y):
                    index.append(slice(None))
                else:
                    coord = np.asarray(ds[d].values)
                    target = sel[d] if sel[d] is not None else coord[0]
                    index.append(int(np.nanargmin(np.abs(coord - target))))
            v = vals[tuple(index)]
            kept = [d for d in space_dims if d in (x, y)]
            if kept.index(y) != 0:
                v = v.T
            # matplotlib needs finite coordinates: non-finite axis values (nonfinite_input) go
            X, Y = np.asarray(ds[x].values, float), np.asarray(ds[y].values, float)
            fx, fy = np.isfinite(X), np.isfinite(Y)
            X, Y, v = X[fx], Y[fy], v[np.ix_(fy, fx)]
            cmap = plt.get_cmap("RdBu_r" if np.nanmin(v) < 0 < np.nanmax(v) else "viridis")
            cmap = cmap.with_extremes(bad="0.8")
            kw = {}
            if cmap.name.startswith("RdBu"):
                vmax = np.nanmax(np.abs(v))
                kw = {"vmin": -vmax, "vmax": vmax}
            mesh = ax.pcolormesh(X, Y, np.ma.masked_invalid(v), cmap=cmap, shading="auto", **kw)
            plt.colorbar(mesh, ax=ax, label=label)
            if kw and min(v.shape) > 1:  # a diverging map: draw where the value crosses 0
                ax.contour(X, Y, v, levels=[0.0], colors="k", linewidths=1.0)
            ax.set_xlabel(x)
            ax.set_ylabel(y)
    ax.set_title(title or f"{label}   ({_summary_line(counts)})", fontsize=9)
    return ax
