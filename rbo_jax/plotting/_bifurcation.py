"""Bifurcation diagrams (equilibria and limit cycles) and Hopf boundaries."""

from __future__ import annotations

import numpy as np

from ._common import pyplot
from ._maps import _unstable_level

__all__ = ["plot_bifurcation_diagram", "plot_hopf_boundary"]


_SPECIAL_STYLE = {  # type: (marker, colour, label)
    "hopf": ("o", "C3", "Hopf point"),
    "fold": ("s", "C2", "fold"),
    "branch_point": ("^", "C4", "branch point"),
}


def _branch_parameter(ds) -> str:
    name = ds.attrs.get("parameter")
    if name is None or name not in ds.data_vars:
        raise ValueError(
            "not a continuation result: attrs['parameter'] must name its parameter "
            "variable (rbo_jax.continue_equilibria / continue_limit_cycles)."
        )
    return name


def _fill_undefined(stable, defined):
    """Per-point stability with undefined points (e.g. the Hopf point of a cycle branch, whose
    multipliers are NaN) given their nearest defined neighbour's."""
    stable = np.asarray(stable, dtype=bool).copy()
    where = np.flatnonzero(defined)
    if where.size == 0:
        return stable
    for i in np.flatnonzero(~np.asarray(defined)):
        stable[i] = stable[where[np.argmin(np.abs(where - i))]]
    return stable


def _styled_runs(x, y, stable, breaks=None):
    """``(xs, ys, stable)`` runs of consecutive points of equal stability. Where the stability
    changes between points i and i + 1, the two runs meet at ``breaks[i]`` (a special point
    between them) or else at the midpoint, so the branch is drawn without a gap."""
    breaks = breaks or {}
    runs, xs, ys = [], [x[0]], [y[0]]
    for i in range(len(x) - 1):
        if stable[i + 1] != stable[i]:
            xb, yb = breaks.get(i, (0.5 * (x[i] + x[i + 1]), 0.5 * (y[i] + y[i + 1])))
            runs.append((np.array(xs + [xb]), np.array(ys + [yb]), bool(stable[i])))
            xs, ys = [xb], [yb]
        xs.append(x[i + 1])
        ys.append(y[i + 1])
    runs.append((np.array(xs), np.array(ys), bool(stable[-1])))
    return runs


def _draw_runs(ax, runs, colour, what):
    labelled = set()
    for xs, ys, stable in runs:
        label = f"{'stable' if stable else 'unstable'} {what}"
        ax.plot(
            xs,
            ys,
            "-" if stable else "--",
            color=colour,
            lw=1.8 if stable else 1.2,
            label=None if label in labelled else label,
        )
        labelled.add(label)


def _equilibrium_y(ds, component):
    theta = np.asarray(ds["theta"].values, dtype=float)
    if component is None:
        return np.linalg.norm(theta, axis=1), r"$|\theta|$ of the equilibrium"
    names = [str(c) for c in ds["component"].values]
    index = (
        component
        if isinstance(component, (int, np.integer))
        else (names.index(component) if component in names else None)
    )
    if index is None or not 0 <= index < theta.shape[1]:
        raise ValueError(f"component must be None, one of {names} or an index, got {component!r}.")
    return theta[:, index], rf"$\theta_{names[index]}$ of the equilibrium"


def _special_points(ds, x, y):
    """``[(type, value, y)]`` of the special points, y interpolated on their bracketing
    segment."""
    if "special_type" not in ds:
        return []
    out = []
    for kind, value, i in zip(
        ds["special_type"].values, ds["special_value"].values, ds["special_index"].values
    ):
        i = int(min(max(i, 0), len(x) - 2)) if len(x) > 1 else 0
        if len(x) > 1 and x[i + 1] != x[i]:
            w = float(np.clip((value - x[i]) / (x[i + 1] - x[i]), 0.0, 1.0))
            out.append((str(kind), float(value), float(y[i] + w * (y[i + 1] - y[i])), i))
        else:
            out.append((str(kind), float(value), float(y[i]), i))
    return out


def plot_bifurcation_diagram(
    equilibria, cycles=None, *, ax=None, component=None, title: str | None = None
):
    r"""Bifurcation diagram of a :func:`rbo_jax.continue_equilibria` result: the equilibrium
    branch, $|\theta|$ (or the ``component`` ``"x"``, ``"y"``, ``"z"`` or 0–2 of θ) against the
    parameter, solid where ``stable`` and dashed where not, with its special points (Hopf
    points, folds, branch points from the ``special_*`` variables) marked. ``cycles`` (a
    :func:`rbo_jax.continue_limit_cycles` result) adds the limit cycles' ``amplitude``
    $\max_t|\theta - \bar\theta|$ against the parameter on a second y axis (right), solid where
    orbitally stable, dashed where not. Returns the Axes of the equilibria; the cycles' Axes
    is ``ax.cycles_ax`` (None without cycles).
    """
    plt = pyplot()
    name = _branch_parameter(equilibria)
    x = np.asarray(equilibria[name].values, dtype=float)
    if x.size == 0:
        raise ValueError("the equilibrium branch has no points.")
    y, ylabel = _equilibrium_y(equilibria, component)
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    specials = _special_points(equilibria, x, y)
    stable = np.asarray(equilibria["stable"].values, dtype=bool)
    breaks = {i: (v, yv) for kind, v, yv, i in specials if kind == "hopf"}
    _draw_runs(ax, _styled_runs(x, y, stable, breaks), "C0", "equilibria")
    labelled = set()
    for kind, value, yv, _ in specials:
        marker, colour, label = _SPECIAL_STYLE.get(kind, ("X", "k", kind))
        ax.plot(
            [value],
            [yv],
            marker=marker,
            color=colour,
            ms=8,
            ls="none",
            label=None if kind in labelled else f"{label} ({name} = {value:.5g})",
        )
        labelled.add(kind)
    ax.set_xlabel(name)
    ax.set_ylabel(ylabel)
    ax.cycles_ax = None
    handles, labels = ax.get_legend_handles_labels()
    if cycles is not None:
        ax.cycles_ax = _draw_cycles(ax, cycles, name, specials)
        more = ax.cycles_ax.get_legend_handles_labels()
        handles, labels = handles + more[0], labels + more[1]
    ax.legend(handles, labels, fontsize=8, loc="upper left")
    ax.set_title(title or f"bifurcation diagram in {name}")
    return ax


