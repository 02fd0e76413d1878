"""Sweeps on Dask: ``rbo_jax.sweep(..., client=...)`` and ``rbo-jax sweep --scheduler/--workers``,
with real worker processes (one local cluster of 2 processes with one thread each serves the
module; ``--workers 2`` starts its own).

Expected values come from the same sweep in this process (one device, as each worker has): the
workers run the same chunk program with the same padding and settings, so values, statuses and
error records must be equal bit for bit, and stores file for file (data, checksums, markers,
metadata) — also when a worker is SIGKILLed mid-sweep and the scheduler runs its chunks again
elsewhere.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from helpers import needs_zarr
from sweep_quantities import (
    DASK_AXES,
    DASK_CHUNK,
    NIKOLAI_DIMS,
    SMALL_CONFIG,
    kills_its_worker,
    nikolai_spectrum,
    raises_for_large_c,
    slowed,
)

from rbo_jax.app import _cluster, cli
from rbo_jax.app.cli import _cluster as cli_cluster
from rbo_jax.batch import SweepError, _dask, _store, status_counts, sweep

distributed = pytest.importorskip("distributed")

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

CONFIG = SMALL_CONFIG.replace('output = "small.zarr"', 'output = "map.zarr"').replace(
    "chunk_size = 4", "chunk_size = 1"
)


@pytest.fixture(scope="module")
def client():
    """A local cluster of 2 worker processes (one thread each). Its workers import the
    quantities of this folder by name (tests/sweep_quantities.py), hence PYTHONPATH. A task
    whose workers died twice fails (allowed-failures 1, Dask's default is 3).

    The fault tests SIGKILL workers; each nanny starts a new process. LocalCluster also closes
    a lost worker's nanny for good when ``distributed.deploy.lost-worker-timeout`` (15 s) after
    the loss its own view of the scheduler has no worker of that name. On a loaded machine a
    restarted worker can be missing from that view at that instant (a later kill, or a slow
    restart), and the cluster loses a worker for the rest of the module: CI saw a chunk fail on
    "2 workers died" and the next test find 1 of 2 workers. The nannies restart their workers;
    the cluster is told not to close them."""
    import dask

    saved = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (str(HERE), str(ROOT), saved) if p)
    try:
        with (
            dask.config.set(
                {
                    "distributed.scheduler.allowed-failures": 1,
                    "distributed.deploy.lost-worker-timeout": "1 hour",
                }
            ),
            distributed.LocalCluster(
                n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
            ) as cluster,
            distributed.Client(cluster) as c,
        ):
            c.wait_for_workers(2, timeout=60)
            yield c
    finally:
        if saved is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = saved


def _files(path: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()
    }


def _assert_identical(ds, ref):
    """Same variables, dtypes, bytes (NaN payloads included), statuses and error records."""
    assert set(ds.data_vars) == set(ref.data_vars)
    for name in ref.data_vars:
        a, b = np.asarray(ds[name].values), np.asarray(ref[name].values)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        assert a.tobytes() == b.tobytes(), name
    assert ds.attrs["status_counts"] == ref.attrs["status_counts"]
    assert ds.attrs["errors"] == ref.attrs["errors"]


def _kill_when_busy(client, ready=lambda: True):
    """Start a thread that SIGKILLs one worker as soon as ``ready()`` and the worker runs a
    chunk; returns ``stop()``, which ends the thread and returns the killed pids."""
    client.wait_for_workers(2, timeout=60)  # a worker killed by an earlier test is back
    address, pid = next(iter(client.run(os.getpid).items()))
    killed: list[int] = []
    done = threading.Event()

    def watch():
        while not done.is_set():
            busy = client.processing(workers=[address]).get(address) or ()
            if ready() and any(str(k).startswith("rbo_jax-sweep-chunk") for k in busy):
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                return
            time.sleep(0.02)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()

    def stop():
        done.set()
        thread.join()
        return killed

    return stop


# ---------------------------------------------------------------------------------------------
# The API.
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow  # integration: a Dask cluster of real processes
@needs_zarr
def test_two_workers_equal_one_process_bit_for_bit(client, tmp_path, capsys):
    """In memory and to a store; the progress bar counts points, the summary line is printed;
    float64; each worker traced the quantity once for both sweeps, under this process's JAX
    settings (the test run's strict dtype promotion)."""
    kwargs = dict(chunk_size=DASK_CHUNK, dims=NIKOLAI_DIMS)
    one = sweep(nikolai_spectrum, DASK_AXES, progress=False, **kwargs)
    sweep(nikolai_spectrum, DASK_AXES, store=tmp_path / "one.zarr", progress=False, **kwargs)
    in_memory = sweep(
        nikolai_spectrum, DASK_AXES, client=client, progress=True, desc="dask", **kwargs
    )
    err = capsys.readouterr().err
    assert "24.0/24.0" in err and "dask: 24 points: 20 successful, 4 nonfinite_input" in err
    stored = sweep(
        nikolai_spectrum,
        DASK_AXES,
        client=client,
        store=tmp_path / "dask.zarr",
        progress=False,
        **kwargs,
    ).load()
    _assert_identical(in_memory, one)
    _assert_identical(stored, one)
    assert _files(tmp_path / "dask.zarr") == _files(tmp_path / "one.zarr")
    assert stored["abscissa"].dtype == np.float64 and stored["p"].dtype == np.complex128
    built = client.run(lambda: dict(_dask.BUILT))
    assert built and all(n == 1 for b in built.values() for n in b.values())
    settings = client.run(lambda: (jax.config.jax_enable_x64, jax.config.jax_numpy_dtype_promotion))
    assert set(settings.values()) == {(True, "strict")}


@pytest.mark.slow  # fault test: SIGKILL to a Dask worker
@needs_zarr
def test_a_worker_killed_mid_sweep_changes_nothing(client, tmp_path):
    """A worker SIGKILLed once two chunks are written, while it computes one: its chunks are
    computed again by the others and the store equals the one-process store file for file."""
    store, ref = tmp_path / "killed.zarr", tmp_path / "ref.zarr"
    done = store / "_sweep" / "chunk_done"

    def two_written():
        return (
            done.exists()
            and sum(p.is_file() and p.name != "zarr.json" for p in done.rglob("*")) >= 2
        )

    stop = _kill_when_busy(client, two_written)
    kwargs = dict(chunk_size=DASK_CHUNK, dims=NIKOLAI_DIMS, progress=False)
    sweep(slowed(0.25), DASK_AXES, store=store, client=client, **kwargs)
    assert stop(), "no worker was killed: the sweep ended first"
    sweep(slowed(0.0), DASK_AXES, store=ref, **kwargs)
    assert _files(store) == _files(ref)


@pytest.mark.slow  # integration: a Dask cluster of real processes
def test_a_point_that_raises_is_flagged_as_on_one_process(client):
    """eqx.error_if at c = 2: those points get `error` with their message, the others their
    values; the records list the points in chunk order, as on one process."""
    one = sweep(raises_for_large_c, DASK_AXES, chunk_size=DASK_CHUNK, progress=False)
    on_dask = sweep(
        raises_for_large_c, DASK_AXES, chunk_size=DASK_CHUNK, progress=False, client=client
    )
    _assert_identical(on_dask, one)
    assert status_counts(on_dask)["error"] == 5
    assert all(
        e["message"] == "c too large" and e["point"]["c"] == 2.0 for e in on_dask.attrs["errors"]
    )


@pytest.mark.slow  # integration: a Dask cluster of real processes
@needs_zarr
def test_resume_on_dask_submits_only_the_missing_chunks(client, tmp_path):
    path = tmp_path / "resume.zarr"
    kwargs = dict(chunk_size=DASK_CHUNK, dims=NIKOLAI_DIMS, progress=False, store=path)
    sweep(nikolai_spectrum, DASK_AXES, **kwargs)
    before = _files(path)
    group = _store.open_group(path, "r+")
    _store.mark_missing(
        group, _store.space_from_store(group, _store.read_descriptor(group, path)), [1, 5, 10]
    )
    with distributed.get_task_stream(client) as tasks:
        sweep(nikolai_spectrum, DASK_AXES, resume=True, client=client, **kwargs)
    assert sorted(int(str(t["key"]).rsplit("-", 1)[1]) for t in tasks.data) == [1, 5, 10]
    assert _files(path) == before


@pytest.mark.slow  # integration: a Dask cluster of real processes
def test_bad_arguments_with_a_client(client):
    with pytest.raises(ValueError, match="devices must be None"):
        sweep(
            nikolai_spectrum,
            DASK_AXES,
            chunk_size=DASK_CHUNK,
            client=client,
            devices=jax.local_devices(),
        )
    lock = threading.Lock()
    with pytest.raises(TypeError, match="must be picklable"):
        sweep(
            lambda c, M: c + M + 0.0 * (lock is None),
            DASK_AXES,
            chunk_size=DASK_CHUNK,
            client=client,
            progress=False,
        )


# ---------------------------------------------------------------------------------------------
# The command line.
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def one_process(tmp_path_factory):
    """The configuration and the files of its store written by one process."""
    folder = tmp_path_factory.mktemp("one")
    cfg = folder / "map.toml"
    cfg.write_text(CONFIG)
    assert cli.main(["sweep", str(cfg), "--quiet", "--no-plot"]) == 0
    return cfg, _files(folder / "map.zarr")


@pytest.mark.slow  # fault test: SIGKILL to a Dask worker
@needs_zarr
def test_cli_on_a_scheduler_survives_a_killed_worker(client, one_process, tmp_path):
    cfg, expected = one_process
    out = tmp_path / "map.zarr"
    stop = _kill_when_busy(client)
    assert (
        cli.main(
            [
                "sweep",
                str(cfg),
                "--quiet",
                "--no-plot",
                "--output",
                str(out),
                "--scheduler",
                client.scheduler.address,
            ]
        )
        == 0
    )
    assert stop(), "no worker was killed: the sweep ended first"
    assert _files(out) == expected


@pytest.mark.slow  # integration: a Dask cluster of real processes
@needs_zarr
def test_cli_workers_end_to_end(one_process, tmp_path, capsys):
    cfg, expected = one_process
    out = tmp_path / "map.zarr"
    assert cli.main(["sweep", str(cfg), "--no-plot", "--output", str(out), "--workers", "2"]) == 0
    assert _files(out) == expected
    captured = capsys.readouterr()
    assert "spectral_abscissa: 12 points: 12 successful" in captured.err
    assert f"spectral_abscissa: 12 points -> {out}" in captured.out


@pytest.mark.parametrize(
    "options, message",
    [
        (["--scheduler", "tcp://127.0.0.1:8786", "--workers", "2"], "exclude each other"),
        (
            [
                "--workers",
                "2",
                "--coordinator",
                "127.0.0.1:1234",
                "--num-processes",
                "2",
                "--process-id",
                "0",
            ],
            "--workers (Dask) and --coordinator, --num-processes, --process-id (jax.distributed)",
        ),
        (
            ["--scheduler", "tcp://127.0.0.1:8786", "--coordinator", "127.0.0.1:1234"],
            "--scheduler (Dask) and --coordinator (jax.distributed) exclude each other",
        ),
        (["--workers", "0"], "--workers must be >= 1"),
        (["--scheduler", " "], "--scheduler needs an address"),
    ],
)
def test_cli_refuses_bad_cluster_options(tmp_path, capsys, options, message):
    cfg = tmp_path / "map.toml"
    cfg.write_text(CONFIG)
    assert cli.main(["sweep", str(cfg), "--quiet", *options]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "map.zarr").exists()


def test_cli_without_dask_says_how_to_install_it(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cli_cluster, "dask_installed", lambda: False)
    cfg = tmp_path / "map.toml"
    cfg.write_text(CONFIG)
    assert cli.main(["sweep", str(cfg), "--quiet", "--workers", "2"]) == 2
    err = capsys.readouterr().err
    assert "pip install 'rbo_jax[dask]'" in err and err.count("\n") == 1


def test_cli_unreachable_scheduler(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(_cluster, "CONNECT_TIMEOUT_S", 1)
    cfg = tmp_path / "map.toml"
    cfg.write_text(CONFIG)
    assert cli.main(["sweep", str(cfg), "--quiet", "--scheduler", "tcp://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert "cannot reach the Dask scheduler 'tcp://127.0.0.1:9'" in err and err.count("\n") == 1


@pytest.mark.slow  # fault test: a Dask cluster of real processes
@needs_zarr
def test_a_chunk_that_kills_every_worker_is_reported(client, tmp_path):
    """A quantity that ends its process at c = 2 (as a crash in native code would): the chunk
    is tried on two workers (allowed-failures 1), then the sweep stops with a SweepError naming
    it; the chunks already written are kept. (Last: both workers are restarting afterwards.)"""
    client.wait_for_workers(2, timeout=60)
    path = tmp_path / "crash.zarr"
    with pytest.raises(
        SweepError,
        match=r"chunk \d+ was lost with every worker that ran it.*"
        r"resume the sweep",
    ):
        sweep(
            kills_its_worker,
            DASK_AXES,
            chunk_size=DASK_CHUNK,
            store=path,
            client=client,
            progress=False,
        )
    assert not (tmp_path / "crash.zarr.lock").exists()
