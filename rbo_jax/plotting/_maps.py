"""Stability maps, root loci and sweeps."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..batch import POINT_DIM, status_counts, summary_line
from ._common import pyplot

__all__ = ["plot_stability_map", "plot_root_locus", "plot_sweep"]


def plot_stability_map(
    ds,
    x: str,
    y: str,
    *,
    ax=None,
    select: dict | None = None,
    cmap: str = "RdBu_r",
    title: str | None = None,
):
    r"""Spectral abscissa max Re p over two axes of a :func:`rbo_jax.stability_map` dataset, with
    the stability boundary (the contour where max Re p crosses the classification tolerance).

    ``select`` picks the other axes, e.g. ``{"A3": 0.5}`` (nearest value). Returns the Axes.
    """
    plt = pyplot()
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
    level = _unstable_level(ds)
    if np.nanmin(vals) < level < np.nanmax(vals) and min(vals.shape) > 1:
        ax.contour(X, Y, vals, levels=[level], colors="k", linewidths=1.5)
    ax.set_xlabel(x)
    ax.set_ylabel(y)
    ax.set_title(title or "stability map (black: boundary max Re p = 0)")
    return ax


def _unstable_level(ds) -> float:
    """The spectral abscissa above which a point of a stability map counts as unstable: the
    map's classification tolerance times the largest eigenvalue modulus."""
    scale = np.nanmax(np.abs(np.asarray(ds["eigenvalues"].values)))
    return float(ds.attrs.get("classify_rtol", 1e-9)) * (scale if np.isfinite(scale) else 1.0)


def plot_root_locus(
    values,
    eigenvalues,
    *,
    ax=None,
    label: str = "parameter",
    cmap: str = "viridis",
    title: str | None = None,
):
    """Root locus: eigenvalues p (n, m) in the complex plane, coloured by the parameter values
    (n,). Returns the Axes."""
    plt = pyplot()
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


def _sweep_values(ds, variable):
    """The values drawn for ``variable`` (norms of vectors, moduli of complex numbers; NaN where
    the status is not successful), their label and the success mask."""
    da, status = ds[variable], ds["status"]
    space_dims = list(status.dims)
    vals = np.asarray(da.values)
    label = variable
    if any(d not in space_dims for d in da.dims):
        vals = np.linalg.norm(np.abs(vals).reshape(vals.shape[: len(space_dims)] + (-1,)), axis=-1)
        label = f"|{variable}|"
    elif np.iscomplexobj(vals):
        vals, label = np.abs(vals), f"|{variable}|"
    flags = status.attrs["flag_meanings"].split()
    ok = np.asarray(status.values) == (flags.index("successful") if "successful" in flags else 0)
    return np.where(ok, vals.astype(float), np.nan), label, ok


def _plot_points(plt, ax, ds, vals, ok, label):
    names = [n for n in ds.coords if ds[n].dims == (POINT_DIM,)]
    xs = np.asarray(ds[names[0]].values)
    if len(names) >= 2:
        ys = np.asarray(ds[names[1]].values)
        sc = ax.scatter(xs, ys, c=vals, s=12, cmap="viridis")
        ax.scatter(xs[~ok], ys[~ok], marker="x", c="0.5", s=12)
        plt.colorbar(sc, ax=ax, label=label)
        ax.set_ylabel(names[1])
    else:
        ax.plot(xs, vals, ".")
        ax.set_ylabel(label)
    ax.set_xlabel(names[0])


def _grid_slice(ds, vals, space_dims, x, y, select):
    """``vals`` over (y, x) with the other axes at ``select`` (nearest) or their first value."""
    index = []
    for d in space_dims:
        if d in (x, y):
            index.append(slice(None))
        else:
            coord = np.asarray(ds[d].values)
            target = (select or {}).get(d)
            target = coord[0] if target is None else target
            index.append(int(np.nanargmin(np.abs(coord - target))))
    v = vals[tuple(index)]
    kept = [d for d in space_dims if d in (x, y)]
    return v.T if kept.index(y) != 0 else v


def _plot_grid(plt, ax, ds, vals, label, x, y, select):
    space_dims = list(ds["status"].dims)
    x = x or space_dims[0]
    if len(space_dims) == 1:
        ax.plot(np.asarray(ds[x].values), vals, "-o", ms=3)
        ax.set_xlabel(x)
        ax.set_ylabel(label)
        return
    y = y or next(d for d in space_dims if d != x)
    for d in (x, y):
        if d not in space_dims:
            raise ValueError(f"{d!r} is not an axis of the sweep ({space_dims}).")
    v = _grid_slice(ds, vals, space_dims, x, y, select)
    # matplotlib needs finite coordinates: non-finite axis values (nonfinite_input) go
    X, Y = np.asarray(ds[x].values, float), np.asarray(ds[y].values, float)
    fx, fy = np.isfinite(X), np.isfinite(Y)
    X, Y, v = X[fx], Y[fy], v[np.ix_(fy, fx)]
    cmap = plt.get_cmap("RdBu_r" if np.nanmin(v) < 0 < np.nanmax(v) else "viridis")
    cmap = cmap.with_extremes(bad="0.8")
    kw = {}
    if cmap.name.startswith("RdBu"):
        vmax = np.nanmax(np.abs(v))
        kw = {"vmin": -vmax, "vmax": vmax}
    mesh = ax.pcolormesh(X, Y, np.ma.masked_invalid(v), cmap=cmap, shading="auto", **kw)
    plt.colorbar(mesh, ax=ax, label=label)
    if kw and min(v.shape) > 1:  # a diverging map: draw where the value crosses 0
        ax.contour(X, Y, v, levels=[0.0], colors="k", linewidths=1.0)
    ax.set_xlabel(x)
    ax.set_ylabel(y)


def plot_sweep(
    ds,
    variable: str | None = None,
    *,
    x: str | None = None,
    y: str | None = None,
    select: Mapping[str, float] | None = None,
    ax=None,
    title: str | None = None,
):
    """Draw one variable of a :func:`rbo_jax.sweep` result; points whose status is not
    ``successful`` are left blank (grey). Vector-valued outputs are drawn by their norm.

    Grid: a colour map over axes ``x``, ``y`` (default the first two; other axes at ``select``
    or their first value), or a curve for a one-axis grid. Points: a scatter over the first two
    parameters. Returns the Axes.
    """
    plt = pyplot()
    if variable is None:
        variable = next(n for n in ds.data_vars if n != "status")
    if variable not in ds.data_vars:
        raise KeyError(f"no variable {variable!r}; the sweep has {sorted(ds.data_vars)}.")
    vals, label, ok = _sweep_values(ds, variable)
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    if POINT_DIM in ds["status"].dims:
        _plot_points(plt, ax, ds, vals, ok, label)
    else:
        _plot_grid(plt, ax, ds, vals, label, x, y, select)
    ax.set_title(title or f"{label}   ({summary_line(status_counts(ds))})", fontsize=9)
    return ax


# --- bifurcation diagrams (rbo_jax.continue_equilibria / continue_limit_cycles / continue_hopf)
