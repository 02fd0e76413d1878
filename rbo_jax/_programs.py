"""Traced programs kept on disk (``jax.export``), so that a second process skips their Python
tracing and lowering, not only their XLA compilation.

JAX's persistent compilation cache is keyed on the *lowered* program: a second process that
loads a compiled program from it has still traced and lowered it, which for the fit's program
(the DOP853 loop of :func:`rbo_jax.fast_simulate` and its forward-mode derivative) is 1.5–2.5 s
of the command line's start (benchmarks/README.md). A function decorated with :func:`stored`
is exported once per structure of its arguments and the exported StableHLO module is written to
the store; a later process deserialises it (milliseconds) and calls it, and XLA's compilation
of that call is a hit in the persistent compilation cache.

The store is off unless :func:`enable_program_store` is called (the command line does; library
calls trace as usual). The key of a program is a SHA-256 of everything its tracing depends on:

- the function (module and qualified name);
- the structure of the arguments, every node's type by module and qualified name and its static
  data by ``repr`` (equinox's static fields), the non-array leaves by ``repr`` (a Python float's
  ``repr`` round-trips exactly), shape, dtype and weak type of every array;
- the source of every module of ``rbo_jax`` and the versions of jax, jaxlib, equinox, diffrax,
  optimistix and lineax; the backend and its devices.

A static value whose ``repr`` holds a memory address (``<function f at 0x…>``: a plain callable
foundation or load) could name different functions in different processes: such arguments are
never stored, they trace as usual. So does a program that cannot be exported (host callbacks,
outputs that are not plain containers). An entry that cannot be read is exported again; a store
that cannot be written is skipped with a warning. Entries are written to a temporary file first
and renamed, so that concurrent processes never read half an entry. The results are those of the
traced program, bit for bit (the same StableHLO).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import os
import pathlib
import re
import struct
import warnings
from collections.abc import Callable

import equinox as eqx
import jax

__all__ = ["enable_program_store", "program_store", "stored"]

_STORE: pathlib.Path | None = None
_CALLS: dict[str, Callable | None] = {}
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")
_PACKAGES = ("jax", "jaxlib", "equinox", "diffrax", "optimistix", "lineax")


def enable_program_store(path: str | pathlib.Path | None) -> pathlib.Path | None:
    """Keep the programs of :func:`stored` functions under ``path`` (``None``: off)."""
    global _STORE
    _STORE = None if path is None else pathlib.Path(path)
    _CALLS.clear()
    return _STORE


def program_store() -> pathlib.Path | None:
    """The directory of the program store (``None``: off)."""
    return _STORE


@functools.cache
def _environment() -> str:
    """Sources of the package and versions of what traces and lowers its programs."""
    h = hashlib.sha256()
    root = pathlib.Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    for name in _PACKAGES:
        try:
            h.update(f"{name}={importlib.metadata.version(name)};".encode())
        except importlib.metadata.PackageNotFoundError:
            h.update(f"{name}=none;".encode())
    h.update(repr((jax.default_backend(), [d.device_kind for d in jax.devices()])).encode())
    return h.hexdigest()


def _describe_treedef(treedef) -> list:
    """Every node of a tree structure: its type (module, qualified name) and static data."""
    if treedef.num_nodes == 1 and treedef.num_leaves == 1:
        return ["*"]
    data = treedef.node_data()
    if data is None:
        return ["*"]
    kind, aux = data
    out = [f"{kind.__module__}.{kind.__qualname__}", repr(aux)]
    for child in treedef.children():
        out.append(_describe_treedef(child))
    return out


def _key(fn: Callable, args: tuple) -> tuple[str | None, list, object, object]:
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    static_leaves, static_def = jax.tree_util.tree_flatten(static)
    avals = [
        (tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False))) for x in leaves
    ]
    text = repr((
        f"{fn.__module__}.{fn.__qualname__}",
        _describe_treedef(treedef),
        _describe_treedef(static_def),
        [(type(v).__qualname__, repr(v)) for v in static_leaves],
        avals,
        _environment(),
    ))
    if _ADDRESS.search(text):
        return None, leaves, treedef, static
    return hashlib.sha256(text.encode()).hexdigest(), leaves, treedef, static


def _export(fn, leaves, treedef, static, path: pathlib.Path):
    def flat(*xs):
        return fn(*eqx.combine(jax.tree_util.tree_unflatten(treedef, list(xs)), static))

    flat.__name__ = flat.__qualname__ = f"{_name(fn)}_export"  # JAX_LOG_COMPILES names it

    specs = [
        jax.ShapeDtypeStruct(x.shape, x.dtype, weak_type=bool(getattr(x, "weak_type", False)))
        for x in leaves
    ]
    exported = jax.export.export(jax.jit(flat))(*specs)
    data = exported.serialize()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        tmp.write_bytes(data)
        tmp.replace(path)
    except OSError as e:
        warnings.warn(f"program store: cannot write {path} ({e}); the program is traced in "
                      "every process.", RuntimeWarning, stacklevel=3)
    return exported


def _program(fn, key, leaves, treedef, static) -> Callable | None:
    if key in _CALLS:  # None: not exportable, remembered so that it is tried once per process
        return _CALLS[key]
    path = _STORE / f"{key}.jaxexport"
    exported = None
    if path.exists():
        try:
            exported = jax.export.deserialize(bytearray(path.read_bytes()))
        except (OSError, struct.error, ValueError, IndexError) as e:  # truncated or foreign
            warnings.warn(f"program store: cannot read {path} ({type(e).__name__}: {e}); it is "
                          "exported again.", RuntimeWarning, stacklevel=3)
    if exported is None:
        try:
            exported = _export(fn, leaves, treedef, static, path)
        except (NotImplementedError, ValueError):
            # what jax.export refuses: host callbacks (NotImplementedError), custom calls without
            # a compatibility guarantee and outputs of unregistered pytree types (ValueError).
            # The program then traces as usual in every process.
            _CALLS[key] = None
            return None

    def call(*xs):
        return exported.call(*xs)

    call.__name__ = call.__qualname__ = _name(fn)  # the compiled program keeps fn's name
    call = _CALLS[key] = jax.jit(call)
    return call


def _name(fn) -> str:
    return getattr(fn, "__name__", None) or getattr(fn, "__qualname__", "program")


def stored(fn: Callable) -> Callable:
    """Decorate a jitted function (``eqx.filter_jit``) whose programs the store keeps: with the
    store on, a call looks its program up by the key of the module docstring (exporting it the
    first time); with it off, or for arguments that cannot be keyed safely, it calls ``fn``."""

    @functools.wraps(fn)
    def wrapper(*args):
        if _STORE is None:
            return fn(*args)
        key, leaves, treedef, static = _key(fn, args)
        call = None if key is None else _program(fn, key, leaves, treedef, static)
        if call is None:
            return fn(*args)
        return call(*leaves)

    wrapper.__wrapped__ = fn
    if hasattr(fn, "lower"):
        wrapper.lower = fn.lower  # the traced program, as for the jitted function itself
    return wrapper
