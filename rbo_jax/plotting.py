"""Figures: stability maps and root loci (optional dependency: matplotlib, ``pip install
rbo_jax[plot]``)."""

from __future__ import annotations

import numpy as np

__all__ = ["plot_stability_map", "plot_root_locus"]


def _pyplot():
    try:
        import matplotlib.pyplot as plt  # headless machines fall back to the Agg backend
    except ImportError as e:  # pragma: no cover - exercised only without matplotlib
        raise ImportError("rbo_jax.plotting needs matplotlib: pip install 'rbo_jax[plot]'.") from e
    return plt


def plot_stability_map(ds, x: str, y: str, *, ax=None, select: dict | None = None,
                       cmap: str = "RdBu_r", title: str | None = None):
    r"""Spectral abscissa max Re p over two axes of a :func:`rbo_jax.stability_map` dataset, with
    the stability boundary (the contour where max Re p crosses the classification tolerance).

    ``select`` picks the other axes, e.g. ``{"A3": 0.5}`` (nearest value). Returns the Axes.
    """
    plt = _pyplot()
    da = ds["spectral_abscissa"]
    if select:
        da = da.sel(select, method="nearest")
    extra = [d for d in da.dims if d not in (x, y)]
    if extra:
        raise ValueError(f"select values for the other axes {extra} (select={{name: value}}).")
    da = da.transpose(y, x)
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    vals = np.asarray(da.values, dtype=float)
    if not np.any(np.isfinite(vals)):
        raise ValueError(
            "nothing to plot: the spectral abscissa is NaN everywhere (no equilibria)."
        )
    vmax = np.nanmax(np.abs(vals)) or 1.0
    X, Y = np.asarray(da[x].values), np.asarray(da[y].values)
    mesh = ax.pcolormesh(X, Y, vals, cmap=cmap, vmin=-vmax, vmax=vmax, shading="auto")
    plt.colorbar(mesh, ax=ax, label="spectral abscissa  max Re p")
    # Boundary between Re p ≈ 0 (stable / marginal) and Re p > 0 (unstable).
    scale = np.nanmax(np.abs(np.asarray(ds["eigenvalues"].values)))
    level = float(ds.attrs.get("classify_rtol", 1e-9)) * (scale if np.isfinite(scale) else 1.0)
    if np.nanmin(vals) < level < np.nanmax(vals) and min(vals.shape) > 1:
        ax.contour(X, Y, vals, levels=[level], colors="k", linewidths=1.5)
    ax.set_xlabel(x)
    ax.set_ylabel(y)
    ax.set_title(title or "stability map (black: boundary max Re p = 0)")
    return ax


def plot_root_locus(values, eigenvalues, *, ax=None, label: str = "parameter",
                    cmap: str = "viridis", title: str | None = None):
    """Root locus: eigenvalues p (n, m) in the complex plane, coloured by the parameter values
    (n,). Returns the Axes."""
    plt = _pyplot()
    values = np.asarray(values, dtype=float)
    p = np.asarray(eigenvalues)
    if p.ndim != 2 or p.shape[0] != values.shape[0]:
        raise ValueError(
            f"eigenvalues must have shape (len(values), m), got {p.shape} "
            f"for {values.shape[0]} values."
        )
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    c = np.repeat(values[:, None], p.shape[1], axis=1)
    sc = ax.scatter(p.real.ravel(), p.imag.ravel(), c=c.ravel(), s=6, cmap=cmap)
    plt.colorbar(sc, ax=ax, label=label)
    ax.axvline(0.0, color="k", lw=0.8)
    ax.set_xlabel("Re p")
    ax.set_ylabel("Im p")
    ax.set_title(title or f"root locus against {label}")
    return ax
