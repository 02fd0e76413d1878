"""Parameter sweeps (rbo_jax.sweep): chunks, devices, processes, storage, resumption, statuses,
the CLI configuration.

Expected values come from evaluating the quantity point by point (outside the sweep), from the
store written by an uninterrupted run (for the killed-and-resumed one), and from a one-process
run (for the two-process and four-device ones). The subprocess tests use the Nikolai spectrum at
the closed-form equilibrium (cheap to compile); the statuses use real failing simulations.
"""

from __future__ import annotations

import json
import logging
import os
import pickle
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import xarray as xr
from helpers import needs_zarr, zarr
from sweep_quantities import (
    DIST_AXES,
    DIST_CHUNK,
    HOOK,
    KILL_AXES,
    KILL_CHUNK,
    NIKOLAI_AXES,
    NIKOLAI_DIMS,
    SMALL_CONFIG,
    K,
    nikolai_abscissa,
    nikolai_model,
)

import rbo_jax as rbo
from rbo_jax._enumeration import code, names
from rbo_jax.app import cli
from rbo_jax.app.config import QUANTITIES, ConfigError, load_config
from rbo_jax.batch import SweepError, open_sweep, status_counts, sweep
from rbo_jax.batch._chunks import Chunks
from rbo_jax.batch._space import _chunk_shape, make_space
from rbo_jax.plotting import plot_sweep
from rbo_jax.simulate import SolveStatus
from rbo_jax.stability import StabilityKind

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
WORKER = HERE / "_sweep_worker.py"
EXAMPLES = sorted((ROOT / "examples").glob("*.toml"))
CHUNK = 2  # every in-process Nikolai sweep uses it: one compiled program for all of them


def _child_env(**extra) -> dict:
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("XLA_FLAGS", "RBO_SWEEP_TEST_LOG", "RBO_SWEEP_TEST_SLEEP")
    }
    env["JAX_ENABLE_X64"] = "1"
    env["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(HERE), str(ROOT), os.environ.get("PYTHONPATH")) if p
    )
    env.update(extra)
    return env


def _nikolai(**kwargs):
    return sweep(
        nikolai_abscissa,
        NIKOLAI_AXES,
        chunk_size=CHUNK,
        dims=NIKOLAI_DIMS,
        progress=False,
        **kwargs,
    )


@pytest.fixture(scope="module")
def nikolai():
    return _nikolai()


@pytest.fixture
def hook_log(tmp_path):
    """Counts the calls of the quantity's host hook (one per chunk and device)."""
    log = tmp_path / "hook.log"
    HOOK["log"] = str(log)
    yield lambda: len(log.read_text().splitlines()) if log.exists() else 0
    HOOK["log"] = None


def _store_files(path: Path) -> dict[str, bytes]:
    files = sorted(p for p in path.rglob("*") if p.is_file())
    return {str(p.relative_to(path)): p.read_bytes() for p in files}


# ---------------------------------------------------------------------------------------------
# Values, labels, chunks.
# ---------------------------------------------------------------------------------------------


def test_grid_sweep_equals_pointwise_evaluation(nikolai):
    """Every grid point equals the quantity evaluated alone; coordinates and dims are labelled;
    the NaN value of M gives nonfinite_input with NaN values (and nothing is evaluated there)."""
    ds = nikolai
    assert ds["abscissa"].dims == ("c", "M") and ds["p"].dims == ("c", "M", "mode")
    np.testing.assert_array_equal(ds["c"].values, NIKOLAI_AXES["c"])
    np.testing.assert_array_equal(ds["M"].values, NIKOLAI_AXES["M"])
    assert ds["abscissa"].dtype == np.float64 and ds["p"].dtype == np.complex128
    single = jax.jit(nikolai_abscissa)
    for i, c in enumerate(NIKOLAI_AXES["c"]):
        for j, M in enumerate(NIKOLAI_AXES["M"]):
            if np.isnan(M):
                assert ds["status"].values[i, j] == code(SolveStatus.nonfinite_input)
                assert np.isnan(ds["abscissa"].values[i, j])
                assert np.all(np.isnan(ds["p"].values[i, j]))
                continue
            ref = single(c, M)
            assert ds["status"].values[i, j] == code(SolveStatus.successful)
            np.testing.assert_allclose(ds["abscissa"].values[i, j], ref["abscissa"], rtol=1e-12)
            np.testing.assert_allclose(ds["p"].values[i, j], ref["p"], rtol=1e-12, atol=1e-14)
            assert ds["kind"].values[i, j] == int(code(ref["kind"]))
    # The follower moment of the Nikolai problem makes the undamped equilibrium flutter (4.69).
    ok = ds["status"].values == 0
    assert np.all(ds["kind"].values[ok] == code(StabilityKind.flutter))
    assert ds["kind"].attrs["flag_meanings"].split()[int(code(StabilityKind.flutter))] == "flutter"


def test_status_counts_and_flags(nikolai):
    counts = status_counts(nikolai)
    assert counts["successful"] == 12 and counts["nonfinite_input"] == 3
    assert sum(counts.values()) == 15
    assert nikolai.attrs["status_counts"] == counts
    flags = nikolai["status"].attrs["flag_meanings"].split()
    assert flags == [*names(SolveStatus), "error"]  # SolveStatus codes, in order, then error
    assert nikolai["status"].attrs["enumeration"] == "rbo_jax.SolveStatus"


