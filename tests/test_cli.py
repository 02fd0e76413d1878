"""The `rbo-jax` command: demo, reproduce (the main job of `make demo`), benchmark smoke runs."""

import os
import subprocess
import sys

import pytest

from rbo_jax import cli
from rbo_jax.reproduce import Check

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_demo_prints_tables(capsys):
    assert cli.main(["demo", "--t1", "2", "--samples", "3"]) == 0
    out = capsys.readouterr().out
    assert "K + U" in out and "bending dev." in out
    # the conservative run reports a tiny energy drift, the Nikolai run a growing deviation
    drift = float(out.split("max |energy drift| = ")[1].split()[0])
    assert drift < 1e-8


def test_reproduce_exit_status_reflects_failed_checks(monkeypatch, tmp_path, capsys):
    """`rbo-jax reproduce` exits non-zero when any check fails (and zero when all pass)."""
    import rbo_jax.reproduce as rep

    ok = Check("s", "q", "p", "o", 0.0, 1.0)
    bad = Check("s", "q", "p", "o", 2.0, 1.0)
    monkeypatch.setattr(rep, "run_reproduction", lambda out, quick, figures: [ok, bad])
    assert cli.main(["reproduce", "--out", str(tmp_path)]) == 1
    monkeypatch.setattr(rep, "run_reproduction", lambda out, quick, figures: [ok])
    assert cli.main(["reproduce", "--out", str(tmp_path)]) == 0
    assert not Check("s", "q", "p", "o", float("nan"), 1.0).passed


@pytest.mark.slow
def test_reproduce_quick_passes_and_writes_the_report(tmp_path):
    """The full chain of `make demo` at --quick size: every check of the paper passes, the report
    lists them and the figures exist."""
    assert cli.main(["reproduce", "--quick", "--out", str(tmp_path)]) == 0
    report = (tmp_path / "report.md").read_text()
    assert "checks passed" in report and "**FAIL**" not in report
    assert report.count("| pass |") >= 20
    for name in ["map_M_c.png", "map_M_A3.png", "root_locus.png", "nikolai_growth.png",
                 "simplest_oscillator.png", "precession_growth.png"]:
        assert (tmp_path / name).stat().st_size > 1000


@pytest.mark.slow
def test_benchmarks_smoke_run():
    """Every benchmark runs at a tiny size (benchmarks are not part of the default suite)."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", "run.py"), "--smoke"],
                          capture_output=True, text=True, timeout=900, env=env, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for marker in ["speed-up per trajectory", "max |p - (4.69)|", "first fit", "shard_map over"]:
        assert marker in proc.stdout
