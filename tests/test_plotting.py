"""Figures (rbo_jax.plotting): stability maps, root loci, bifurcation diagrams, Hopf boundaries
and the lattices' space-time images and dispersion branches, drawn headless (Agg)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.collections import PathCollection, QuadMesh  # noqa: E402
from matplotlib.contour import ContourSet  # noqa: E402

import rbo_jax as rbo  # noqa: E402
from rbo_jax.plotting import (  # noqa: E402
    plot_bifurcation_diagram,
    plot_dispersion,
    plot_hopf_boundary,
    plot_root_locus,
    plot_space_time,
    plot_stability_map,
)

K = jnp.array([0.0, 0.0, 1.0])


def damped_nikolai(M, b, A3):
    """The Nikolai problem (4.50), (4.57) with friction (4.84): stable below M ≈ 2b√(c/A1),
    flutter above."""
    return rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(1.0, A3, K),
        rbo.QuadraticFoundation(1.0, 2.0, K),
        (rbo.FollowerMoment(M, K), rbo.Friction(b)),
    )


def theta_eq(M, b, A3):
    return (M / 2.0) * K  # (4.62)


@pytest.fixture(scope="module")
def damped_map():
    axes = {
        "M": np.linspace(0.0, 0.6, 13),
        "b": np.linspace(0.0, 0.3, 7),
        "A3": np.array([0.6, 1.2]),
    }
    return rbo.stability_map(damped_nikolai, axes, theta_eq_fn=theta_eq)


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _contours(ax):
    return [c for c in ax.collections if isinstance(c, ContourSet)]


def test_stability_map_figure_with_boundary(damped_map, tmp_path):
    """Both signs of max Re p on the (M, b) plane: a colour mesh and the boundary contour;
    the figure saves to a non-empty PNG."""
    a = damped_map["spectral_abscissa"].sel(A3=0.6).values
    assert np.nanmin(a) < 0 < np.nanmax(a)  # the map really has both signs
    ax = plot_stability_map(damped_map, "M", "b", select={"A3": 0.6})
    meshes = [c for c in ax.collections if isinstance(c, QuadMesh)]
    assert len(meshes) == 1
    np.testing.assert_array_equal(
        np.asarray(meshes[0].get_array()).ravel(),
        damped_map["spectral_abscissa"].sel(A3=0.6).values.T.ravel(),
    )
    assert len(_contours(ax)) == 1
    assert ax.get_xlabel() == "M" and ax.get_ylabel() == "b"
    path = tmp_path / "map.png"
    ax.figure.savefig(path)
    assert path.stat().st_size > 1000


def test_stability_map_without_boundary_on_given_axes(damped_map):
    """Where the map has one sign only (b ≥ 0.15, M ≤ 0.2: all stable) no boundary is drawn;
    an existing Axes is used and returned."""
    sub = damped_map.sel(M=damped_map["M"][:5], b=damped_map["b"][3:])
    assert np.all(sub["spectral_abscissa"].sel(A3=1.2).values < 0)
    fig, ax = plt.subplots()
    out = plot_stability_map(sub, "b", "M", select={"A3": 1.2}, ax=ax, title="stable corner")
    assert out is ax
    assert _contours(ax) == []
    assert ax.get_title() == "stable corner"


def test_stability_map_needs_select_for_other_axes(damped_map):
    with pytest.raises(ValueError, match="A3"):
        plot_stability_map(damped_map, "M", "b")


def test_root_locus_figure(damped_map, tmp_path):
    """Root locus of the six roots against M (b = 0.1): 13 × 6 points."""
    line = damped_map.isel(b=2).sel(A3=0.6)
    ax = plot_root_locus(line["M"].values, line["eigenvalues"].values, label="M")
    points = [c for c in ax.collections if isinstance(c, PathCollection)]
    assert len(points) == 1
    offsets = points[0].get_offsets()
    assert offsets.shape == (13 * 6, 2)
    np.testing.assert_array_equal(
        np.asarray(offsets)[:, 0], line["eigenvalues"].values.real.ravel()
    )
    assert ax.get_xlabel() == "Re p" and ax.get_ylabel() == "Im p"
    path = tmp_path / "locus.png"
    ax.figure.savefig(path)
    assert path.stat().st_size > 1000


@pytest.mark.parametrize(
    "values, eigenvalues",
    [
        (np.arange(3.0), np.zeros(3, complex)),  # 1-D eigenvalues
        (np.arange(3.0), np.zeros((4, 6), complex)),  # wrong length
        (np.arange(3.0), np.zeros((3, 6, 1), complex)),  # 3-D
    ],
    ids=["1-D", "length", "3-D"],
)
def test_root_locus_bad_shapes(values, eigenvalues):
    with pytest.raises(ValueError, match="shape"):
        plot_root_locus(values, eigenvalues)


def test_jax_arrays_are_accepted(damped_map):
    """Values and eigenvalues as jax arrays (straight from rbo_jax) plot as well."""
    line = damped_map.isel(b=2).sel(A3=0.6)
    ax = plot_root_locus(jnp.asarray(line["M"].values), jnp.asarray(line["eigenvalues"].values))
    assert ax.collections[0].get_offsets().shape == (13 * 6, 2)


# --- bifurcation diagrams and Hopf boundaries, from small hand-built continuation results


def _equilibria(stable, special=(("hopf", 0.23, 2),)):
    """A continue_equilibria-shaped Dataset: M = 0, 0.1, ..., 0.5 and θ = (0.1 M, 0, M/2)."""
    import xarray as xr

    M = np.linspace(0.0, 0.5, 6)
    theta = np.stack([0.1 * M, 0 * M, 0.5 * M], axis=1)
    kinds, values, index = (list(v) for v in zip(*special)) if special else ([], [], [])
    nan = np.full(len(kinds), np.nan)
    return xr.Dataset(
        {
            "M": ("point", M),
            "theta": (("point", "component"), theta),
            "eigenvalues": (("point", "mode"), np.zeros((6, 6), complex)),
            "spectral_abscissa": ("point", np.where(stable, -0.1, 0.1)),
            "stable": ("point", np.asarray(stable)),
            "special_type": ("special", np.array(kinds, dtype=str)),
            "special_value": ("special", np.array(values, dtype=float)),
            "special_index": ("special", np.array(index, dtype=int)),
            "special_frequency": ("special", nan),
            "special_first_lyapunov": ("special", nan),
        },
        coords={"component": ["x", "y", "z"], "mode": np.arange(6)},
        attrs={"parameter": "M", "stop_reason": "reached stop"},
    )


def _cycles(M, amplitude, stable, parameter="M"):
    """A continue_limit_cycles-shaped Dataset; the first point (the Hopf point) has NaN
    multipliers."""
    import xarray as xr

    n = len(M)
    mu = np.full((n, 6), 0.5 + 0j)
    mu[0] = np.nan
    return xr.Dataset(
        {
            parameter: ("point", np.asarray(M, float)),
            "period": ("point", np.full(n, 6.3)),
            "amplitude": ("point", np.asarray(amplitude, float)),
            "theta0": (("point", "component"), np.zeros((n, 3))),
            "Omega0": (("point", "component"), np.zeros((n, 3))),
            "multipliers": (("point", "index"), mu),
            "trivial_multiplier_error": ("point", np.full(n, 1e-12)),
            "stable": ("point", np.asarray(stable)),
        },
        coords={"component": ["x", "y", "z"], "index": np.arange(6)},
        attrs={"parameter": parameter, "stop_reason": "max_points"},
    )


def _branch_lines(ax):
    """The drawn branch segments (lines with a line style), as (style, x, y)."""
    return [
        (ln.get_linestyle(), np.asarray(ln.get_xdata(), float), np.asarray(ln.get_ydata(), float))
        for ln in ax.get_lines()
        if ln.get_linestyle() in ("-", "--")
    ]


def _markers(ax):
    return [ln for ln in ax.get_lines() if ln.get_linestyle() == "None"]


def test_bifurcation_diagram_splits_the_branch_at_the_hopf_point(tmp_path):
    """Stable for M ≤ 0.2, unstable from 0.3, Hopf point at 0.23 (between points 2 and 3): a
    solid segment up to the Hopf point and a dashed one from it, both through it (not through
    the midpoint 0.25); |θ| drawn; the Hopf point marked there."""
    eq = _equilibria([True, True, True, False, False, False])
    ax = plot_bifurcation_diagram(eq)
    norm = np.linalg.norm(eq["theta"].values, axis=1)
    (s1, x1, y1), (s2, x2, y2) = _branch_lines(ax)
    y_h = np.interp(0.23, eq["M"].values, norm)
    assert s1 == "-" and s2 == "--"
    np.testing.assert_allclose(x1, [0.0, 0.1, 0.2, 0.23])
    np.testing.assert_allclose(y1, np.append(norm[:3], y_h))
    np.testing.assert_allclose(x2, [0.23, 0.3, 0.4, 0.5])
    np.testing.assert_allclose(y2, np.insert(norm[3:], 0, y_h))
    (hopf,) = _markers(ax)
    assert hopf.get_marker() == "o"
    np.testing.assert_allclose([hopf.get_xdata()[0], hopf.get_ydata()[0]], [0.23, y_h])
    labels = ax.get_legend().get_texts()
    assert [t.get_text() for t in labels] == [
        "stable equilibria",
        "unstable equilibria",
        "Hopf point (M = 0.23)",
    ]
    assert ax.cycles_ax is None and len(ax.figure.axes) == 1
    ax.figure.savefig(tmp_path / "diagram.png")
    assert (tmp_path / "diagram.png").stat().st_size > 1000


def test_bifurcation_diagram_component_fold_and_midpoint_breaks():
    """A chosen component (θ_z = M/2), a change of stability without special point (break at
    the midpoint, 0.35), a regained stability (three segments) and a fold marked by a square."""
    eq = _equilibria([True, True, True, False, True, True], special=(("fold", 0.45, 4),))
    ax = plot_bifurcation_diagram(eq, component="z")
    lines = _branch_lines(ax)
    assert [s for s, _, _ in lines] == ["-", "--", "-"]
    np.testing.assert_allclose(lines[0][1], [0.0, 0.1, 0.2, 0.25])
    np.testing.assert_allclose(lines[1][1], [0.25, 0.3, 0.35])
    np.testing.assert_allclose(lines[2][1], [0.35, 0.4, 0.5])
    np.testing.assert_allclose(lines[2][2], [0.175, 0.2, 0.25])  # θ_z = M/2, not |θ|
    (fold,) = _markers(ax)
    assert fold.get_marker() == "s"
    np.testing.assert_allclose([fold.get_xdata()[0], fold.get_ydata()[0]], [0.45, 0.225])
    assert "theta_z" in ax.get_ylabel()
    ax = plot_bifurcation_diagram(eq, component=0)
    np.testing.assert_allclose(_branch_lines(ax)[2][2], [0.035, 0.04, 0.05])
    with pytest.raises(ValueError, match="component"):
        plot_bifurcation_diagram(eq, component="w")


def test_bifurcation_diagram_with_cycles():
    """Cycles on the right axis: the Hopf point (NaN multipliers) takes its neighbour's
    stability, a stable stretch then an unstable one (dashed) after the midpoint; the cycles
    start at amplitude 0 on the marked Hopf point; one legend lists both branches."""
    eq = _equilibria([True, True, True, False, False, False])
    cy = _cycles([0.23, 0.26, 0.28, 0.27], [0.0, 0.1, 0.2, 0.3], [False, True, True, False])
    ax = plot_bifurcation_diagram(eq, cy)
    twin = ax.cycles_ax
    assert twin is not None and twin in ax.figure.axes and twin is not ax
    (s1, x1, y1), (s2, x2, y2) = _branch_lines(twin)
    assert (s1, s2) == ("-", "--")
    np.testing.assert_allclose(x1, [0.23, 0.26, 0.28, 0.275])
    np.testing.assert_allclose(y1, [0.0, 0.1, 0.2, 0.25])
    np.testing.assert_allclose(x2, [0.275, 0.27])
    (birth,) = _markers(twin)
    assert (birth.get_xdata()[0], birth.get_ydata()[0]) == (0.23, 0.0)
    assert twin.get_ylim()[0] == 0.0
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert texts[-2:] == ["stable limit cycles", "unstable limit cycles"]


def test_bifurcation_diagram_checks_its_input():
    eq = _equilibria([True] * 6, special=())
    with pytest.raises(ValueError, match="continued in 'b'"):
        plot_bifurcation_diagram(eq, _cycles([0.1, 0.2], [0.0, 0.1], [True, True], "b"))
    with pytest.raises(ValueError, match="attrs"):
        plot_bifurcation_diagram(eq.drop_attrs())
    ax = plot_bifurcation_diagram(eq)  # no special points: one solid line, no markers
    assert [s for s, _, _ in _branch_lines(ax)] == ["-"] and _markers(ax) == []


def _hopf_curve(cs, bs):
    """A continue_hopf-shaped Dataset over (c, b): the small-damping boundary 2b√c."""
    import xarray as xr

    M = 2 * bs[None, :] * np.sqrt(cs[:, None])
    M[-1, -1] = np.nan  # a failed point
    dims = ("c", "b")
    zeros = np.zeros_like(M)
    ds = xr.Dataset(
        {
            "M": (dims, M),
            "frequency": (dims, zeros + 1.0),
            "first_lyapunov": (dims, zeros - 0.1),
            "transversality": (dims, zeros + 0.25),
            "theta": (dims + ("component",), np.zeros(M.shape + (3,))),
            "num_steps": (dims, np.full(M.shape, 3, np.int32)),  # as continue_hopf has them
            "status": (dims, np.zeros(M.shape, np.int8)),
        },
        coords={"c": cs, "b": bs, "component": ["x", "y", "z"]},
    )
    ds["status"].attrs["flag_meanings"] = "successful not_converged"
    return ds


def test_hopf_boundary_over_the_sign_of_a_stability_map(damped_map):
    """The boundary M = 2b√c (c = 1) over the map's sign of max Re p, A3 = 0.6 selected: the
    mesh holds 1 exactly where max Re p exceeds the map's tolerance, the line holds the curve's
    values; without select the curve's two c values give two lines."""
    bs = damped_map["b"].values
    curve = _hopf_curve(np.array([0.5, 1.0]), bs)
    ax = plot_hopf_boundary(curve, damped_map, select={"A3": 0.6, "c": 1.0})
    (mesh,) = [c for c in ax.collections if isinstance(c, QuadMesh)]
    a = damped_map["spectral_abscissa"].sel(A3=0.6).transpose("M", "b").values
    shown = np.asarray(mesh.get_array()).reshape(a.shape)
    np.testing.assert_array_equal(
        shown, (a > 1e-9 * np.nanmax(np.abs(damped_map["eigenvalues"].values))).astype(float)
    )
    assert 0 < shown.mean() < 1  # both signs shown
    (line,) = ax.get_lines()
    np.testing.assert_array_equal(line.get_xdata(), bs)
    np.testing.assert_array_equal(line.get_ydata(), curve["M"].sel(c=1.0).values)
    assert ax.get_xlabel() == "b" and ax.get_ylabel() == "critical M"
    # the boundary separates the map's stable cells (below) from the unstable ones (above),
    # except in the grid cells it crosses
    Ms = damped_map["M"].values
    dM = Ms[1] - Ms[0]
    below = Ms[:, None] < curve["M"].sel(c=1.0).values[None, :] - dM
    above = Ms[:, None] > curve["M"].sel(c=1.0).values[None, :] + dM
    assert np.all(shown[below] == 0) and np.all(shown[above] == 1)
    assert below.sum() > 10 and above.sum() > 10

    ax = plot_hopf_boundary(curve)
    lines = ax.get_lines()
    assert len(lines) == 2 and not [c for c in ax.collections if isinstance(c, QuadMesh)]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        "Hopf boundary (c = 0.5)",
        "Hopf boundary (c = 1)",
    ]
    assert np.isnan(lines[1].get_ydata()[-1])