def test_one_compilation_serves_every_chunk(hook_log):
    """3 × 5 points in blocks of 1 × 2: 9 chunks, three of them partial (padded); one compiled
    program runs them all, and repeated sweeps reuse it."""
    space = make_space(NIKOLAI_AXES, None, CHUNK)
    assert space.chunk_shape == (1, 2) and space.n_chunks == 9
    chunks = Chunks(nikolai_abscissa, space, tuple(jax.local_devices()[:1]), NIKOLAI_DIMS)
    program = chunks.program
    assert program.strategy == "shard_map"
    ds = _nikolai(devices=1)
    again = _nikolai(devices=1)
    assert Chunks(nikolai_abscissa, space, tuple(jax.local_devices()[:1])).program is program
    # one call per chunk that holds a finite point (a chunk of NaN points only is not evaluated)
    n_calls = sum(
        np.isfinite(space.points(space.slices(c))).all(axis=1).any() for c in range(space.n_chunks)
    )
    assert hook_log() == 2 * n_calls
    xr.testing.assert_identical(ds, again)


def test_points_mode_matches_grid(nikolai):
    cs = np.array([2.0, 0.5, 1.0, 1.0, 0.5])
    Ms = np.array([0.4, 0.1, np.nan, 0.5, 0.2])
    ds = sweep(
        nikolai_abscissa,
        points={"c": cs, "M": Ms},
        chunk_size=CHUNK,
        dims=NIKOLAI_DIMS,
        progress=False,
    )
    assert ds["abscissa"].dims == ("point",)
    np.testing.assert_array_equal(ds["c"].values, cs)
    np.testing.assert_array_equal(ds["M"].values, Ms)
    for n, (c, M) in enumerate(zip(cs, Ms)):
        i = int(np.flatnonzero(NIKOLAI_AXES["c"] == c)[0])
        if np.isnan(M):
            assert ds["status"].values[n] == code(SolveStatus.nonfinite_input)
            continue
        j = int(np.flatnonzero(NIKOLAI_AXES["M"] == M)[0])
        for v in ("abscissa", "p", "kind", "status"):
            np.testing.assert_array_equal(ds[v].values[n], nikolai[v].values[i, j])


