"""The ``rbo-jax`` command.

``rbo-jax reproduce`` (run by ``make demo``) reproduces the paper into ``out/report.md``;
``rbo-jax demo`` prints two short simulations; ``rbo-jax sweep CONFIG.toml`` runs a declarative
parameter sweep (of one body, or the Bloch waves of a ``[lattice]`` of bodies);
``rbo-jax simulate`` integrates one oscillator given on the command line (with
``--lattice chain:N`` or ``grid:NxM``: a chain or grid of copies of it, :mod:`rbo_jax.lattice`);
``rbo-jax stability-map`` draws the Nikolai map (4.57)–(4.62), (4.69) over a grid of M, c, d,
A3; ``rbo-jax fit`` fits foundation parameters to a recorded (or synthetic) trajectory.
Negative values need no ``=`` (``--M -0.8:0.8:41``, ``--theta0 -0.1,0,0.2``: a word that starts
like a number is a value, :class:`._options.Parser`).

The commands only compose library calls: a :class:`~rbo_jax.app.spec.ModelSpec` from the
options, the library's functions, xarray Datasets written as netCDF or zarr.

Compiled programs are kept in JAX's persistent compilation cache, so that a second process
skips their XLA compilation; the programs of ``fit``, ``simulate``, ``fast_simulate`` and the
stability map's chunks are also kept traced (``jax.export``, in the ``programs`` folder of the
cache: :mod:`rbo_jax._programs`), so a second process neither traces nor lowers them. JAX does
not keep programs with host callbacks, which equinox's runtime checks (``eqx.error_if``) are:
``simulate`` leaves out diffrax's checks of inputs it has checked itself
(:func:`rbo_jax._validation.checked_inputs_trusted`); a check in a user's function keeps its
program out of both stores. The console command ends its process at once when the command is
done (:func:`exit_process`: no teardown of JAX by the interpreter), and while it runs Python's
cyclic garbage collector waits for more allocations than its default (:func:`fewer_collections`:
no full collections over the heap of JAX, xarray and pandas); what each saves is measured in
benchmarks/README.md, History. Both stores are
:func:`rbo_jax.enable_compilation_cache`'s; the directory is ``$RBO_JAX_COMPILATION_CACHE``, by
default ``rbo_jax/jax-cache`` under the user's cache directory (``$XDG_CACHE_HOME`` or
``~/.cache``); ``RBO_JAX_COMPILATION_CACHE=off`` turns it off.

Exit codes: 0 success; 1 the computation failed (a solver status, a fit that did not converge)
or an unexpected error (one line ``rbo-jax CMD: error: TYPE: MESSAGE``; the traceback with
``RBO_JAX_TRACEBACK=1``); 2 invalid input (options, parameters, files, output paths, requests
larger than the memory), with one line naming it, before anything is computed; 130 interrupted
by Ctrl-C (143: SIGTERM), with one line saying what was kept (:mod:`._interrupt`). Outputs are
written whole or not at all (:mod:`rbo_jax.app._outputs`).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import os
import sys
from pathlib import Path
from typing import NoReturn

import rbo_jax  # noqa: F401  (enables float64 before any array is made)

from ... import _cache
from .. import _outputs
from . import _interrupt
from ._common import Failure
from ._fit import fit_command
from ._map import stability_map_command
from ._misc import demo, reproduce_command, sweep_command
from ._options import Parser, add_command
from ._simulate import simulate_command

__all__ = ["build_parser", "exit_process", "fewer_collections", "main", "run"]

# Allocations between two collections of the youngest generation while a command runs (Python's
# default: 700).
GC_THRESHOLD = 10_000


def build_parser() -> argparse.ArgumentParser:
    """The ``rbo-jax`` argument parser (all subcommands)."""
    parser = Parser(
        prog="rbo-jax",
        description="Rigid body oscillator in JAX: simulation and analysis of the turn-vector "
        "model.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name, func in [
        ("demo", demo),
        ("reproduce", reproduce_command),
        ("sweep", sweep_command),
        ("simulate", simulate_command),
        ("stability-map", stability_map_command),
        ("fit", fit_command),
    ]:
        add_command(sub, name, func)
    return parser


def compilation_cache_dir() -> Path | None:
    """The persistent compilation cache directory of the command (None: off)."""
    return _cache.compilation_cache_dir()


def enable_compilation_cache() -> Path | None:
    """:func:`rbo_jax.enable_compilation_cache` at :func:`compilation_cache_dir`: JAX's
    persistent cache with every program kept, also the small ones, and the program store. A
    directory that cannot be made turns both off with a warning; the command still runs."""
    return _cache.enable_compilation_cache()


@contextlib.contextmanager
def fewer_collections(threshold: int = GC_THRESHOLD):
    """Python's cyclic garbage collector run less often inside the block: its youngest
    generation collected after ``threshold`` allocations instead of the default 700, the other
    thresholds as they were; restored afterwards.

    A command allocates hundreds of thousands of objects at its start (imports of xarray and
    pandas, JAX's tracing of a program), and at the default a collection of the whole heap,
    also of the objects of every module already imported, can follow every 70,000 net
    allocations (700 x 10 x 10); with 10,000 a command makes no full collection
    (benchmarks/README.md, History). Garbage cycles are still collected, a little later;
    results do not change."""
    old = gc.get_threshold()
    gc.set_threshold(max(old[0], threshold), *old[1:])
    try:
        yield
    finally:
        gc.set_threshold(*old)


def _unexpected(command: str | None, error: BaseException) -> int:
    """An exception no command expected: one line (the traceback only on request), status 1."""
    text = " ".join(str(error).split())
    if len(text) > 400:
        text = text[:397] + "..."
    where = f"rbo-jax {command}" if command else "rbo-jax"
    if os.environ.get("RBO_JAX_TRACEBACK", "") not in ("", "0"):
        import traceback

        traceback.print_exception(error)
        hint = ""
    else:
        hint = " (run with RBO_JAX_TRACEBACK=1 for the traceback)"
    print(f"{where}: error: {type(error).__name__}: {text}{hint}", file=sys.stderr)
    return 1


def main(argv: list[str] | None = None) -> int:
    """Run ``rbo-jax ARGV``; returns the exit status (usage errors raise ``SystemExit(2)``, as
    argparse does, with one line). Nothing escapes as a traceback: a :class:`Failure` prints
    its message, a ``KeyboardInterrupt`` what was kept (status 130), any other exception one
    line (status 1)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = build_parser().parse_args(argv)
    except Exception as e:  # an option's type raised something other than a usage error
        return _unexpected(None, e)
    args.argv = argv
    _outputs.WRITTEN.clear()
    _interrupt.set_command(args.command)
    _interrupt.set_describer(None)
    try:
        with fewer_collections():
            enable_compilation_cache()
            return args.func(args)
    except Failure as e:
        print(f"rbo-jax {args.command}: error: {e}", file=sys.stderr)
        return e.code
    except KeyboardInterrupt:
        _interrupt.cleanup()
        print(_interrupt.message(), file=sys.stderr)
        return 130
    except Exception as e:
        return _unexpected(args.command, e)


def exit_process(code: int) -> NoReturn:
    """End the process with ``code`` at once: standard output and error flushed, the
    interpreter's teardown (JAX's and XLA's objects, every module) skipped. Every file a
    command writes is closed before it returns, and JAX writes its cache entries when it
    compiles."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed or broken pipe: nothing more to say
            pass
    os._exit(code)


def run() -> NoReturn:
    """The ``rbo-jax`` console command: Ctrl-C and SIGTERM taken over (:func:`._interrupt.install`:
    they stop the command at once, also inside a compiled solve), :func:`main`, then
    :func:`exit_process`."""
    _interrupt.install()
    try:
        code = main()
    except SystemExit as e:  # argparse: --help (0) and usage errors (2)
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    exit_process(code)


if __name__ == "__main__":
    run()