def test_hopf_boundary_checks_its_input(damped_map):
    curve = _hopf_curve(np.array([1.0]), damped_map["b"].values)
    with pytest.raises(ValueError, match="A3"):
        plot_hopf_boundary(curve, damped_map)  # the map's A3 axis is not selected
    with pytest.raises(ValueError, match="missing"):
        plot_hopf_boundary(curve.rename(b="A1"), damped_map, select={"A3": 0.6})
    with pytest.raises(ValueError, match="continue_hopf"):
        plot_hopf_boundary(curve.drop_vars("status"))


# --- lattices: space-time images and dispersion branches


def _chain_trajectory(theta, Omega=None, shape=None):
    """A LatticeTrajectory of the given samples (T, N, 3), made by hand (nothing simulated)."""
    from rbo_jax import lattice as L
    from rbo_jax.trajectory import SolveStatus

    theta = jnp.asarray(theta)
    n = theta.shape[1]
    body = rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(1.0, 0.6, K), rbo.QuadraticFoundation(1.0, 2.0, K)
    )
    W = rbo.QuadraticFoundation(0.7, 0.3, K)
    lat = L.chain(n, body, W) if shape is None else L.grid(shape, body, W)
    return L.LatticeTrajectory(
        ts=jnp.linspace(0.0, 2.0, theta.shape[0]),
        theta=theta,
        Omega=jnp.zeros_like(theta) if Omega is None else jnp.asarray(Omega),
        turns=jnp.zeros(theta.shape[:2], jnp.int32),
        lattice=lat,
        status=SolveStatus.successful,
        num_steps=jnp.asarray(1),
        num_recentred=jnp.asarray(0),
    )