@pytest.mark.parametrize(
    "shape, size",
    [
        ((101, 41), 4096),
        ((5, 2000), 1500),
        ((1000, 3), 1024),
        ((7,), 3),
        ((3, 4, 5), 1),
        ((2, 2), 99),
    ],
)
def test_chunk_shape_bounded_and_balanced(shape, size):
    c = _chunk_shape(shape, size)
    assert np.prod(c) <= size and all(1 <= ci <= si for ci, si in zip(c, shape))
    # the split axis is cut in nearly equal parts (no tiny last block)
    for ci, si in zip(c, shape):
        parts = -(-si // ci)
        assert si - (parts - 1) * ci >= ci - parts + 1 or parts == 1
    if np.prod(shape) <= size:
        assert c == shape


# ---------------------------------------------------------------------------------------------
# Bad points: statuses from real failing simulations.
# ---------------------------------------------------------------------------------------------

E1 = jnp.array([1.0, 0.0, 0.0])


def failing_simulation(alpha, th, wt, t1):
    """Body on the barrier foundation (4.49), c = d = 0.01, A = E, started at θ = th·e1 spinning
    about e1 with a transverse component wt: status from simulate(..., throw=False)."""
    model = rbo.RigidBodyOscillator(jnp.eye(3), rbo.BarrierFoundation(0.01, 0.01, alpha, 100.0, K))
    traj = rbo.simulate(
        model,
        th * E1,
        jnp.stack([1.0, wt, 0.0]),
        jnp.linspace(0.0, 1.0, 5) * t1,
        rtol=1e-8,
        atol=1e-8,
        max_steps=256,
        throw=False,
    )
    E = traj.energy
    return {
        "theta": traj.theta[-1],
        "drift": jnp.max(jnp.abs(E - E[0])),
        "num_steps": traj.num_steps,
    }, traj.status


def test_bad_points_get_their_status_and_the_others_complete():
    S = SolveStatus
    cases = {  # name: (alpha, th, wt, t1)
        "successful": (100.0, 0.5, 0.1, 1.0),
        "domain_error": (0.3, 0.5, 0.1, 1.0),  # starts beyond the bending barrier α = 0.3
        "max_steps_reached": (100.0, 0.5, 0.1, 1e4),  # 256 steps cannot reach t1 = 1e4
        "singular_point": (100.0, 6.0, 1e-5, 1.0),  # |θ| reaches 2π with θ×Ω ≠ 0 (4.11)
        "nonfinite_input": (100.0, np.nan, 0.1, 1.0),
    }
    cols = np.array(list(cases.values())).T
    ds = sweep(
        failing_simulation,
        points=dict(zip(("alpha", "th", "wt", "t1"), cols)),
        chunk_size=8,
        dims={"theta": ["component"]},
        progress=False,
    )
    names = ds["status"].attrs["flag_meanings"].split()
    assert [names[s] for s in ds["status"].values] == list(cases)
    assert [int(code(getattr(S, n))) for n in cases] == list(ds["status"].values)
    counts = status_counts(ds)
    assert all(counts[n] == 1 for n in cases) and sum(counts.values()) == len(cases)
    ok = ds.isel(point=0)
    assert np.all(np.isfinite(ok["theta"].values)) and float(ok["drift"]) < 1e-7  # K + U conserved
    assert np.all(np.isinf(ds["theta"].values[1])) and np.all(np.isnan(ds["theta"].values[4]))
    assert ds["num_steps"].values[4] == -1  # not evaluated


def test_postprocess_may_edit_its_chunk_in_place():
    """A ``postprocess`` gets writable arrays, whether every point of the chunk was computed
    (the outputs are then the program's own buffers, read-only, and are copied for it) or some
    were not (filled arrays)."""

    def square(x, y):
        return {"v": jnp.stack([x * x, y])}

    def scale(result):
        result["v"] *= 2.0  # in place
        return result

    x = np.array([1.0, 2.0, 3.0, np.nan])
    for xs in (x[:3], x):
        ds = sweep(square, points={"x": xs, "y": xs + 1}, postprocess=scale, progress=False)
        ok = np.isfinite(xs)
        np.testing.assert_array_equal(ds["v"].values[ok], 2.0 * np.stack([xs**2, xs + 1], 1)[ok])
        assert np.all(np.isnan(ds["v"].values[~ok]))


# ---------------------------------------------------------------------------------------------
# Storage and resumption.
# ---------------------------------------------------------------------------------------------


@needs_zarr
def test_store_equals_in_memory_and_opens_with_xarray(tmp_path, nikolai):
    path = tmp_path / "map.zarr"
    ds = _nikolai(store=path)
    xr.testing.assert_identical(ds.load(), nikolai)
    raw = xr.open_zarr(path, consolidated=False, chunks=None)  # plain xarray reads it too
    for v in nikolai.data_vars:
        np.testing.assert_array_equal(raw[v].values, nikolai[v].values)
    xr.testing.assert_identical(open_sweep(path).load(), nikolai)
    # one zarr chunk (one file) per sweep chunk and variable
    space = make_space(NIKOLAI_AXES, None, CHUNK)
    assert sum(f.is_file() for f in (path / "abscissa").rglob("*")) == space.n_chunks + 1
    assert zarr.open_group(path, mode="r")["abscissa"].chunks == space.chunk_shape


def test_store_without_zarr_says_why(tmp_path, monkeypatch):
    """Where zarr >= 3 cannot be installed (Python 3.10), sweep(store=...) says what is missing
    and why, before computing anything; the in-memory sweep needs no zarr."""
    monkeypatch.setitem(sys.modules, "zarr", None)  # import zarr -> ImportError
    with pytest.raises(ImportError, match=r"needs zarr >= 3, which needs Python >= 3.11"):
        sweep(
            nikolai_abscissa,
            NIKOLAI_AXES,
            chunk_size=CHUNK,
            dims=NIKOLAI_DIMS,
            store=tmp_path / "map.zarr",
            progress=False,
        )
    assert not (tmp_path / "map.zarr").exists()


@needs_zarr
def test_points_mode_store_is_labelled(tmp_path):
    pts = {"c": np.array([0.5, 1.0, 2.0]), "M": np.array([0.1, 0.2, 0.3])}
    ds = sweep(
        nikolai_abscissa,
        points=pts,
        chunk_size=CHUNK,
        store=tmp_path / "p.zarr",
        dims=NIKOLAI_DIMS,
        progress=False,
    )
    assert set(ds.coords) >= {"c", "M"} and ds["c"].dims == ("point",)
    np.testing.assert_array_equal(ds["M"].values, pts["M"])


@needs_zarr
def test_store_guards(tmp_path, nikolai):
    path = tmp_path / "map.zarr"
    _nikolai(store=path)
    with pytest.raises(FileExistsError, match="resume=True"):
        _nikolai(store=path)
    other = dict(NIKOLAI_AXES, M=NIKOLAI_AXES["M"] * 2)
    with pytest.raises(SweepError, match="values of 'M' differ"):
        sweep(
            nikolai_abscissa,
            other,
            chunk_size=CHUNK,
            dims=NIKOLAI_DIMS,
            store=path,
            resume=True,
            progress=False,
        )
    with pytest.raises(SweepError, match="attribute 'run'"):
        _nikolai(store=path, resume=True, attrs={"run": 2})
    with pytest.raises(SweepError, match="variables"):
        sweep(
            nikolai_abscissa,
            NIKOLAI_AXES,
            chunk_size=CHUNK,
            store=path,
            resume=True,
            progress=False,
        )  # other dimension names: a different sweep
    with pytest.raises(ValueError, match="need a store"):
        _nikolai(resume=True)
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "x.txt").write_text("x")
    with pytest.raises(SweepError, match="not a zarr store"):
        _nikolai(store=tmp_path / "junk")
    # A complete store resumes to itself, recomputing nothing.
    before = _store_files(path)
    xr.testing.assert_identical(_nikolai(store=path, resume=True).load(), nikolai)
    assert _store_files(path) == before
    # A missing marker makes the store incomplete (open_sweep refuses it) until resumed.
    (path / "_sweep" / "chunk_done" / "c" / "1" / "0").unlink()
    with pytest.raises(SweepError, match="incomplete: 1 of 9"):
        open_sweep(path)
    xr.testing.assert_identical(_nikolai(store=path, resume=True).load(), nikolai)
    assert _store_files(path) == before
    ds = _nikolai(store=path, overwrite=True)
    xr.testing.assert_identical(ds.load(), nikolai)


def _wait_for(predicate, proc, timeout):
    t0 = time.monotonic()
    while not predicate():
        if proc.poll() is not None:
            return False
        if time.monotonic() - t0 > timeout:
            return False
        time.sleep(0.02)
    return True


