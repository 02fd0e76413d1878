r"""Rods from the front ends (issue 32 G): `rbo-jax simulate --rod SPEC` and the `[rod]` table of
`rbo-jax sweep` with the quantities `rod_stability` and `rod_critical_load`
(examples/beck_ziegler_pflueger.toml).

Quick tier: the `[rod]` table (its numbers, axes, loads and load factor built into the rod the
library's constructors make; its errors naming the key) and the options of `simulate --rod`,
refused before anything is compiled. Slow tier (compilation: a rod's Newton solve, its spectrum
and a diffrax solve each compile for tens of seconds on a loaded two-core machine): a CLI run
whose energy is conserved (Hamiltonian: dead loads, no damping), an equilibrium that stays put,
and tiny sweeps checked against Beck's column: stable at $P = 10\,EI/L^2$, flutter at
$P = 30\,EI/L^2$ (Beck 1952: $P_{cr} = 20.05\,EI/L^2$), and a critical load equal to the one of
:func:`rbo_jax.lattice.critical_load` on the same rod.
"""

from __future__ import annotations

import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import open_output as _open
from helpers import run_cli as _run

from rbo_jax import lattice as L
from rbo_jax.app import cli
from rbo_jax.app._reader import Reader, Ref
from rbo_jax.app.cli._options import tomllib  # tomli before Python 3.11
from rbo_jax.app.config import ConfigError, load_config
from rbo_jax.app.rodspec import RodSpec

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "beck_ziegler_pflueger.toml"
BECK = 'loads = [{ type = "tip_force", f = [0.0, 0.0, -1.0], scale = "P", follower = true }]'


# ---------------------------------------------------------------------------------------------
# The [rod] table.
# ---------------------------------------------------------------------------------------------


def test_rod_table_builds_the_rod_of_the_constructor():
    r"""Every key of the table reaches :func:`rbo_jax.lattice.rod`: the segment stiffnesses
    $K^\varphi = \mathrm{diag}(EI, EI, GJ)/h$, $K^g = \mathrm{diag}(\kappa GA, \kappa GA, EA)/h$
    with $h = L/N$, the lumped masses $\rho A h$ (half at the tip, plus the tip mass), the
    Kelvin–Voigt times; an axis value at a point; the follower tip force ``scale`` × ``f`` ×
    the load factor."""
    axes = {"P": np.array([10.0, 30.0]), "eta": np.array([0.0, 1e-3])}
    r = Reader(axes)
    spec = RodSpec.from_mapping(
        {
            "n": 4,
            "length": 2.0,
            "bending": 3.0,
            "torsion": 5.0,
            "shear": 7.0,
            "stretch": 11.0,
            "mass": 0.5,
            "tip_mass": 0.25,
            "damping": "eta",
            "shear_damping": 0.0,
            "loads": [
                {"type": "tip_force", "f": [0.0, 0.0, -1.0], "scale": "P", "follower": True},
                {"type": "gravity", "g": [-1.0, 0.0, 0.0]},
            ],
        },
        reader=r,
    )
    assert r.used == {"P", "eta"} and spec.parameters() == ("eta", "P")
    assert spec.value("damping") == Ref("eta") and spec.to_mapping()["loads"][0]["scale"] == "P"
    rod = spec.build({"P": 30.0, "eta": 1e-3}, factor=0.5)
    h = 2.0 / 4
    np.testing.assert_allclose(rod.turn_stiffness, np.tile([3.0, 3.0, 5.0], (4, 1)) / h)
    np.testing.assert_allclose(rod.gap_stiffness, np.tile([7.0, 7.0, 11.0], (4, 1)) / h)
    np.testing.assert_allclose(rod.mass, [0.125, 0.25, 0.25, 0.25, 0.125 + 0.25])
    np.testing.assert_allclose(rod.turn_damping, 1e-3)
    np.testing.assert_allclose(rod.gap_damping, 0.0)
    force, gravity = rod.loads
    assert isinstance(force, L.TipForce) and force.follower
    np.testing.assert_allclose(force.force, [0.0, 0.0, -15.0])  # 30 x (0, 0, -1) x 0.5
    assert isinstance(gravity, L.Gravity)
    np.testing.assert_allclose(gravity.g, [-0.5, 0.0, 0.0])
    assert rod.base == "clamped" and rod.n == 4