def _mesh(ax):
    (mesh,) = [c for c in ax.collections if isinstance(c, QuadMesh)]
    return mesh


def test_space_time_image_of_a_chain(tmp_path):
    """A kink-like front (theta_z from 0 to 2 pi, moving right): the mesh holds theta_z with
    sites along x and times along y, a sequential colour map (one sign); the norm, Omega and
    the values modulo 2 pi are drawn on request; non-finite samples are masked."""
    T, n = 5, 7
    front = np.arange(n)[None, :] - 1.0 - np.arange(T)[:, None]
    theta = np.zeros((T, n, 3))
    theta[..., 2] = 4 * np.arctan(np.exp(front))
    theta[..., 0] = 0.01 * np.arange(n)
    Omega = np.zeros((T, n, 3))
    Omega[..., 1] = np.sin(front)
    traj = _chain_trajectory(theta, Omega)
    ax = plot_space_time(traj)
    shown = np.asarray(_mesh(ax).get_array()).reshape(T, n)
    np.testing.assert_allclose(shown, theta[..., 2])
    assert ax.get_xlabel() == "site n" and "time" in ax.get_ylabel()
    assert _mesh(ax).get_cmap().name == "viridis"
    colorbar = ax.figure.axes[-1].get_ylabel()
    assert "theta_z" in colorbar and "(4.1)" in colorbar
    ax.figure.savefig(tmp_path / "space_time.png")
    assert (tmp_path / "space_time.png").stat().st_size > 1000

    ax = plot_space_time(traj, "norm")
    np.testing.assert_allclose(
        np.asarray(_mesh(ax).get_array()).reshape(T, n), np.linalg.norm(theta, axis=-1)
    )
    ax = plot_space_time(traj, 1, quantity="Omega", title="Omega_y")
    mesh = _mesh(ax)
    np.testing.assert_allclose(np.asarray(mesh.get_array()).reshape(T, n), Omega[..., 1])
    assert mesh.get_cmap().name.startswith("RdBu") and mesh.norm.vmin == -mesh.norm.vmax
    assert ax.get_title() == "Omega_y"
    ax = plot_space_time(traj, "z", wrap=True)
    np.testing.assert_allclose(
        np.asarray(_mesh(ax).get_array()).reshape(T, n),
        np.angle(np.exp(1j * theta[..., 2])),
        atol=1e-12,
    )
    theta[-1] = np.inf  # samples after a failed solve
    fig, ax = plt.subplots()
    assert plot_space_time(_chain_trajectory(theta), ax=ax) is ax
    assert np.asarray(np.ma.getmaskarray(_mesh(ax).get_array())).reshape(T, n)[-1].all()


