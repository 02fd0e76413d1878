"""Every core by default (issue 31): ``import rbo_jax`` asks JAX for one CPU device per core of
the process's affinity, the batch engine spreads chunks over them without waiting forever, and
the results are bit for bit the same on any number of devices. Each test runs real processes
(the device count is fixed when JAX's backend starts)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
WORKER = HERE / "_devices_worker.py"
DEVICE_VARIABLES = ("XLA_FLAGS", "JAX_NUM_CPU_DEVICES", "RBO_JAX_CPU_DEVICES", "JAX_PLATFORMS")


def _run(tmp_path, what, affinity=None, timeout=300, **env_extra):
    env = {k: v for k, v in os.environ.items() if k not in DEVICE_VARIABLES}
    env["JAX_PLATFORMS"] = "cpu"
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    env.update(env_extra)
    out = tmp_path / f"{what}.json"
    cmd = [sys.executable, str(WORKER), what, str(out)]
    if affinity is not None:  # as taskset: the child pins itself, then becomes the worker
        pin = (
            f"import os, sys; os.sched_setaffinity(0, {sorted(affinity)!r}); "
            "os.execv(sys.executable, [sys.executable] + sys.argv[1:])"
        )
        cmd = [sys.executable, "-c", pin] + cmd[1:]
    res = subprocess.run(
        cmd,
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,  # a hang fails the test instead of waiting forever
    )
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(out.read_text())


def test_a_fresh_process_has_one_cpu_device_per_core(tmp_path):
    """Nothing set: as many CPU devices as cores in the affinity."""
    report = _run(tmp_path, "devices")
    assert report["platform"] == "cpu"
    assert report["devices"] == report["cores"] == len(os.sched_getaffinity(0))


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity here")
def test_the_affinity_counts_not_the_machine(tmp_path):
    """``taskset -c 0``: one core, one device."""
    first = min(os.sched_getaffinity(0))
    report = _run(tmp_path, "devices", affinity={first})
    assert report["cores"] == 1 and report["devices"] == 1


@pytest.mark.parametrize(
    "env, expected",
    [
        ({"RBO_JAX_CPU_DEVICES": "off"}, 1),
        ({"RBO_JAX_CPU_DEVICES": "3"}, 3),
        ({"JAX_NUM_CPU_DEVICES": "5"}, 5),
        ({"XLA_FLAGS": "--xla_force_host_platform_device_count=6"}, 6),
    ],
)
def test_the_user_chooses(tmp_path, env, expected):
    """The opt-out, an explicit count, and JAX's own settings are respected."""
    assert _run(tmp_path, "devices", **env)["devices"] == expected


def test_a_bad_setting_is_named(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in DEVICE_VARIABLES}
    env.update(RBO_JAX_CPU_DEVICES="many", PYTHONPATH=str(ROOT))
    res = subprocess.run(
        [sys.executable, "-c", "import rbo_jax"], env=env, capture_output=True, text=True
    )
    assert res.returncode != 0 and "RBO_JAX_CPU_DEVICES='many'" in res.stderr


def test_fewer_devices_asked_for_are_not_warned_about(tmp_path):
    """``RBO_JAX_CPU_DEVICES=1`` on a machine of several cores: one device, as asked, and no
    warning that JAX started first (it said so, wrongly, before 2026-11-27)."""
    report = _run(tmp_path, "chosen_sweep", RBO_JAX_CPU_DEVICES="1")
    assert report["devices"] == 1
    assert report["warnings"] == []


def test_jax_started_first_is_said_once(tmp_path):
    """A computation before ``import rbo_jax`` fixes one device; the first sweep on a machine
    of several cores says what to do, once."""
    report = _run(tmp_path, "started_first")
    assert report["devices"] == 1
    if len(os.sched_getaffinity(0)) > 1:
        assert len(report["warnings"]) == 1
        assert "import rbo_jax before the first jax computation" in report["warnings"][0].lower()
    else:
        assert report["warnings"] == []


@pytest.mark.slow  # cost: ~10 s a process, Newton maps on 2 and 4 devices
@pytest.mark.parametrize("devices", [2, 4])
def test_stability_map_with_newton_equilibria_ends_on_several_devices(tmp_path, devices):
    """The map of issue 31 (Newton equilibria, LAPACK eigenvalues; 40 x 40 is the smallest grid
    that waited forever on 2 devices) ends on 2 and 4 CPU devices and equals the one-device map
    bit for bit."""
    report = _run(tmp_path, "newton_map", RBO_JAX_CPU_DEVICES=str(devices))
    assert report["devices"] == devices
    assert report["identical"]
    assert report["counts"]["successful"] == 1600


