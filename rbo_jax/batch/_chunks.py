"""The chunk loop of the batch engine: every sweep, map and critical-load computation runs its
chunks through :class:`Chunks`.

One chunk is computed while the previous one is stored (dispatch is asynchronous). A chunk whose
program raises (an :func:`equinox.error_if` inside the user's quantity, a failed host callback,
...) is not fatal: it is re-run in halves, down to single points, with the same compiled program
(each part padded with its own points, so no new compilation and no other point is involved);
the points that raise on their own get the status ``error``, fill values (NaN) and their message
in the chunk's ``errors`` (with their coordinates); every other point of the chunk is kept. While
chunks run, JAX's log of each failed call of an :func:`equinox.error_if` (a traceback per call,
one per re-run half) is left out (:class:`_KnownErrors`): the sweep reports each such point's
message itself; and after them a host callback that succeeds runs on every device, so that JAX
does not raise the last failed one again when it synchronises (:func:`_settle_callbacks`; at the
interpreter's exit it printed a traceback).
"""

from __future__ import annotations

import contextlib
import logging
import re
from concurrent.futures import ThreadPoolExecutor

import jax
import numpy as np

from .._sharding import deal, undeal_shards
from ._errors import SweepError
from ._output import OutputSpec, fill_value, make_output_spec
from ._program import program
from ._space import Space


def error_text(e: Exception) -> str:
    """The message of a runtime error raised inside compiled code, without the host traceback
    that jax wraps around a failing callback (equinox.error_if)."""
    text = str(e)
    found = re.findall(r"EquinoxRuntimeError: (.+)", text)
    if found:
        return found[-1].strip()
    return text if len(text) <= 600 else text[:600] + " ..."


class _KnownErrors(logging.Filter):
    """Drops JAX's log record of a host callback that raised an :func:`equinox.error_if` error
    (``logger.exception("jax.pure_callback failed")``, with its traceback): the chunk loop
    catches that error and reports the point's message. Other callback failures are kept.
    ``failed``: the failed callbacks seen."""

    def __init__(self):
        super().__init__()
        self.failed = 0

    def filter(self, record: logging.LogRecord) -> bool:
        error = record.exc_info[1] if record.exc_info else None
        self.failed += error is not None
        return not (error is not None and "EquinoxRuntimeError" in type(error).__name__)


_CALLBACK_LOGGER = "jax._src.callback"  # where jax logs a failed pure_callback


def _echo(x):
    return jax.pure_callback(lambda v: v, jax.ShapeDtypeStruct(x.shape, x.dtype), x)


_SETTLE: dict = {}  # device -> the compiled _echo


def _settle_callbacks():
    """Run a host callback that succeeds on every local device. JAX keeps, for each device, the
    runtime token of the last program there with a host callback, and waits on it when it next
    synchronises (:func:`jax.effects_barrier`, and at the interpreter's exit): after a failed
    callback it raises the error again, at exit as a traceback. The program run here becomes
    the last one: compiled ahead of time, as the chunks' programs are (a ``jax.jit`` function's
    later calls take a path that leaves JAX's record as it was)."""
    for device in jax.local_devices():
        x = jax.device_put(np.zeros((), np.float32), device)
        if device not in _SETTLE:
            _SETTLE[device] = jax.jit(_echo).lower(x).compile()
        _SETTLE[device](x).block_until_ready()


@contextlib.contextmanager
def _known_errors_unlogged():
    """The chunks run here: JAX's log of their failed ``equinox.error_if`` calls left out, and
    after a failed callback a successful one on every device (:func:`_settle_callbacks`)."""
    logger, known = logging.getLogger(_CALLBACK_LOGGER), _KnownErrors()
    logger.addFilter(known)
    try:
        yield
    finally:
        logger.removeFilter(known)
        if known.failed:
            _settle_callbacks()