def test_space_time_of_a_grid_row_and_bad_input():
    """A grid needs its sites chosen (a row); wrong components, quantities and sites are
    refused with the name of the argument."""
    T = 3
    theta = np.random.default_rng(0).normal(size=(T, 12, 3))
    traj = _chain_trajectory(theta, shape=(3, 4))
    with pytest.raises(ValueError, match="sites="):
        plot_space_time(traj)
    row = np.ravel_multi_index((1, np.arange(4)), (3, 4))
    ax = plot_space_time(traj, "x", sites=row)
    np.testing.assert_allclose(np.asarray(_mesh(ax).get_array()).reshape(T, 4), theta[:, 4:8, 0])
    assert "selected" in ax.get_xlabel()
    with pytest.raises(ValueError, match="component"):
        plot_space_time(traj, "w", sites=row)
    with pytest.raises(ValueError, match="component"):
        plot_space_time(traj, 3, sites=row)
    with pytest.raises(ValueError, match="quantity"):
        plot_space_time(traj, quantity="omega", sites=row)
    for bad in ([0, 12], [-1, 0], [0.0, 1.0], []):
        with pytest.raises(ValueError, match="sites"):
            plot_space_time(traj, sites=bad)


A1_, A3_, C_, D_, KB_, KT_ = 1.0, 0.6, 1.0, 2.0, 0.7, 0.3