def test_rod_table_defaults_are_the_documented_ones():
    """``n`` alone: L = EI = GJ = rhoA = 1, kGA = EA = 1e6, rhoI = 1e-6 (polar 2e-6), no
    damping, no tip mass, clamped, no loads."""
    rod = RodSpec.from_mapping({"n": 2}).build()
    np.testing.assert_allclose(rod.turn_stiffness, np.tile([1.0, 1.0, 1.0], (2, 1)) * 2)
    np.testing.assert_allclose(rod.gap_stiffness, np.tile([1e6, 1e6, 1e6], (2, 1)) * 2)
    np.testing.assert_allclose(rod.mass, [0.25, 0.5, 0.25])
    np.testing.assert_allclose(np.diagonal(rod.inertia[1]), [0.5e-6, 0.5e-6, 1e-6])
    assert rod.loads == () and rod.base == "clamped"
    np.testing.assert_allclose(rod.turn_damping, 0.0)


# a taper of EI along 6 segments, base to tip (each segment's own value; none repeated)
TAPER = [2.0, 1.6, 1.3, 1.0, 0.8, 0.6]


def _leaves_equal(a, b):
    """Two rods hold the same arrays (every leaf, also the loads') and the same static parts."""
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_tapered_rod_table_builds_the_tapered_rod_of_the_constructor():
    r"""A list of ``n`` values of a constant (base to tip) is :func:`rbo_jax.lattice.rod`'s
    per-segment array: the rod of ``bending = [...]`` (TOML, as ``--rod`` and ``[rod]`` read it)
    holds exactly the arrays of ``rod(n, ..., bending=np.array([...]))``, also with every other
    per-segment constant a list; a list round-trips through ``to_mapping``; an element may be an
    axis name, built at a point and traced under ``jax.vmap``; a taper ``{ base, tip }`` is the
    linear one sampled at the segments' middles."""
    n = len(TAPER)
    spec = RodSpec.from_mapping(
        tomllib.loads(f"[rod]\nn = {n}\nlength = 2.0\nbending = {TAPER}\ntip_mass = 0.5\n")["rod"]
    )
    assert spec.value("bending") == tuple(TAPER)
    assert spec.to_mapping()["bending"] == TAPER
    assert RodSpec.from_mapping(spec.to_mapping()) == spec
    lib = dict(length=2.0, torsion=1.0, shear=1e6, stretch=1e6, mass=1.0, rotary=1e-6)
    _leaves_equal(spec.build(), L.rod(n, bending=np.array(TAPER), tip_mass=0.5, **lib))

    # every per-segment key of the library as a list, one element an axis
    per_segment = {
        "bending": TAPER,
        "torsion": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
        "shear": [10.0, 20.0, 30.0, 40.0, 50.0, 60.0],
        "stretch": [11.0, 21.0, 31.0, 41.0, 51.0, 61.0],
        "mass": [0.5, 0.6, 0.7, 0.8, 0.9, "m"],
        "rotary": [1e-3, 2e-3, 3e-3, 4e-3, 5e-3, 6e-3],
        "damping": [0.0, 1e-3, 0.0, 1e-3, 0.0, 1e-3],
        "shear_damping": [0.0, 0.0, 0.0, 0.0, 0.0, 2e-3],
    }
    r = Reader({"m": np.array([1.0, 3.0])})
    spec = RodSpec.from_mapping({"n": n, **per_segment}, reader=r)
    assert r.used == {"m"} and spec.parameters() == ("m",)
    assert spec.to_mapping()["mass"][-1] == "m"
    arrays = {k: np.array([3.0 if x == "m" else x for x in v]) for k, v in per_segment.items()}
    _leaves_equal(spec.build({"m": 3.0}), L.rod(n, 1.0, **arrays))
    tip_masses = jax.vmap(lambda m: spec.build({"m": m}).mass[-1])(jnp.array([1.0, 3.0]))
    np.testing.assert_allclose(tip_masses, np.array([1.0, 3.0]) * 0.5 / n, rtol=1e-15)

    # the taper: EI from 2 at the base to 0.5 at the tip, at the middles of the segments
    taper = RodSpec.from_mapping({"n": n, "bending": {"base": 2.0, "tip": 0.5}})
    assert taper.to_mapping()["bending"] == {"base": 2.0, "tip": 0.5}
    middles = (np.arange(n) + 0.5) / n
    rod = L.rod(n, **{**lib, "length": 1.0}, bending=2.0 - 1.5 * middles)
    np.testing.assert_allclose(taper.build().turn_stiffness, rod.turn_stiffness, rtol=1e-15)


