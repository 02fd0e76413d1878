"""Re-exports that load on first use (PEP 562), so that ``import rbo_jax`` costs little more than
``import jax``: the layers above the kinematics pull in equinox, diffrax, optimistix, optax,
xarray and zarr, and a user who only wants ``rbo_jax.turn_tensor`` (or a command that only
prints its help) should not wait for them.

A package's ``__init__.py`` gives one table, module -> public names, and :func:`attach` returns
its ``__getattr__``, ``__dir__`` and ``__all__``: ``package.name`` and ``from package import
name`` import the module on first access and keep the object as a module attribute, so later
lookups cost nothing. ``__all__`` is the table's names; ``dir(package)`` lists them before they
are loaded. A submodule not imported yet loads on first access too (``rbo_jax.kinematics``),
as it did when the package imported every layer.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import types
from collections.abc import Callable, Mapping, Sequence

_EXPORTS: dict[str, dict[str, str]] = {}  # package -> public name -> module (relative)


class _LazyPackage(types.ModuleType):
    """A package whose public names may coincide with its submodules' names.

    The import system binds a submodule to its parent's attribute of the same name once the
    submodule is loaded (``rbo_jax.simulate`` would become the module ``rbo_jax/simulate.py``
    the first time any code imports it); for a re-exported name that belongs to the object the
    table names, so that binding is skipped and the attribute resolves through ``__getattr__``,
    as the eager ``from .simulate import simulate`` it replaces did."""

    def __setattr__(self, name: str, value) -> None:
        if (
            name in _EXPORTS.get(self.__name__, ())
            and isinstance(value, types.ModuleType)
            and value.__name__ == f"{self.__name__}.{name}"
        ):
            return
        super().__setattr__(name, value)


def attach(
    package: str, table: Mapping[str, Sequence[str]]
) -> tuple[Callable[[str], object], Callable[[], list[str]], list[str]]:
    """``__getattr__, __dir__, __all__`` for ``package``, whose public names are
    ``table[module]`` for each (relative, e.g. ``".model"``) ``module``."""
    exports: dict[str, str] = {}
    for module, names in table.items():
        for name in names:
            if name in exports:
                raise ValueError(
                    f"{package}: {name!r} is exported from both {exports[name]!r} and {module!r}."
                )
            exports[name] = module
    _EXPORTS[package] = exports
    pkg = sys.modules[package]
    pkg.__class__ = _LazyPackage

    def __getattr__(name: str):
        if name not in exports:  # a submodule not imported yet, as after an eager import
            if name.startswith("__") or importlib.util.find_spec(f"{package}.{name}") is None:
                raise AttributeError(f"module {package!r} has no attribute {name!r}")
            return importlib.import_module(f"{package}.{name}")
        value = getattr(importlib.import_module(exports[name], package), name)
        types.ModuleType.__setattr__(pkg, name, value)  # later lookups skip __getattr__
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(pkg)) | set(exports))

    return __getattr__, __dir__, list(exports)
