"""What a sweep's quantity returns, and the labelled dataset it becomes.

A quantity returns values (an array or a dict ``{name: array}``; arrays of any fixed shape per
point, or enumeration items such as :class:`rbo_jax.StabilityKind`), optionally with a status per
point. The structure is recorded while the quantity is traced (:func:`describe_output`) and named
by :func:`make_output_spec`; :func:`dataset` assembles the :class:`xarray.Dataset`.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence

import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from ..trajectory import SolveStatus
from ._space import POINT_DIM, Space

NONFINITE = "nonfinite_input"  # status of a point whose parameters are not finite
ERROR = "error"  # status of a point whose evaluation raised


def to_json(x):
    """``x`` through JSON (plain lists, dicts, numbers, strings: what store attributes hold)."""
    return json.loads(json.dumps(x))


def split_output(out):
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
class Variable:
    """One output of the quantity: per-point shape, dtype and dimension names; ``flags``/``enum``
    for an enumeration-valued output (stored as int8 codes)."""

    name: str
    shape: tuple[int, ...]
    dtype: str
    dims: tuple[str, ...]
    flags: tuple[str, ...] | None
    enum: str | None

    def attrs(self) -> dict:
        if self.flags is None:
            return {}
        return {
            "flag_values": list(range(len(self.flags))),
            "flag_meanings": " ".join(self.flags),
            "enumeration": self.enum,
        }


@dataclasses.dataclass(frozen=True)
class OutputSpec:
    """The outputs of a quantity and the names of its status codes."""

    variables: tuple[Variable, ...]
    status_names: tuple[str, ...]
    status_enum: str

    @property
    def nonfinite_code(self) -> int:
        return self.status_names.index(NONFINITE)

    @property
    def error_code(self) -> int:
        return self.status_names.index(ERROR)

    def status_attrs(self) -> dict:
        return {
            "flag_values": list(range(len(self.status_names))),
            "flag_meanings": " ".join(self.status_names),
            "enumeration": self.status_enum,
            "long_name": "outcome of the quantity at each point",
        }

    def describe(self) -> dict:
        return {
            "variables": [dataclasses.asdict(v) for v in self.variables],
            "status_flags": list(self.status_names),
            "status_enumeration": self.status_enum,
        }

    @classmethod
    def from_description(cls, d) -> OutputSpec:
        variables = tuple(
            Variable(
                v["name"],
                tuple(v["shape"]),
                v["dtype"],
                tuple(v["dims"]),
                None if v["flags"] is None else tuple(v["flags"]),
                v["enum"],
            )
            for v in d["variables"]
        )
        return cls(variables, tuple(d["status_flags"]), d["status_enumeration"])


def _status_structure(status):
    if status is None:
        return enum.names(SolveStatus), enum.label(SolveStatus)
    if enum.is_item(status):
        if enum.code(status).shape != ():
            raise TypeError(
                f"the status must be one item per point, got shape {enum.code(status).shape}."
            )
        cls = enum.enumeration_of(status)
        return enum.names(cls), enum.label(cls)
    shape, dtype = getattr(status, "shape", None), getattr(status, "dtype", None)
    if shape != () or dtype is None or not jnp.issubdtype(dtype, jnp.integer):
        raise TypeError(
            "the status returned with the values must be an eqx.Enumeration item (e.g. the "
            "`status` of simulate(..., throw=False)) or an integer scalar code of "
            f"rbo_jax.SolveStatus; got {getattr(dtype, 'name', type(status).__name__)}"
            f"{list(shape) if shape is not None else ''}. To return several arrays, return a "
            "dict."
        )
    return enum.names(SolveStatus), enum.label(SolveStatus)


def describe_output(values, status) -> dict:
    """Per-point structure of one output of the quantity (at trace time), validated."""
    out = {}
    for name, leaf in values.items():
        if enum.is_item(leaf):
            cls = enum.enumeration_of(leaf)
            out[name] = (tuple(enum.code(leaf).shape), "int8", enum.names(cls), enum.label(cls))
        elif hasattr(leaf, "shape") and hasattr(leaf, "dtype"):
            out[name] = (tuple(leaf.shape), np.dtype(leaf.dtype).name, None, None)
        else:
            raise TypeError(
                f"quantity output {name!r} must be an array, got {type(leaf).__name__}."
            )
    return {"values": out, "status": _status_structure(status)}


def encode_output(values, status):
    """The values as arrays (enumeration items as int8 codes) and the status as an int32 code."""
    codes = {
        k: (enum.code(v).astype(jnp.int8) if enum.is_item(v) else jnp.asarray(v))
        for k, v in values.items()
    }
    if status is None:
        s = enum.code(SolveStatus.successful)
    else:
        s = enum.code(status) if enum.is_item(status) else status
    return codes, jnp.asarray(s).astype(jnp.int32)


def make_output_spec(
    structure: dict, space: Space, dims: Mapping[str, Sequence[str]] | None
) -> OutputSpec:
    """Names the per-point dimensions of the outputs; checks names against the parameters."""
    dims = dict(dims or {})
    values = structure["values"]
    unknown = set(dims) - set(values)
    if unknown:
        raise ValueError(
            f"dims names outputs {sorted(unknown)} that the quantity does not return "
            f"(it returns {sorted(values)})."
        )
    variables, dim_sizes = [], {}
    for name, (shape, dtype, flags, enum_label) in values.items():
        if name in space.names or name in space.dims or name == "status":
            raise ValueError(f"quantity output {name!r} clashes with a parameter or reserved name.")
        vdims = tuple(dims.get(name, tuple(f"{name}_dim{j}" for j in range(len(shape)))))
        if len(vdims) != len(shape):
            raise ValueError(
                f"dims[{name!r}] = {list(vdims)} has {len(vdims)} names for an output "
                f"of shape {shape} per point."
            )
        for dname, size in zip(vdims, shape):
            if dname in space.dims or dname in space.names:
                raise ValueError(f"dims[{name!r}]: {dname!r} is already a parameter dimension.")
            if dim_sizes.setdefault(dname, size) != size:
                raise ValueError(
                    f"dimension {dname!r} has sizes {dim_sizes[dname]} and {size} in "
                    "different outputs."
                )
        variables.append(Variable(name, shape, dtype, vdims, flags, enum_label))
    status_names, status_enum = structure["status"]
    for extra in (NONFINITE, ERROR):
        if extra not in status_names:
            status_names = status_names + (extra,)
    return OutputSpec(tuple(variables), status_names, status_enum)


def sort_eigenvalues(result: dict) -> dict:
    """The ``postprocess`` of the stability maps: each point's eigenvalues sorted by real, then
    imaginary part, like :func:`rbo_jax.spectrum`; on the host, where it is cheap. It only reads
    the chunk's arrays (``reads_only``: :class:`rbo_jax.batch._chunks.Chunks` hands it the
    program's outputs without a copy)."""
    result["eigenvalues"] = np.sort_complex(result["eigenvalues"])
    return result