@needs_zarr
def test_killed_sweep_resumes_to_an_identical_store(tmp_path, hook_log):
    """A sweep killed by SIGKILL after some chunks are on disk: resume=True computes only the
    missing chunks, and the store is byte for byte the store of an uninterrupted run."""
    store = tmp_path / "killed.zarr"
    done_dir = store / "_sweep" / "chunk_done" / "c"
    proc = subprocess.Popen(
        [sys.executable, str(WORKER), "kill", str(store)],
        cwd=ROOT,
        env=_child_env(RBO_SWEEP_TEST_SLEEP="0.4"),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        started = _wait_for(
            lambda: done_dir.exists() and sum(1 for p in done_dir.rglob("*") if p.is_file()) >= 3,
            proc,
            180,
        )
        proc.send_signal(signal.SIGKILL)
        out = proc.communicate(timeout=30)[0].decode()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
    assert started, f"the sweep did not write 3 chunks in time:\n{out[-2000:]}"
    assert proc.returncode == -signal.SIGKILL
    space = make_space(KILL_AXES, None, KILL_CHUNK)
    done = np.asarray(zarr.open_group(store, mode="r")["_sweep/chunk_done"][...]).ravel()
    n_done = int(done.sum())
    assert 3 <= n_done < space.n_chunks, "killed too late to test anything"
    with pytest.raises(SweepError, match="incomplete"):
        open_sweep(store)

    resumed = sweep(
        nikolai_abscissa,
        KILL_AXES,
        chunk_size=KILL_CHUNK,
        dims=NIKOLAI_DIMS,
        store=store,
        resume=True,
        progress=False,
    )
    # only the missing chunks were computed (the hook runs once per chunk and device)
    assert hook_log() == jax.local_device_count() * (space.n_chunks - n_done)

    fresh = tmp_path / "fresh.zarr"
    uninterrupted = sweep(
        nikolai_abscissa,
        KILL_AXES,
        chunk_size=KILL_CHUNK,
        dims=NIKOLAI_DIMS,
        store=fresh,
        progress=False,
    )
    assert _store_files(store) == _store_files(fresh)
    xr.testing.assert_identical(resumed.load(), uninterrupted.load())


# ---------------------------------------------------------------------------------------------
# Devices and processes.
# ---------------------------------------------------------------------------------------------


def test_four_local_devices_share_each_chunk(tmp_path):
    """XLA_FLAGS=--xla_force_host_platform_device_count=4 in a child: each chunk is split over
    the 4 devices by shard_map, and the results equal a one-device sweep bitwise."""
    out = tmp_path / "report.json"
    res = subprocess.run(
        [sys.executable, str(WORKER), "devices", str(out)],
        cwd=ROOT,
        capture_output=True,
        env=_child_env(XLA_FLAGS="--xla_force_host_platform_device_count=4"),
        timeout=300,
    )
    assert res.returncode == 0, res.stderr.decode()[-3000:]
    report = json.loads(out.read_text())
    assert report["local_devices"] == 4
    assert report["strategy"] == "shard_map"
    # a chunk of 6 points padded to 4 devices x 16 points (the quantity's eigenvalues are one
    # LAPACK call per block, here one block of 16 points per device: _program.Layout)
    assert report["batch"] == 64
    assert report["shard_devices"] == 4 and report["shard_shapes"] == [[16]] * 4
    assert report["identical"]
    assert report["status_counts"]["nonfinite_input"] == 3


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow  # cost: ~11-16 s, two processes started and compiling, a gloo rendezvous
@needs_zarr
def test_two_processes_equal_one_process(tmp_path, hook_log):
    """Two processes on localhost (jax.distributed, gloo): each computes its share of the chunks
    (logged by the hook), the in-memory results are gathered and the store is written by both;
    both equal the one-process sweep exactly."""
    reference = sweep(
        nikolai_abscissa, DIST_AXES, chunk_size=DIST_CHUNK, dims=NIKOLAI_DIMS, progress=False
    )
    port, store, log = _free_port(), tmp_path / "two.zarr", tmp_path / "calls.log"
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                str(WORKER),
                "distributed",
                str(port),
                "2",
                str(i),
                str(store),
                str(tmp_path / f"out{i}.pkl"),
            ],
            cwd=ROOT,
            env=_child_env(RBO_SWEEP_TEST_LOG=str(log)),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        for i in range(2)
    ]
    outputs = []
    try:
        for p in procs:
            outputs.append(p.communicate(timeout=300)[0].decode())
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(timeout=30)
    for p, o in zip(procs, outputs):
        assert p.returncode == 0, o[-3000:]
    for i in range(2):
        result = pickle.loads((tmp_path / f"out{i}.pkl").read_bytes())
        assert result["process_count"] == 2
        xr.testing.assert_identical(result["in_memory"], reference)
        xr.testing.assert_identical(result["stored"], reference)
    xr.testing.assert_identical(open_sweep(store).load(), reference)
    calls = [line.split()[0] for line in log.read_text().splitlines()]
    space = make_space(DIST_AXES, None, DIST_CHUNK)
    evaluated = sum(
        np.isfinite(space.points(space.slices(c))).all(axis=1).any() for c in range(space.n_chunks)
    )
    # two sweeps (in memory, stored); every evaluated chunk once, shared by the processes, and
    # split over each process's devices (one per core, as here: the hook runs once per device)
    assert len(calls) == 2 * evaluated * jax.local_device_count()
    assert 0 < calls.count("0") < len(calls) and 0 < calls.count("1") < len(calls)


# ---------------------------------------------------------------------------------------------
# Progress, errors, validation.
# ---------------------------------------------------------------------------------------------


def test_progress_bar_and_quiet_mode(capsys):
    _nikolai()
    assert capsys.readouterr().err == ""
    sweep(
        nikolai_abscissa,
        NIKOLAI_AXES,
        chunk_size=CHUNK,
        dims=NIKOLAI_DIMS,
        progress=True,
        desc="nikolai",
    )
    err = capsys.readouterr().err
    assert "nikolai" in err and "15.0/15.0" in err and "pt/s" in err  # done/total, rate
    assert "nikolai: 15 points: 12 successful, 3 nonfinite_input" in err


def _raises_for_large_c(c, M):
    import equinox as eqx

    return {"x": eqx.error_if(c + M, c > 1.5, "c too large")}


