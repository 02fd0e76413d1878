"""The Dask options of ``rbo-jax sweep`` (``--scheduler``, ``--workers``), checked before anything
starts: one line and exit 2 for a combination that cannot run."""

from __future__ import annotations

import argparse
import os

from .._cluster import MISSING, dask_installed
from ._common import Failure

_JAX_DISTRIBUTED = (
    ("--coordinator", "coordinator"),
    ("--num-processes", "num_processes"),
    ("--process-id", "process_id"),
)


def check_cluster_options(args: argparse.Namespace) -> None:
    """Raise :class:`Failure` (exit 2) for ``--scheduler`` with ``--workers``, either with the
    ``jax.distributed`` options (Dask's workers or jax.distributed's processes compute the
    chunks, not both), ``--workers`` below 1, or either without Dask installed."""
    scheduler, workers = getattr(args, "scheduler", None), getattr(args, "workers", None)
    if scheduler is None and workers is None:
        return
    if scheduler is not None and workers is not None:
        raise Failure(
            "--scheduler and --workers exclude each other: connect to a running Dask "
            "scheduler, or start a local cluster of N workers."
        )
    ours = "--scheduler" if scheduler is not None else "--workers"
    theirs = [flag for flag, name in _JAX_DISTRIBUTED if getattr(args, name, None) is not None]
    if theirs:
        raise Failure(
            f"{ours} (Dask) and {', '.join(theirs)} (jax.distributed) exclude each "
            "other: one process with a Dask cluster computes the chunks, or several "
            "jax.distributed processes do."
        )
    if workers is not None and workers < 1:
        raise Failure(f"--workers must be >= 1, got {workers}.")
    most = 4 * (os.cpu_count() or 1)  # each worker is a process that imports JAX (~0.3 GB)
    if workers is not None and workers > most:
        raise Failure(
            f"--workers {workers}: more than {most} local worker processes (4 per core of "
            "this machine); for more, start workers on other machines and use --scheduler."
        )
    if scheduler is not None and not scheduler.strip():
        raise Failure("--scheduler needs an address, e.g. tcp://HOST:8786.")
    if not dask_installed():
        raise Failure(MISSING)
