"""Lattices from the front ends: `rbo-jax simulate --lattice SPEC` (a chain of copies of the
body of the model options; its table, summary and dataset; the kink; options refused before
anything is compiled) and the `[lattice]` table of `rbo-jax sweep` with the Bloch quantities
(examples/lattice_flutter_bands.toml).

Compilation is what these tests cost: every simulation runs one lattice structure (a periodic
chain of 8 bodies on the cosine foundation, 5 samples, the default tolerances), so the perturbed
run and the kink share one compiled solve; the sweep compiles one chunk of the Bloch quantity."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from helpers import open_output as _open
from helpers import run_cli as _run

import rbo_jax
from rbo_jax import lattice as L
from rbo_jax.app.config import ConfigError, load_config
from rbo_jax.app.spec import LatticeSpec

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "lattice_flutter_bands.toml"
K = np.array([0.0, 0.0, 1.0])
# one lattice structure for every simulation here: a periodic chain of 8 cosine bodies
CHAIN = [
    "simulate",
    "--lattice",
    "chain:8",
    "--foundation",
    "cosine",
    "--t1",
    "2",
    "--samples",
    "5",
]


def test_simulate_chain_prints_a_conserved_energy_and_writes_the_lattice(capsys, tmp_path):
    """A periodic chain of 8 cosine bodies, every one at theta0, Omega0 plus Gaussian noise of
    standard deviation --perturbation (seeded): no loads, so the total energy is conserved to
    the tolerance; the netCDF file holds theta (t, site, component) from that initial state, the
    energy, and the lattice's shape (JSON text: netCDF has no list attributes)."""
    out_file = tmp_path / "chain.nc"
    code, out, err = _run(
        capsys,
        CHAIN
        + [
            "--theta0",
            "0.3,0,0.1",
            "--Omega0",
            "0,0.2,0",
            "--perturbation",
            "0.05",
            "--seed",
            "3",
            "--out",
            str(out_file),
        ],
    )
    assert code == 0, err
    assert "max |theta_i|" in out and "status: successful" in out
    drift = float(re.search(r"max \|energy drift\| = (\S+)", out).group(1))
    assert drift < 1e-8
    ds = _open(out_file)
    assert ds["theta"].shape == ds["Omega"].shape == (5, 8, 3)
    assert ds.attrs["status"] == "successful" and ds.attrs["shape"] == "[8]"
    noise = 0.05 * np.random.default_rng(3).standard_normal((2, 8, 3))
    np.testing.assert_array_equal(ds["theta"].values[0], np.array([0.3, 0.0, 0.1]) + noise[0])
    np.testing.assert_array_equal(ds["Omega"].values[0], np.array([0.0, 0.2, 0.0]) + noise[1])
    E = ds["energy"].values
    np.testing.assert_allclose(E, E[0], rtol=1e-8)
    assert np.abs(ds["theta"].values[-1] - ds["theta"].values[0]).max() > 1e-2  # it moved


def test_simulate_kink_runs_as_plane_rotations(capsys, tmp_path):
    """--wave kink on the same chain: the sine-Gordon kink of rbo_jax.lattice.kink (turns about
    k rising by 2 pi along the chain, the periodic ends joined by a whole turn) moves as plane
    rotations about k, its energy conserved; written as zarr."""
    out_file = tmp_path / "kink.zarr"
    code, out, err = _run(
        capsys,
        CHAIN
        + ["--wave", "kink", "--coupling-kt", "4", "--wave-speed", "0.5", "--out", str(out_file)],
    )
    assert code == 0, err
    ds = _open(out_file)
    theta = ds["theta"].values
    theta0, _ = L.kink(8, 1.0, 4.0, 0.6, x0=3.5, v=0.5, k=K)
    np.testing.assert_array_equal(theta[0], theta0)
    assert np.abs(theta[..., :2]).max() == 0.0 and theta[0, -1, 2] > 1.5 * np.pi
    np.testing.assert_allclose(ds["energy"].values, ds["energy"].values[0], rtol=1e-8)


BAD_OPTIONS = [
    (["--lattice", "chain:1"], "--lattice chain:1: a chain needs N >= 2"),
    (["--lattice", "grid:4"], "--lattice grid:4: expected chain:N"),
    (["--lattice", "chain:8:open"], "--lattice chain:8:open: expected"),
    (["--lattice", "chain:8", "--wave", "wavy"], "--wave"),
    (["--lattice", "chain:8", "--wave", "kink"], "--wave kink needs --foundation cosine"),
    (
        ["--lattice", "grid:4x4", "--foundation", "cosine", "--wave", "kink"],
        "--wave kink needs a chain",
    ),
    (["--lattice", "chain:8:free", "--wave", "twist"], "--wave twist needs a periodic chain"),
    (
        ["--lattice", "chain:8", "--follower", "0.3", "--method", "splitting", "--dt", "0.01"],
        "--method splitting integrates lattices without loads",
    ),
    (["--lattice", "chain:8", "--method", "splitting"], "--method splitting needs --dt"),
    (["--lattice", "chain:8", "--coupling-kt=-1"], "--coupling-kt: must be > 0"),
    (["--lattice", "chain:8", "--wave-speed", "1"], "--wave-speed belongs to --wave kink"),
    (["--coupling-kb", "2"], "--coupling-kb belongs to --lattice"),
    (["--lattice", "chain:8", "--out", "run.csv"], "--out run.csv: unknown format"),
]