class Chunks:
    """Runs chunks through the compiled program. ``postprocess`` (optional) maps a finished
    chunk's host arrays ``{name: array}`` to new arrays of the same shapes and dtypes; it gets
    writable copies, unless it says that it only reads them (a ``reads_only = True``
    attribute: the maps' sort of the eigenvalues), then it gets the read-only views of the
    program's outputs (a copy less per chunk)."""

    def __init__(self, quantity, space: Space, devices, dims=None, postprocess=None):
        self.program = program(quantity, space.names, tuple(devices), space.chunk_points)
        self.batch = self.program.batch  # the padded chunk (_program.Layout)
        self.space = space
        self.spec: OutputSpec = make_output_spec(self.program.structure, space, dims)
        self.dummy = space.dummy()
        self.postprocess = postprocess

    # -- evaluation of points --------------------------------------------------------------

    def _call(self, pts: np.ndarray):
        """Dispatch the program on ``pts`` (m ≤ batch finite points), padded with its first."""
        block = np.empty((self.batch, pts.shape[1]))
        block[:] = pts[0]
        block[: pts.shape[0]] = pts
        block = deal(block, len(self.program.devices))  # alike shares (_sharding.deal)
        return self.program.call(jax.device_put(block, self.program.sharding))

    def _host(self, future, m: int):
        """(status, values) of the first ``m`` points of a finished call (raises what the
        program raised)."""
        spec = self.spec
        values, status = future
        n_dev = len(self.program.devices)
        status = undeal_shards(status, n_dev)[:m]
        bad = (status < 0) | (status >= len(spec.status_names))
        if bad.any():
            raise SweepError(
                f"the quantity returned status codes {sorted(set(status[bad].tolist()))} "
                f"outside {spec.status_enum} (0..{len(spec.status_names) - 1})."
            )
        return status, {
            v.name: undeal_shards(values[v.name], n_dev)[:m] for v in self.spec.variables
        }

    def _empty(self, m: int, code: int):
        return (
            np.full(m, code, np.int32),
            {
                v.name: np.full((m,) + v.shape, fill_value(v.dtype), v.dtype)
                for v in self.spec.variables
            },
        )

    def isolate(self, pts: np.ndarray, error: Exception | None = None):
        """(status, values, {index: message}) of ``pts``; a part that raises is split in halves
        down to single points, which get the status ``error``. ``error`` is what a first call on
        all of ``pts`` raised, if it was already made."""
        if error is None:
            try:
                return (*self._host(self._call(pts), len(pts)), {})
            except SweepError:
                raise
            except Exception as e:  # raised inside the compiled quantity
                error = e
        if len(pts) == 1:
            return (*self._empty(1, self.spec.error_code), {0: error_text(error)})
        half = len(pts) // 2
        s1, v1, e1 = self.isolate(pts[:half])
        s2, v2, e2 = self.isolate(pts[half:])
        values = {k: np.concatenate([v1[k], v2[k]]) for k in v1}
        return np.concatenate([s1, s2]), values, e1 | {half + i: m for i, m in e2.items()}

    # -- chunks ----------------------------------------------------------------------------

    def launch(self, cid: int):
        slices = self.space.slices(cid)
        return self.launch_points(cid, slices, self.space.points(slices))

    def launch_points(self, cid: int, slices, pts: np.ndarray):
        """Dispatch chunk ``cid`` given its points (a Dask worker gets them from the client,
        whose space it does not hold: :mod:`rbo_jax.batch._dask`)."""
        valid = np.all(np.isfinite(pts), axis=1)
        future, error = None, None
        if valid.any():
            try:
                future = self._call(pts[valid])
            except SweepError:
                raise
            except Exception as e:  # a runtime error raised at dispatch
                error = e
        return cid, slices, pts, valid, future, error

    def compute_points(self, cid: int, slices, pts: np.ndarray):
        """Chunk ``cid`` from its points, dispatched and finished (a Dask worker's task), with
        JAX's log of its failed ``equinox.error_if`` calls left out, as in :meth:`run`."""
        with _known_errors_unlogged():
            return self.finish(*self.launch_points(cid, slices, pts))

    def finish(self, cid, slices, pts, valid, future, error):
        """The chunk's result ``{name: block array, "status": ..., "errors": [...]}``."""
        m = int(valid.sum())
        errors: dict[int, str] = {}
        if m == 0:
            status, out = self._empty(0, 0)
        elif error is None:
            try:
                status, out = self._host(future, m)
            except SweepError:
                raise
            except Exception as e:  # raised inside the compiled quantity: find the points
                status, out, errors = self.isolate(pts[valid], e)
        else:
            status, out, errors = self.isolate(pts[valid], error)
        return self._assemble(slices, pts, valid, status, out, errors)

    def _assemble(self, slices, pts, valid, status, out, errors):
        block_shape = tuple(sl.stop - sl.start for sl in slices)
        if valid.all():  # the common case: the outputs are the block, no fill and no scatter
            full_status = np.asarray(status, np.int8)
            # (views of the device's buffers, read-only: a postprocess gets writable copies)
            copy = self.postprocess is not None and not getattr(
                self.postprocess, "reads_only", False
            )
            result = {
                v.name: np.array(out[v.name], v.dtype, copy=copy or None).reshape(
                    block_shape + v.shape
                )
                for v in self.spec.variables
            }
        else:
            full_status = np.full(valid.size, self.spec.nonfinite_code, np.int8)
            full_status[valid] = status
            result = {}
            for v in self.spec.variables:
                a = np.full((valid.size,) + v.shape, fill_value(v.dtype), v.dtype)
                a[valid] = out[v.name]
                result[v.name] = a.reshape(block_shape + v.shape)
        result["status"] = full_status.reshape(block_shape)
        if self.postprocess is not None:
            result = self.postprocess(result)
        where = np.flatnonzero(valid)
        result["errors"] = [
            {
                "point": dict(zip(self.space.names, pts[where[i]].tolist())),
                "index": [int(x) for x in np.unravel_index(where[i], block_shape)],
                "message": msg,
            }
            for i, msg in sorted(errors.items())
        ]
        for e in result["errors"]:  # the index within the whole space, not the chunk
            e["index"] = [int(sl.start) + j for sl, j in zip(slices, e["index"])]
        return result

    def run(self, chunk_ids, consume, bar=None):
        """Compute the chunks and hand each result to ``consume(cid, slices, result)``; one chunk
        is computed while the previous one is consumed.

        The next chunk is dispatched from a worker thread: a program over several CPU devices
        can block its caller until the devices are free (most of a chunk's time in a stability
        map: benchmarks/README.md, History), which in this thread would hold up the previous
        chunk's host work (its outputs, statuses, store) until then; dispatched there, that
        work overlaps the next chunk's computation."""
        pending = None
        pool = ThreadPoolExecutor(1, thread_name_prefix="rbo_jax-dispatch")
        with _known_errors_unlogged():
            try:
                for cid in chunk_ids:
                    launched = pool.submit(self.launch, cid)
                    if pending is not None:
                        self._consume(pending, consume, bar)
                    pending = launched.result()
                if pending is not None:
                    self._consume(pending, consume, bar)
            finally:
                pool.shutdown(wait=False, cancel_futures=True)

    def _consume(self, pending, consume, bar):
        cid, slices = pending[0], pending[1]
        result = self.finish(*pending)
        consume(cid, slices, result)
        if bar is not None:
            bar.update(pending[3].size)

    def recompute(self, points: np.ndarray):
        """(status, values, errors) of arbitrary finite points (``retry_errors``), in batches."""
        with _known_errors_unlogged():
            batches = range(0, len(points), self.batch)
            outs = [self.isolate(points[i : i + self.batch]) for i in batches]
        status = np.concatenate([o[0] for o in outs]).astype(np.int8)
        values = {k: np.concatenate([o[1][k] for o in outs]) for k in outs[0][1]}
        errors, offset = {}, 0
        for o in outs:
            errors |= {offset + i: m for i, m in o[2].items()}
            offset += len(o[0])
        return status, values, errors
