"""The `rbo-jax` command: demo, reproduce (the main job of `make demo`), simulate,
stability-map, fit, benchmark smoke runs."""

import argparse
import os
import sys

import numpy as np
import pytest
from helpers import open_output as _open
from helpers import run_cli as _run
from helpers import spectrum_match_error

from rbo_jax.app import cli
from rbo_jax.app.reproduce import Check

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_demo_prints_tables(capsys):
    """`rbo-jax demo` is a printed demonstration: it runs and prints its two tables."""
    assert cli.main(["demo", "--t1", "2", "--samples", "3"]) == 0
    out = capsys.readouterr().out
    assert "K + U" in out and "bending dev." in out


def test_a_command_runs_with_fewer_garbage_collections_and_restores_them(monkeypatch, capsys):
    """While a command runs, Python's youngest generation is collected after
    ``cli.GC_THRESHOLD`` allocations (full collections of the heap of JAX, xarray and pandas
    cost a fresh process 0.2-0.4 s); the thresholds are restored after it, also after an error."""
    import gc

    before = gc.get_threshold()
    seen = []

    def command(args):
        seen.append(gc.get_threshold())
        if len(seen) == 2:
            raise RuntimeError("broken")
        return 0

    monkeypatch.setattr(cli, "demo", command)
    assert cli.main(["demo"]) == 0
    assert gc.get_threshold() == before
    assert cli.main(["demo"]) == 1  # an unexpected error: one line, status 1
    assert gc.get_threshold() == before
    assert seen == [(max(before[0], cli.GC_THRESHOLD), *before[1:])] * 2
    assert "RuntimeError: broken" in capsys.readouterr().err


def test_reproduce_exit_status_reflects_failed_checks(monkeypatch, tmp_path, capsys):
    """`rbo-jax reproduce` exits non-zero when any check fails (and zero when all pass)."""
    import rbo_jax.app.reproduce as rep

    ok = Check("s", "q", "p", "o", 0.0, 1.0)
    bad = Check("s", "q", "p", "o", 2.0, 1.0)
    monkeypatch.setattr(rep, "run_reproduction", lambda out, quick, figures: [ok, bad])
    assert cli.main(["reproduce", "--out", str(tmp_path)]) == 1
    monkeypatch.setattr(rep, "run_reproduction", lambda out, quick, figures: [ok])
    assert cli.main(["reproduce", "--out", str(tmp_path)]) == 0
    assert not Check("s", "q", "p", "o", float("nan"), 1.0).passed


@pytest.mark.slow  # integration: reproduce --quick, ~3 min
def test_reproduce_quick_passes_and_writes_the_report(tmp_path):
    """The full chain of `make demo` at --quick size: every check of the paper passes, the report
    lists them and the figures exist."""
    assert cli.main(["reproduce", "--quick", "--out", str(tmp_path)]) == 0
    report = (tmp_path / "report.md").read_text()
    assert "checks passed" in report and "**FAIL**" not in report
    assert report.count("| pass |") >= 20
    for name in [
        "map_M_c.png",
        "map_M_A3.png",
        "root_locus.png",
        "nikolai_growth.png",
        "simplest_oscillator.png",
        "precession_growth.png",
        "rods_statics.png",
        "rods_stability.png",
        "rods_flutter.png",
    ]:
        assert (tmp_path / name).stat().st_size > 1000


# ---------------------------------------------------------------------------------------------
# simulate, stability-map, fit
# ---------------------------------------------------------------------------------------------

# Runs of one model structure share one compiled solve (diffrax caches on the structure, the
# number of samples and the solver settings), so the tests below keep them equal where they can:
# the quadratic foundation without loads always runs with 21 samples at the default tolerances.
K = (0.0, 0.0, 1.0)
N_QUAD = "21"


def _estimates(path) -> dict[str, tuple[float, float]]:
    """{name: (estimate, standard error)} of a fit result written with --out."""
    ds = _open(path)
    return {
        str(n): (float(v), float(e))
        for n, v, e in zip(ds["parameter"].values, ds["estimate"].values, ds["stderr"].values)
    }