@pytest.mark.parametrize("argv, message", BAD_OPTIONS, ids=[" ".join(a) for a, _ in BAD_OPTIONS])
def test_bad_lattice_options_exit_2_naming_the_option_before_compiling(
    capsys, monkeypatch, argv, message
):
    def never(*args, **kwargs):
        raise AssertionError("simulated although the options are invalid")

    monkeypatch.setattr(L, "simulate", never)
    code, _, err = _run(capsys, ["simulate"] + argv)
    assert code == 2 and message in err, err


# ---------------------------------------------------------------------------------------------
# rbo-jax sweep with a [lattice]
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow  # cost: ~15 s, an example sweep end to end
def test_flutter_band_example_sweeps_the_bloch_growth_and_frequencies(capsys, tmp_path):
    """The example's chain of Nikolai bodies with friction, swept on a 2 x 2 grid of (q, M)
    with quantity bloch_frequencies (which gives bloch_growth too) through `rbo-jax sweep`: the
    values are those of rbo_jax.lattice.dispersion at the uniform equilibrium (M/d) k (4.62);
    at M = 0.3 the long waves grow and the short ones decay (the flutter band)."""
    cfg = load_config(EXAMPLE)
    assert cfg.quantity_name == "bloch_growth" and cfg.lattice.kind == "chain"
    assert set(cfg.axes) == {"q", "M"} and cfg.lattice.parameters() == ("q",)
    assert LatticeSpec.from_mapping(cfg.lattice.to_mapping(), axes=cfg.axes) == cfg.lattice
    text = EXAMPLE.read_text().replace(
        'quantity = "bloch_growth"', 'quantity = "bloch_frequencies"'
    )
    text = re.sub(r"(?m)^q = \{.*$", "q = [0.0, 2.5]", text)
    text = re.sub(r"(?m)^M = \{.*$", "M = [0.0, 0.3]", text)
    config = tmp_path / "bands.toml"
    config.write_text(text)
    store = tmp_path / "bands.zarr"
    code, _, err = _run(
        capsys, ["sweep", str(config), "--quiet", "--no-plot", "--output", str(store)]
    )
    assert code == 0, err
    ds = rbo_jax.open_sweep(store)
    assert ds["bloch_frequencies"].dims == ("q", "M", "branch")
    growth = ds["bloch_growth"].values
    assert growth[0, 1] > 0 > growth[1, 1] and np.all(growth[:, 0] < 0)
    M, q = 0.3, 2.5
    body = rbo_jax.nikolai_model(M, 1.0, 2.0, A1=1.0, A3=0.6, k=K, friction=0.1)
    lat = L.chain(32, body, rbo_jax.QuadraticFoundation(0.8, 0.5, K))
    lam = np.asarray(L.dispersion(lat, q))
    np.testing.assert_allclose(ds["theta_eq"].values[1, 1], [0.0, 0.0, M / 2.0], atol=1e-14)
    np.testing.assert_allclose(growth[1, 1], np.max(lam.real), rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(ds["bloch_frequencies"].values[1, 1], lam.imag[3:], rtol=1e-10)
    assert np.all(ds["bloch_frequencies"].values >= 0)


BASE = """
[sweep]
quantity = "bloch_growth"
output = "b.zarr"

[axes]
q = [0.0, 1.0]

[model]
inertia = { A1 = 1.0, A3 = 0.6 }
foundation = { type = "quadratic", c = 1.0, d = 2.0 }
"""
LATTICE = '\n[lattice]\nkind = "chain"\nn = 8\nq = "q"\n'
BAD_CONFIGS = [
    (BASE, "config: missing required key 'lattice'"),
    (
        BASE.replace("bloch_growth", "spectral_abscissa") + LATTICE,
        "[lattice]: is only used by the quantities bloch_growth, bloch_frequencies",
    ),
    (BASE + LATTICE.replace('"chain"', '"ring"'), "[lattice] kind: must be one of"),
    (BASE + LATTICE.replace("n = 8", "n = 1"), "[lattice] n: must be an integer >= 2"),
    (BASE + LATTICE.replace('"chain"', '"grid"'), "[lattice] n: is not a key of kind = 'grid'"),
    (
        BASE + LATTICE.replace('"chain"', '"grid"').replace("n = 8", "shape = [4, 4]"),
        "[lattice] q: a grid needs one wavenumber per axis",
    ),
    (BASE + LATTICE + 'kappa_b = "q"\n', "axis 'q' takes the value 0, but kappa_b must be > 0"),
    (BASE + LATTICE + "periodic = 1\n", "[lattice] periodic: must be true or false"),
    (BASE + LATTICE + "[solver]\nt1 = 1.0\n", "[solver]: is not used by quantity 'bloch_growth'"),
]


@pytest.mark.parametrize("text, message", BAD_CONFIGS)
def test_lattice_config_errors_name_the_key(tmp_path, text, message):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(cfg)
    assert message in str(info.value), str(info.value)
