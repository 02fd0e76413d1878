"""The sweep store: a `Zarr <https://zarr.dev>`_ (format 3) directory laid out as xarray writes one.

One array per variable on the grid dimensions, with zarr chunks equal to sweep chunks, so every
sweep chunk is exactly one file per variable (atomic writes by zarr; no two processes ever write
the same file). In the hidden group ``_sweep`` every chunk has a checksum (BLAKE2b of the bytes of
its data, written after the data) and a done marker (written last); the points of a chunk whose
evaluation raised are listed in ``_sweep/errors/CHUNK.json``. The store's metadata is
consolidated (at creation and when the sweep finishes), so ``xarray.open_zarr(PATH)`` opens it
directly. :func:`open_sweep` checks that the store is complete and that every chunk matches its
checksum (a crash mid-write, a flipped byte); ``resume=True`` recomputes the chunks without a
marker and those that fail their checksum, and the store then ends byte for byte identical to an
uninterrupted run's.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import shutil
import sys
import warnings
from pathlib import Path

import numpy as np

from ._errors import SweepError
from ._output import OutputSpec, counts, fill_value, to_json
from ._space import POINT_DIM, Space

FORMAT = "rbo_jax.sweep"
FORMAT_VERSION = 2  # 2: chunk checksums and error records (rbo_jax 0.2)
META = "_sweep"  # hidden subgroup of the store (markers); xarray does not open subgroups
_PARTIAL = re.compile(r"\.[0-9a-f]{32}\.partial$")


def _zarr():
    try:
        import zarr
    except ImportError as e:  # exercised on Python 3.10, where zarr >= 3 does not install
        raise ImportError(
            "sweep(store=...) needs zarr >= 3, which needs Python >= 3.11: pip install 'zarr>=3'"
        ) from e
    return zarr


def open_group(path, mode):
    return _zarr().open_group(str(path), mode=mode, zarr_format=3)


def consolidate(path: Path):
    """Consolidate the store's metadata, so that ``xarray.open_zarr`` reads it in one go and
    without its "failed to open with consolidated metadata" warning. (zarr notes that
    consolidated metadata is not yet part of the format 3 specification; zarr and xarray read
    it, which is what this store is for.)"""
    zarr = _zarr()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part")
        zarr.consolidate_metadata(str(path))


def descriptor(space: Space, spec: OutputSpec) -> dict:
    """The store's own layout (attribute ``rbo_jax.sweep``): what resuming must match."""
    return to_json(
        {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "mode": "grid" if space.grid else "points",
            "names": list(space.names),
            "dims": list(space.dims),
            "shape": list(space.shape),
            "chunk_shape": list(space.chunk_shape),
            **spec.describe(),
        }
    )


def read_descriptor(group, path) -> dict:
    d = group.attrs.get(FORMAT)
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise SweepError(f"{path} is not an rbo_jax sweep store (no {FORMAT!r} attribute).")
    if d.get("format_version") != FORMAT_VERSION:
        raise SweepError(
            f"{path}: sweep store format {d.get('format_version')} is not supported "
            f"(this rbo_jax writes {FORMAT_VERSION})."
        )
    return d


def space_from_store(group, d) -> Space:
    names = tuple(d["names"])
    values = {n: np.asarray(group[n][...]) for n in names}
    return Space(names, values, d["mode"] == "grid", tuple(d["chunk_shape"]))


def _create(path: Path, space: Space, spec: OutputSpec, attrs: dict):
    group = open_group(path, "w")
    config = {"write_empty_chunks": True}
    for n in space.names:  # a grid's axis in one chunk; a list's values in the points' chunks
        shape = space.values[n].shape
        a = group.create_array(
            n,
            shape=shape,
            dtype="float64",
            chunks=shape if space.grid else space.chunk_shape,
            dimension_names=[n if space.grid else POINT_DIM],
            fill_value=np.nan,
            config=config,
        )
        a[...] = space.values[n]
    point_coords = {} if space.grid else {"coordinates": " ".join(space.names)}
    for v in spec.variables:
        group.create_array(
            v.name,
            shape=space.shape + v.shape,
            dtype=v.dtype,
            chunks=space.chunk_shape + v.shape,
            dimension_names=list(space.dims + v.dims),
            fill_value=fill_value(v.dtype),
            attributes=to_json({**v.attrs(), **point_coords}),
            config=config,
        )
    group.create_array(
        "status",
        shape=space.shape,
        dtype="int8",
        chunks=space.chunk_shape,
        dimension_names=list(space.dims),
        fill_value=-1,
        attributes=to_json({**spec.status_attrs(), **point_coords}),
        config=config,
    )
    meta = group.create_group(META)
    for name, dtype in (("chunk_done", "uint8"), ("checksum", "uint64")):  # one value per chunk
        meta.create_array(
            name,
            shape=space.chunk_grid,
            dtype=dtype,
            chunks=(1,) * len(space.chunk_grid),
            fill_value=0,
            compressors=None,
            config=config,
        )
    # the error records of a chunk (JSON text; "" when none raised), one file per chunk
    meta.create_array(
        "errors",
        shape=space.chunk_grid,
        dtype=str,
        chunks=(1,) * len(space.chunk_grid),
        fill_value="",
        config=config,
    )
    group.attrs.update(to_json({**attrs, FORMAT: descriptor(space, spec)}))
    consolidate(path)
    return group