@needs_zarr
@pytest.mark.parametrize("chunk_size", [CHUNK, 64])
def test_a_point_that_raises_is_flagged_and_the_rest_completes(tmp_path, chunk_size, caplog):
    """A quantity that raises (equinox.error_if) at the points c = 2 is not fatal: its chunk is
    re-run in halves, the raising points get the status `error` with their message and
    coordinates, every other point is computed — whether the chunk holds 2 points or all 15.
    JAX's traceback of each failed call is not logged: the sweep reports the message; and JAX
    does not raise the last failed call again when it synchronises (at the interpreter's exit
    it printed a traceback)."""
    path = tmp_path / f"err{chunk_size}.zarr"
    with caplog.at_level(logging.ERROR):
        ds = sweep(
            _raises_for_large_c, NIKOLAI_AXES, chunk_size=chunk_size, store=path, progress=False
        ).load()
    assert not [r for r in caplog.records if "callback failed" in r.getMessage()]
    flags = ds["status"].attrs["flag_meanings"].split()
    status = np.asarray(ds["status"].values)
    c, M = np.meshgrid(NIKOLAI_AXES["c"], NIKOLAI_AXES["M"], indexing="ij")
    raised = (c > 1.5) & np.isfinite(M)
    assert np.all(status[raised] == flags.index("error"))
    assert np.all(np.isnan(ds["x"].values[raised]))
    ok = ~raised & np.isfinite(M)
    assert np.all(status[ok] == flags.index("successful"))
    np.testing.assert_array_equal(ds["x"].values[ok], (c + M)[ok])
    errors = ds.attrs["errors"]
    assert sorted(e["point"]["M"] for e in errors) == [0.1, 0.2, 0.4, 0.5]
    assert all(e["point"]["c"] == 2.0 and e["message"] == "c too large" for e in errors)
    assert all(tuple(e["index"]) in {(2, 0), (2, 1), (2, 3), (2, 4)} for e in errors)
    assert status_counts(ds)["error"] == 4
    jax.effects_barrier()  # what jax's exit handler calls: raised the last failed call


@needs_zarr
def test_retry_errors_recomputes_only_the_raising_points(tmp_path):
    """resume keeps the error points; retry_errors=True recomputes them only (here with a fixed
    quantity of the same outputs): the store then equals a fresh run's."""
    path = tmp_path / "retry.zarr"
    sweep(_raises_for_large_c, NIKOLAI_AXES, chunk_size=CHUNK, store=path, progress=False)
    kept = sweep(
        _raises_for_large_c, NIKOLAI_AXES, chunk_size=CHUNK, store=path, resume=True, progress=False
    )
    assert status_counts(kept)["error"] == 4

    def fixed(c, M):
        return {"x": c + M}

    retried = sweep(
        fixed,
        NIKOLAI_AXES,
        chunk_size=CHUNK,
        store=path,
        resume=True,
        retry_errors=True,
        progress=False,
    ).load()
    fresh = sweep(fixed, NIKOLAI_AXES, chunk_size=CHUNK, progress=False)
    assert status_counts(retried)["error"] == 0 and retried.attrs["errors"] == []
    np.testing.assert_array_equal(retried["x"].values, fresh["x"].values)
    np.testing.assert_array_equal(retried["status"].values, fresh["status"].values)
    open_sweep(path)  # the rewritten chunks carry valid checksums


@needs_zarr
def test_one_writer_per_store_and_a_dead_owner_is_taken_over(tmp_path, capsys):
    """A live owner's lock (here: this process's parent, alive) refuses a second writer, naming
    the store and the owner; the lock of a process that no longer exists is taken over with a
    message; a finished sweep leaves no lock."""
    import json
    import os
    import socket

    path = tmp_path / "locked.zarr"
    lock = tmp_path / "locked.zarr.lock"
    owner = {"host": socket.gethostname(), "pid": os.getppid(), "since": "then"}
    lock.write_text(json.dumps(owner))
    with pytest.raises(SweepError, match=f"{path} is being written by process {os.getppid()}"):
        sweep(_raises_for_large_c, NIKOLAI_AXES, chunk_size=CHUNK, store=path, progress=False)
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    ).stdout.strip()
    lock.write_text(json.dumps({**owner, "pid": int(dead)}))
    sweep(_raises_for_large_c, NIKOLAI_AXES, chunk_size=CHUNK, store=path, progress=False)
    assert "taking over the lock" in capsys.readouterr().err and not lock.exists()


@needs_zarr
def test_a_corrupted_chunk_is_reported_and_recomputed_on_resume(tmp_path, capsys):
    """A flipped byte in a chunk file and a truncated one: open_sweep refuses the store naming
    the chunks; resume recomputes exactly them and the store equals an uninterrupted run's."""
    import shutil

    path, clean = tmp_path / "bad.zarr", tmp_path / "clean.zarr"
    sweep(_raises_for_large_c, NIKOLAI_AXES, chunk_size=CHUNK, store=clean, progress=False)
    shutil.copytree(clean, path)
    files = sorted(p for p in (path / "x" / "c").rglob("*") if p.is_file())
    raw = bytearray(files[0].read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    files[0].write_bytes(bytes(raw))
    files[1].write_bytes(files[1].read_bytes()[:5])
    with pytest.raises(SweepError, match="2 chunk\\(s\\) fail their checksum"):
        open_sweep(path)
    sweep(
        _raises_for_large_c, NIKOLAI_AXES, chunk_size=CHUNK, store=path, resume=True, progress=False
    )
    assert capsys.readouterr().err.count("is recomputed") == 2
    assert _store_files(path) == _store_files(clean)


def _store_files(path):
    return {
        str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()
    }


@pytest.mark.parametrize(
    "quantity, error, match",
    [
        (lambda c, M: (c, M, c), TypeError, "pair"),
        (lambda c, M: (c, M), TypeError, "status .* got float64"),
        (lambda c, M: [c, M], TypeError, "return a dict"),
        (lambda c, M: {"c": c}, ValueError, "clashes"),
        (lambda c, M: {"x": "text"}, TypeError, "'x' must be an array"),
    ],
)
def test_bad_quantity_outputs_are_explained(quantity, error, match):
    with pytest.raises(error, match=match):
        sweep(quantity, {"c": [1.0], "M": [0.1]}, progress=False)


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({}, ValueError, "exactly one of"),
        ({"axes": {"c": [1.0]}, "points": {"c": [1.0]}}, ValueError, "exactly one of"),
        ({"points": {"c": [1.0, 2.0], "M": [1.0]}}, ValueError, "same number of values"),
        ({"axes": {"c": []}}, ValueError, r"axes\['c'\] must be a non-empty"),
        ({"axes": {"status": [1.0]}}, ValueError, "reserved"),
        ({"axes": {"c": ["a"]}}, TypeError, "numbers"),
        ({"axes": {"c": [1.0]}, "chunk_size": 0}, ValueError, "chunk_size must be >= 1"),
        ({"axes": {"c": [1.0]}, "devices": 99}, ValueError, "local device"),
    ],
)
def test_bad_sweep_arguments_are_explained(kwargs, error, match):
    with pytest.raises(error, match=match):
        sweep(lambda c, M=0.0: c, progress=False, **kwargs)