def test_tapered_cantilever_tip_deflection_is_the_piecewise_closed_form():
    r"""A cantilever of piecewise-constant $EI_i$ (the list ``TAPER``, 6 segments of length
    $h = L/n$, ``shear = stretch = 1e9``) under a small dead tip force $F = 10^{-6}$ from the
    front end (TOML ``[rod]`` table, :meth:`RodSpec.build`, then
    :func:`rbo_jax.lattice.solve_equilibrium`): the tip deflection against the Euler–Bernoulli
    closed form $\delta = F\sum_i \frac{1}{EI_i}\int_{z_{i-1}}^{z_i}(L - x)^2\,dx$.

    The discrete rod is not exact for it, but its error is known in closed form: the moment of
    segment $i$ is $F(L - z_{i-1/2})$, exact at the middle, so the turns of the bodies are the
    continuum's slopes at the nodes exactly (the midpoint rule of a linear integrand), while
    the gap follows the mean turn of its two bodies, the trapezoid rule of the slope, quadratic
    within a segment: $\delta_N = \delta - F\frac{h^3}{12}\sum_i \frac{1}{EI_i}
    + F\sum_i \frac{h}{\kappa GA_i}$ (for a uniform rod the known relative error
    $-1/(4N^2)$, the $-2.4\times10^{-3}$ of docs/topics/rods.md at N = 10). The solve agrees
    with $\delta_N$ to 1e-9 (measured 1.2e-12: Newton's rtol 1e-10, the geometric
    nonlinearity $O((F L^2/EI)^2) \sim 10^{-12}$), and with the continuum $\delta$ to the
    second-order term, $-1.03\times10^{-2}$ relative at N = 6 (within 1.1e-2). The order of
    the list matters: the same values tip to base give a $\delta_N$ 60 % larger."""
    n, F, stiff = len(TAPER), 1e-6, 1e9
    text = f"""[rod]
n = {n}
bending = {TAPER}
shear = {stiff:g}
stretch = {stiff:g}
loads = [{{ type = "tip_force", f = [{F:g}, 0.0, 0.0] }}]
"""
    sol = L.solve_equilibrium(RodSpec.from_mapping(tomllib.loads(text)["rod"]).build())
    assert bool(sol.ok)
    tip = float(sol.state.tip[0])

    EI, h = np.array(TAPER), 1.0 / n
    a = np.arange(n) * h  # segment i from a_i to a_i + h
    continuum = F * np.sum(((1.0 - a) ** 3 - (1.0 - a - h) ** 3) / 3.0 / EI)
    discrete = continuum - F * h**3 / 12.0 * np.sum(1.0 / EI) + F * n * h / stiff
    np.testing.assert_allclose(tip, discrete, rtol=1e-9)
    np.testing.assert_allclose(tip, continuum, rtol=1.1e-2)
    assert tip < continuum  # the trapezoid's error: below the continuum, by O(h^2)
    reversed_ = F * np.sum(((1.0 - a) ** 3 - (1.0 - a - h) ** 3) / 3.0 / EI[::-1])
    assert reversed_ > 1.5 * continuum


SMALL = f"""
[sweep]
quantity = "rod_stability"
output = "small.zarr"

[axes]
P = [10.0, 30.0]

[rod]
n = 5
{BECK}
"""