def check_compatible(group, path, space: Space, spec: OutputSpec, attrs: dict) -> Space:
    """The store's space if it was made by the same sweep (its chunk layout wins), else raise."""
    d = read_descriptor(group, path)
    new = descriptor(space, spec)
    diffs = [k for k in new if k != "chunk_shape" and new[k] != d.get(k)]
    if diffs:
        detail = "; ".join(f"{k}: store {d.get(k)!r}, now {new[k]!r}" for k in diffs)
        raise SweepError(f"cannot resume {path}: it was written by a different sweep ({detail}).")
    stored = space_from_store(group, d)
    for n in space.names:
        if not np.array_equal(stored.values[n], space.values[n], equal_nan=True):
            raise SweepError(f"cannot resume {path}: the values of {n!r} differ from the store's.")
    for k, v in to_json(attrs).items():
        if group.attrs.get(k) != v:
            raise SweepError(
                f"cannot resume {path}: attribute {k!r} differs from the store's "
                "(e.g. a different configuration)."
            )
    return stored


def resumed_layout(path: Path, space: Space) -> Space:
    """The space with the chunk layout of an existing store (a resumed sweep keeps it)."""
    if not (path / "zarr.json").exists():
        return space
    d = read_descriptor(open_group(path, "r"), path)
    shape = d.get("chunk_shape")
    if not (isinstance(shape, list) and len(shape) == len(space.shape)):
        return space  # check_compatible reports the mismatch
    return dataclasses.replace(space, chunk_shape=tuple(int(c) for c in shape))


def missing_chunks(group, space: Space) -> list[int]:
    done = np.asarray(group[f"{META}/chunk_done"][...]).ravel()
    return [int(i) for i in np.flatnonzero(done == 0)]


def _remove_partial_files(path: Path):
    """Temporary files of zarr's atomic writes left by a killed writer."""
    for root, _, files in os.walk(path):
        for f in files:
            if _PARTIAL.search(f):
                Path(root, f).unlink(missing_ok=True)


def prepare(path: Path, space, spec, attrs, resume, overwrite) -> Space:
    """Create the store, or open it to resume (checking it is the same sweep). Returns the
    space with the store's chunk layout."""
    if path.exists() and not (path.is_dir() and not any(path.iterdir())):
        if not (path / "zarr.json").exists():
            raise SweepError(f"{path} exists and is not a zarr store; choose another path.")
        if overwrite:
            shutil.rmtree(path)
        elif not resume:
            raise FileExistsError(
                f"{path} already holds a sweep: pass resume=True (CLI: --resume) to finish it, "
                "or overwrite=True to start again."
            )
        else:
            group = open_group(path, "r+")
            space = check_compatible(group, path, space, spec, attrs)
            _remove_partial_files(path)
            bad = corrupted_chunks(group, space, spec, _done_chunks(group, space))
            for cid, why in sorted(bad.items()):
                print(f"rbo_jax.sweep: {path}: chunk {cid} is recomputed: {why}.", file=sys.stderr)
            mark_missing(group, space, bad)
            return space
    _create(path, space, spec, attrs)
    return space


def checksum(arrays) -> int:
    """BLAKE2b (64 bits) of the bytes of a chunk's arrays, in order."""
    h = hashlib.blake2b(digest_size=8)
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return int.from_bytes(h.digest(), "little")


def _names(spec: OutputSpec) -> list[str]:
    return [v.name for v in spec.variables] + ["status"]


class Writer:
    """Writes computed chunks into the store: data, errors, checksum, the done marker last."""

    def __init__(self, path: Path, spec: OutputSpec):
        group = open_group(path, "r+")
        self.path = Path(path)
        self.names = _names(spec)
        self.arrays = {name: group[name] for name in self.names}
        self.done = group[f"{META}/chunk_done"]
        self.sums = group[f"{META}/checksum"]
        self.errors = group[f"{META}/errors"]

    def __call__(self, cid, slices, result):
        for name in self.names:
            self.arrays[name][slices] = result[name]
        index = np.unravel_index(cid, self.done.shape)
        self.errors[index] = json.dumps(result["errors"]) if result.get("errors") else ""
        self.sums[index] = np.uint64(
            checksum(np.asarray(result[n], dtype=self.arrays[n].dtype) for n in self.names)
        )
        # The marker last: a chunk counts as done only once all its data is on disk.
        self.done[index] = 1