def test_dims_must_match_the_outputs():
    with pytest.raises(ValueError, match="does not return"):
        sweep(nikolai_abscissa, NIKOLAI_AXES, chunk_size=CHUNK, dims={"q": ["x"]}, progress=False)
    with pytest.raises(ValueError, match="2 names for an output of shape \\(6,\\)"):
        sweep(
            nikolai_abscissa, NIKOLAI_AXES, chunk_size=CHUNK, dims={"p": ["a", "b"]}, progress=False
        )


# ---------------------------------------------------------------------------------------------
# Figures.
# ---------------------------------------------------------------------------------------------


def test_plot_sweep_draws_grids_curves_and_points(nikolai):
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ds = nikolai.copy(deep=True)
    ds["status"].values[1, 3] = code(SolveStatus.max_steps_reached)  # (c, M) = (1.0, 0.4)
    ax = plot_sweep(ds, "abscissa")
    mesh = ax.collections[0]
    assert ax.get_xlabel() == "c" and ax.get_ylabel() == "M"
    # y (M) rows, x (c) columns; the row M = nan (non-finite coordinate) is left out
    values = np.ma.getdata(mesh.get_array()).reshape(4, 3)
    np.testing.assert_allclose(values[0], nikolai["abscissa"].values[:, 0])
    assert np.isnan(values[2, 1]) and np.isfinite(values[2, 0])  # a failed point: blank
    assert "3 nonfinite_input" in ax.get_title() and "1 max_steps_reached" in ax.get_title()
    ax = plot_sweep(nikolai.isel(c=0), "p")  # one axis, complex vector: |p| against M
    assert ax.get_ylabel() == "|p|" and len(ax.lines) == 1
    pts = nikolai.stack(point=("c", "M")).reset_index("point")
    ax = plot_sweep(pts, "abscissa")
    assert ax.get_xlabel() == "c" and ax.get_ylabel() == "M"
    with pytest.raises(KeyError, match="no variable 'nope'"):
        plot_sweep(nikolai, "nope")
    plt.close("all")


# ---------------------------------------------------------------------------------------------
# The CLI and its configuration.
# ---------------------------------------------------------------------------------------------


@needs_zarr
def test_cli_sweep_writes_store_and_png_and_resumes(tmp_path, capsys):
    cfg = tmp_path / "small.toml"
    cfg.write_text(SMALL_CONFIG)
    assert cli.main(["sweep", str(cfg), "--quiet"]) == 0
    store, png = tmp_path / "small.zarr", tmp_path / "small.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    ds = open_sweep(store).load()
    assert status_counts(ds) == {
        "successful": 12,
        "not_converged": 0,
        "singular_point": 0,
        "domain_error": 0,
        "nonfinite": 0,
        "invalid_parameters": 0,
        "nonfinite_input": 0,
        "error": 0,
    }
    assert ds["theta_eq"].dims == ("M", "b", "component")
    # Newton finds θ_eq = (M/d) k (4.62); without friction the spectrum there is (4.69).
    np.testing.assert_allclose(
        ds["theta_eq"].values[..., 2], ds["M"].values[:, None] / 2.0 * np.ones((1, 4)), atol=1e-12
    )
    for M in (0.2, 0.4):
        closed_form = float(jnp.max(jnp.real(rbo.nikolai_spectrum(1.0, 0.5, 1.0, 2.0, M))))
        np.testing.assert_allclose(
            float(ds["spectral_abscissa"].sel(M=M, b=0.0)), closed_form, rtol=1e-9
        )
    # conservative (M = 0, b = 0): marginally stable; friction without load: asymptotically
    kinds = ds["kind"].attrs["flag_meanings"].split()
    assert kinds[int(ds["kind"].sel(M=0.0, b=0.0))] == "marginally_stable"
    assert kinds[int(ds["kind"].sel(M=0.0, b=0.1, method="nearest"))] == "asymptotically_stable"
    capsys.readouterr()
    assert cli.main(["sweep", str(cfg), "--quiet"]) == 2
    assert "--resume" in capsys.readouterr().err
    before = _store_files(store)
    assert cli.main(["sweep", str(cfg), "--quiet", "--resume"]) == 0
    assert _store_files(store) == before
    # --retry-errors implies --resume; no point has status 'error': nothing is recomputed
    assert cli.main(["sweep", str(cfg), "--quiet", "--retry-errors"]) == 0
    assert _store_files(store) == before
    cfg.write_text(SMALL_CONFIG.replace("c = 1.0", "c = 1.5"))
    assert cli.main(["sweep", str(cfg), "--quiet", "--resume"]) == 2
    assert "attribute 'config' differs" in capsys.readouterr().err