def _branches(q):
    """The closed-form branches of a chain at rest, (4.50) with a quadratic coupling:
    omega^2 = (c + 4 kb sin^2(q/2))/A1 (bending, double) and (d + 4 kt sin^2(q/2))/A3."""
    s = np.sin(np.asarray(q) / 2) ** 2
    return np.stack([np.sqrt((C_ + 4 * KB_ * s) / A1_), np.sqrt((D_ + 4 * KT_ * s) / A3_)], -1)


def _frequency_lines(ax):
    return [ln for ln in ax.get_lines() if ln.get_linestyle() == "-"]


def test_dispersion_of_a_chain_matches_the_closed_form(tmp_path):
    """A chain at rest at theta = 0, its eigenvalues computed here (one compiled program for
    every chain length): three frequency branches on the closed forms (drawn dashed), no growth
    panel (all Re = 0)."""
    from rbo_jax import lattice as L

    body = rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(A1_, A3_, K), rbo.QuadraticFoundation(C_, D_, K)
    )
    lat = L.chain(10, body, rbo.QuadraticFoundation(KB_, KT_, K))
    qs = np.linspace(-np.pi, np.pi, 21)
    ax = plot_dispersion(
        lat,
        qs,
        theta_eq=np.zeros(3),  # at rest
        closed_form={"bending": lambda q: _branches(q)[:, 0], "torsion": _branches(qs)[:, 1]},
    )
    lines = _frequency_lines(ax)
    assert len(lines) == 3
    w = _branches(qs)
    expected = np.sort(np.stack([w[:, 0], w[:, 0], w[:, 1]], 1), 1)
    got = np.stack([ln.get_ydata() for ln in lines], 1)
    np.testing.assert_allclose(got, expected, rtol=1e-12)
    np.testing.assert_array_equal(lines[0].get_xdata(), qs)
    dashed = [ln for ln in ax.get_lines() if ln.get_linestyle() == "--"]
    assert len(dashed) == 2
    np.testing.assert_allclose(dashed[1].get_ydata(), w[:, 1])
    assert ax.growth_ax is None and len(ax.figure.axes) == 1
    assert [t.get_text() for t in ax.get_legend().get_texts()][1:] == ["bending", "torsion"]
    assert "wavenumber" in ax.get_xlabel() and "Im" in ax.get_ylabel()
    ax.figure.savefig(tmp_path / "dispersion.png")
    assert (tmp_path / "dispersion.png").stat().st_size > 1000