def errors(path: Path) -> list[dict]:
    """The error records of every chunk (points whose evaluation raised), in chunk order."""
    texts = np.asarray(open_group(path, "r")[f"{META}/errors"][...]).ravel()
    return [r for text in texts if text for r in json.loads(str(text))]


def corrupted_chunks(group, space: Space, spec: OutputSpec, chunk_ids) -> dict[int, str]:
    """``{chunk: reason}`` of the done chunks whose data does not match its checksum or cannot
    be read (a truncated or corrupted file)."""
    sums = np.asarray(group[f"{META}/checksum"][...])
    bad = {}
    for cid in chunk_ids:
        slices = space.slices(cid)
        try:
            data = [np.asarray(group[n][slices]) for n in _names(spec)]
        except Exception as e:  # a file zarr cannot decode
            bad[cid] = f"unreadable ({type(e).__name__}: {e})"
            continue
        if checksum(data) != int(sums[np.unravel_index(cid, space.chunk_grid)]):
            bad[cid] = "its data does not match its checksum"
    return bad


def errors_of_chunk(group, space: Space, cid: int) -> list[dict]:
    text = str(group[f"{META}/errors"][np.unravel_index(cid, space.chunk_grid)])
    return json.loads(text) if text else []


def rewrite_chunk_record(group, space: Space, spec: OutputSpec, cid: int, records: list[dict]):
    """After points of chunk ``cid`` were rewritten: its error records and checksum."""
    index = np.unravel_index(cid, space.chunk_grid)
    group[f"{META}/errors"][index] = json.dumps(records) if records else ""
    slices = space.slices(cid)
    data = [np.asarray(group[n][slices]) for n in _names(spec)]
    group[f"{META}/checksum"][index] = np.uint64(checksum(data))


def mark_missing(group, space: Space, chunk_ids):
    """Clear the done markers of ``chunk_ids`` (they will be recomputed)."""
    done = group[f"{META}/chunk_done"]
    for cid in chunk_ids:
        done[np.unravel_index(cid, space.chunk_grid)] = 0


def finalize(path: Path):
    """Record the status counts and the errors, and consolidate the metadata, of a finished
    store."""
    group = open_group(path, "r+")
    d = read_descriptor(group, path)
    status = np.asarray(group["status"][...])
    group.attrs.update(
        to_json({"status_counts": counts(status, d["status_flags"]), "errors": errors(path)})
    )
    consolidate(path)


def _done_chunks(group, space):
    done = np.asarray(group[f"{META}/chunk_done"][...]).ravel()
    return [int(i) for i in np.flatnonzero(done == 1)]


def open_sweep(path, *, allow_incomplete: bool = False, verify: bool = True):
    """Open a sweep store written by :func:`rbo_jax.sweep` as a labelled
    :class:`xarray.Dataset` (lazily: values are read on access; ``.load()`` reads them all).

    Raises :class:`rbo_jax.SweepError` if some chunks are missing (an interrupted sweep: finish
    it with ``sweep(..., store=path, resume=True)``) unless ``allow_incomplete`` (missing points
    then hold the fill values: NaN, and status -1), and, with ``verify`` (default), if a chunk's
    data does not match its checksum (``resume=True`` recomputes such chunks). The points whose
    evaluation raised are listed in ``ds.attrs["errors"]``.
    """
    import xarray as xr

    path = Path(path)
    if not (path / "zarr.json").exists():
        raise FileNotFoundError(f"{path} is not a zarr store.")
    group = open_group(path, "r")
    d = read_descriptor(group, path)
    space = space_from_store(group, d)
    missing = missing_chunks(group, space)
    if missing and not allow_incomplete:
        raise SweepError(
            f"{path} is incomplete: {len(missing)} of {space.n_chunks} chunks "
            "missing; finish it with sweep(..., store=path, resume=True)."
        )
    if verify:
        bad = corrupted_chunks(
            group, space, OutputSpec.from_description(d), _done_chunks(group, space)
        )
        if bad:
            detail = "; ".join(f"chunk {c}: {why}" for c, why in sorted(bad.items())[:5])
            raise SweepError(
                f"{path}: {len(bad)} chunk(s) fail their checksum ({detail}); "
                "resume the sweep (resume=True, CLI --resume) to recompute them."
            )
    # Stores written before rbo_jax consolidated their metadata are read without it.
    consolidated = group.metadata.consolidated_metadata is not None
    ds = xr.open_zarr(str(path), consolidated=consolidated, chunks=None, zarr_format=3)
    ds.attrs.pop(FORMAT, None)  # the store's own layout, not a property of the result
    ds.attrs.setdefault("errors", errors(path))
    return ds
