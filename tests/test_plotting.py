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
from rbo_jax.plotting import plot_root_locus, plot_stability_map  # noqa: E402

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