BAD_CONFIGS = [
    (SMALL.replace("n = 5", "n = 1"), "[rod] n: must be an integer >= 2, got 1"),
    (SMALL.replace("n = 5", "n = 5\nbending = -1.0"), "[rod] bending: must be > 0, got -1"),
    (
        SMALL.replace("n = 5", "n = 5\nbendng = 1.0"),
        "unknown key 'bendng' (did you mean 'bending'?)",
    ),
    (SMALL.replace("n = 5", 'n = 5\nbase = "glued"'), "[rod] base: must be one of 'clamped'"),
    (
        SMALL.replace("[10.0", "[-10.0").replace("n = 5", 'n = 5\ndamping = "P"'),
        "[rod] damping: axis 'P' takes the value -10, but damping must be >= 0",
    ),
    (SMALL.replace("n = 5", "n = 5\ntip_mass = -0.5"), "[rod] tip_mass: must be >= 0, got -0.5"),
    (
        SMALL.replace("n = 5", "n = 5\nbending = [1.0, 1.0, 1.0]"),
        "[rod] bending: must be a number, an axis name or a list of n = 5 values (one per "
        "segment, base to tip), got a list of 3",
    ),
    (
        SMALL.replace("n = 5", "n = 5\nbending = [1.0, 1.0, 1.0, -1.0, 1.0]"),
        "[rod] bending[3]: must be > 0, got -1",
    ),
    (
        SMALL.replace("n = 5", "n = 5\nmass = [1.0, 0.0, 1.0, 1.0, 1.0]"),
        "[rod] mass[1]: must be > 0, got 0",
    ),
    (
        SMALL.replace("[10.0", "[-10.0").replace("n = 5", 'n = 5\ndamping = [0, 0, 0, 0, "P"]'),
        "[rod] damping[4]: axis 'P' takes the value -10, but damping[4] must be >= 0",
    ),
    (
        SMALL.replace("n = 5", 'n = 5\nshear = [1, 1, "Q", 1, 1]'),
        "[rod] shear[2]: 'Q' is neither a number nor an axis name",
    ),
    (
        SMALL.replace("n = 5", "n = 5\nrotary = { base = 1e-6, tip = -1e-6 }"),
        "[rod] rotary tip: must be > 0, got -1e-06",
    ),
    (
        SMALL.replace("n = 5", "n = 5\ntorsion = { base = 1.0, end = 2.0 }"),
        "[rod] torsion: unknown key 'end'",
    ),
    (
        SMALL.replace("n = 5", "n = 5\nlength = [1.0, 1.0, 1.0, 1.0, 1.0]"),
        "[rod] length: must be a number or an axis name, got [1.0, 1.0, 1.0, 1.0, 1.0]",
    ),
    (SMALL.replace('"tip_force"', '"push"'), "[rod.loads][0] type: must be one of 'tip_force'"),
    (
        SMALL.replace("f = [0.0, 0.0, -1.0]", "f = [0.0, -1.0]"),
        "[rod.loads][0] f: must be a list of 3",
    ),
    (
        SMALL.replace("follower = true", "follower = 1"),
        "[rod.loads][0] follower: must be true or false",
    ),
    (SMALL.replace('scale = "P"', 'scale = "Q"'), "[rod.loads][0] scale: 'Q' is neither a number"),
    (
        SMALL.replace("follower = true", "body = 9"),
        "[rod.loads][0] body: must be an integer in -6..5",
    ),
    (SMALL.replace('scale = "P", ', ""), "[axes] P: this axis is not used by any parameter"),
    (SMALL.replace("[rod]", "[rodd]"), "unknown table [rodd] (did you mean [rod]?)"),
    (SMALL.replace("[rod]", "[model]"), "config: missing required key 'rod'"),
    (SMALL + "[model]\naxis = [0, 0, 1]\n", "[model]: is not used by quantity 'rod_stability'"),
    (SMALL + "[stability]\nload_max = 40.0\n", "[stability] load_max: is only used by quantity"),
    (SMALL + "[stability]\nrtol = -1.0\n", "[stability] rtol: must be > 0, got -1"),
    (
        SMALL.replace("rod_stability", "rod_critical_load")
        .replace('scale = "P", ', "")
        .replace("P = [10.0, 30.0]", "Mt = [0.0]")
        .replace("n = 5", 'n = 5\ntip_mass = "Mt"'),
        "config: missing required key 'stability'",
    ),
    (
        SMALL.replace("rod_stability", "rod_critical_load") + "[stability]\nload_max = -1.0\n",
        "[stability] load_max: must exceed load_min (0), got -1",
    ),
    (
        SMALL.replace("rod_stability", "spectral_abscissa"),
        "[rod]: is only used by the quantities rod_stability, rod_critical_load",
    ),
    (SMALL.replace("rod_stability", "rod_motion"), "config: missing required key 'solver'"),
    (
        SMALL.replace("rod_stability", "rod_motion") + "[solver]\nsamples = 11\n",
        "[solver]: missing required key 't1'",
    ),
    (
        SMALL.replace("rod_stability", "rod_motion") + "[solver]\nt1 = 1.0\ndt = 0.0\n",
        "[solver] dt: must be > 0, got 0",
    ),
    (
        SMALL.replace("rod_stability", "rod_motion") + "[solver]\nt1 = 1.0\nintegrator = 'x'\n",
        "[solver]: unknown key 'integrator'",
    ),
    (
        SMALL.replace("rod_stability", "rod_motion") + "[solver]\nt1 = 1\n[stability]\nrtol = 1\n",
        "[stability]: is not used by quantity 'rod_motion' (of a [rod]); remove it",
    ),
    (SMALL + "[solver]\nt1 = 1.0\n", "[solver]: is not used by quantity 'rod_stability'"),
]


