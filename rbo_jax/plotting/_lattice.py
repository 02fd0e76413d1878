"""Lattices (:mod:`rbo_jax.lattice`): space-time images of a chain's motion and dispersion
branches of the Bloch waves."""

from __future__ import annotations

import functools
from collections.abc import Mapping

import numpy as np

from .._programs import jit
from ._common import pyplot

__all__ = ["plot_space_time", "plot_dispersion"]


_COMPONENTS = {"x": 0, "y": 1, "z": 2}
_QUANTITY_LABELS = {  # quantity: (symbol, units, what it is)
    "theta": (r"\theta", "rad", "turn-vector (4.1)"),
    "Omega": (r"\Omega", "rad/s", "right angular velocity (4.55)–(4.56)"),
}


def _space_time_values(traj, component, quantity, sites, wrap):
    """The (T, S) values drawn by :func:`plot_space_time`, their label and the sites' axis."""
    if quantity not in _QUANTITY_LABELS:
        raise ValueError(f"quantity must be 'theta' or 'Omega', got {quantity!r}.")
    lattice = traj.lattice
    if sites is None:
        if lattice.ndim != 1:
            raise ValueError(
                f"a space-time image draws the sites along one axis: this lattice "
                f"has the shape {lattice.shape}; pick them with sites=..., e.g. a "
                f"row of the grid, sites=np.ravel_multi_index((i, np.arange("
                f"{lattice.shape[-1]})), {lattice.shape})."
            )
        sites = np.arange(lattice.size)
        xlabel = "site n"
    else:
        sites = np.asarray(sites)
        if (
            sites.ndim != 1
            or sites.size == 0
            or not np.issubdtype(sites.dtype, np.integer)
            or sites.min() < 0
            or sites.max() >= lattice.size
        ):
            raise ValueError(
                f"sites must be a non-empty 1-D array of site indices 0 … "
                f"{lattice.size - 1} (row-major), got {sites!r}."
            )
        xlabel = "position along the selected sites"
    vec = np.asarray(getattr(traj, quantity), dtype=float)[:, sites, :]
    symbol, units, what = _QUANTITY_LABELS[quantity]
    if component in ("norm", None):
        vals, label = np.linalg.norm(vec, axis=-1), rf"$|{symbol}|$ ({units}), {what}"
    else:
        index = _COMPONENTS.get(component, component)
        if (
            not isinstance(index, (int, np.integer))
            or isinstance(index, bool)
            or not 0 <= index < 3
        ):
            raise ValueError(f"component must be 'x', 'y', 'z', 0–2 or 'norm', got {component!r}.")
        name = "xyz"[index]
        vals, label = vec[..., index], rf"${symbol}_{name}$ ({units}), {what}"
    if wrap:
        finite = np.isfinite(vals)
        vals = np.where(finite, np.angle(np.exp(1j * np.where(finite, vals, 0.0))), np.nan)
        label += r", modulo $2\pi$"
    return vals, label, xlabel


