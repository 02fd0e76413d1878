"""The identity of a user's callable by what it computes, not by the object: a notebook cell run
again makes a new ``lambda c, d: nikolai_model(...)``, equal to the last one in everything that
its trace depends on, and its compiled program should be reused.

:func:`callable_key` (within a process: a hashable key for caches of compiled programs) and
:func:`stable_text` (across processes: a text for the keys of the program store,
:mod:`rbo_jax._programs`) describe an object recursively:

- a function by its code object (bytecode, constants with nested code objects, names, variable
  names, argument counts, flags, qualified name, file name (its last component: a notebook's
  cell files differ by the kernel's process id) and first line), its defaults, the contents of
  its closure cells and the values of the globals its code (or nested code) names;
- a function or class of an importable module (not ``__main__``) by that module and name:
  within a process the object itself; across processes only for modules whose content the
  program store's key covers (rbo_jax, by its sources; JAX and the libraries of :data:`PACKAGES`,
  by version; Python's standard library), a user's module's functions by their code as above;
- ``functools.partial`` and bound methods by their parts; modules by name (across processes,
  the same covered modules only);
- numbers, strings, ``None`` by type and ``repr`` (``1`` and ``1.0``, ``0.0`` and ``-0.0``
  differ); tuples, lists and dicts element by element (a list's contents when the key is made:
  a counter list that tracing appends to gives a new key every time); NumPy and (concrete) JAX
  arrays by type, dtype, shape, weak type and the SHA-256 of their bytes; pytrees (equinox
  Modules, named tuples) by their structure and leaves;
- anything else: within a process by identity (no reuse unless it is the same object; a
  hashable value by equality), across processes not at all (:func:`stable_text` is ``None``:
  the program is traced as usual).

Keys are computed when a program is looked up, so a value changed in place (an array, a list
in a closure) gives a new key. What the description does not see is a global read through an
attribute of a module (``mymodule.K``: the module, not ``K``), which within a process is
treated as the same module.
"""

from __future__ import annotations

import builtins
import functools
import hashlib
import os
import sys
import types

import jax
import numpy as np

__all__ = ["callable_key", "describe_treedef", "stable_text"]

_SCALARS = (bool, int, float, complex, str, bytes, type(None), type(Ellipsis))
# The libraries that trace and lower rbo_jax's programs, whose versions the program store's key
# holds (rbo_jax._programs re-exports this list).
PACKAGES = (
    "jax",
    "jaxlib",
    "equinox",
    "diffrax",
    "optimistix",
    "lineax",
    "numpy",
    "scipy",
    "optax",
    "jaxtyping",
)
# Modules whose content the program store's key covers (by the package's sources or the
# versions of PACKAGES) or that come with Python.
COVERED = ("rbo_jax", *PACKAGES)


class _Unkeyable(Exception):
    """Raised by the cross-process description of an object it cannot name safely."""


class _Identity:
    """An object compared by identity (kept alive, so that its id is not reused)."""

    __slots__ = ("obj",)

    def __init__(self, obj):
        self.obj = obj

    def __hash__(self):
        return id(self.obj)

    def __eq__(self, other):
        return isinstance(other, _Identity) and other.obj is self.obj


def _covered(module: str | None) -> bool:
    top = (module or "").split(".")[0]
    return top in COVERED or top in sys.stdlib_module_names or top == "builtins"


def _named(obj) -> bool:
    """Whether ``obj`` is what its module's attribute of its qualified name holds."""
    module, qualname = getattr(obj, "__module__", None), getattr(obj, "__qualname__", None)
    if not isinstance(module, str) or not isinstance(qualname, str) or module == "__main__":
        return False
    target = sys.modules.get(module)
    try:
        for part in qualname.split("."):
            target = getattr(target, part)
    except AttributeError:
        return False
    return target is obj


