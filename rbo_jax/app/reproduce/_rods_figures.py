"""The figures of the rods' section (:mod:`._rods`): shapes, stability diagrams, flutter."""

from __future__ import annotations

import numpy as np

from . import _rod_references as ref
from ._common import save


def statics_figure(plt, out, lines, alphas, elastica):
    """The elastica's shapes with the reference tip deflections, and the closed circle."""
    fig, ax = plt.subplots(figsize=(6.5, 5), layout="constrained")
    for k, alpha in enumerate(alphas, 1):
        (line,) = ax.plot(lines[k, :, 0], lines[k, :, 2], ".-", ms=3, label=f"α = {alpha:g}")
        ax.axvline(elastica[alpha], color=line.get_color(), ls=":", lw=0.8)
    ax.plot(lines[-1, :, 0], lines[-1, :, 2], ".-", ms=3, color="k", label="tip moment 2πEI/L")
    ax.set_aspect("equal")
    ax.set_xlabel("x / L")
    ax.set_ylabel("z / L")
    ax.set_title("cantilever: elastica (dotted: reference tip deflections) and the circle")
    ax.legend(fontsize=8)
    save(plt, fig, out, "rods_statics.png")


def stability_figure(plt, out, columns, ziegler):
    """Beck's column against Kelvin-Voigt damping, Pflüger's against its tip mass, Ziegler's
    pendulum against its dampers; the rods' points on the references' curves."""
    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(15, 4.5), layout="constrained")
    Pc, mus, etas = columns["Pc"], columns["mus"], columns["etas"]
    grid = np.geomspace(1e-4, 0.1, 10)
    a1.semilogx(
        grid, [ref.column_galerkin(0.0, e) for e in grid], "-", label=f"Galerkin, {ref.MODES} modes"
    )
    a1.semilogx(etas, Pc[2 + len(mus) : -1], "o", label="rod, N = 20")
    a1.axhline(ref.BECK, color="k", ls="--", lw=0.8, label=f"undamped {ref.BECK}")
    a1.axhline(Pc[1], color="C1", ls=":", lw=0.8, label=f"rod undamped {Pc[1]:.3f}")
    a1.axhline(ref.BECK_KV_LIMIT, color="k", ls=":", lw=0.8, label=f"η → 0: {ref.BECK_KV_LIMIT}")
    a1.set(xlabel="Kelvin–Voigt time η", ylabel="critical load P L²/EI", ylim=(0, 22))
    a1.set_title("Beck's column: damping halves the flutter load")
    a1.legend(fontsize=8)
    mu_grid = np.array([0.0, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0])
    a2.plot(
        mu_grid,
        [ref.column_galerkin(m) for m in mu_grid],
        "-",
        label=f"Galerkin, {ref.MODES} modes",
    )
    a2.plot([0.0, *mus], [Pc[1], *Pc[2 : 2 + len(mus)]], "o", label="rod, N = 20")
    a2.set(xlabel="tip mass / rod mass μ", ylabel="critical load P L²/EI")
    a2.set_title("Pflüger's column")
    a2.legend(fontsize=8)
    b_grid = np.linspace(0.0, max(ziegler["bs"].max(), 0.1), 50)
    a3.plot(b_grid, ref.ziegler_damped(b_grid), "-", label="41/28 + b²/2")
    a3.plot(ziegler["bs"][1:], ziegler["Pc"][1:], "o", label="two bodies, damped")
    a3.plot([0.0], ziegler["Pc"][:1], "s", label="two bodies, undamped")
    a3.axhline(ref.ZIEGLER, color="k", ls="--", lw=0.8, label="7/2 − √2")
    a3.set(xlabel="hinge damper b (c·s)", ylabel="critical load P l/c")
    a3.set_title("Ziegler's pendulum: the paradox")
    a3.legend(fontsize=8)
    save(plt, fig, out, "rods_stability.png")


def flutter_figure(plt, out, motion):
    """The tip's motion past the flutter load, with e^{σt} of the unstable eigenvalue."""
    ts, x, p = motion["ts"], motion["x"], motion["p"]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4), layout="constrained")
    a1.plot(ts, x, lw=0.8)
    a1.set(xlabel="t √(EI/ρAL⁴)", ylabel="tip deflection x / L")
    a1.set_title(f"Beck's column at P = {motion['P']:.3f} = 1.05 P_c: flutter")
    a2.semilogy(ts, np.abs(x), lw=0.6, label="|x_tip|")
    a2.semilogy(motion["tp"], motion["hp"], "o", ms=3, label="peaks fitted")
    if len(motion["hp"]):
        scale = motion["hp"][0] * np.exp(-p.real * motion["tp"][0])
        a2.semilogy(
            ts, scale * np.exp(p.real * ts), "k--", lw=0.8, label=f"e^(σt), σ = {p.real:.3f}"
        )
    a2.set(xlabel="t √(EI/ρAL⁴)", ylim=(1e-7, 1.0))
    a2.set_title("growth against the spectrum's Re p")
    a2.legend(fontsize=8)
    save(plt, fig, out, "rods_flutter.png")