@pytest.mark.parametrize("text, message", BAD_CONFIGS)
def test_rod_config_errors_name_the_key(tmp_path, text, message, capsys):
    """A bad [rod] (or [stability]) table: a ConfigError naming the file and the key, and
    `rbo-jax sweep` exits 2 with the same line, before anything is computed."""
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(cfg)
    assert message in str(info.value) and str(cfg) in str(info.value)
    assert cli.main(["sweep", str(cfg)]) == 2
    assert message in capsys.readouterr().err


def test_example_config_is_a_rod_sweep():
    """The example: rod_stability over (P, damping, tip mass), a Beck column of unit follower
    force times the axis P (Beck, Ziegler's paradox, Pflüger)."""
    cfg = load_config(EXAMPLE)
    assert cfg.quantity_name == "rod_stability" and cfg.model is None
    assert set(cfg.axes) == {"P", "eta", "Mt"}
    assert cfg.rod.loads[0].follower and cfg.rod.loads[0].scale == Ref("P")


# ---------------------------------------------------------------------------------------------
# rbo-jax simulate --rod: the options, refused before anything is compiled.
# ---------------------------------------------------------------------------------------------

BAD_OPTIONS = [
    (["--rod-start", "equilibrium"], "--rod-start belongs to --rod"),
    (["--rod", "n = 1"], "--rod: [rod] n: must be an integer >= 2, got 1"),
    (["--rod", "n = 4, bending = -2"], "--rod: [rod] bending: must be > 0, got -2"),
    (["--rod", "n = 4, stiffness = 2"], "--rod: [rod]: unknown key 'stiffness'"),
    (["--rod", "n = 4, bending = 'EI'"], "'EI' is neither a number nor an axis name"),
    (["--rod", "n = 4, bending = [1, 2]"], "--rod: [rod] bending: must be a number, an axis"),
    (["--rod", "n = 3, torsion = [1, 2, -3]"], "--rod: [rod] torsion[2]: must be > 0, got -3"),
    (["--rod", "n = 4,, x"], "--rod: 'n = 4,, x' is neither a FILE.toml nor the keys"),
    (["--rod", "missing.toml"], "--rod missing.toml: cannot be read"),
    (["--rod", "n = 4", "--follower", "0.3"], "--follower is an option of one body"),
    (["--rod", "n = 4", "--theta0", "0.1,0,0"], "--theta0 is an option of one body"),
    (["--rod", "n = 4", "--lattice", "chain:8"], "--lattice is an option of one body"),
    (["--rod", "n = 4", "--integrator", "simulate"], "--integrator is an option of one body"),
    (["--rod", "n = 4", "--progress"], "--progress is an option of one body"),
    (["--rod", "n = 4", "--out", "x.csv"], "--out"),
    (["--rod", "n = 4", "--rod-steps", "3"], "--rod-steps belongs to --rod-start equilibrium"),
    (["--rod", "n = 4", "--rod-perturbation", "nan"], "--rod-perturbation must be finite"),
    (["--rod", "n = 4", "--t1", "-1"], "--t1 must be finite and > 0"),
    (["--rod", "n = 4", "--rod-method", "verlet"], "--rod-method"),
    (
        ["--rod", "n = 4, loads = [{ type = 'gravity', g = [0, 0] }]"],
        "[rod.loads][0] g: must be a list of 3",
    ),
]


