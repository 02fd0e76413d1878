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
- **Loop** (:class:`Chunks`, here): one chunk is computed while the previous one is stored
  (dispatch is asynchronous); a progress bar counts points.
- **Output** (``_output.py``): values and a status per point, assembled into a Dataset.
- **Store** (``_store.py``): with ``store=PATH`` each chunk is written to a zarr store as soon as
  it is computed; ``resume=True`` finishes an interrupted sweep.
- **Hosts** (``_hosts.py``): after ``jax.distributed.initialize(...)`` every process computes its
  share of the chunks.

**Bad points** never stop the sweep. Each point carries a ``status``: the quantity returns
``(values, status)`` with ``status`` an :class:`equinox.Enumeration` item (typically
:class:`rbo_jax.SolveStatus` from ``simulate(..., throw=False)``, or
:class:`rbo_jax.EquilibriumStatus`) or an integer code of :class:`rbo_jax.SolveStatus`. Points
with a non-finite parameter are not evaluated at all (they would raise in the models'
constructors); they get ``nonfinite_input`` and NaN values. :func:`status_counts` counts the
statuses (also stored in ``ds.attrs["status_counts"]``).
"""

from __future__ import annotations

import math
import os
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from . import _store
from ._errors import SweepError
from ._hosts import Hosts
from ._output import (
    OutputSpec,
    dataset,
    fill_value,
    make_output_spec,
    summary_line,
    to_json,
)
from ._program import local_devices, program
from ._space import Space, make_space


def error_text(e: Exception) -> str:
    """The message of a runtime error raised inside compiled code, without the host traceback
    that jax wraps around a failing callback (equinox.error_if)."""
    text = str(e)
    found = re.findall(r"EquinoxRuntimeError: (.+)", text)
    if found:
        return found[-1].strip()
    return text if len(text) <= 600 else text[:600] + " ..."


class Chunks:
    """Runs chunks through the compiled program, one chunk in flight while the previous one is
    stored (dispatch is asynchronous). ``postprocess`` (optional) maps a finished chunk's host
    arrays ``{name: array}`` to new arrays of the same shapes and dtypes."""

    def __init__(self, quantity, space: Space, devices, dims=None, postprocess=None):
        n_dev = len(devices)
        self.batch = -(-space.chunk_points // n_dev) * n_dev
        self.program = program(quantity, space.names, tuple(devices), self.batch)
        self.space = space
        self.spec: OutputSpec = make_output_spec(self.program.structure, space, dims)
        self.dummy = space.dummy()
        self.postprocess = postprocess

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

    def _host_values(self, cid, m, future):
        spec = self.spec
        if future is None:
            return (np.zeros(m, np.int32),
                    {v.name: np.zeros((m,) + v.shape, v.dtype) for v in spec.variables})
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
        return status, {v.name: np.asarray(values[v.name])[:m] for v in spec.variables}

    def finish(self, cid, slices, valid, future):
        block_shape = tuple(sl.stop - sl.start for sl in slices)
        status, out = self._host_values(cid, valid.size, future)
        status = np.where(valid, status, self.spec.nonfinite_code).astype(np.int8)
        result = {}
        for v in self.spec.variables:
            a = out[v.name].astype(v.dtype, copy=True)
            a[~valid] = fill_value(v.dtype)
            result[v.name] = a.reshape(block_shape + v.shape)
        result["status"] = status.reshape(block_shape)
        if self.postprocess is not None:
            result = self.postprocess(result)
        return cid, slices, result

    def error(self, cid: int, e: Exception) -> SweepError:
        slices = self.space.slices(cid)
        pts = self.space.points(slices)
        first = dict(zip(self.space.names, pts[0].tolist()))
        return SweepError(
            f"chunk {cid} ({pts.shape[0]} points, the first {first}) raised: {error_text(e)}\n"
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
# The sweep.
# ---------------------------------------------------------------------------------------------


def _check_attrs(attrs) -> dict:
    attrs = to_json(dict(attrs or {}))
    for k in attrs:
        if k in (_store.FORMAT, "status_counts"):
            raise ValueError(f"attrs: {k!r} is reserved.")
    return attrs


def _open_store(path: Path, space: Space, spec: OutputSpec, attrs, resume, overwrite,
                hosts: Hosts) -> tuple[Space, list[int]]:
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

    n_mine = sum(int(math.prod(s.stop - s.start for s in space.slices(c))) for c in mine)
    label = desc if hosts.count == 1 else f"{desc} [process {hosts.index}/{hosts.count}]"
    return tqdm(total=n_mine, desc=label, unit="pt", unit_scale=True, dynamic_ncols=True)


def _run_chunks(chunks: Chunks, mine, consume, bar, hosts: Hosts, path):
    """Run this process's chunks; every process meets afterwards, errors are re-raised."""
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
    postprocess: Callable[[dict], dict] | None = None,
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
    - `desc`: the label of the progress bar and of the summary line.
    - `postprocess`: optional host function applied to each finished chunk, ``{name: array} ->
      {name: array}`` of the same shapes and dtypes (e.g. sorting eigenvalues on the host).

    **Returns:** an :class:`xarray.Dataset` with coordinates the parameters (grid: one dimension
    per axis; points: dimension ``point``), one variable per output, and ``status`` (int8 codes,
    names in its ``flag_meanings``; non-finite parameters give ``nonfinite_input`` and NaN values);
    ``attrs["status_counts"]`` counts the statuses. With a store the dataset is read from it
    (lazily). The same on every process of a multi-process run.

    Multi-process (after ``jax.distributed.initialize``): every process calls ``sweep`` with the
    same arguments; the store must be on a file system that all of them see.
    """
    space = make_space(axes, points, chunk_size)
    local = local_devices(devices)
    attrs = _check_attrs(attrs)
    if resume and store is None:
        raise ValueError("resume=True needs a store.")
    path = None if store is None else Path(store)
    if path is not None and resume and not overwrite:
        space = _store.resumed_layout(path, space)
    hosts = Hosts()
    chunks = Chunks(quantity, space, local, dims, postprocess)  # traced now, compiled later
    spec = chunks.spec
    if path is not None:
        space, missing = _open_store(path, space, spec, attrs, resume, overwrite, hosts)
        consume, arrays, kept = _store.Writer(path, spec), None, None
    else:
        missing = list(range(space.n_chunks))
        arrays = {v.name: np.empty(space.shape + v.shape, v.dtype) for v in spec.variables}
        arrays["status"] = np.empty(space.shape, np.int8)
        kept = {}

        def consume(cid, slices, result):
            if hosts.count == 1:
                for name, a in result.items():
                    arrays[name][slices] = a
            else:
                kept[cid] = result

    mine = hosts.share(missing)
    bar = _progress_bar(progress, space, mine, hosts, desc)
    _run_chunks(chunks, mine, consume, bar, hosts, path)
    if path is not None:
        if hosts.index == 0:
            _store.finalize(path)
        hosts.barrier("store finalized")
        ds = _store.open_sweep(path)
    else:
        if hosts.count > 1:
            hosts.gather(arrays, kept, missing, space, spec)
        ds = dataset(space, spec, arrays, attrs)
    if progress and hosts.index == 0:
        print(f"{desc}: {summary_line(ds.attrs['status_counts'])}", file=sys.stderr)
    return ds
