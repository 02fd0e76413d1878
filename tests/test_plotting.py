"""Figures (rbo_jax.plotting): stability maps and root loci, drawn headless (Agg)."""

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
    plot_hopf_boundary,
    plot_root_locus,
    plot_stability_map,
)

K = jnp.array([0.0, 0.0, 1.0])


def damped_nikolai(M, b, A3):
    """The Nikolai problem (4.50), (4.57) with friction (4.84): stable below M ≈ 2b√(c/A1),
    flutter above."""
    return rbo.RigidBodyOscillator(
        rbo.transversely_isotropic_inertia(1.0, A3, K), rbo.QuadraticFoundation(1.0, 2.0, K),
        (rbo.FollowerMoment(M, K), rbo.Friction(b)))


def theta_eq(M, b, A3):
    return (M / 2.0) * K  # (4.62)


@pytest.fixture(scope="module")
def damped_map():
    axes = {"M": np.linspace(0.0, 0.6, 13), "b": np.linspace(0.0, 0.3, 7),
            "A3": np.array([0.6, 1.2])}
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
    np.testing.assert_array_equal(np.asarray(meshes[0].get_array()).ravel(),
                                  damped_map["spectral_abscissa"].sel(A3=0.6).values.T.ravel())
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
    np.testing.assert_array_equal(np.asarray(offsets)[:, 0],
                                  line["eigenvalues"].values.real.ravel())
    assert ax.get_xlabel() == "Re p" and ax.get_ylabel() == "Im p"
    path = tmp_path / "locus.png"
    ax.figure.savefig(path)
    assert path.stat().st_size > 1000


@pytest.mark.parametrize("values, eigenvalues", [
    (np.arange(3.0), np.zeros(3, complex)),           # 1-D eigenvalues
    (np.arange(3.0), np.zeros((4, 6), complex)),      # wrong length
    (np.arange(3.0), np.zeros((3, 6, 1), complex)),   # 3-D
], ids=["1-D", "length", "3-D"])
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
        {"M": ("point", M), "theta": (("point", "component"), theta),
         "eigenvalues": (("point", "mode"), np.zeros((6, 6), complex)),
         "spectral_abscissa": ("point", np.where(stable, -0.1, 0.1)),
         "stable": ("point", np.asarray(stable)),
         "special_type": ("special", np.array(kinds, dtype=str)),
         "special_value": ("special", np.array(values, dtype=float)),
         "special_index": ("special", np.array(index, dtype=int)),
         "special_frequency": ("special", nan), "special_first_lyapunov": ("special", nan)},
        coords={"component": ["x", "y", "z"], "mode": np.arange(6)},
        attrs={"parameter": "M", "stop_reason": "reached stop"})


def _cycles(M, amplitude, stable, parameter="M"):
    """A continue_limit_cycles-shaped Dataset; the first point (the Hopf point) has NaN
    multipliers."""
    import xarray as xr

    n = len(M)
    mu = np.full((n, 6), 0.5 + 0j)
    mu[0] = np.nan
    return xr.Dataset(
        {parameter: ("point", np.asarray(M, float)), "period": ("point", np.full(n, 6.3)),
         "amplitude": ("point", np.asarray(amplitude, float)),
         "theta0": (("point", "component"), np.zeros((n, 3))),
         "Omega0": (("point", "component"), np.zeros((n, 3))),
         "multipliers": (("point", "index"), mu),
         "trivial_multiplier_error": ("point", np.full(n, 1e-12)),
         "stable": ("point", np.asarray(stable))},
        coords={"component": ["x", "y", "z"], "index": np.arange(6)},
        attrs={"parameter": parameter, "stop_reason": "max_points"})


def _branch_lines(ax):
    """The drawn branch segments (lines with a line style), as (style, x, y)."""
    return [(ln.get_linestyle(), np.asarray(ln.get_xdata(), float),
             np.asarray(ln.get_ydata(), float))
            for ln in ax.get_lines() if ln.get_linestyle() in ("-", "--")]


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
        "stable equilibria", "unstable equilibria", "Hopf point (M = 0.23)"]
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
        {"M": (dims, M), "frequency": (dims, zeros + 1.0), "first_lyapunov": (dims, zeros - 0.1),
         "transversality": (dims, zeros + 0.25), "theta": (dims + ("component",),
                                                           np.zeros(M.shape + (3,))),
         "status": (dims, np.zeros(M.shape, np.int8))},
        coords={"c": cs, "b": bs, "component": ["x", "y", "z"]})
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
    np.testing.assert_array_equal(shown, (a > 1e-9 * np.nanmax(np.abs(
        damped_map["eigenvalues"].values))).astype(float))
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
        "Hopf boundary (c = 0.5)", "Hopf boundary (c = 1)"]
    assert np.isnan(lines[1].get_ydata()[-1])


def test_hopf_boundary_checks_its_input(damped_map):
    curve = _hopf_curve(np.array([1.0]), damped_map["b"].values)
    with pytest.raises(ValueError, match="A3"):
        plot_hopf_boundary(curve, damped_map)  # the map's A3 axis is not selected
    with pytest.raises(ValueError, match="missing"):
        plot_hopf_boundary(curve.rename(b="A1"), damped_map, select={"A3": 0.6})
    with pytest.raises(ValueError, match="continue_hopf"):
        plot_hopf_boundary(curve.drop_vars("status"))