def _fluttering(qs):
    """Eigenvalues of made-up flutter bands: a pair with growth rates -0.05 ± 0.1 cos q (some
    wave grows for cos q > 1/2 and for cos q < -1/2) and a decaying torsion wave."""
    w = _branches(qs)
    g = 0.1 * np.cos(qs)
    up = np.stack([g - 0.05 + 1j * w[:, 0], -g - 0.05 + 1j * w[:, 0], -0.05 + 1j * w[:, 1]], 1)
    return np.concatenate([np.conj(up), up], 1)[:, ::-1]


def test_dispersion_growth_panel_and_flutter_bands():
    """Given eigenvalues with growth: a second panel below with the growth rates (sorted), the
    two bands of growing waves shaded on both panels; on a given Axes the growth rates go to a
    second y axis; growth=False draws none."""
    from matplotlib.patches import Polygon, Rectangle

    qs = np.linspace(0.0, np.pi, 12)  # k pi/11: bands k <= 3 and k >= 8
    lam = _fluttering(qs)
    ax = plot_dispersion(None, qs, eigenvalues=lam)
    g = ax.growth_ax
    assert g is not None and len(ax.figure.axes) == 2
    rates = np.stack([ln.get_ydata() for ln in g.get_lines() if len(ln.get_xdata()) == 12], 1)
    a = np.abs(0.1 * np.cos(qs))
    np.testing.assert_allclose(rates, np.stack([a - 0.05, np.full(12, -0.05), -a - 0.05], 1))

    def bands(axes):
        spans = [p for p in axes.patches if isinstance(p, (Polygon, Rectangle))]
        return sorted(
            (min(x), max(x))
            for x in (
                np.asarray(p.get_xy())[:, 0]
                if isinstance(p, Polygon)
                else [p.get_x(), p.get_x() + p.get_width()]
                for p in spans
            )
        )

    top = a - 0.05  # the largest growth rate; the bands end where it crosses 0 between samples
    ends = [qs[i] + (qs[i + 1] - qs[i]) * top[i] / (top[i] - top[i + 1]) for i in (3, 7)]
    assert qs[3] < ends[0] < np.pi / 3 < qs[4] and qs[7] < 2 * np.pi / 3 < ends[1] < qs[8]
    for axes in (ax, g):
        np.testing.assert_allclose(bands(axes), [(0.0, ends[0]), (ends[1], np.pi)])
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels.count("flutter band (some Re λ > 0)") == 1
    fig, ax = plt.subplots()
    out = plot_dispersion(None, qs, eigenvalues=lam, ax=ax)
    assert out is ax and ax.growth_ax is not None and ax.growth_ax is not ax
    assert ax.growth_ax.bbox.bounds == ax.bbox.bounds  # a twin of the same Axes
    ax = plot_dispersion(None, qs, eigenvalues=lam, growth=False)
    assert ax.growth_ax is None and len(ax.figure.axes) == 1


