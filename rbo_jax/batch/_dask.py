"""Sweeps on Dask: each chunk is one task of a :class:`distributed.Client`
(``sweep(..., client=client)``).

Dask is the scheduler that the xarray/zarr community already runs on laptops, clusters and
SLURM/PBS machines (through dask-jobqueue); with it a sweep survives the loss of any host and
keeps every worker busy. (The ``jax.distributed`` path, ``_hosts.py``, survives the loss of a
process other than 0, whose coordination service every process needs; Dask's scheduler can run
apart from the workers.) How:

- **One writer.** The client process traces the quantity (for the outputs' structure and the
  store's layout), holds the store's lock and writes every chunk as its result arrives, with
  :class:`rbo_jax.batch._store.Writer` (data, checksum, done marker last). The store, its
  checksums and ``resume`` are therefore those of a one-process sweep: only missing chunks are
  submitted, and a chunk counts as done once it is on disk, whoever computed it.
- **The same program on the workers.** A task is :func:`compute_chunk`: the worker unpickles the
  job (the quantity, the layout of a chunk, the devices, the client's JAX settings and its
  compilation cache; cloudpickled once per sweep by the client, so lambdas and closures travel)
  and builds its :class:`~rbo_jax.batch._chunks.Chunks` once per process (a cache keyed by the
  job's hash): the quantity is traced once per worker, not per task, and with the program store
  on (:func:`rbo_jax.enable_compilation_cache`, the client's directory) loaded from it and
  compiled at most once. Chunks are padded as on one process, with the same batch, under the
  client's precision and promotion settings (``jax_enable_x64`` and the others that key a
  stored program), so a point's values are bit for bit those of the one-process sweep, on any
  number of devices (:mod:`rbo_jax.batch._program`).
- **Only points travel.** A worker's space holds no values: the client sends each task its
  chunk's points (``chunk_size`` x parameters floats), so a list of a million points is never
  shipped whole to every worker.
- **No fixed shares, bounded memory.** At most ``IN_FLIGHT_PER_THREAD`` tasks per worker thread
  (at least ``MIN_IN_FLIGHT``) are submitted; a new one is added as each result arrives
  (:func:`distributed.as_completed`), and the scheduler gives it to whichever worker is idle.
  Neither the scheduler nor the client holds more than that many chunks, whatever the grid.
- **Lost workers.** The scheduler runs again elsewhere the tasks of a worker that dies; a task
  whose workers died more than ``distributed.scheduler.allowed-failures`` times (3 by default)
  is reported (:class:`~rbo_jax.SweepError`): the quantity probably kills its process (memory,
  a crash in native code). An exception inside a task is not retried: the points that raise
  are already isolated there (status ``error``, as on one process), so what still raises is
  deterministic (e.g. a quantity returning bad status codes) and would raise again.

``distributed`` and ``cloudpickle`` are imported only here, and only when a client is given.
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import math
import pickle
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .. import _cache, _programs
from ._chunks import Chunks
from ._errors import SweepError
from ._program import local_devices
from ._space import Space

IN_FLIGHT_PER_THREAD = 2  # tasks submitted per worker thread: one running, one queued
MIN_IN_FLIGHT = 2  # before any worker has joined (a scheduler whose workers are on their way)
_THREADS_CHECK_S = 1.0  # how often the client asks the scheduler for its worker threads
_KEEP = 4  # jobs (their traced Chunks) kept per worker process


def check_devices(devices):
    """With a client, ``devices`` counts each worker's local devices (``None``: all of them);
    device objects belong to this process and cannot be sent."""
    if devices is None or (
        isinstance(devices, (int, np.integer)) and not isinstance(devices, bool) and devices >= 1
    ):
        return None if devices is None else int(devices)
    raise ValueError(
        "with client=..., devices must be None (all of each worker's local devices) "
        f"or a number of them, got {devices!r}."
    )


@dataclasses.dataclass(frozen=True)
class _Job:
    """What a worker needs to build the chunk program of a sweep (pickled once by the client)."""

    quantity: Any
    names: tuple[str, ...]
    grid: bool
    chunk_shape: tuple[int, ...]
    dims: Any
    postprocess: Any
    devices: int | None
    settings: dict  # the client's JAX settings that change a trace (rbo_jax._programs._FLAGS)
    cache_dir: str | None  # the client's compilation cache and program store, if on

    def build(self) -> Chunks:
        for name, value in self.settings.items():
            if getattr(jax.config, name) != value:
                jax.config.update(name, value)
        if self.cache_dir is not None:
            store = _cache.program_store()
            if store is None or store != Path(self.cache_dir) / "programs":
                _cache.enable_compilation_cache(self.cache_dir)
        space = Space(self.names, {n: np.empty(0) for n in self.names}, self.grid, self.chunk_shape)
        return Chunks(
            self.quantity, space, local_devices(self.devices), self.dims, self.postprocess
        )


# -- the worker's side ----------------------------------------------------------------------

_LOCK = threading.Lock()
_JOBS: collections.OrderedDict[str, Chunks] = collections.OrderedDict()
BUILT: collections.Counter = collections.Counter()  # jobs built in this process, by token


def _chunks_of(token: str, blob: bytes) -> Chunks:
    """The job's Chunks, built once per process (worker threads wait for the first build)."""
    with _LOCK:
        chunks = _JOBS.get(token)
        if chunks is None:
            chunks = pickle.loads(blob).build()
            _JOBS[token] = chunks
            BUILT[token] += 1
            while len(_JOBS) > _KEEP:
                _JOBS.popitem(last=False)
        else:
            _JOBS.move_to_end(token)
    return chunks