def test_every_subcommand_help_explains_each_option(capsys):
    """`rbo-jax CMD --help` lists every option of CMD with a help text; the new subcommands cite
    the paper's equations and give examples."""
    parser = cli.build_parser()
    (subparsers,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    assert {"demo", "reproduce", "sweep", "simulate", "stability-map", "fit"} <= set(
        subparsers.choices
    )
    for name, sub in subparsers.choices.items():
        code, out, _ = _run(capsys, [name, "--help"])
        assert code == 0
        for action in sub._actions:
            assert action.help, (name, action.dest)
            for option in action.option_strings:
                assert option in out, (name, option)
        if name in ("simulate", "stability-map", "fit"):
            assert "examples:" in out and "(4.4" in out and "(4.5" in out, name
            assert "default" in out
    code, out, _ = _run(capsys, ["fit", "--help"])
    for array in ("t ", "theta ", "Omega ", "(n, 3)"):
        assert array in out  # the data file format


def test_simulate_conservative_energy_and_files_match_rbo_jax_simulate(capsys, tmp_path):
    """Barrier foundation (4.49), no loads: K + U of the written dataset is constant to 1e-9
    (4.124), and the trajectory of --out (netCDF, zarr and CSV alike) is rbo_jax.fast_simulate's
    (the default integrator), and rbo_jax.simulate's (diffrax) with --integrator simulate; the two
    agree to the tolerance."""
    import jax.numpy as jnp

    from rbo_jax import (
        BarrierFoundation,
        RigidBodyOscillator,
        fast_simulate,
        simulate,
        transversely_isotropic_inertia,
    )

    argv = [
        "simulate",
        "--foundation",
        "barrier",
        "--c",
        "1",
        "--d",
        "2",
        "--alpha",
        "2",
        "--beta",
        "1.5",
        "--A1",
        "1",
        "--A3",
        "0.6",
        "--theta0",
        "0.8,-0.3,0.5",
        "--Omega0=0.2,1.1,-0.7",
        "--t1",
        "5",
        "--samples",
        "11",
        "--rtol",
        "1e-12",
        "--atol",
        "1e-12",
    ]
    code, out, err = _run(capsys, argv + ["--out", str(tmp_path / "run.nc")])
    assert code == 0, err
    ds = _open(tmp_path / "run.nc")
    E = ds["energy"].values
    assert ds["theta"].shape == ds["Omega"].shape == (11, 3) and E.shape == (11,)
    assert ds.attrs["status"] == "successful" and bool(ds["reached"].all())
    assert np.max(np.abs(E - E[0])) < 1e-9
    k = jnp.asarray(K)
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(1.0, 0.6, k), BarrierFoundation(1.0, 2.0, 2.0, 1.5, k)
    )
    ts = jnp.linspace(0.0, 5.0, 11)
    traj = fast_simulate(
        model, jnp.array([0.8, -0.3, 0.5]), jnp.array([0.2, 1.1, -0.7]), ts, rtol=1e-12, atol=1e-12
    )
    diffrax_traj = simulate(
        model, jnp.array([0.8, -0.3, 0.5]), jnp.array([0.2, 1.1, -0.7]), ts, rtol=1e-12, atol=1e-12
    )
    np.testing.assert_allclose(traj.theta, diffrax_traj.theta, rtol=0, atol=1e-9)
    code, _, err = _run(
        capsys, argv + ["--integrator", "simulate", "--out", str(tmp_path / "diffrax.nc")]
    )
    assert code == 0, err
    np.testing.assert_array_equal(
        _open(tmp_path / "diffrax.nc")["theta"].values, np.asarray(diffrax_traj.theta)
    )
    np.testing.assert_allclose(ds["t"].values, np.asarray(ts), rtol=0, atol=0)
    np.testing.assert_allclose(ds["theta"].values, np.asarray(traj.theta), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(ds["Omega"].values, np.asarray(traj.Omega), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(ds["omega"].values, np.asarray(traj.omega), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(E, np.asarray(traj.energy), rtol=1e-12)
    # the same run as zarr and as CSV: the same numbers, to the last digit (%.17g in the CSV)
    code, out, _ = _run(capsys, argv + ["--out", str(tmp_path / "run.zarr"), "--max-rows", "0"])
    assert code == 0 and "K + U" not in out  # --max-rows 0: the summary only
    z = _open(tmp_path / "run.zarr")
    np.testing.assert_array_equal(z["theta"].values, ds["theta"].values)
    assert list(z["component"].values) == ["x", "y", "z"]
    code, out, _ = _run(capsys, argv + ["--out", str(tmp_path / "run.csv"), "--max-rows", "0"])
    csv = np.loadtxt(tmp_path / "run.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(
        csv, np.column_stack([ds["t"].values, ds["theta"].values, ds["Omega"].values, E])
    )


def test_simulate_inertia_forms_and_a_rotated_axis_give_the_same_motion(capsys, tmp_path):
    """--principal A1,A1,A3 (4.39) is --A1/--A3 (4.40) with k = e3; turning k, the principal axes
    and the initial state by R (e3 -> e1, e1 -> e2, e2 -> e3) turns the whole motion, θ -> Rθ
    (to the solver's tolerance: the rotated run rounds, so steps, differently)."""

    common = [
        "simulate",
        "--c",
        "1",
        "--d",
        "2",
        "--t1",
        "4",
        "--samples",
        N_QUAD,
        "--rtol",
        "1e-12",
        "--atol",
        "1e-12",
    ]
    runs = {
        "ti": ["--A1", "1", "--A3", "0.6", "--theta0", "0.3,-0.2,0.5", "--Omega0", "0.4,0.1,-0.6"],
        "principal": [
            "--principal",
            "1,1,0.6",
            "--theta0",
            "0.3,-0.2,0.5",
            "--Omega0",
            "0.4,0.1,-0.6",
        ],
        "rotated": [
            "--principal",
            "0.6,1,1",
            "--axis",
            "1,0,0",
            "--theta0=0.5,0.3,-0.2",
            "--Omega0=-0.6,0.4,0.1",
        ],
    }
    theta = {}
    for name, extra in runs.items():
        code, out, err = _run(capsys, common + extra + ["--out", str(tmp_path / f"{name}.nc")])
        assert code == 0, err
        theta[name] = _open(tmp_path / f"{name}.nc")["theta"].values
    assert np.max(np.abs(theta["ti"])) > 0.3  # a real motion
    np.testing.assert_allclose(theta["principal"], theta["ti"], rtol=0, atol=1e-13)
    R = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # R e3 = e1, R e1 = e2
    np.testing.assert_allclose(theta["rotated"], theta["ti"] @ R.T, rtol=0, atol=1e-9)


def test_simulate_follower_moment_near_equilibrium_grows_at_the_rate_of_4_69(capsys, tmp_path):
    """--follower M --about-equilibrium: Newton finds θ = (M/d)k (4.62); a 1e-6 bending offset
    grows like exp(t max Re p) with the Nikolai root of (4.69), while the torsion stays put."""

    from rbo_jax import nikolai_bending_roots

    M, c, d = 0.4, 1.0, 2.0
    code, out, err = _run(
        capsys,
        [
            "simulate",
            "--follower",
            str(M),
            "--c",
            str(c),
            "--d",
            str(d),
            "--about-equilibrium",
            "--theta0",
            "1e-6,0,0",
            "--t1",
            "60",
            "--samples",
            "61",
            "--max-rows",
            "5",
            "--out",
            str(tmp_path / "nikolai.nc"),
        ],
    )
    assert code == 0, err
    ds = _open(tmp_path / "nikolai.nc")
    t, theta = ds["t"].values, ds["theta"].values
    np.testing.assert_allclose(theta[0], [1e-6, 0.0, M / d], rtol=0, atol=1e-15)
    bending = np.linalg.norm(theta[:, :2], axis=1)
    late = t >= 20
    rate = np.polyfit(t[late], np.log(bending[late]), 1)[0]
    expected = float(np.max(np.real(nikolai_bending_roots(1.0, c, d, M))))
    assert rate == pytest.approx(expected, rel=0.03)
    assert bending[-1] > 50 * bending[0]
    assert np.max(np.abs(theta[:, 2] - M / d)) < 1e-8  # second order in the bending deviation


def test_simulate_loads_add_up_as_in_the_package(capsys, tmp_path):
    """--follower, --dead and --friction together are the model with FollowerMoment (4.57),
    DeadMoment (4.75) and Friction (4.84), in any order of the options."""
    import jax.numpy as jnp

    from rbo_jax import (
        DeadMoment,
        FollowerMoment,
        Friction,
        QuadraticFoundation,
        RigidBodyOscillator,
        fast_simulate,
        transversely_isotropic_inertia,
    )

    code, out, err = _run(
        capsys,
        [
            "simulate",
            "--friction",
            "0.2",
            "--dead",
            "0.1",
            "--follower",
            "0.3",
            "--theta0",
            "0.4,0.2,0.1",
            "--Omega0",
            "0.3,-0.5,0.2",
            "--t1",
            "8",
            "--samples",
            "9",
            "--out",
            str(tmp_path / "loads.nc"),
        ],
    )
    assert code == 0, err
    ds = _open(tmp_path / "loads.nc")
    assert (
        "follower (4.57) M = 0.3; dead (4.75) M = 0.1; friction (4.84) b = 0.2" in ds.attrs["model"]
    )
    k = jnp.asarray(K)
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(1.0, 0.6, k),
        QuadraticFoundation(1.0, 2.0, k),
        [FollowerMoment(0.3, k), DeadMoment(0.1, k), Friction(0.2)],
    )
    traj = fast_simulate(
        model, jnp.array([0.4, 0.2, 0.1]), jnp.array([0.3, -0.5, 0.2]), jnp.linspace(0.0, 8.0, 9)
    )
    np.testing.assert_allclose(ds["theta"].values, np.asarray(traj.theta), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(ds["energy"].values, np.asarray(traj.energy), rtol=1e-12)


def test_simulate_singular_point_exits_1_with_the_solver_status(capsys, tmp_path):
    """A nearly plane rotation through |θ| = 2π (4.11) (cf. tests/test_simulate.py): exit status 1,
    the SolveStatus message, the table up to the failure, the samples after it inf in --out."""

    code, out, err = _run(
        capsys,
        [
            "simulate",
            "--A1",
            "1",
            "--A3",
            "1",
            "--c",
            "0.01",
            "--d",
            "0.01",
            "--theta0",
            "0,0,6",
            "--Omega0",
            "1e-5,0,1",
            "--t1",
            "4",
            "--samples",
            N_QUAD,
            "--out",
            str(tmp_path / "singular.nc"),
        ],
    )
    assert code == 1
    assert "singular point" in err and "(eq. 4.11)" in err and "after t = 0.2 " in err
    # |θ| = R cos(wt − φ) reaches 2π at t ≈ 0.28 (w = 0.1): the first two samples exist
    ds = _open(tmp_path / "singular.nc")
    theta = ds["theta"].values
    assert np.all(np.isfinite(theta[:2])) and np.all(np.isinf(theta[2:]))
    assert list(ds["reached"].values[:3]) == [True, True, False]
    assert ds.attrs["status"] == "singular_point" and "singular point" in ds.attrs["message"]


def test_simulate_step_budget_exits_1(capsys):
    """--max-steps exhausted: exit status 1 with SolveStatus.max_steps_reached's message."""
    code, out, err = _run(
        capsys,
        ["simulate", "--theta0", "0.5,0,0", "--t1", "50", "--samples", N_QUAD, "--max-steps", "4"],
    )
    assert code == 1
    assert "maximum number of solver steps" in err and "max_steps" in err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--c", "-1"], "--c: must be > 0, got -1"),
        (["--d", "0"], "--d: must be > 0, got 0"),
        (["--theta0", "1,2"], "theta0 must have shape (3,)"),
        (["--Omega0", "1,2,3,4"], "Omega0 must have shape (3,)"),
        (["--A3", "-0.6"], "--A3: must be > 0"),
        (["--principal", "1,2"], "--principal: must be a list of 3 numbers"),
        (["--principal", "1,1,0.6", "--A1", "2"], "--principal replaces --A1"),
        (["--foundation", "barrier", "--alpha", "1"], "needs --alpha and --beta"),
        (["--alpha", "1"], "belong to --foundation barrier"),
        (["--foundation", "barrier", "--alpha", "1", "--beta", "0"], "--beta: must be > 0 or inf"),
        (["--friction", "-0.1"], "--friction: must be >= 0"),
        (["--axis", "0,0,0"], "--axis: must be a nonzero vector"),
        (["--c", "nan"], "--c: must be > 0, got nan"),
        (["--out", "run.txt"], "unknown format '.txt'"),
        (["--samples", "1"], "--samples must be >= 2"),
        (["--theta0", "a,b,c"], None),
    ],
)
def test_simulate_invalid_input_exits_2_naming_the_parameter(capsys, argv, message):
    code, out, err = _run(capsys, ["simulate", *argv])
    assert code == 2
    assert "Traceback" not in err
    assert (message or "--theta0") in err


def test_stability_map_matches_the_closed_form_4_69(capsys, tmp_path):
    """A grid over M, c and A3: the spectral abscissa is max Re of the roots (4.69) to 1e-10, the
    eigenvalues are the six roots, θ_eq = (M/d)k, M = 0 is marginally stable and M ≠ 0 flutter."""

    from rbo_jax import nikolai_bending_roots, nikolai_spectrum

    d, A1 = 2.0, 1.0
    code, out, err = _run(
        capsys,
        [
            "stability-map",
            "--M=-0.6:0.6:5",
            "--c",
            "0.5,1,2",
            "--A3",
            "0.4:1.2:2",
            "--d",
            str(d),
            "--A1",
            str(A1),
            "--out",
            str(tmp_path / "map.nc"),
            "--progress",
        ],
    )
    assert code == 0, err
    ds = _open(tmp_path / "map.nc")
    a = ds["spectral_abscissa"]
    assert a.dims == ("M", "c", "A3") and a.shape == (5, 3, 2)
    assert float(ds["d"]) == d
    names = np.asarray(ds["kind"].attrs["flag_meanings"].split())
    kinds = names[ds["kind"].values]
    p = ds["eigenvalues_real"].values + 1j * ds["eigenvalues_imag"].values
    closed = np.empty((5, 3, 2))
    for i, M in enumerate(ds["M"].values):
        for j, c in enumerate(ds["c"].values):
            for m, A3 in enumerate(ds["A3"].values):
                closed[i, j, m] = np.max(np.real(nikolai_bending_roots(A1, c, d, M)))
                assert spectrum_match_error(p[i, j, m], nikolai_spectrum(A1, A3, c, d, M)) < 1e-10
                np.testing.assert_allclose(
                    ds["theta_eq"].values[i, j, m], [0, 0, M / d], atol=1e-15
                )
                assert kinds[i, j, m] == ("marginally_stable" if M == 0 else "flutter")
    assert np.sum(kinds == "marginally_stable") == 6  # the 6 points with M = 0
    np.testing.assert_allclose(a.values, closed, rtol=0, atol=1e-10)
    assert np.all(closed[ds["M"].values != 0] > 0.01)  # the Nikolai paradox
    assert float(ds.attrs["max_deviation_from_4_69"]) < 1e-10


def test_stability_map_writes_netcdf_zarr_and_a_figure(capsys, tmp_path):
    """--out .nc (complex eigenvalues as real/imaginary parts), .zarr and --plot: the same map;
    with friction b > 0 (4.84) the M = 0 equilibrium becomes asymptotically stable."""
    from rbo_jax.app._io import netcdf_engine

    pytest.importorskip("matplotlib")
    args = ["stability-map", "--M=-0.4:0.4:3", "--c", "0.5:1.5:3", "--friction", "0.1"]
    nc, zarr_store, png = tmp_path / "map.nc", tmp_path / "map.zarr", tmp_path / "map.png"
    if netcdf_engine() is not None:
        code, out, err = _run(capsys, args + ["--out", str(nc), "--plot", str(png)])
        assert code == 0, err
        assert png.read_bytes()[:4] == b"\x89PNG" and png.stat().st_size > 1000
        ds = _open(nc)
        a = ds["spectral_abscissa"].values
        p = ds["eigenvalues_real"].values + 1j * ds["eigenvalues_imag"].values
        assert float(ds.attrs["friction_b"]) == 0.1 and "max_deviation_from_4_69" not in ds.attrs
        assert np.all(a[1] < 0) and np.all(a[[0, 2]] > 0)
        assert np.max(np.abs(np.max(p.real, axis=-1) - a)) == 0
    pytest.importorskip("zarr")
    code, out, err = _run(capsys, args + ["--out", str(zarr_store)])
    assert code == 0, err
    ds = _open(zarr_store)
    assert ds["eigenvalues"].dtype == np.complex128
    assert (
        ds["kind"].attrs["flag_meanings"].split()[int(ds["kind"][1, 0])] == "asymptotically_stable"
    )


def test_stability_map_invalid_input_exits_2(capsys, monkeypatch, tmp_path):
    """Bad grid values name the parameter; --plot needs two ranged axes and matplotlib (checked
    before anything is computed)."""
    code, _, err = _run(capsys, ["stability-map", "--c=-1:1:3"])
    assert code == 2 and "--c: axis 'c' takes the value -1, but c must be > 0" in err
    code, _, err = _run(capsys, ["stability-map", "--A3", "0"])
    assert code == 2 and "--A3: axis 'A3' takes the value 0, but A3 must be > 0" in err
    code, _, err = _run(capsys, ["stability-map", "--M", "0:1:x"])
    assert code == 2 and "start:stop:num" in err
    code, _, err = _run(capsys, ["stability-map", "--c", "1", "--plot", str(tmp_path / "a.png")])
    assert code == 2 and "two axes" in err
    code, _, err = _run(capsys, ["stability-map", "--out", str(tmp_path / "a.npz")])
    assert code == 2 and "unknown format '.npz'" in err
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    code, _, err = _run(capsys, ["stability-map", "--plot", str(tmp_path / "a.png")])
    assert code == 2 and "needs matplotlib" in err


@pytest.mark.parametrize(
    "integrator",
    [
        # cost: ~16 s, the fit compiled on fast_simulate (the other integrator's stays quick)
        pytest.param("fast_simulate", marks=pytest.mark.slow),
        "simulate",
    ],
)
def test_fit_synthetic_recovers_c_and_d(capsys, tmp_path, integrator):
    """fit --synthetic: noise-free data of c = 1, d = 2 (4.50), the fit started 30 % off recovers
    both to 1e-6 relative with tiny standard errors, through either integrator; the result
    dataset says so."""
    code, out, err = _run(
        capsys,
        [
            "fit",
            "--synthetic",
            "--c",
            "1",
            "--d",
            "2",
            "--t1",
            "4",
            "--samples",
            N_QUAD,
            "--integrator",
            integrator,
            "--out",
            str(tmp_path / "fit.nc"),
        ],
    )
    assert code == 0, err
    assert f"through the ODE solver ({integrator})" in out
    est = _estimates(tmp_path / "fit.nc")
    assert set(est) == {"c", "d"}
    for name, truth in (("c", 1.0), ("d", 2.0)):
        value, se = est[name]
        assert value == pytest.approx(truth, rel=1e-6)
        assert se < 1e-6 * truth
    ds = _open(tmp_path / "fit.nc")
    assert int(ds.attrs["converged"]) == 1 and ds.attrs["truth"] == "c=1 d=2"
    assert ds["loss_history"].values[-1] < 1e-12 < ds["loss_history"].values[0]
    assert "c = 1.3, d = 2.6" in ds.attrs["model"]  # the starting values, 30 % off


def test_fit_synthetic_with_noise_reports_consistent_standard_errors(capsys, tmp_path):
    """fit --synthetic --noise 1e-3: the residuals are whitened by the known noise, so their rms
    is ≈ 1 at the answer (no local-minimum note), and c, d lie within 4 standard errors of the
    truth."""
    code, out, err = _run(
        capsys,
        [
            "fit",
            "--synthetic",
            "--c",
            "1",
            "--d",
            "2",
            "--t1",
            "4",
            "--samples",
            N_QUAD,
            "--noise",
            "1e-3",
            "--seed",
            "3",
            "--out",
            str(tmp_path / "fit.zarr"),
        ],
    )
    assert code == 0, err
    est = _estimates(tmp_path / "fit.zarr")
    for name, truth in (("c", 1.0), ("d", 2.0)):
        value, se = est[name]
        assert 0 < se < 1e-2 and abs(value - truth) < 4 * se
    ds = _open(tmp_path / "fit.zarr")
    assert 0.5 < float(ds.attrs["residual_rms"]) < 1.5
    assert ds.attrs["note"] == ""


def test_simulate_out_then_fit_data_roundtrip(capsys, tmp_path):
    """`simulate --out obs.nc` then `fit --data obs.nc` from wrong starting values: the
    stiffnesses of the simulation come back."""
    path = str(tmp_path / "obs.nc")
    code, _, err = _run(
        capsys,
        [
            "simulate",
            "--c",
            "1",
            "--d",
            "2",
            "--theta0",
            "0.8,-0.3,0.5",
            "--Omega0=0.2,1.1,-0.7",
            "--t1",
            "4",
            "--samples",
            N_QUAD,
            "--out",
            path,
            "--max-rows",
            "0",
        ],
    )
    assert code == 0, err
    code, out, err = _run(
        capsys,
        ["fit", "--data", path, "--c", "1.3", "--d", "2.6", "--out", str(tmp_path / "fit.nc")],
    )
    assert code == 0, err
    ds = _open(tmp_path / "fit.nc")
    assert int(ds.attrs["num_samples"]) == 21 and ds.attrs["observed"] == "Omega theta"
    est = _estimates(tmp_path / "fit.nc")
    assert est["c"][0] == pytest.approx(1.0, rel=1e-6)
    assert est["d"][0] == pytest.approx(2.0, rel=1e-6)


@pytest.mark.slow  # cost: 45 s, staged fits of an unstable record
def test_fit_of_an_unstable_record_needs_staged_horizons(capsys, tmp_path):
    """The Nikolai problem (4.57)-(4.62) grows from 0.18 to 1.7 rad over t in [0, 50]: fitted over
    the whole record at once, Levenberg-Marquardt stops in a local minimum far from (c, d) = (1, 2)
    and the result says so; fitted on growing horizons (0.2, 0.5, 1) it recovers them."""
    path = str(tmp_path / "nikolai.zarr")
    code, _, err = _run(
        capsys,
        [
            "simulate",
            "--c",
            "1",
            "--d",
            "2",
            "--follower",
            "0.3",
            "--theta0",
            "0.1,0,0.15",
            "--t1",
            "50",
            "--samples",
            "11",
            "--out",
            path,
            "--max-rows",
            "0",
        ],
    )
    assert code == 0, err
    start = ["fit", "--data", path, "--c", "1.3", "--d", "1.6", "--follower", "0.3"]
    once, staged = str(tmp_path / "once.nc"), str(tmp_path / "staged.nc")
    code, out, err = _run(capsys, start + ["--out", once])
    if code == 0 and abs(_estimates(once)["c"][0] - 1.0) > 1e-3:  # stopped away from the answer
        assert "local minimum" in _open(once).attrs["note"]  # (it does here): say why
    code, out, err = _run(capsys, start + ["--horizons", "0.2,0.5,1", "--out", staged])
    assert code == 0, err
    est = _estimates(staged)
    assert est["c"][0] == pytest.approx(1.0, rel=1e-6)
    assert est["d"][0] == pytest.approx(2.0, rel=1e-6)
    assert _open(staged).attrs["note"] == ""
    code, _, err = _run(capsys, start + ["--horizons", "0.5,0.2"])
    assert code == 2 and "increasing fractions" in err


@pytest.mark.parametrize(
    "arrays, message",
    [
        ({"theta": np.zeros((5, 3))}, "missing array 't'"),
        ({"t": np.arange(5.0), "energy": np.zeros(5)}, "missing array 'theta'"),
        ({"t": np.arange(5.0), "theta": np.zeros((5, 2))}, "theta must have shape (n, 3)"),
        ({"t": np.arange(5.0), "theta": np.zeros((4, 3))}, "theta has 4 samples but ts has 5"),
        ({"t": np.arange(5.0), "theta": np.zeros((5, 3))}, "Omega0 is needed"),
        (
            {"t": np.arange(5.0)[::-1], "theta": np.zeros((5, 3)), "Omega": np.zeros((5, 3))},
            "strictly increasing",
        ),
        (None, "no such file"),
    ],
)
def test_fit_bad_data_file_exits_2_naming_the_problem(capsys, tmp_path, arrays, message):
    path = tmp_path / "data.npz"
    if arrays is not None:
        np.savez(path, **arrays)
    code, _, err = _run(capsys, ["fit", "--data", str(path)])
    assert code == 2 and "Traceback" not in err
    assert message in err and str(path) in err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--params", "c,e"], "--params must be distinct names"),
        (["--params", "alpha"], "needs --foundation barrier"),
        (["--params", "b"], "needs --friction"),
        (["--c", "0"], "starting value must be finite and > 0"),
    ],
)
def test_fit_invalid_options_exit_2(capsys, argv, message):
    code, _, err = _run(capsys, ["fit", "--synthetic", *argv])
    assert code == 2 and message in err