@needs_zarr
def test_cli_final_state_at_equilibrium(tmp_path):
    """A list of points, each started exactly at its equilibrium θ = (M/d)k (4.62), at rest: the
    final state of the simulation is the equilibrium."""
    cfg = tmp_path / "rest.toml"
    cfg.write_text("""
[sweep]
quantity = "final_state"
output = "rest.zarr"

[points]
M = [0.1, 0.3, 0.5]
d = [2.0, 1.0, 4.0]

[model]
inertia = { moments = [1.0, 0.8, 0.6] }
foundation = { type = "quadratic", c = 1.0, d = "d" }
loads = [{ type = "follower", M = "M" }]

[initial]
about_equilibrium = true

[solver]
t1 = 2.0
""")
    assert cli.main(["sweep", str(cfg), "--quiet", "--no-plot"]) == 0
    ds = open_sweep(tmp_path / "rest.zarr")
    assert not (tmp_path / "rest.png").exists()
    assert ds["theta"].dims == ("point", "component") and status_counts(ds)["successful"] == 3
    expected = (ds["M"].values / ds["d"].values)[:, None] * np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(ds["theta"].values, expected, atol=1e-12)
    np.testing.assert_allclose(ds["Omega"].values, 0.0, atol=1e-12)
    assert np.all(ds["num_steps"].values > 0)


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_example_configs_are_valid(path):
    cfg = load_config(path)
    assert cfg.quantity_name in QUANTITIES
    assert cfg.output.parent == path.parent and cfg.png.suffix == ".png"
    assert (cfg.axes is None) != (cfg.points is None)


BAD_CONFIGS = [
    ("[sweep]\nquantity='x'", "exactly one of the tables [axes]"),
    (SMALL_CONFIG + "[solverr]\n", "unknown table [solverr] (did you mean [solver]?)"),
    (
        SMALL_CONFIG.replace("chunk_size = 4", "chunk_size = 4\nchunks = 3"),
        "[sweep]: unknown key 'chunks' (did you mean 'chunk_size'?)",
    ),
    (
        SMALL_CONFIG.replace('M = "M"', 'M = "MM"'),
        "[model.loads][0] M: 'MM' is neither a number nor an axis name (axes: M, b)",
    ),
    (SMALL_CONFIG.replace('b = "b"', "b = 0.1"), "[axes] b: this axis is not used"),
    (SMALL_CONFIG.replace("c = 1.0", "c = -1.0"), "[model.foundation] c: must be > 0, got -1"),
    (SMALL_CONFIG.replace("c = 1.0", 'c = "M"'), "axis 'M' takes the value 0, but c must be > 0"),
    (
        SMALL_CONFIG.replace("chunk_size = 4", "chunk_size = 'big'"),
        "[sweep] chunk_size: must be an",
    ),
    (SMALL_CONFIG.replace("spectral_abscissa", "speed"), "[sweep] quantity: must be one of"),
    (SMALL_CONFIG.replace('"quadratic"', '"cubic"'), "[model.foundation] type: must be"),
    (SMALL_CONFIG.replace("num = 4", "num = 0"), "[axes] b.num: must be an integer >= 1"),
    (
        SMALL_CONFIG + "[solver]\nt1 = 1.0\n",
        "[solver]: is not used by quantity 'spectral_abscissa'",
    ),
    (
        SMALL_CONFIG.replace("spectral_abscissa", "final_state"),
        "config: missing required key 'solver'",
    ),
    (
        SMALL_CONFIG.replace("spectral_abscissa", "energy_drift") + "[solver]\nrtol = 1e-8\n",
        "[solver]: missing required key 't1'",
    ),
    (
        SMALL_CONFIG.replace("[axes]", "[points]").replace(
            "b = { start = 0.0, stop = 0.3, num = 4 }", "b = [0.1, 0.2]"
        ),
        "[points]: every parameter needs the same number of values",
    ),
    (SMALL_CONFIG.replace("A1 = 1.0, ", ""), "[model.inertia]: missing required key 'A1'"),
    (SMALL_CONFIG.replace('output = "small.zarr"', "output = 3"), "[sweep] output: must be a path"),
    (SMALL_CONFIG + "plot = 'x'\n", "unknown key 'plot'"),
    (
        SMALL_CONFIG.replace("chunk_size = 4", "chunk_size = 4\nplot = 'energy'"),
        "[sweep] plot: must be an output of 'spectral_abscissa'",
    ),
    ("[sweep\n", "not valid TOML"),
]