def compute_chunk(token: str, blob: bytes, cid: int, slices, points: np.ndarray) -> dict:
    """One task: chunk ``cid`` (its ``points``, in the order of the client's space) through the
    job's program; the result of :meth:`Chunks.finish` (raising points isolated)."""
    chunks = _chunks_of(token, blob)
    return chunks.compute_points(cid, slices, points)


# -- the client's side ----------------------------------------------------------------------


class DaskChunks:
    """Runs the chunks of a sweep on a Dask cluster: the ``run`` of :class:`Chunks` (same
    ``consume(cid, slices, result)`` in this process, as results arrive)."""

    def __init__(self, client, chunks: Chunks, quantity, dims, postprocess, devices):
        import cloudpickle

        space = chunks.space
        store = _cache.program_store()
        job = _Job(
            quantity,
            space.names,
            space.grid,
            space.chunk_shape,
            dims,
            postprocess,
            devices,
            {name: getattr(jax.config, name) for name in _programs._FLAGS},
            None if store is None else str(store.parent),
        )
        try:
            self.blob = cloudpickle.dumps(job)
        except Exception as e:  # a lock, an open file, a C object in the quantity's closure
            raise TypeError(
                "client=...: the quantity (and postprocess) must be picklable to "
                f"run on Dask workers; cloudpickle failed: {type(e).__name__}: {e}"
            ) from e
        self.token = hashlib.blake2b(self.blob, digest_size=16).hexdigest()
        self.client, self.space = client, space
        self._threads, self._checked = 0, -math.inf

    def _in_flight(self) -> int:
        """How many tasks may be submitted: per worker thread of the cluster as it is now
        (workers may join or leave during a sweep; asked at most once a second)."""
        now = time.monotonic()
        if now - self._checked > _THREADS_CHECK_S:
            self._threads = sum(self.client.nthreads().values())
            self._checked = now
        return max(MIN_IN_FLIGHT, IN_FLIGHT_PER_THREAD * self._threads)

    def run(self, chunk_ids, consume, bar=None):
        from distributed import as_completed
        from distributed.scheduler import KilledWorker

        space, run_id = self.space, uuid.uuid4().hex[:8]
        todo = iter(chunk_ids)
        submitted: dict = {}  # task key -> (chunk id, slices, future)
        # results fetched by the client's event loop as tasks finish, not on request from here
        done = as_completed(with_results=True, raise_errors=False)

        def top_up():
            while len(submitted) < self._in_flight():
                cid = next(todo, None)
                if cid is None:
                    return
                slices = space.slices(cid)
                future = self.client.submit(
                    compute_chunk,
                    self.token,
                    self.blob,
                    cid,
                    slices,
                    space.points(slices),
                    key=f"rbo_jax-sweep-chunk-{run_id}-{cid}",
                    pure=False,
                    retries=0,
                )
                submitted[future.key] = (cid, slices, future)
                done.add(future)

        self._in_flight()  # asks the scheduler how many worker threads it has
        if bar is not None and self._threads == 0:
            print(
                f"rbo_jax.sweep: no Dask worker yet; waiting for workers of "
                f"{self.client.scheduler.address}.",
                file=sys.stderr,
            )
        try:
            top_up()
            for future, result in done:
                cid, slices, _ = submitted.pop(future.key)
                try:
                    if future.status != "finished":
                        future.result()  # raises the task's error, with its traceback
                except KilledWorker as e:
                    raise SweepError(
                        f"chunk {cid} was lost with every worker that ran it ({e}); the "
                        "quantity probably ends its process (memory, a crash in native code). "
                        "The chunks already written are kept: fix the cause and resume the "
                        "sweep (resume=True, CLI --resume)."
                    ) from None
                consume(cid, slices, result)
                if bar is not None:
                    bar.update(math.prod(sl.stop - sl.start for sl in slices))
                future.release()
                top_up()
        finally:
            if submitted:  # an error or an interruption: nothing more is computed
                self.client.cancel([f for _, _, f in submitted.values()])