def _draw_cycles(ax, cycles, name, specials):
    if _branch_parameter(cycles) != name:
        raise ValueError(
            f"the cycles were continued in {_branch_parameter(cycles)!r}, the "
            f"equilibria in {name!r}."
        )
    twin = ax.twinx()
    xc = np.asarray(cycles[name].values, dtype=float)
    amp = np.asarray(cycles["amplitude"].values, dtype=float)
    defined = np.all(np.isfinite(np.asarray(cycles["multipliers"].values)), axis=-1)
    stable = _fill_undefined(cycles["stable"].values, defined)
    _draw_runs(twin, _styled_runs(xc, amp, stable), "C1", "limit cycles")
    for kind, value, _, _ in specials:  # the cycles are born with amplitude 0 at Hopf points
        if kind == "hopf":
            twin.plot([value], [0.0], marker="o", color="C3", ms=8, mfc="none", ls="none")
    twin.set_ylim(bottom=0.0)
    twin.set_ylabel(r"limit cycle amplitude $\max_t|\theta - \bar\theta|$", color="C1")
    return twin


def _hopf_curve_names(curve):
    known = {"frequency", "first_lyapunov", "transversality", "theta", "num_steps", "status"}
    names = [n for n in curve.data_vars if n not in known]
    if len(names) != 1 or "status" not in curve:
        raise ValueError(
            "not a continue_hopf result: expected one critical-value variable, "
            f"'frequency', ..., 'status'; got {sorted(curve.data_vars)}."
        )
    return names[0], curve[names[0]].dims[-1]


def plot_hopf_boundary(
    curve, stability_map=None, *, ax=None, select: dict | None = None, title: str | None = None
):
    r"""The flutter boundary of a :func:`rbo_jax.continue_hopf` result: the critical value of
    its parameter (y) against the second parameter (x), one line per value of its batch axes,
    drawn over the sign of a :func:`rbo_jax.stability_map` dataset's spectral abscissa (blue:
    stable, max Re p ≤ the map's tolerance; red: unstable) when ``stability_map`` is given.
    The map needs both parameters as axes; ``select`` picks its other axes and the curve's
    batch axes (nearest value). Returns the Axes.
    """
    plt = pyplot()
    parameter, along = _hopf_curve_names(curve)
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    if stability_map is not None:
        _draw_sign(plt, ax, stability_map, along, parameter, select)
    da = curve[parameter]
    batch_sel = {k: v for k, v in (select or {}).items() if k in da.dims and k != along}
    if batch_sel:
        da = da.sel(batch_sel, method="nearest")
    batch = [d for d in da.dims if d != along]
    xs = np.asarray(da[along].values, dtype=float)
    vals = np.asarray(da.transpose(*batch, along).values, dtype=float).reshape(-1, xs.size)
    grids = np.meshgrid(*[np.asarray(da[d].values) for d in batch], indexing="ij")
    tags = [
        ", ".join(f"{d} = {g.ravel()[i]:.4g}" for d, g in zip(batch, grids))
        for i in range(vals.shape[0])
    ]
    for i, row in enumerate(vals):
        ax.plot(
            xs,
            row,
            "-",
            color="k" if len(vals) == 1 else f"C{i % 10}",
            lw=2,
            label="Hopf boundary" + (f" ({tags[i]})" if tags[i] else ""),
        )
    ax.set_xlabel(along)
    ax.set_ylabel(f"critical {parameter}")
    ax.legend(fontsize=8)
    ax.set_title(title or f"Hopf boundary: critical {parameter} against {along}")
    return ax


def _draw_sign(plt, ax, ds, x, y, select):
    from matplotlib.colors import ListedColormap

    da = ds["spectral_abscissa"]
    other = {k: v for k, v in (select or {}).items() if k in da.dims and k not in (x, y)}
    if other:
        da = da.sel(other, method="nearest")
    missing = [d for d in (x, y) if d not in da.dims]
    extra = [d for d in da.dims if d not in (x, y)]
    if missing or extra:
        raise ValueError(
            f"the stability map needs the axes {x!r} and {y!r} and values for the "
            f"others (select=...): missing {missing}, unselected {extra}."
        )
    vals = np.asarray(da.transpose(y, x).values, dtype=float)
    sign = np.where(np.isfinite(vals), (vals > _unstable_level(ds)).astype(float), np.nan)
    cmap = ListedColormap(["#cfe0f3", "#f6cfc9"]).with_extremes(bad="0.85")
    ax.pcolormesh(
        np.asarray(da[x].values, float),
        np.asarray(da[y].values, float),
        np.ma.masked_invalid(sign),
        cmap=cmap,
        vmin=0.0,
        vmax=1.0,
        shading="auto",
    )
    from matplotlib.patches import Patch

    ax.add_artist(
        ax.legend(
            handles=[
                Patch(color="#cfe0f3", label="stable (map)"),
                Patch(color="#f6cfc9", label="unstable (map)"),
            ],
            fontsize=8,
            loc="lower right",
        )
    )