@pytest.mark.parametrize("argv, message", BAD_OPTIONS, ids=[" ".join(a) for a, _ in BAD_OPTIONS])
def test_simulate_rod_refuses_bad_options(capsys, argv, message, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = _run(capsys, ["simulate", *argv])
    assert code == 2, (out, err)
    assert message in err, err
    assert "Rod (" not in out  # nothing was built or computed


def test_simulate_rod_reads_a_toml_file_and_refuses_a_file_without_rod(capsys, tmp_path):
    """--rod FILE.toml reads its [rod] table (the same as a sweep's, numbers only)."""
    (tmp_path / "none.toml").write_text("[model]\nx = 1\n")
    code, _, err = _run(capsys, ["simulate", "--rod", str(tmp_path / "none.toml")])
    assert code == 2 and "has no [rod] table" in err
    (tmp_path / "axis.toml").write_text(f"[rod]\nn = 4\n{BECK}\n")
    code, _, err = _run(capsys, ["simulate", "--rod", str(tmp_path / "axis.toml")])
    assert code == 2 and "[rod.loads][0] scale: 'P' is neither a number nor an axis name" in err


# ---------------------------------------------------------------------------------------------
# Slow: runs (each compiles a rod's programs: tens of seconds on the two-core test machine).
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow  # a diffrax solve of a rod compiles for ~30 s here
def test_simulate_rod_conserves_energy_under_gravity_and_writes_the_centreline(capsys, tmp_path):
    r"""A cantilever of 4 bodies released straight under a dead transverse gravity: a
    Hamiltonian system (dead load with potential $-\sum m_i g\cdot r_i$, no damping), so the
    energy is conserved to the tolerance; it starts straight along $e_3$ at rest, the tip moves
    toward $g$; the netCDF file holds the same centreline the table printed."""
    out_file = tmp_path / "sag.nc"
    rod = (
        "n = 4, shear = 1e4, stretch = 1e4, rotary = 1e-4, "
        "loads = [{ type = 'gravity', g = [-1, 0, 0] }]"
    )
    argv = ["simulate", "--rod", rod, "--t1", "1", "--samples", "5", "--rtol", "1e-9"]
    code, out, err = _run(capsys, [*argv, "--atol", "1e-9", "--out", str(out_file)])
    assert code == 0, err
    assert "status: successful" in out and "tip x" in out
    drift = float(re.search(r"max \|energy drift\| = (\S+)", out).group(1))
    assert drift < 1e-6
    ds = _open(out_file)
    assert ds["centreline"].shape == (5, 5, 3) and ds.attrs["status"] == "successful"
    np.testing.assert_allclose(ds["centreline"].values[0, :, 2], np.linspace(0.0, 1.0, 5))
    np.testing.assert_array_equal(ds["v"].values[0], 0.0)
    np.testing.assert_array_equal(ds["tip"].values, ds["centreline"].values[:, -1])
    assert ds["tip"].values[-1, 0] < -1e-3  # the tip fell toward g
    np.testing.assert_allclose(ds["energy"].values, ds["energy"].values[0], atol=1e-6)


@pytest.mark.slow  # Newton, then a diffrax solve: ~40 s of compilation here
def test_simulate_rod_from_equilibrium_stays_there(capsys, tmp_path):
    r"""--rod-start equilibrium with no perturbation: a cantilever under a dead tip force rests
    at its equilibrium, so the motion is none (to the tolerance); the tip's deflection is
    Timoshenko's $F L/(\kappa GA) + F L^3/(3EI)$ to the discretisation (second order in 1/N:
    -2.4e-3 relative at N = 10, docs/topics/rods.md; N = 4 here, 2 %)."""
    out_file = tmp_path / "rest.nc"
    rod = (
        "n = 4, shear = 1e3, stretch = 1e4, rotary = 1e-3, "
        "loads = [{ type = 'tip_force', f = [1e-3, 0, 0] }]"
    )
    argv = ["simulate", "--rod", rod, "--rod-start", "equilibrium", "--rod-perturbation", "0"]
    code, out, err = _run(capsys, [*argv, "--t1", "1", "--samples", "3", "--out", str(out_file)])
    assert code == 0, err
    tip = _open(out_file)["tip"].values
    timoshenko = 1e-3 * (1 / 1e3 + 1 / 3)
    np.testing.assert_allclose(tip[0, 0], timoshenko, rtol=2e-2)
    np.testing.assert_allclose(tip, np.broadcast_to(tip[0], tip.shape), atol=1e-10)


@pytest.mark.slow  # one chunk of the spectrum at the equilibrium: ~40 s of compilation here
def test_rod_stability_sweep_beck_stable_below_flutter_unstable_above(tmp_path):
    r"""Beck's column (a clamped cantilever under a compressive follower force $P$, Beck 1952:
    flutter at $P_{cr} = 20.05\,EI/L^2$) of 5 bodies: at $P = 10$ the equilibrium (straight:
    a follower force along the axis does not bend it) is stable, at $P = 30$ it flutters: a
    complex pair with $\mathrm{Re}\,p > 0$ and a frequency near the merging one (about
    $11\sqrt{EI/(\rho A L^4)}$)."""
    from rbo_jax.app.config import run_config

    cfg = tmp_path / "beck.toml"
    cfg.write_text(SMALL)
    ds, _ = run_config(cfg, progress=False, plot=False)
    assert list(ds["stable"].values) == [True, False]
    assert ds["spectral_abscissa"].values[1] > 1.0
    assert 5.0 < ds["frequency"].values[1] < 20.0
    np.testing.assert_allclose(
        ds["tip"].values, [[0.0, 0.0, 1.0 - 10e-6], [0, 0, 1.0 - 30e-6]], atol=1e-9
    )
    # the same numbers as the library's spectrum at the same equilibrium
    rod = L.rod(
        5,
        1.0,
        bending=1.0,
        torsion=1.0,
        shear=1e6,
        stretch=1e6,
        mass=1.0,
        rotary=1e-6,
        loads=L.TipForce(jnp.array([0.0, 0.0, -30.0]), follower=True),
    )
    p = L.spectrum(rod)
    np.testing.assert_allclose(ds["spectral_abscissa"].values[1], np.max(p.real), rtol=1e-9)


@pytest.mark.slow  # critical_load in a sweep chunk: a scan and bisection of spectra
def test_rod_critical_load_sweep_is_becks_load(tmp_path):
    r"""rod_critical_load of a unit follower force: the load factor is Beck's flutter load of
    the 5-body column, equal to :func:`rbo_jax.lattice.critical_load` on the same rod, and
    off Beck's 20.05 EI/L² by the discretisation (second order in 1/N: 20.196 at N = 20)."""
    from rbo_jax.app.config import run_config

    cfg = tmp_path / "crit.toml"
    cfg.write_text(
        SMALL.replace("rod_stability", "rod_critical_load")
        .replace('scale = "P", ', "")
        .replace("P = [10.0, 30.0]", "EI = [1.0, 2.0]")
        .replace("n = 5", 'n = 5\nbending = "EI"')
        + "[stability]\nload_max = 60.0\n"
    )
    ds, _ = run_config(cfg, progress=False, plot=False)
    crit = ds["critical_load"].values
    beck = lambda P: L.rod(  # noqa: E731
        5,
        1.0,
        bending=1.0,
        torsion=1.0,
        shear=1e6,
        stretch=1e6,
        mass=1.0,
        rotary=1e-6,
        loads=L.TipForce(jnp.stack([0.0, 0.0, -P]), follower=True),
    )
    direct = float(L.critical_load(beck, 60.0))
    np.testing.assert_allclose(crit[0], direct, rtol=1e-9)
    # Beck's 20.0509 approached at second order in 1/N: the error times N^2 is that of the
    # 20-body column (20.196, docs/topics/rods.md "Checks") to 15 % (measured: 22.555 at N = 5)
    beck_load = 20.0509
    np.testing.assert_allclose(
        (crit[0] - beck_load) * 5**2, (20.196 - beck_load) * 20**2, rtol=0.15
    )
    # P_cr scales with EI (Beck's load is 20.05 EI/L^2; GJ, the mass and the stretch fixed)
    np.testing.assert_allclose(crit[1] / crit[0], 2.0, rtol=2e-2)


MOTION = """
[sweep]
quantity = "rod_motion"
output = "motion.zarr"

[axes]
f = [1e-4, 2e-4]

[rod]
n = 8
bending = 1.0
torsion = 0.8
shear = 1e4
stretch = 1e4
mass = 1.0
rotary = 1e-4
loads = [{ type = "tip_force", f = [1.0, 0.0, 0.0], scale = "f" }]

[solver]
t1 = 1.8
samples = 181
"""


@pytest.mark.slow  # cost: ~30 s, the midpoint rule compiled in the sweep's chunk and eagerly
def test_rod_motion_sweep_is_a_step_load_with_its_dynamic_amplification(tmp_path):
    r"""rod_motion: the cantilever (EI = ρA = L = 1, first period $2\pi/3.516 = 1.787$) released
    straight under a small dead tip force applied at $t = 0$. Each mode's tip response to a
    step load is $c_i(1 - \cos\omega_i t)$ with $c_i > 0$ (load and output at the tip), the
    static deflection $\sum c_i$, the first mode's share about 97 %: over one first period
    the tip's largest deflection is between 1.9 and 2 times the static deflection of
    :func:`rbo_jax.lattice.equilibrium` (the dynamic amplification of a step load), linear in
    the force; and the sweep's numbers are those of :func:`rbo_jax.lattice.simulate` of the
    same rod."""
    from rbo_jax.app.config import run_config

    cfg = tmp_path / "motion.toml"
    cfg.write_text(MOTION)
    ds, _ = run_config(cfg, progress=False, plot=False)
    assert (ds["status"].values == 0).all() and (ds["num_steps"].values > 0).all()
    peak = ds["max_deflection"].values

    def rod(f):
        return L.rod(8, 1.0, bending=1.0, torsion=0.8, shear=1e4, stretch=1e4, mass=1.0,
                     rotary=1e-4, loads=L.TipForce(jnp.array([f, 0.0, 0.0])))  # fmt: skip

    static = float(L.equilibrium(rod(1e-4)).r[-1, 0])
    assert 1.9 < peak[0] / static <= 2.0 + 1e-6, peak[0] / static
    np.testing.assert_allclose(peak[1], 2 * peak[0], rtol=1e-3)
    ts = jnp.linspace(0.0, 1.8, 181)
    traj = L.simulate(rod(2e-4), rod(2e-4).straight(), ts)
    tip = np.asarray(traj.centreline[:, -1, :])
    np.testing.assert_allclose(ds["tip"].values[1], tip[-1], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(peak[1], np.linalg.norm(tip - tip[0], axis=1).max(), rtol=1e-9)
