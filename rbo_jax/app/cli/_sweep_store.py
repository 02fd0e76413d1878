"""The files of ``rbo-jax sweep``: its store and map checked before the sweep starts, and what
an interrupted sweep kept.

A sweep creates the folders above its store, so the store's path needs only a writable folder
as its nearest existing ancestor and no file in the way; the PNG of the map goes beside the
store (or where the configuration says) and is checked likewise. When the sweep is interrupted
(Ctrl-C, SIGTERM: :mod:`._interrupt`), its finished chunks are in the store, each with its done
marker and checksum; the message counts them and gives the command that finishes the sweep.
"""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from . import _interrupt
from ._common import Failure, check_output


def png_path(args: argparse.Namespace, cfg) -> Path:
    """Where :func:`rbo_jax.app.config.run_config` draws the map."""
    return Path(args.output).with_suffix(".png") if args.output is not None else cfg.png


def check_paths(args: argparse.Namespace, cfg, plot: bool) -> Path:
    """The store's path and (with ``plot``) the PNG's, checked before anything is computed
    (exit status 2 naming the option or the configuration key). Returns the store's path."""
    if args.output is not None:
        text, option = args.output, "--output"  # as given: Path("") would be "."
    else:
        text, option = str(cfg.output), f"[sweep] output (in {cfg.source})"
    check_output(text, option, directory=True, make_parents=True)
    out = Path(text)
    if plot:
        png = png_path(args, cfg)
        where = (
            "the map (PNG) of --output"
            if args.output is not None
            else f"[sweep] png (in {cfg.source})"
            if png != cfg.output.with_suffix(".png")
            else f"the map (PNG) of [sweep] output (in {cfg.source})"
        )
        if png.resolve() == out.resolve():
            raise Failure(
                f"{where} {png}: the store's own path; give the store another suffix (e.g. .zarr)."
            )
        check_output(str(png), where, make_parents=png.parent == out.parent)
    return out


def resume_command(args: argparse.Namespace) -> str:
    """The command line that finishes this sweep: the same, with --resume, without
    --overwrite."""
    argv = [a for a in args.argv if not (len(a) > 4 and "--overwrite".startswith(a))]
    if not any(a in argv for a in ("--resume", "--retry-errors")):
        argv.append("--resume")
    return "rbo-jax " + shlex.join(argv)


def report_on_interrupt(args: argparse.Namespace, store: Path) -> None:
    """Say, when the sweep is interrupted, how many chunks the store kept and how to finish."""

    from ...batch.progress import chunks_done

    def describe() -> str:
        counts = chunks_done(store)
        if counts is None:
            return f"no store was written ({store}); run the command again"
        done, total = counts
        return f"kept {done} of {total} chunks in {store}; finish with: {resume_command(args)}"

    _interrupt.set_describer(describe)