sort_eigenvalues.reads_only = True


def fill_value(dtype: str):
    """What a point that was not computed holds: NaN, False, -1 or 0."""
    dt = np.dtype(dtype)
    if dt.kind in "fc":
        return np.nan
    if dt.kind == "b":
        return False
    return -1 if dt.kind == "i" else 0


# ---------------------------------------------------------------------------------------------
# The labelled result.
# ---------------------------------------------------------------------------------------------


def counts(status: np.ndarray, names: Sequence[str]) -> dict[str, int]:
    """``{name: number of points}`` of an array of status codes (-1, not computed, is left out)."""
    status = np.asarray(status, dtype=np.int64).ravel()
    c = np.bincount(status[status >= 0], minlength=len(names))
    return {n: int(k) for n, k in zip(names, c)}


def dataset(space: Space, spec: OutputSpec, arrays: dict, attrs: dict):
    """The in-memory :class:`xarray.Dataset` of a sweep."""
    import xarray as xr

    data = {v.name: (space.dims + v.dims, arrays[v.name], v.attrs()) for v in spec.variables}
    data["status"] = (space.dims, arrays["status"], spec.status_attrs())
    if space.grid:
        coords = {n: space.values[n] for n in space.names}
    else:
        coords = {n: (POINT_DIM, space.values[n]) for n in space.names}
    attrs = dict(attrs)
    attrs["status_counts"] = counts(arrays["status"], spec.status_names)
    attrs.setdefault("errors", [])
    return xr.Dataset(data, coords=coords, attrs=to_json(attrs))


def status_counts(ds) -> dict[str, int]:
    """Number of points with each status, ``{name: count}``, of a :func:`sweep` result."""
    names = ds["status"].attrs["flag_meanings"].split()
    return counts(np.asarray(ds["status"].values), names)


def summary_line(counts: Mapping[str, int]) -> str:
    """``"N points: successful n1, max_steps_reached n2"`` (zero counts left out)."""
    total = sum(counts.values())
    parts = [f"{k} {n}" for n, k in counts.items() if k]
    return f"{total} points: " + ", ".join(parts)