def plot_space_time(
    traj,
    component="z",
    *,
    quantity: str = "theta",
    sites=None,
    wrap=False,
    ax=None,
    cmap: str | None = None,
    title: str | None = None,
):
    r"""Space-time image of one quantity of a :class:`rbo_jax.lattice.LatticeTrajectory`: the
    sites of a chain along x, the sample times along y, the value in colour.

    ``quantity``: ``"theta"`` (the turn-vectors, (4.1)) or ``"Omega"`` (the right angular
    velocities, (4.55)–(4.56)); ``component``: ``"x"``, ``"y"``, ``"z"`` or 0–2 (e.g. ``"z"``:
    the turn about $k = e_z$ of plane rotations, a sine-Gordon kink), or ``"norm"`` (the angle
    of turn $|\theta|$). ``sites``: flat (row-major) indices of the sites to draw, e.g. a row of
    a grid (default: every site of a chain). ``wrap``: draw the values modulo $2\pi$, in
    $(-\pi, \pi]$ (angles of plane rotations). Values of both signs get a diverging colour map
    centred on 0; samples that are not finite (after a failed solve) are left blank (grey).
    Returns the Axes.
    """
    plt = pyplot()
    vals, label, xlabel = _space_time_values(traj, component, quantity, sites, wrap)
    ts = np.asarray(traj.ts, dtype=float)
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    finite = vals[np.isfinite(vals)]
    vmax = float(np.abs(finite).max()) if finite.size else 0.0
    kw = {}
    # both signs of some size (not the rounding errors about 0 of a kink's tail): diverging
    diverging = vmax > 0 and finite.min() < -0.01 * vmax and finite.max() > 0.01 * vmax
    if diverging:
        kw = {"vmin": -vmax, "vmax": vmax}
    colours = plt.get_cmap(cmap or ("RdBu_r" if diverging else "viridis"))
    mesh = ax.pcolormesh(
        np.arange(vals.shape[1]),
        ts,
        np.ma.masked_invalid(vals),
        cmap=colours.with_extremes(bad="0.8"),
        shading="auto",
        **kw,
    )
    plt.colorbar(mesh, ax=ax, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("time t (s)")
    ax.set_title(title or f"space-time: {label.split(' (')[0]} of {vals.shape[1]} bodies")
    return ax


def _canonical_cell(lattice):
    """The lattice on a periodic cell of 3 sites per axis: its Bloch matrix is the same (the
    blocks are computed on that cell, :func:`rbo_jax.lattice.bloch_blocks`), and one compiled
    program then serves chains and grids of every size."""
    from ..lattice import Lattice

    if not isinstance(lattice, Lattice) or not lattice.is_grid or lattice.per_site:
        return lattice  # rbo_jax.lattice.dispersion says what is wrong with it
    return Lattice(lattice.body, lattice.coupling, (3,) * lattice.ndim, (True,) * lattice.ndim)


@functools.partial(jit, small=True)
def _lattice_eigenvalues(lattice, qs, theta_eq):
    """The six eigenvalues of the Bloch matrix at every row of ``qs`` (one compiled program)."""
    import jax

    from ..lattice import bloch_blocks, dispersion

    blocks = bloch_blocks(lattice, theta_eq)
    return jax.vmap(lambda q: dispersion(lattice, q, blocks=blocks))(qs)


def _dispersion_data(lattice, qs, eigenvalues, theta_eq):
    """``(x, xlabel, branches (Q, 3) complex)``: the three eigenvalues of largest frequency at
    every wavevector (for a real Bloch matrix, the upper half of the conjugate pairs)."""
    qs = np.asarray(qs, dtype=float)
    if qs.ndim not in (1, 2) or qs.shape[0] < 1:
        raise ValueError(
            f"qs must be (Q,) wavenumbers of a chain or (Q, dim) wavevectors, got shape {qs.shape}."
        )
    if eigenvalues is None:
        if lattice is None:
            raise ValueError("plot_dispersion needs a lattice or its eigenvalues=...")
        ndim = getattr(lattice, "ndim", None)
        if ndim is not None and (
            qs.ndim == 1 and ndim != 1 or qs.ndim == 2 and qs.shape[1] != ndim
        ):
            raise ValueError(
                f"qs needs one wavenumber per axis of the lattice ({ndim}): shape "
                f"(Q,) for a chain, (Q, {ndim}) for a grid; got {qs.shape}."
            )
        import jax.numpy as jnp

        q = jnp.asarray(qs if qs.ndim == 2 else qs[:, None])
        eq = None if theta_eq is None else jnp.asarray(theta_eq, dtype=q.dtype)
        eigenvalues = _lattice_eigenvalues(_canonical_cell(lattice), q, eq)
    lam = np.asarray(eigenvalues)
    if lam.shape != (qs.shape[0], 6):
        raise ValueError(
            f"eigenvalues must have shape (len(qs), 6) = ({qs.shape[0]}, 6) (the "
            f"six of rbo_jax.lattice.dispersion per wavevector), got {lam.shape}."
        )
    order = np.argsort(lam.imag, axis=1, kind="stable")[:, 3:]
    branches = np.take_along_axis(lam, order, axis=1)
    if qs.ndim == 1:
        return qs, r"wavenumber $q$ (rad per site)", branches
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(qs, axis=0), axis=1))])
    return path, r"path length through the wavevectors $q$ (rad per site)", branches


def _closed_form_curves(closed_form, qs, n):
    """``[(label, (Q, B) values)]`` of the closed forms (a callable of the wavevectors, an array,
    or a mapping label -> either)."""
    if closed_form is None:
        return []
    items = (
        closed_form.items() if isinstance(closed_form, Mapping) else [("closed form", closed_form)]
    )
    out = []
    for label, f in items:
        vals = np.asarray(f(np.asarray(qs, dtype=float)) if callable(f) else f, dtype=float)
        vals = vals[:, None] if vals.ndim == 1 else vals
        if vals.ndim != 2 or vals.shape[0] != n:
            raise ValueError(
                f"the closed form {label!r} must give (Q,) or (Q, B) frequencies "
                f"for the {n} wavevectors, got shape {vals.shape}."
            )
        out.append((str(label), vals))
    return out


def _plot_frequencies(ax, x, branches, curves):
    """The three frequency branches Im lambda(q) and the closed-form curves."""
    style = "o-" if x.shape[0] <= 40 else "-"
    for i in range(3):
        ax.plot(
            x,
            branches[:, i].imag,
            style,
            color="C0",
            ms=3,
            lw=1.5,
            label=r"$\mathrm{Im}\,\lambda(q)$, Bloch matrix" if i == 0 else None,
        )
    for j, (label, vals) in enumerate(curves):
        for b in range(vals.shape[1]):
            ax.plot(
                x,
                vals[:, b],
                "--",
                color="k" if j == 0 else f"C{j + 2}",
                lw=1.2,
                label=label if b == 0 else None,
            )