@pytest.mark.slow  # cost: ~30 s, two Newton maps of 65,536 points compiled
def test_a_newton_map_in_chunks_of_65536_points_ends_on_2_devices(tmp_path):
    """A chunk of 65,536 points on 2 devices waited forever in ``lapack_dtrsm_ffi``: lineax's
    ``lu_solve`` is traced only when the program is lowered, and was lowered outside the
    LAPACK-in-blocks rules, so each device's share of 32,768 triangular solves was one call that
    jaxlib split over XLA's pool. It ends now (the test's timeout fails a hang), with the
    one-device bits."""
    report = _run(tmp_path, "newton_map_large_chunks", timeout=240, RBO_JAX_CPU_DEVICES="2")
    assert report["devices"] == 2
    assert report["identical"]
    assert sum(report["counts"].values()) == 65536


@pytest.mark.parametrize("devices", [2, 4])
def test_a_vmap_inside_a_point_ends_on_several_devices(tmp_path, devices):
    """LAPACK batched inside one point (the rods' ``critical_load`` scans its spectra over the
    loads) ran split over XLA's pool and waited forever on 2 CPU devices; it ends now, with the
    one-device bits."""
    report = _run(tmp_path, "inner_eig", timeout=120, RBO_JAX_CPU_DEVICES=str(devices))
    assert report["devices"] == devices
    assert report["finite"] and report["identical"]


def test_a_program_for_several_devices_keeps_its_loops_whole(tmp_path):
    """XLA:CPU cuts a program's large loops into tasks for its intra-op pool, which has a thread
    per device whatever the CPU affinity (so at least 2 here); a chunk program for several CPU
    devices is compiled without the cuts (``_sharding.compile_options``), one for one device
    keeps them (its only way of using several cores)."""
    report = _run(tmp_path, "partitions", RBO_JAX_CPU_DEVICES="2")
    assert report["devices"] == 2
    assert report["found"]["2"] in ([], ['""'])  # no cut anywhere
    assert any(c.strip('"') not in ("", "1") for c in report["found"]["1"])  # cut in tasks


@pytest.mark.slow  # cost: ~35 s, six sweeps compiled
def test_fast_simulate_sweep_is_bitwise_the_same_on_any_number_of_devices(tmp_path):
    """Refilled lanes, chunks of 1230 and 500 points, over 1, 2 and 4 devices, some with their
    tails compacted: one result."""
    report = _run(tmp_path, "fast_sweep", RBO_JAX_CPU_DEVICES="4")
    assert report["devices"] == 4 and len(report["runs"]) == 6
    assert report["finite"]
    assert report["differ"] == []


@pytest.mark.slow  # cost: ~60 s, six sweeps compiled for up to 16 devices
def test_sweeps_on_8_and_16_devices_end_with_the_same_bits(tmp_path):
    """Issue 31: 8 and 16 CPU devices on this machine's cores (more devices than cores) end,
    every device holds an equal share of a chunk (a multiple of 16 points), and the results are
    the one-device bits."""
    report = _run(
        tmp_path,
        "fast_sweep",
        timeout=600,
        RBO_JAX_CPU_DEVICES="16",
        RBO_TEST_DEVICE_COUNTS="1,8,16",
    )
    assert report["devices"] == 16 and len(report["runs"]) == 6
    assert report["finite"] and report["differ"] == []
    for key, share in report["shares"].items():
        devices, chunk = (int(x) for x in key.split("/"))
        assert share % 16 == 0 and share * devices >= chunk > (share - 16) * devices


def _sharded_vmap(tmp_path, devices, **env):
    report = _run(tmp_path, "sharded_vmap", timeout=400, RBO_JAX_CPU_DEVICES=str(devices), **env)
    assert report["devices"] == devices
    assert report["finite"] and report["differ"] == []
    assert all(n == devices for n in report["spread"].values()), report["spread"]
    # each device runs its own lanes: the collectives (the inputs dealt to the devices, the
    # outputs gathered back) lie outside every loop; GSPMD's partition of the lanes' loop had
    # an all-reduce in it, and ran every lane on every device
    assert report["collectives"]["loops"] > 0 and report["collectives"]["in_loops"] == 0
    return report


@pytest.mark.slow  # cost: ~40-60 s, a process compiling three batch programs
def test_jit_vmap_on_a_named_sharding_runs_a_share_on_each_device(tmp_path):
    """Issue 49 G: ``jax.jit(jax.vmap(fast_simulate))`` of a batch sharded over 2 CPU devices
    runs each device's share on its own refilled lanes, and gives the one-device bits; so does
    a batch replicated on the devices whose size is not a multiple of them (padded)."""
    _sharded_vmap(tmp_path, 2)


@pytest.mark.slow  # cost: ~60 s a process, five programs compiled, one of them eagerly
@pytest.mark.parametrize("devices", [1, 4])
def test_jit_vmap_on_a_named_sharding_on_1_and_4_devices_and_without_jit(tmp_path, devices):
    """The same on 4 devices (the shares not ordered longest first, the one-device run
    ordered) and on a mesh of one device (the batch as before), and sharded inputs under
    ``jax.vmap`` without ``jit``, and with a time grid per trajectory (lockstep loops, one
    device's share each)."""
    _sharded_vmap(tmp_path, devices, RBO_TEST_EAGER="1")