@pytest.mark.parametrize("text, message", BAD_CONFIGS)
def test_config_errors_name_the_key(tmp_path, text, message, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(cfg)
    assert message in str(info.value) and str(cfg) in str(info.value)
    assert cli.main(["sweep", str(cfg)]) == 2
    assert message in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# Slow: the examples end to end, and a million points in bounded memory.
# ---------------------------------------------------------------------------------------------


@needs_zarr
@pytest.mark.slow
@pytest.mark.parametrize("path", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_examples_run(tmp_path, path):
    store = tmp_path / "out.zarr"
    assert cli.main(["sweep", str(path), "--quiet", "--output", str(store)]) == 0
    ds = open_sweep(store)
    assert status_counts(ds)["successful"] > 0
    assert (tmp_path / "out.png").read_bytes()[:4] == b"\x89PNG"


def _energy(c, M):
    model = nikolai_model(c, M)
    return {"U": model.potential_energy(M * K)}


@needs_zarr
@pytest.mark.slow
def test_a_million_points_in_bounded_memory(tmp_path):
    """10⁶ points in chunks of 2¹⁶ written to a store: the peak memory stays far below what
    holding every chunk's device buffers would take, and U = ½ d (M/d)² (4.50)."""
    import resource

    axes = {"c": np.linspace(0.5, 2.0, 1000), "M": np.linspace(0.0, 1.0, 1000)}
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    ds = sweep(_energy, axes, chunk_size=2**16, store=tmp_path / "big.zarr", progress=False)
    grown_mib = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert ds["U"].shape == (1000, 1000)
    np.testing.assert_allclose(ds["U"].values[3], 0.5 * axes["M"] ** 2, rtol=1e-14, atol=1e-16)
    assert grown_mib < 400, grown_mib


# ---------------------------------------------------------------------------------------------
# Fuzzed configurations: any value at any key gives a ConfigError naming where, never a crash.
# ---------------------------------------------------------------------------------------------

FINAL_STATE_CONFIG = """
[sweep]
quantity = "final_state"
output = "fs.zarr"
chunk_size = 4

[axes]
M = [0.0, 0.2]
c = { start = 0.5, stop = 1.5, num = 2 }

[model]
inertia = { A1 = 1.0, A3 = 0.5 }
foundation = { type = "barrier", c = "c", d = 2.0, alpha = 2.0, beta = 1.5 }
loads = [{ type = "follower", M = "M" }, { type = "semi_tangential", M = 0.1, l1 = 0.5, l2 = 0.5 }]

[initial]
theta0 = [0.1, 0.0, 0.0]
Omega0 = [0.0, 0.2, 0.0]

[solver]
t1 = 1.0
rtol = 1e-8
integrator = "fast_simulate"
"""


def _toml_string(v: str) -> str:
    return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")


def _toml_value(v) -> str:
    """A TOML literal of a str, bool, int, float (nan, inf too), list or dict (inline table)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, float):
        return "nan" if v != v else ("inf" if v == np.inf else "-inf" if v == -np.inf else repr(v))
    if isinstance(v, int):
        return str(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{_toml_string(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"


def _to_toml(cfg: dict) -> str:
    lines = []
    for table, body in cfg.items():
        if not isinstance(body, dict):  # a mutated top level: a plain key
            lines.insert(0, f"{_toml_string(table)} = {_toml_value(body)}")
            continue
        lines.append(f"[{table}]")
        lines += [f"{_toml_string(k)} = {_toml_value(v)}" for k, v in body.items()]
    return "\n".join(lines) + "\n"


def _paths(tree, prefix=()):
    """Every (table, key[, index or subkey]) path of the parsed config."""
    out = []
    for k, v in tree.items() if isinstance(tree, dict) else enumerate(tree):
        out.append(prefix + (k,))
        if isinstance(v, (dict, list)) and len(prefix) < 3:
            out += _paths(v, prefix + (k,))
    return out


def _set(tree, path, value):
    for k in path[:-1]:
        tree = tree[k]
    tree[path[-1]] = value


def _fuzz_values():
    from hypothesis import strategies as st

    scalars = st.one_of(
        st.booleans(),
        st.integers(-(10**20), 10**20),
        st.floats(allow_nan=True, allow_infinity=True),
        st.text(max_size=6),
        st.sampled_from(["M", "c", "quadratic", "barrier", "follower", "simulate", ""]),
    )
    return st.recursive(
        scalars,
        lambda inner: st.one_of(
            st.lists(inner, max_size=4),
            st.dictionaries(
                st.sampled_from(
                    ["type", "c", "d", "M", "b", "start", "stop", "num", "A1", "A3", "x"]
                ),
                inner,
                max_size=3,
            ),
        ),
        max_leaves=6,
    )


def test_fuzzed_configs_fail_with_a_config_error_naming_the_key(tmp_path):
    """Hypothesis replaces the value at one key of a valid configuration (of every table, list
    entry and inline-table key) with a random TOML value (any type, NaN, inf, huge integers,
    nested lists and tables): loading either succeeds or raises ConfigError whose message names
    the table or key at fault; nothing else escapes (no TypeError, KeyError, ...)."""
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib
    from hypothesis import given, settings
    from hypothesis import strategies as st

    base = tomllib.loads(FINAL_STATE_CONFIG)
    paths = _paths(base)
    counts = {"accepted": 0, "refused": 0}

    @settings(max_examples=500)
    @given(st.sampled_from(paths), _fuzz_values())
    def check(path, value):
        cfg = json.loads(json.dumps(base))
        _set(cfg, path, value)
        file = tmp_path / "fuzz.toml"
        file.write_text(_to_toml(cfg))
        try:
            load_config(file)
        except ConfigError as e:
            counts["refused"] += 1
            message = str(e)
            named = [str(p) for p in path if isinstance(p, str)]
            assert any(n in message for n in named) or "[axes]" in message, (path, message)
        else:
            counts["accepted"] += 1

    check()
    assert counts["refused"] > 0
    print(f"fuzzed configurations: {counts}")


@pytest.mark.parametrize("n", range(1, len(jax.local_devices()) + 1))
def test_outputs_are_undealt_from_the_devices_shards(n):
    """A chunk's rows are dealt to the devices like cards (``_sharding.deal``); its outputs are
    put back in order from each device's shard (``undeal_shards``): the same rows as
    ``undeal`` of the whole array, for vectors and for rows of complex numbers. On every
    number of this process's devices (one per core: 2 and 4 devices are also covered by the
    maps of ``test_devices.py``, equal bit for bit to the one-device map)."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    from rbo_jax._sharding import deal, undeal, undeal_shards

    mesh = Mesh(np.array(jax.local_devices()[:n]), ("d",))
    sharding = NamedSharding(mesh, PartitionSpec("d"))
    rows = 12 * n
    rng = np.random.default_rng(n)
    block = rng.normal(size=(rows, 3)) + 1j * rng.normal(size=(rows, 3))
    for x in (block, np.arange(rows, dtype=np.int8)):
        on_devices = jax.device_put(deal(x, n), sharding)
        got = undeal_shards(on_devices, n)
        np.testing.assert_array_equal(got, undeal(np.asarray(on_devices), n))
        np.testing.assert_array_equal(got, x)