def test_dispersion_of_a_grid_path_and_bad_input():
    """(Q, 2) wavevectors of a grid: drawn against the length of their path; shapes that do not
    fit are refused."""
    qs = np.stack([np.linspace(0.0, np.pi, 5), np.zeros(5)], 1)
    qs = np.concatenate([qs, np.stack([np.full(4, np.pi), np.linspace(0.0, np.pi, 5)[1:]], 1)])
    lam = 1j * _fluttering(qs[:, 0]).imag  # no growth
    ax = plot_dispersion(None, qs, eigenvalues=lam)
    np.testing.assert_allclose(_frequency_lines(ax)[0].get_xdata(), np.pi / 4 * np.arange(9))
    assert "path" in ax.get_xlabel() and ax.growth_ax is None
    with pytest.raises(ValueError, match="eigenvalues must have shape"):
        plot_dispersion(None, qs, eigenvalues=lam[:, :3])
    with pytest.raises(ValueError, match="lattice or its eigenvalues"):
        plot_dispersion(None, qs)
    with pytest.raises(ValueError, match="closed form"):
        plot_dispersion(None, qs, eigenvalues=lam, closed_form=np.zeros(3))
    from rbo_jax import lattice as L

    body = rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(A1_, A3_, K), rbo.QuadraticFoundation(C_, D_, K)
    )
    with pytest.raises(ValueError, match="one wavenumber per axis"):
        plot_dispersion(
            L.grid((3, 3), body, rbo.QuadraticFoundation(KB_, KT_, K)), np.linspace(0.0, 1.0, 4)
        )
