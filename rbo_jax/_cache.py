"""``enable_compilation_cache``: keep compiled and traced programs on disk, so that a second
process answers in about a second instead of tracing and compiling again.

Two stores under one directory:

- JAX's persistent compilation cache (``jax_compilation_cache_dir``), with every program kept
  (minimum compile time 0 s, minimum entry size 0 bytes): a second process loads XLA's output
  instead of compiling;
- rbo_jax's program store (``PATH/programs``, :mod:`rbo_jax._programs`): the *traced* programs
  of the main entry points (``jax.export``), so that a second process also skips Python tracing
  and lowering, which JAX's cache does not (its key is the lowered program).

The directory is ``path``, else ``$RBO_JAX_COMPILATION_CACHE``, else ``rbo_jax/jax-cache`` under
the user's cache directory (``$XDG_CACHE_HOME`` or ``~/.cache``); ``off`` (or ``0``, ``no``,
``false``, ``none``) turns both off. ``import rbo_jax`` calls :func:`enable_from_environment`,
which switches them on when ``$RBO_JAX_COMPILATION_CACHE`` is set. This module imports nothing
heavier than JAX, which ``import rbo_jax`` loads anyway.

The cache is trusted code: JAX's documentation warns that whoever can write to it can run code
in the processes that read it. Keep it in a directory only you can write to.
"""

from __future__ import annotations

import os
import pathlib
import warnings

import jax

__all__ = [
    "CACHE_ENV",
    "compilation_cache_dir",
    "enable_compilation_cache",
    "enable_from_environment",
    "program_store",
    "set_program_store",
]

CACHE_ENV = "RBO_JAX_COMPILATION_CACHE"
_OFF = ("off", "0", "no", "false", "none")

_PROGRAMS: pathlib.Path | None = None  # the program store (rbo_jax._programs); None: off
_JAX_DIR: str | None = None  # the JAX cache directory this module set, if any


def compilation_cache_dir(path: str | os.PathLike | None = None) -> pathlib.Path | None:
    """The cache directory that :func:`enable_compilation_cache` uses for ``path`` (``None``:
    off)."""
    if path is not None and not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str, an os.PathLike or None, got {type(path).__name__}.")
    value = os.environ.get(CACHE_ENV, "") if path is None else os.fspath(path)
    if not isinstance(value, str):
        raise TypeError(f"path must name a directory as text, got {value!r}.")
    if value.strip().lower() in _OFF:
        return None
    if value.strip():
        return pathlib.Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return pathlib.Path(base) / "rbo_jax" / "jax-cache"


def program_store() -> pathlib.Path | None:
    """The directory of the program store (``None``: off)."""
    return _PROGRAMS


def set_program_store(path: str | os.PathLike | None) -> pathlib.Path | None:
    """Keep exported programs under ``path`` (``None``: off); JAX's cache is left as it is."""
    global _PROGRAMS
    _PROGRAMS = None if path is None else pathlib.Path(path)
    return _PROGRAMS


def _set_jax_dir(path: str | None) -> None:
    """Point JAX's persistent cache at ``path``; a cache JAX already opened is reset first (it
    keeps the directory it was opened with)."""
    global _JAX_DIR
    if path != jax.config.jax_compilation_cache_dir:
        from jax.experimental.compilation_cache import compilation_cache

        compilation_cache.reset_cache()
        jax.config.update("jax_compilation_cache_dir", path)
    _JAX_DIR = path


def enable_compilation_cache(path: str | os.PathLike | None = None) -> pathlib.Path | None:
    r"""Keep the programs of this process on disk for the next ones: JAX's persistent
    compilation cache (every program, however small or quick to compile) and rbo_jax's program
    store of traced programs (``PATH/programs``: :func:`rbo_jax.simulate`,
    :func:`rbo_jax.fast_simulate`, the chunk program of :func:`rbo_jax.sweep` and
    :func:`rbo_jax.stability_map`, :func:`rbo_jax.fit`, :func:`rbo_jax.hopf_point`,
    :func:`rbo_jax.periodic_orbit`, a rod's eager midpoint rule in
    :func:`rbo_jax.lattice.simulate`), so that a second process neither traces nor compiles
    them.

    **Arguments:** ``path``, the directory (made if missing); default
    ``$RBO_JAX_COMPILATION_CACHE``, else ``~/.cache/rbo_jax/jax-cache`` (``$XDG_CACHE_HOME``
    replaces ``~/.cache``). ``"off"`` (also ``"0"``, ``"no"``, ``"false"``, ``"none"``) turns
    off the program store, and JAX's cache if this function turned it on.

    **Returns:** the directory, or ``None`` when off. A directory that cannot be made gives a
    :class:`RuntimeWarning` and leaves both off; nothing else fails. Setting
    ``RBO_JAX_COMPILATION_CACHE`` before ``import rbo_jax`` has the same effect as calling this.
    Entries are keyed on everything their program depends on (the package's sources, the
    versions of JAX and its libraries, the structure and static data of the arguments), so a
    stale entry is never used; only a directory you alone can write to should be used (JAX
    loads compiled code from it).
    """
    target = compilation_cache_dir(path)
    if target is not None:
        try:
            (target / "programs").mkdir(parents=True, exist_ok=True)
        except OSError as e:
            warnings.warn(
                f"rbo_jax: compilation cache off ({target}: {e.strerror or e}); set "
                f"{CACHE_ENV}=off to silence this.",
                RuntimeWarning,
                stacklevel=2,
            )
            target = None
    if target is None:
        set_program_store(None)
        if _JAX_DIR is not None:  # only what this function turned on
            _set_jax_dir(None)
        return None
    _set_jax_dir(str(target))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    set_program_store(target / "programs")
    return target


def enable_from_environment() -> pathlib.Path | None:
    """:func:`enable_compilation_cache` when ``$RBO_JAX_COMPILATION_CACHE`` is set (called by
    ``import rbo_jax``); otherwise nothing."""
    if os.environ.get(CACHE_ENV, "").strip():
        return enable_compilation_cache()
    return None
