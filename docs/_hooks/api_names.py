"""The public names of rbo_jax and where the API pages document them.

``public_names()`` lists every ``(package, name)`` of the packages below, from their ``__all__``;
``identifier(package, name)`` is the dotted path that a ``::: identifier`` entry of an API page
uses for it: the module that defines the name (the lazy exports of ``rbo_jax/_lazy.py`` are
followed to it, since a static reader such as griffe does not see names that a package's
``__getattr__`` loads). Used by the mkdocs hook ``api_check.py`` and by
``tests/test_docs_browser.py``.
"""

from __future__ import annotations

import importlib

PACKAGES = (
    "rbo_jax",
    "rbo_jax.lattice",
    "rbo_jax.plotting",
    "rbo_jax.batch",
    "rbo_jax.bifurcation",
    "rbo_jax.fitting",
    "rbo_jax.ensemble",
)


def public_names() -> list[tuple[str, str]]:
    out = []
    for package in PACKAGES:
        module = importlib.import_module(package)
        out.extend((package, name) for name in module.__all__)
    return out


def identifier(package: str, name: str) -> str:
    """The dotted path of the module that defines ``package.name``, plus the name."""
    from rbo_jax import _lazy

    importlib.import_module(package)  # its table of lazy exports
    exports = _lazy._EXPORTS.get(package)
    if exports is None or name not in exports:
        return f"{package}.{name}"
    module = importlib.util.resolve_name(exports[name], package)
    if module != package:  # followed through every package that exports lazily
        return identifier(module, name)
    return f"{module}.{name}"