def plot_dispersion(
    lattice,
    qs,
    *,
    ax=None,
    eigenvalues=None,
    closed_form=None,
    growth: bool | None = None,
    growth_ax=None,
    theta_eq=None,
    title: str | None = None,
):
    r"""The dispersion branches of a chain or grid (:func:`rbo_jax.lattice.dispersion`): the
    frequencies $\omega = \mathrm{Im}\,\lambda(q)$ of the Bloch matrix $B(q)$ against the
    wavenumber, and the growth rates $\mathrm{Re}\,\lambda(q)$ in a second panel or on a second
    y axis, with the bands of wavenumbers where some wave grows (flutter) shaded. At $q = 0$
    the eigenvalues are those of one body's linearization ((4.63)–(4.67); for the Nikolai
    problem the roots of (4.69)).

    **Arguments:**

    - `lattice`: a :class:`rbo_jax.lattice.Lattice` (chain or grid, one body on every site),
      linearized about ``theta_eq`` (default its uniform equilibrium); or ``None`` when
      ``eigenvalues`` are given.
    - `qs`: ``(Q,)`` wavenumbers of a chain (rad per site), or ``(Q, dim)`` wavevectors of a
      grid: a path through the Brillouin zone, drawn against its length.
    - `eigenvalues`: ``(Q, 6)`` eigenvalues already computed at ``qs`` (e.g. vmapped
      :func:`rbo_jax.lattice.dispersion`); else computed here (one compiled program for every
      size of the lattice). The three of largest $\mathrm{Im}\,\lambda$ at every $q$ are drawn.
    - `closed_form`: curves to overlay (black, dashed): ``(Q,)`` or ``(Q, B)`` frequencies at
      ``qs``, a function of ``qs`` that returns them, or a mapping label -> either.
    - `growth`: draw the growth rates (default: when some $|\mathrm{Re}\,\lambda|$ exceeds
      $10^{-9}\max|\lambda|$). On ``growth_ax`` if given, else a panel below a new figure's
      (``ax=None``), else a second y axis of ``ax`` (right).

    Returns the Axes of the frequencies; that of the growth rates is ``ax.growth_ax`` (None
    without them).
    """
    plt = pyplot()
    x, xlabel, branches = _dispersion_data(lattice, qs, eigenvalues, theta_eq)
    curves = _closed_form_curves(closed_form, qs, x.shape[0])
    re = branches.real
    scale = float(np.max(np.abs(branches))) or 1.0
    if growth is None:
        growth = bool(np.max(np.abs(re)) > 1e-9 * scale)
    panel = ax is None and growth and growth_ax is None  # a panel below, made here
    if panel:
        _, (ax, growth_ax) = plt.subplots(
            2,
            1,
            figsize=(6, 6),
            sharex=True,
            gridspec_kw={"height_ratios": (2, 1)},
            layout="constrained",
        )
    elif ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    twin = growth and growth_ax is None
    if twin:
        growth_ax = ax.twinx()
    _plot_frequencies(ax, x, branches, curves)
    style = "o-" if x.shape[0] <= 40 else "-"
    excess = np.max(re, axis=1) - 1e-9 * scale
    targets = [ax] + ([growth_ax] if growth and not twin else [])
    if np.any(excess > 0):
        for a in targets:
            _shade_band(a, x, excess)
    if not panel:
        ax.set_xlabel(xlabel)
    ax.set_ylabel(r"frequency $\omega = \mathrm{Im}\,\lambda$ (rad/s)")
    ax.growth_ax = None
    if growth:
        # sorted by growth rate, not paired with the frequencies: branches of nearly equal
        # frequency (the two bending waves under a follower moment) swap their order in Im
        rates = -np.sort(-re, axis=1)
        for i in range(3):
            growth_ax.plot(
                x,
                rates[:, i],
                style,
                color="C3",
                ms=3,
                lw=1.2,
                label=r"$\mathrm{Re}\,\lambda(q)$, sorted" if i == 0 else None,
            )
        growth_ax.axhline(0.0, color="k", lw=0.8)
        growth_ax.set_ylabel(r"growth rate $\mathrm{Re}\,\lambda$ (1/s)", color="C3")
        growth_ax.set_xlabel(xlabel)
        ax.growth_ax = growth_ax
    ax.legend(fontsize=8, loc="best")
    ax.set_title(title or r"dispersion: eigenvalues $\lambda(q)$ of the Bloch matrix $B(q)$")
    return ax


def _shade_band(ax, x, excess):
    """Shade the runs of wavenumbers where some wave grows (``excess`` = the largest growth rate
    less the threshold > 0), to the zero crossings of ``excess`` interpolated linearly between
    the samples."""
    unstable = excess > 0
    edges = np.flatnonzero(np.diff(np.concatenate([[0], unstable.astype(int), [0]])))

    def crossing(i, j):
        return x[i] + (x[j] - x[i]) * excess[i] / (excess[i] - excess[j])

    for n, (start, stop) in enumerate(zip(edges[::2], edges[1::2])):
        lo = x[start] if start == 0 else crossing(start - 1, start)
        hi = x[stop - 1] if stop == len(x) else crossing(stop - 1, stop)
        ax.axvspan(
            lo,
            hi,
            color="C3",
            alpha=0.12,
            lw=0,
            label="flutter band (some Re λ > 0)" if n == 0 else None,
        )