@pytest.mark.slow  # integration: rbo-jax in fresh processes, twice each
def test_persistent_compilation_cache_is_written_and_reused(tmp_path):
    """The command keeps its compiled programs in $RBO_JAX_COMPILATION_CACHE: the first process
    writes entries, a second one reads them (same output) and adds none; ``off`` writes
    nothing. The fit's program (residuals and Jacobian through fast_simulate) has no host
    callback, so the second ``rbo-jax fit`` loads it instead of compiling it."""
    import subprocess

    cache = tmp_path / "cache"
    code = "import sys; from rbo_jax.app.cli import main; sys.exit(main(sys.argv[1:]))"
    argv = ["fit", "--synthetic", "--c", "1", "--d", "2", "--t1", "2", "--samples", "11"]

    def run(value):
        env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
        env.update(RBO_JAX_COMPILATION_CACHE=value, JAX_PLATFORMS="cpu", JAX_LOG_COMPILES="1")
        proc = subprocess.run(
            [sys.executable, "-c", code, *argv],
            capture_output=True,
            text=True,
            env=env,
            timeout=600,
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
        return proc.stdout.split("wall time")[0], proc.stderr

    first, log = run(str(cache))
    assert "cache hit for 'jit_residuals_and_jacobian'" not in log
    entries = sorted(p.name for p in cache.iterdir())
    assert entries, "no compiled program was cached"
    assert "Finished tracing residuals_and_jacobian_export" in log  # exported to the store
    again, log = run(str(cache))
    assert again == first
    assert "Persistent compilation cache hit for 'jit_residuals_and_jacobian'" in log
    assert "Finished tracing residuals_and_jacobian_export" not in log  # loaded, not traced
    assert sorted(p.name for p in cache.iterdir()) == entries
    run("off")
    assert sorted(p.name for p in cache.iterdir()) == entries
