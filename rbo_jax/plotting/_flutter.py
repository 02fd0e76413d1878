"""Soft/hard flutter maps with the Bautin curve, and hysteresis loops over a continued branch."""

from __future__ import annotations

import numpy as np

from ._common import pyplot

__all__ = ["plot_flutter_map", "plot_hysteresis"]


def plot_flutter_map(ds, *, ax=None, title: str | None = None):
    r"""A :func:`rbo_jax.bifurcation.flutter_map` result: soft flutter ($\ell_1 < 0$, blue) and
    hard flutter ($\ell_1 > 0$, red) over its two parameters ($\beta$ on y, $\gamma$ on x), the
    grid's $\ell_1 = 0$ contour and the Bautin points (black line with dots) where they were
    found. Returns the Axes."""
    plt = pyplot()
    beta, gamma = ds.attrs["beta"], ds.attrs["gamma"]
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    l1 = np.asarray(ds["first_lyapunov"].transpose(beta, gamma).values, dtype=float)
    x, y = np.asarray(ds[gamma].values, float), np.asarray(ds[beta].values, float)
    scale = np.nanmax(np.abs(l1)) or 1.0
    mesh = ax.pcolormesh(x, y, l1, cmap="coolwarm", vmin=-scale, vmax=scale, shading="auto")
    plt.colorbar(mesh, ax=ax, label=r"first Lyapunov coefficient $\ell_1$")
    if np.nanmin(l1) < 0 < np.nanmax(l1):
        ax.contour(x, y, l1, levels=[0.0], colors="0.3", linestyles="--", linewidths=1)
    key = f"bautin_{beta}"
    if key in ds:
        ax.plot(x, ds[key].values, "k.-", lw=2, label="Bautin points (l1 = 0)")
        ax.legend(fontsize=8, loc="best")
    ax.text(0.02, 0.04, "soft (l1 < 0)", transform=ax.transAxes, color="C0")
    ax.text(0.02, 0.94, "hard (l1 > 0)", transform=ax.transAxes, color="C3")
    ax.set_xlabel(gamma)
    ax.set_ylabel(beta)
    ax.set_title(title or "Soft and hard flutter")
    return ax


def plot_hysteresis(loop, cycles=None, *, hopf_value=None, ax=None, title: str | None = None):
    r"""A :func:`rbo_jax.bifurcation.hysteresis_loop` result: the amplitude against the load,
    rising (triangles up) and falling (triangles down), over the continued branch of limit
    cycles ``cycles`` (:func:`rbo_jax.continue_limit_cycles`; solid where stable, dashed where
    unstable) and the resting state (amplitude 0; solid below ``hopf_value``). Returns the
    Axes."""
    plt = pyplot()
    name = loop.attrs["parameter"]
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    if cycles is not None:
        p = np.asarray(cycles[name].values, float)
        a = np.asarray(cycles["amplitude"].values, float)
        stable = np.asarray(cycles["stable"].values, bool)
        for flag, style, label in ((True, "-", "stable cycles"), (False, "--", "unstable cycles")):
            ax.plot(np.where(stable == flag, p, np.nan), a, style, color="k", lw=1.5, label=label)
    if hopf_value is not None:
        lo = float(np.min(loop[name].values))
        hi = float(np.max(loop[name].values))
        ax.plot([lo, hopf_value], [0, 0], "-", color="0.4", lw=2, label="rest (stable)")
        ax.plot([hopf_value, hi], [0, 0], ":", color="0.4", lw=2, label="rest (unstable)")
    up = loop["direction"].values > 0
    x, amp = loop[name].values, loop["amplitude"].values
    ax.plot(x[up], amp[up], "^", color="C3", ms=5, label="load rising")
    ax.plot(x[~up], amp[~up], "v", color="C0", ms=5, label="load falling")
    ax.set_xlabel(name)
    ax.set_ylabel(r"amplitude $\max_t|\theta - \bar\theta|$ [rad]")
    ax.legend(fontsize=8)
    ax.set_title(title or "Hysteresis under a quasi-static load")
    return ax
