r"""The one batch engine: :func:`sweep` and its chunk loop.

:func:`sweep` evaluates a user's *quantity* — any function of one parameter point, e.g. the final
state of :func:`rbo_jax.simulate`, an energy drift, the spectral abscissa of an equilibrium — on a
grid of named axes (their Cartesian product) or on a list of points, and returns a labelled
:class:`xarray.Dataset`. :func:`rbo_jax.stability_map` and :func:`rbo_jax.critical_load` are
presets of it (``_maps.py``); the CLI's TOML sweeps run through it too.

How it runs (one private module per concern):

- **Chunks** (``_space.py``): the points are cut into chunks of at most ``chunk_size`` points
  (hyper-rectangular blocks of the grid), so device memory is O(``chunk_size``).
- **Program** (``_program.py``): each chunk is one call of ``jit(shard_map(vmap(quantity)))``,
  padded to one shape, so one compilation serves the whole sweep.
- **Loop** (``_chunks.py``): one chunk is computed while the previous one is stored
  (dispatch is asynchronous); a progress bar counts points. A chunk that raises is re-run in
  halves down to single points: only the points that raise on their own get the status
  ``error`` (with their message in ``ds.attrs["errors"]``), the rest completes.
- **Output** (``_output.py``): values and a status per point, assembled into a Dataset.
- **Store** (``_store.py``, ``_lock.py``): with ``store=PATH`` each chunk is written to a zarr
  store as soon as it is computed, with a checksum; one process writes a store at a time (a
  lock beside it); ``resume=True`` finishes an interrupted sweep and recomputes corrupted
  chunks; ``retry_errors=True`` recomputes only the points whose evaluation raised.
- **Hosts** (``_hosts.py``): after ``jax.distributed.initialize(...)`` every process computes its
  share of the chunks.
- **Dask** (``_dask.py``): with ``client=`` a :class:`distributed.Client`, each chunk is one task;
  idle workers take the next chunks, a lost worker's chunks are computed again elsewhere, and
  this process stays the store's one writer (results bit for bit those of one process).

**Bad points** never stop the sweep. Each point carries a ``status``: the quantity returns
``(values, status)`` with ``status`` an :class:`equinox.Enumeration` item (typically
:class:`rbo_jax.SolveStatus` from ``simulate(..., throw=False)``, or
:class:`rbo_jax.EquilibriumStatus`) or an integer code of :class:`rbo_jax.SolveStatus`. Points
with a non-finite parameter are not evaluated at all (they would raise in the models'
constructors); they get ``nonfinite_input`` and NaN values. Points whose evaluation raises get
``error``. :func:`status_counts` counts the
statuses (also stored in ``ds.attrs["status_counts"]``).
"""

from __future__ import annotations

import contextlib
import math
import mmap
import os
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._devices import warn_if_few_devices
from . import _store
from ._chunks import Chunks
from ._dask import DaskChunks, check_devices
from ._errors import SweepError
from ._hosts import Hosts, lost_line
from ._lock import StoreLock
from ._output import OutputSpec, dataset, summary_line, to_json
from ._program import local_devices
from ._space import Space, make_space

# ---------------------------------------------------------------------------------------------
# The sweep.
# ---------------------------------------------------------------------------------------------


def _check_attrs(attrs) -> dict:
    attrs = to_json(dict(attrs or {}))
    for k in attrs:
        if k in (_store.FORMAT, "status_counts"):
            raise ValueError(f"attrs: {k!r} is reserved.")
    return attrs


def _open_store(
    path: Path, space: Space, spec: OutputSpec, attrs, resume, overwrite, hosts: Hosts
) -> tuple[Space, list[int]]:
    """Process 0 prepares the store, every process reads the chunks still missing."""
    error = None
    if hosts.index == 0:
        try:
            space = _store.prepare(path, space, spec, attrs, resume, overwrite)
        except Exception as e:  # reported to the other processes, re-raised below
            error = e
    failed = hosts.any_failed(error is not None)
    if error is not None:
        raise error
    if failed:
        raise SweepError(f"process 0 could not prepare the store {path} (see its error).")
    group = _store.open_group(path, "r")
    if hosts.index != 0:
        _store.check_compatible(group, path, space, spec, attrs)
    missing = _store.missing_chunks(group, space)
    hosts.barrier("missing chunks read")  # nobody writes before everybody has read them
    return space, missing