class _Describer:
    def __init__(self, stable: bool):
        self.stable = stable
        self.stack: set[int] = set()

    def other(self, x):
        if self.stable:
            raise _Unkeyable(type(x).__qualname__)
        try:
            hash(x)
        except TypeError:
            return ("id", _Identity(x))
        return ("value", type(x), x)

    def __call__(self, x):
        if isinstance(x, _SCALARS):
            return (type(x).__name__, repr(x))
        if type(x) in (tuple, list):  # subclasses (named tuples, ...): as pytrees, below
            return (type(x).__name__, tuple(self(v) for v in x))
        if type(x) is dict:
            return ("dict", tuple((self(k), self(v)) for k, v in x.items()))
        if isinstance(x, (np.ndarray, np.generic)) or (
            isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer)
        ):
            return self.array(x)
        if isinstance(x, types.ModuleType):
            if self.stable and not _covered(x.__name__):
                raise _Unkeyable(x.__name__)
            return ("module", x.__name__) if self.stable else ("module", _Identity(x))
        if isinstance(x, types.FunctionType):
            return self.function(x)
        if isinstance(x, functools.partial):
            return ("partial", self(x.func), self(x.args), self(x.keywords))
        if isinstance(x, types.MethodType):
            return ("method", self(x.__func__), self(x.__self__))
        if _named(x) and (not self.stable or _covered(x.__module__)):
            # classes, builtins, jitted library functions, enumeration classes
            return (
                ("named", x.__module__, x.__qualname__) if self.stable else ("named", _Identity(x))
            )
        return self.tree(x)

    def array(self, x):
        a = np.asarray(x)
        if a.dtype.hasobject:
            return self.other(x)
        digest = hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()
        return (
            "array",
            type(x).__name__,
            a.dtype.str,
            a.shape,
            bool(getattr(x, "weak_type", False)),
            digest,
        )

    def tree(self, x):
        """A pytree node (an equinox Module, a registered class) by structure and leaves."""
        try:
            leaves, treedef = jax.tree_util.tree_flatten(x)
        except Exception:  # a pytree whose flattening fails is described by identity
            return self.other(x)
        if treedef.num_nodes == 1:  # a leaf: not a container
            return self.other(x)
        if self.stable:
            text = repr(describe_treedef(treedef))
            if " at 0x" in text:
                raise _Unkeyable(text)
            return ("tree", text, tuple(self(v) for v in leaves))
        try:
            hash(treedef)
        except TypeError:  # unhashable static data
            return self.other(x)
        return ("tree", treedef, tuple(self(v) for v in leaves))

    def function(self, f: types.FunctionType):
        if _named(f) and (not self.stable or _covered(f.__module__)):
            return ("fn", f.__module__, f.__qualname__) if self.stable else ("fn", _Identity(f))
        if id(f) in self.stack:  # recursion: the function is being described already
            return ("recursive", f.__qualname__)
        self.stack.add(id(f))
        try:
            code = f.__code__
            cells = []
            for cell in f.__closure__ or ():
                try:
                    cells.append(self(cell.cell_contents))
                except ValueError:  # an empty cell
                    cells.append(("empty",))
            names = sorted(_global_names(code))
            glob = f.__globals__
            values = tuple(
                (n, self(glob[n]))
                if n in glob
                else (n, ("builtin",) if hasattr(builtins, n) else ("missing",))
                for n in names
            )
            return (
                "code",
                self.code(code),
                self(f.__defaults__),
                self(f.__kwdefaults__),
                tuple(cells),
                values,
            )
        finally:
            self.stack.discard(id(f))

    def code(self, c: types.CodeType):
        consts = tuple(
            self.code(k) if isinstance(k, types.CodeType) else self(k) for k in c.co_consts
        )
        return (
            c.co_code,
            consts,
            c.co_names,
            c.co_varnames,
            c.co_freevars,
            c.co_cellvars,
            c.co_argcount,
            c.co_posonlyargcount,
            c.co_kwonlyargcount,
            c.co_flags,
            c.co_qualname,
            os.path.basename(c.co_filename),
            c.co_firstlineno,
        )


def describe_treedef(treedef) -> list:
    """Every node of a tree structure: its type (module, qualified name) and static data (by
    ``repr``, which for a function holds its address: such a description names nothing across
    processes)."""
    if treedef.num_nodes == 1 and treedef.num_leaves == 1:
        return ["*"]
    data = treedef.node_data()
    if data is None:
        return ["*"]
    kind, aux = data
    out = [f"{kind.__module__}.{kind.__qualname__}", repr(aux)]
    for child in treedef.children():
        out.append(describe_treedef(child))
    return out


def _global_names(code: types.CodeType) -> set[str]:
    """The names a code object and its nested code objects look up (globals, attributes)."""
    names = set(code.co_names)
    for k in code.co_consts:
        if isinstance(k, types.CodeType):
            names |= _global_names(k)
    return names


def callable_key(fn) -> tuple:
    """A hashable key of ``fn`` within this process: equal for functions that trace alike (the
    module docstring); hold it only as long as ``fn`` may be reused."""
    try:
        return _Describer(stable=False)(fn)
    except RecursionError:  # nested too deeply to describe: the object itself
        return ("id", _Identity(fn))


def stable_text(obj) -> str | None:
    """A text that names ``obj`` in every process alike (for the program store's keys), or
    ``None`` if part of it cannot be named safely (then the program is not stored)."""
    try:
        return repr(_Describer(stable=True)(obj))
    except (_Unkeyable, RecursionError):
        return None


_SEEN: dict = {}


def _by_value(key) -> bool:
    """Whether ``key`` describes everything by value: no part known only by identity (a tracer
    or another unhashable object in a closure), which would never match again and would keep
    the object alive."""
    stack = [key]
    while stack:
        k = stack.pop()
        if type(k) is tuple:
            if len(k) == 2 and k[0] == "id" and isinstance(k[1], _Identity):
                return False
            stack.extend(k)
    return True


def canonical(fn):
    """The first function seen that computes what ``fn`` computes (:func:`callable_key`): a
    new but identical lambda (a notebook cell run again) is then the same static argument of a
    compiled solver, and its program is not traced again. ``fn`` itself where part of it is
    known only by identity (:func:`_by_value`), and where the function seen first no longer
    computes the same (a list or dict in its closure changed since)."""
    if fn is None:
        return None
    key = callable_key(fn)
    try:
        seen = _SEEN.setdefault(key, fn) if _by_value(key) else fn
    except TypeError:  # an unhashable key: the function itself
        return fn
    if seen is not fn and callable_key(seen) != key:
        _SEEN[key] = seen = fn
    return seen
