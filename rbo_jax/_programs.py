"""Traced programs kept on disk (``jax.export``), so that a second process skips their Python
tracing and lowering, not only their XLA compilation.

JAX's persistent compilation cache is keyed on the *lowered* program: a second process that
loads a compiled program from it has still traced and lowered it, which for the fit's program
(the DOP853 loop of :func:`rbo_jax.fast_simulate` and its forward-mode derivative) is a large
part of the command line's start (benchmarks/README.md). A function decorated with :func:`stored`
is exported once per structure of its arguments and the exported StableHLO module is written to
the store; a later process deserialises it (milliseconds) and calls it, and XLA's compilation
of that call is a hit in the persistent compilation cache.

The store is off unless :func:`rbo_jax.enable_compilation_cache` (or ``$RBO_JAX_COMPILATION_CACHE``
at import, or the command line) turns it on; then the stored entry points are
:func:`rbo_jax.simulate` and :func:`rbo_jax.fast_simulate` (their compiled solves), the chunk
program of :func:`rbo_jax.sweep` and its presets (``batch/_program.py``, which keys the user's
quantity by :func:`rbo_jax._callables.stable_text`), :func:`rbo_jax.fit`,
:func:`rbo_jax.hopf_point`, :func:`rbo_jax.periodic_orbit` and a rod's midpoint rule (eager
:func:`rbo_jax.lattice.simulate`). Small programs (Newton loops, the
fit) are compiled with :func:`small_program_options`. The key of a program is a SHA-256 of
everything its tracing depends on:

- the function (module and qualified name), or the caller's description of it;
- the structure of the arguments, every node's type by module and qualified name and its static
  data by ``repr`` (equinox's static fields), the non-array leaves by ``repr`` (a Python float's
  ``repr`` round-trips exactly; a function by :func:`rbo_jax._callables.stable_text`), shape,
  dtype and weak type of every array;
- the source of every module of ``rbo_jax``, the versions of Python and of :data:`PACKAGES`,
  the backend and its devices, JAX's settings of precision and promotion (``_FLAGS``).

A static value whose ``repr`` holds a memory address (``<function f at 0x…>``: a plain callable
foundation or load) could name different functions in different processes: such arguments are never
stored, they trace as usual. So does a program that cannot be exported (host callbacks, outputs that
are not plain containers): the store remembers it (a ``KEY.unexportable`` marker), so that later
processes do not trace it for nothing. Arguments that are being traced (the function called inside
``jit`` or ``vmap``) are passed to the function itself. An entry that cannot be read is exported
again; a store that cannot be written is skipped with a warning. Entries are written to a temporary
file first and renamed, so that concurrent processes never read half an entry; each starts with a
format line, so an entry of another format is not read. The results are those of the traced program,
bit for bit (the same StableHLO).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import os
import pathlib
import re
import struct
import sys
import types
import warnings
from collections.abc import Callable

import equinox as eqx
import jax
import numpy as np

from . import _cache
from ._callables import PACKAGES, describe_treedef, stable_text

__all__ = [
    "PACKAGES",
    "enable_program_store",
    "jit",
    "load",
    "program",
    "program_key",
    "program_store",
    "save",
    "small_program_options",
    "stored",
]

_CALLS: dict[tuple[pathlib.Path, str], Callable | None] = {}
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")
# JAX settings that change what a trace gives (or whether it raises)
_FLAGS = (
    "jax_enable_x64",
    "jax_numpy_dtype_promotion",
    "jax_numpy_rank_promotion",
    "jax_default_matmul_precision",
    "jax_default_prng_impl",
)
_MAGIC = b"rbo_jax program 2\n"  # then the length of the metadata (8 bytes), it, the program


def enable_program_store(path: str | pathlib.Path | None) -> pathlib.Path | None:
    """Keep the programs of :func:`stored` functions under ``path`` (``None``: off); JAX's
    persistent cache is left as it is (:func:`rbo_jax.enable_compilation_cache` sets both).
    Programs loaded in this process are forgotten (as in a new process)."""
    _CALLS.clear()
    return _cache.set_program_store(path)


def program_store() -> pathlib.Path | None:
    """The directory of the program store (``None``: off)."""
    return _cache.program_store()


@functools.cache
def _environment() -> str:
    """Sources of the package and versions of what traces and lowers its programs."""
    h = hashlib.sha256()
    root = pathlib.Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    h.update(sys.version.encode())
    for name in PACKAGES:
        try:
            h.update(f"{name}={importlib.metadata.version(name)};".encode())
        except importlib.metadata.PackageNotFoundError:
            h.update(f"{name}=none;".encode())
    h.update(repr((jax.default_backend(), [d.device_kind for d in jax.devices()])).encode())
    return h.hexdigest()


def program_key(text: str) -> str | None:
    """The store's key of a program described by ``text`` (``None`` if the text holds a memory
    address, which may name something else in another process)."""
    if _ADDRESS.search(text):
        return None
    flags = repr([getattr(jax.config, name) for name in _FLAGS])  # may change at run time
    return hashlib.sha256((text + flags + _environment()).encode()).hexdigest()


def _static_text(v) -> tuple[str, str]:
    if isinstance(v, (types.FunctionType, types.MethodType, functools.partial)):
        return ("callable", stable_text(v) or repr(v))  # repr: an address, never stored
    return (type(v).__qualname__, repr(v))


def _key(fn: Callable, args: tuple) -> tuple[str | None, list, object, object]:
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    static_leaves, static_def = jax.tree_util.tree_flatten(static)
    avals = [(tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False))) for x in leaves]
    text = repr(
        (
            f"{fn.__module__}.{fn.__qualname__}",
            describe_treedef(treedef),
            describe_treedef(static_def),
            [_static_text(v) for v in static_leaves],
            avals,
        )
    )
    return program_key(text), leaves, treedef, static


def _path(key: str, suffix: str = ".jaxexport") -> pathlib.Path:
    return _cache.program_store() / f"{key}{suffix}"


def _write(path: pathlib.Path, data: bytes) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        tmp.write_bytes(data)
        tmp.replace(path)
    except OSError as e:
        warnings.warn(
            f"program store: cannot write {path} ({e}); the program is traced in every process.",
            RuntimeWarning,
            stacklevel=4,
        )


def load(key: str) -> tuple[jax.export.Exported, str] | None:
    """The stored program of ``key`` and its metadata, or ``None`` (not stored, or damaged: a
    warning, and the caller exports it again)."""
    path = _path(key)
    if not path.exists():
        return None
    try:
        data = path.read_bytes()
        if not data.startswith(_MAGIC):
            raise ValueError("not an entry of this store")
        start = len(_MAGIC) + 8
        (n,) = struct.unpack("<Q", data[len(_MAGIC) : start])
        if start + n > len(data):
            raise ValueError("truncated")
        meta = data[start : start + n].decode()
        exported = jax.export.deserialize(bytearray(data[start + n :]))
    except (OSError, struct.error, ValueError, IndexError, UnicodeDecodeError) as e:
        warnings.warn(
            f"program store: cannot read {path} ({type(e).__name__}: {e}); it is exported again.",
            RuntimeWarning,
            stacklevel=3,
        )
        return None
    return exported, meta


def save(key: str, exported: jax.export.Exported, meta: str = "") -> None:
    """Store ``exported`` (and a text of metadata) under ``key``."""
    m = meta.encode()
    _write(_path(key), _MAGIC + struct.pack("<Q", len(m)) + m + exported.serialize())


def unexportable(key: str, mark: bool = False) -> bool:
    """Whether the program of ``key`` is known not to export (``mark``: record that it is)."""
    path = _path(key, ".unexportable")
    if mark:
        _write(path, b"")
    return path.exists()


def _export(fn, leaves, treedef, static):
    def flat(*xs):
        return fn(*eqx.combine(jax.tree_util.tree_unflatten(treedef, list(xs)), static))

    flat.__name__ = flat.__qualname__ = f"{_name(fn)}_export"  # JAX_LOG_COMPILES names it

    specs = [
        jax.ShapeDtypeStruct(x.shape, x.dtype, weak_type=bool(getattr(x, "weak_type", False)))
        for x in leaves
    ]
    return jax.export.export(jax.jit(flat))(*specs)


def call_of(exported: jax.export.Exported, name: str, options: dict | None = None) -> Callable:
    """The jitted call of a stored program, named ``name`` (in JAX's logs and cache), compiled
    with XLA's ``options``."""

    def call(*xs):
        return exported.call(*xs)

    call.__name__ = call.__qualname__ = name
    return jax.jit(call, compiler_options=options)


def _program(fn, key, leaves, treedef, static, options=None) -> Callable | None:
    store = _cache.program_store()
    if (store, key) in _CALLS:  # None: not exportable, remembered for this process
        return _CALLS[store, key]
    found = load(key)
    exported = None if found is None else found[0]
    if exported is None:
        if unexportable(key):
            _CALLS[store, key] = None
            return None
        try:
            exported = _export(fn, leaves, treedef, static)
            save(key, exported)
        except (NotImplementedError, ValueError):
            # what jax.export refuses: host callbacks (NotImplementedError), custom calls without
            # a compatibility guarantee and, when serialised, outputs of unregistered pytree
            # types (ValueError). The program then traces as usual, in this process and the
            # next ones.
            unexportable(key, mark=True)
            _CALLS[store, key] = None
            return None
    call = _CALLS[store, key] = call_of(exported, _name(fn), options)  # it keeps fn's name
    return call


def _name(fn) -> str:
    return getattr(fn, "__name__", None) or getattr(fn, "__qualname__", "program")


def stored(fn: Callable, options: Callable[[], dict | None] = lambda: None) -> Callable:
    """Decorate a jitted function (``eqx.filter_jit``) whose programs the store keeps: with the
    store on, a call looks its program up by the key of the module docstring (exporting it the
    first time); with it off, for arguments that cannot be keyed safely, or for traced
    arguments (inside ``jit``, ``vmap``, ...), it calls ``fn``. ``options()``: XLA's options
    for the compilation of a stored program (those ``fn`` is compiled with)."""

    @functools.wraps(fn)
    def wrapper(*args):
        if _cache.program_store() is None:
            return fn(*args)
        key, leaves, treedef, static = _key(fn, args)
        if key is None or any(isinstance(x, jax.core.Tracer) for x in leaves):
            return fn(*args)
        call = _program(fn, key, leaves, treedef, static, options())
        if call is None:
            return fn(*args)
        try:
            return call(*leaves)
        except ValueError as e:  # called inside a jit trace with concrete arguments
            if not _nested_options(e):
                raise
            return fn(*args)

    wrapper.__wrapped__ = fn
    if hasattr(fn, "lower"):
        wrapper.lower = fn.lower  # the traced program, as for the jitted function itself
    return wrapper


# XLA's options for small programs (small_program_options), known to this XLA or not
_SMALL = {"xla_cpu_use_fusion_emitters": False}
# and, added to them, for programs that run in milliseconds (fast_compile_options)
_FAST_COMPILE = {
    "xla_backend_optimization_level": 0,
    "xla_disable_hlo_passes": "while-loop-invariant-code-motion,simplify-while-loops",
    "xla_cpu_parallel_codegen_split_count": 1,
}


@functools.cache
def small_program_options() -> dict | None:
    """XLA's options for programs whose compilation outweighs their run time: a Newton loop
    (:func:`rbo_jax.hopf_point`, :func:`rbo_jax.periodic_orbit`, continuations), a fit's
    residuals and Jacobian (milliseconds per call, seconds to compile), and the chunk program
    of a critical load (Newton and eigenproblems per point: it runs as fast).

    On CPU, XLA's element-wise emitters instead of its newer MLIR fusion emitters
    (``xla_cpu_use_fusion_emitters=False``), which build an MLIR context and pipeline per
    fusion: these programs compile faster, while the same emitters make the vmapped DOP853 of
    :func:`rbo_jax.fast_simulate` slower per trajectory, which is why a sweep of any other
    quantity and the simulation programs keep XLA's defaults (figures: benchmarks/README.md,
    History). ``None`` (the defaults) on other backends and where this XLA does not know the
    option (checked once, by compiling a tiny program)."""
    if jax.default_backend() != "cpu":
        return None
    return _known(dict(_SMALL))


def _known(options: dict) -> dict | None:
    """``options`` if this XLA compiles a tiny program with them, else ``None``."""
    try:
        jax.jit(lambda x: x + 1.0).lower(np.float32(0.0)).compile(options)
    except jax.errors.JaxRuntimeError:
        return None
    return options


@functools.cache
def fast_compile_options() -> dict | None:
    """XLA's options for programs that run in milliseconds and compile in seconds: the Newton
    loops around one traced jet of the vector field (:func:`rbo_jax.hopf_point`,
    :func:`rbo_jax.bautin_point`). Those of :func:`small_program_options`, and LLVM without
    optimisation (``xla_backend_optimization_level=0``), without XLA's two passes over while
    loops that run again and again over the whole loop body (``while-loop-invariant-code-motion``,
    ``simplify-while-loops``; each run also reruns the simplification pipeline) and without
    splitting the LLVM module for parallel code generation (the split costs more than the
    unoptimised code generation it spreads): they compile faster and run slower, still in
    milliseconds (figures: benchmarks/README.md, History). LLVM -O0 forms no fused
    multiply-adds: results move by rounding. Those of :func:`small_program_options` where this
    XLA does not know them."""
    if jax.default_backend() != "cpu":
        return None
    return _known({**_SMALL, **_FAST_COMPILE}) or small_program_options()


def _nested_options(e: ValueError) -> bool:
    """Whether ``e`` is JAX's refusal of compiler options on a jit inside another trace."""
    return "compiler_options" in str(e) and "top-level" in str(e)


# the traces under which a jitted call is still compiled as a program of its own (batched or
# differentiated, then run): no trace around them stages it into a caller's program
_EAGER_TRACES = frozenset({"EvalTrace", "BatchTrace", "JVPTrace"})


def _top_level(leaves) -> bool:
    """Whether a jitted call with these argument leaves is compiled as a program of its own:
    no tracers, or only ``jax.vmap``'s and ``jax.jvp``'s traces over the eager one (no
    ``jax.jit``, ``lax.scan``, ... around). Read from JAX's trace context; where that is not
    available, only calls without tracers count."""
    if not any(isinstance(x, jax.core.Tracer) for x in leaves):
        return True
    try:
        from jax._src import core  # noqa: PLC0415

        trace = core.trace_ctx.trace
        while trace is not None:
            if type(trace).__name__ not in _EAGER_TRACES:
                return False
            trace = getattr(trace, "parent_trace", None)
        return True
    except AttributeError:  # another JAX: the conservative answer
        return False


def jit(fn: Callable, *, small: bool = False, fast_compile: bool = False) -> Callable:
    """``eqx.filter_jit(fn)``, with ``small``: compiled with :func:`small_program_options` when
    it is compiled as a program of its own (:func:`_top_level`: called eagerly, or under
    ``jax.vmap`` or ``jax.jvp`` only; JAX refuses compiler options on a jit inside another
    trace: there it is the plain ``eqx.filter_jit``, inlined in the caller's program);
    ``fast_compile``: with :func:`fast_compile_options` instead. The jitted functions are made
    on first use (the options need JAX's backend, which ``import rbo_jax`` does not start)."""
    made: dict = {}

    def options():
        if fast_compile:
            return fast_compile_options()
        return small_program_options() if small else None

    def jitted(top_level):
        key = repr(options()) if top_level else None
        if key not in made:
            made[key] = eqx.filter_jit(fn, compiler_options=options() if top_level else None)
        return made[key]

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if options() is not None and _top_level(jax.tree_util.tree_leaves((args, kwargs))):
            try:
                return jitted(True)(*args, **kwargs)
            except ValueError as e:  # inside a jit trace, with concrete arguments
                if not _nested_options(e):
                    raise
        return jitted(False)(*args, **kwargs)

    def lower(*args, **kwargs):
        return jitted(options() is not None).lower(*args, **kwargs)

    call.lower = lower
    call.options = options
    return call


def program(fn: Callable, *, small: bool = False, fast_compile: bool = False) -> Callable:
    """The compiled entry point of ``fn``: :func:`jit` of it, kept by the program store
    (:func:`stored`; positional arguments only)."""
    jitted = jit(fn, small=small, fast_compile=fast_compile)
    return stored(jitted, jitted.options)