def _progress_bar(progress, space: Space, mine, hosts: Hosts, desc: str):
    if not progress:
        return None
    from tqdm.auto import tqdm

    n_mine = (
        None
        if mine is None  # taken one at a time: not known beforehand
        else sum(int(math.prod(s.stop - s.start for s in space.slices(c))) for c in mine)
    )
    label = desc if hosts.count == 1 else f"{desc} [process {hosts.index}/{hosts.count}]"
    return tqdm(total=n_mine, desc=label, unit="pt", unit_scale=True, dynamic_ncols=True)


def _run_closing(chunks: Chunks | DaskChunks, mine, consume, bar) -> Exception | None:
    """Run the chunks ``mine`` into ``consume`` and close the progress bar; returns the error
    raised, if any, for the caller to report to the other processes before re-raising it."""
    try:
        chunks.run(mine, consume, bar)
    except Exception as e:  # let every process reach the meeting point first
        return e
    finally:
        if bar is not None:
            bar.close()
    return None


def _raise_failed(error: Exception | None, failed: list[int], path):
    """Re-raise this process's ``error``, else a :class:`SweepError` naming the ``failed``
    processes."""
    if error is not None:
        raise error
    if failed:
        raise SweepError(
            f"process(es) {failed} failed (see their errors); "
            + ("resume the sweep to finish it." if path else "")
        )


def _run_chunks(chunks: Chunks | DaskChunks, mine, consume, bar, hosts: Hosts, path):
    """Run this process's chunks (here, or as tasks of a Dask cluster); every process meets
    afterwards, errors are re-raised."""
    error = _run_closing(chunks, mine, consume, bar)
    _raise_failed(error, hosts.any_failed(error is not None), path)


def _run_shares(chunks: Chunks, mine, writer, bar, hosts: Hosts, path: Path, space: Space):
    """Run this process's share of a multi-process sweep to a store, then meet the others in a
    way that a lost process cannot block (:meth:`Hosts.live`); process 0 computes what the lost
    processes left missing. Errors of any process are re-raised (on process 0 as a
    :class:`SweepError` naming them)."""
    hosts.introduce()  # who each process is, to name a lost one
    error = _run_closing(chunks, mine, writer, bar)
    hosts.report(error is not None)
    alive = hosts.live("shares computed")
    _raise_failed(error, hosts.failed(alive), path)
    lost = [i for i in range(hosts.count) if i not in alive]
    if lost and hosts.index == 0:
        left = _store.missing_chunks(_store.open_group(path, "r"), space)
        print(lost_line(lost, hosts.count, left, hosts.who), file=sys.stderr, flush=True)
        chunks.run(left, writer, None)


# Points per device in a chunk when the caller gives no chunk_size (see sweep's docstring); on
# a GPU, four times its refilled lanes (:data:`rbo_jax.ensemble.ACCELERATOR_LANES`).
CHUNK_PER_DEVICE = 8192
CHUNK_PER_ACCELERATOR = 2**20


def _chunk_per_device(devices) -> int:
    return CHUNK_PER_DEVICE if devices[0].platform == "cpu" else CHUNK_PER_ACCELERATOR


# The in-memory result of a grid must fit: refused beforehand above this share of the memory.
MEMORY_SHARE = 0.5


def _check_memory(space: Space, spec: OutputSpec):
    """Refuse, before any work, an in-memory result larger than half the physical memory."""
    per_point = 1 + sum(
        int(np.prod(v.shape, dtype=np.int64)) * np.dtype(v.dtype).itemsize for v in spec.variables
    )
    need = space.n_points * per_point
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not POSIX: no guard
        return
    if need > MEMORY_SHARE * total:
        raise SweepError(
            f"the results of {space.n_points:,} points need {need / 2**30:.1f} GiB in memory, more "
            f"than {MEMORY_SHARE:.0%} of this machine's {total / 2**30:.1f} GiB: give a store "
            "(store=PATH, written chunk by chunk) or a smaller grid."
        )


# Result arrays from this size on are mapped without transparent huge pages (_result_array)
SMALL_PAGES_FROM = 4 << 20


def _result_array(shape, dtype) -> np.ndarray:
    """An uninitialised array for a sweep's results, its large ones in anonymous memory of
    ordinary pages (``mmap``), not NumPy's allocation, which asks the kernel for transparent
    huge pages (``madvise``) from 4 MiB on.

    Where the kernel must compact memory to find free huge pages (``defrag = madvise``, as on
    the benchmark machine), the first write to such an array stalls, and a map's results are
    written chunk by chunk into fresh memory; ordinary pages do not stall (figures:
    benchmarks/README.md, History)."""
    nbytes = math.prod(shape) * np.dtype(dtype).itemsize
    if nbytes < SMALL_PAGES_FROM:
        return np.empty(shape, dtype)
    return np.frombuffer(mmap.mmap(-1, nbytes), dtype).reshape(shape)


