"""The Dask cluster of a configured sweep (``rbo-jax sweep CONFIG --scheduler ADDRESS`` or
``--workers N``): a client of a running scheduler, or of a local cluster of worker processes
that lives as long as the sweep. :func:`rbo_jax.sweep` (``client=``) does the rest.

``distributed`` is imported only when one of them is asked for (it is an optional extra,
``pip install 'rbo_jax[dask]'``).
"""

from __future__ import annotations

import contextlib
import importlib.util

from ..batch import SweepError

MISSING = (
    "Dask is not installed (--scheduler and --workers run the sweep on it): "
    "pip install 'rbo_jax[dask]'"
)
#: Seconds to reach a scheduler before giving up (Dask's own default, 30 s, is for clusters
#: whose scheduler may start late; a sweep's scheduler is already running).
CONNECT_TIMEOUT_S = 20


def dask_installed() -> bool:
    return importlib.util.find_spec("distributed") is not None


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None):
    """A :class:`distributed.Client` of the scheduler at ``scheduler`` (``tcp://HOST:PORT``)
    or of a local cluster of ``workers`` processes with one thread each (one JAX process per
    core, as the one-process sweep; closed on exit); ``None`` without either. Raises
    :class:`~rbo_jax.SweepError` (a one-line message) when Dask is missing or the scheduler
    cannot be reached, ``ValueError`` for both or a count below 1."""
    if scheduler is None and workers is None:
        yield None
        return
    if scheduler is not None and workers is not None:
        raise ValueError("give a scheduler's address or a number of local workers, not both.")
    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, int) or workers < 1
    ):
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}.")
    if not dask_installed():
        raise SweepError(MISSING)
    import distributed

    if workers is not None:
        import dask

        # the dashboard on a free port: Dask's 8787 may be another cluster's (Dask then warns);
        # the sweep has its progress bar (a `dask scheduler` started by hand keeps 8787).
        # A worker that dies (memory, a crash) is restarted by its nanny; LocalCluster would
        # also close that nanny for good when, lost-worker-timeout (15 s) after the loss, its
        # view of the scheduler lacks the restarted worker (a slow restart on a loaded
        # machine): the sweep would go on with one worker fewer. The cluster lives as long as
        # the sweep, so it is told to wait.
        with (
            dask.config.set({"distributed.deploy.lost-worker-timeout": "1 day"}),
            distributed.LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=":0",
                # one CPU device per worker process: the workers are the cores (import rbo_jax
                # would otherwise give each of them every core, rbo_jax._devices)
                env={"RBO_JAX_CPU_DEVICES": "1"},
            ) as cluster,
            distributed.Client(cluster) as client,
        ):
            yield client
        return
    try:
        client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError, ValueError, TypeError) as e:
        raise SweepError(
            f"cannot reach the Dask scheduler {scheduler!r}: "
            f"{str(e).splitlines()[0] if str(e) else type(e).__name__}"
        ) from None
    with client:
        yield client