class _InMemory:
    """Collects chunk results into arrays (one process) or keeps them (several processes).
    Error records are listed in chunk order, however the chunks arrive (Dask: as they finish)."""

    def __init__(self, space: Space, spec: OutputSpec, hosts: Hosts):
        self.arrays = {
            v.name: _result_array(space.shape + v.shape, v.dtype) for v in spec.variables
        }
        self.arrays["status"] = _result_array(space.shape, np.int8)
        self.kept, self.chunk_errors, self.hosts = {}, {}, hosts

    @property
    def errors(self) -> list[dict]:
        return [e for cid in sorted(self.chunk_errors) for e in self.chunk_errors[cid]]

    def __call__(self, cid, slices, result):
        self.chunk_errors[cid] = result.get("errors", [])
        if self.hosts.count > 1:
            self.kept[cid] = result
            return
        for name, a in self.arrays.items():
            a[slices] = result[name]


def _retry_errors(chunks: Chunks, path: Path, spec: OutputSpec, space: Space):
    """Recompute the points whose status is ``error`` in the store and write them back (their
    chunks' errors and checksums too)."""
    group = _store.open_group(path, "r+")
    status = np.asarray(group["status"][...])
    where = np.argwhere(status == spec.error_code)
    if where.size == 0:
        return
    grid = space.grid
    names = space.names
    pts = (
        np.stack([space.values[n][where[:, i]] for i, n in enumerate(names)], axis=1)
        if grid
        else np.stack([space.values[n][where[:, 0]] for n in names], axis=1)
    )
    new_status, values, errors = chunks.recompute(pts)
    index = tuple(where.T)
    for v in spec.variables:
        group[v.name].vindex[index] = values[v.name].astype(v.dtype)
    group["status"].vindex[index] = new_status
    chunk_of = [
        int(
            np.ravel_multi_index(
                tuple(i // c for i, c in zip(w, space.chunk_shape)), space.chunk_grid
            )
        )
        for w in where
    ]
    for cid in sorted(set(chunk_of)):
        records = [
            e
            for e in _store.errors_of_chunk(group, space, cid)
            if tuple(e["index"]) not in {tuple(int(x) for x in w) for w in where}
        ]
        records += [
            {
                "point": dict(zip(names, pts[i].tolist())),
                "index": [int(x) for x in where[i]],
                "message": msg,
            }
            for i, msg in errors.items()
            if chunk_of[i] == cid
        ]
        _store.rewrite_chunk_record(group, space, spec, cid, records)


def sweep(
    quantity: Callable[..., Any],
    axes: Mapping[str, Any] | None = None,
    *,
    points: Mapping[str, Any] | None = None,
    chunk_size: int | None = None,
    store: str | os.PathLike | None = None,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    devices: int | Sequence[Any] | None = None,
    dims: Mapping[str, Sequence[str]] | None = None,
    attrs: Mapping[str, Any] | None = None,
    desc: str = "sweep",
    postprocess: Callable[[dict], dict] | None = None,
    retry_errors: bool = False,
    client: Any = None,
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
    - `chunk_size`: at most this many points per compiled call (memory is O(``chunk_size``));
      default :data:`CHUNK_PER_DEVICE` (8192) per CPU device, 2²⁰ per GPU. The chunks are
      blocks of the grid, dealt to the devices point by point; every call is padded to one
      shape. Larger chunks waste less at the end of each call (the last trajectories of a share
      run on few lanes), smaller ones report progress and save to the store more often.
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
    - `desc`: the label of the progress bar and of the summary line.
    - `postprocess`: optional host function applied to each finished chunk, ``{name: array} ->
      {name: array}`` of the same shapes and dtypes (e.g. sorting eigenvalues on the host).
    - `retry_errors`: with ``resume``, also recompute the points of the store whose evaluation
      raised (status ``error``), e.g. after fixing the cause.
    - `client`: a :class:`distributed.Client` (``pip install 'rbo_jax[dask]'``): every chunk
      becomes one task of its cluster (see below); ``devices`` then counts each worker's local
      devices (``None``: all).

    **Returns:** an :class:`xarray.Dataset` with coordinates the parameters (grid: one dimension
    per axis; points: dimension ``point``), one variable per output, and ``status`` (int8 codes,
    names in its ``flag_meanings``; non-finite parameters give ``nonfinite_input`` and NaN values,
    points whose evaluation raised ``error``); ``attrs["status_counts"]`` counts the statuses,
    ``attrs["errors"]`` lists the raised points with their coordinates and messages. With a store
    the dataset is read from it (lazily). The same on every process of a multi-process run (an
    in-memory multi-process sweep lists the messages of its own process only).

    Without a store, a grid whose results would not fit in half the memory is refused before any
    work. With a store, one process writes it at a time (``STORE.lock`` beside it names the
    owner; a lock left by a dead process is taken over).

    Multi-process (after ``jax.distributed.initialize``): every process calls ``sweep`` with the
    same arguments; the store must be on a file system that all of them see.

    On Dask (``client``): this process traces the quantity, holds the store's lock and writes
    every chunk as it arrives (checksums, ``resume`` as above); the workers (which need rbo_jax
    and see the same Python modules) run the same chunk program — the quantity is cloudpickled
    (lambdas and closures are fine), traced once per worker process, compiled at most once
    (loaded from this process's :func:`rbo_jax.enable_compilation_cache` directory when it is
    on), under this process's float64 and promotion settings. An idle worker takes the next
    chunk; at most two tasks per worker thread are in flight, so memory does not grow with the
    grid; the chunks of a worker that dies are computed again by the others (the scheduler's
    ``allowed-failures``). Values, statuses and error records equal a one-process sweep's bit
    for bit (same program, padding and batch, given the same number of devices per process).
    ``retry_errors`` recomputes its few points in this process. Not combined with
    ``jax.distributed``.
    """
    if client is not None:
        devices = check_devices(devices)
    # with a client this process only traces (the outputs' structure; the program that one-device
    # workers load from the program store): on one device
    if client is None:
        warn_if_few_devices(devices)
    local = local_devices(1 if client is not None else devices)
    if chunk_size is None:
        chunk_size = _chunk_per_device(local) * (len(local) if client is None else (devices or 1))
    space = make_space(axes, points, chunk_size)
    attrs = _check_attrs(attrs)
    if (resume or retry_errors) and store is None:
        raise ValueError("resume=True and retry_errors=True need a store.")
    path = None if store is None else Path(store)
    if path is not None and (resume or retry_errors) and not overwrite:
        space = _store.resumed_layout(path, space)
    hosts = Hosts()
    if client is not None and hosts.count > 1:
        raise ValueError(
            "client=... (Dask) and jax.distributed are exclusive: run the sweep in "
            "one process, the cluster's workers compute its chunks."
        )
    chunks = Chunks(quantity, space, local, dims, postprocess)  # traced now, compiled later
    spec = chunks.spec
    runner = (
        chunks
        if client is None
        else DaskChunks(client, chunks, quantity, dims, postprocess, devices)
    )
    if path is None:
        _check_memory(space, spec)
        consume = _InMemory(space, spec, hosts)
        mine = hosts.share(list(range(space.n_chunks)))
        bar = _progress_bar(progress, space, mine, hosts, desc)
        _run_chunks(runner, mine, consume, bar, hosts, path)
        if hosts.count > 1:
            hosts.gather(consume.arrays, consume.kept, list(range(space.n_chunks)), space, spec)
        ds = dataset(space, spec, consume.arrays, {**attrs, "errors": consume.errors})
    else:
        lock = StoreLock(path) if hosts.index == 0 else contextlib.nullcontext()
        with lock:
            space, missing = _open_store(
                path, space, spec, attrs, resume or retry_errors, overwrite, hosts
            )
            if hosts.count > 1:
                bar = _progress_bar(progress, space, None, hosts, desc)
                _run_shares(
                    runner, hosts.take(missing), _store.Writer(path, spec), bar, hosts, path, space
                )
            else:
                mine = hosts.share(missing)
                bar = _progress_bar(progress, space, mine, hosts, desc)
                _run_chunks(runner, mine, _store.Writer(path, spec), bar, hosts, path)
            if hosts.index == 0:
                if retry_errors:
                    _retry_errors(chunks, path, spec, space)
                _store.finalize(path)
            hosts.live("store finalized")  # a barrier that a lost process does not block
        ds = _store.open_sweep(path)
    if progress and hosts.index == 0:
        print(f"{desc}: {summary_line(ds.attrs['status_counts'])}", file=sys.stderr)
    return ds
