"""Sections 4.4–4.5: the Nikolai paradox. Stability maps against the closed form (4.69), the
linear theory (4.73)–(4.74) that misses the instability, the root locus and the growth rate of a
simulated perturbation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ...analytic import nikolai_equilibrium, nikolai_spectrum
from ...batch import stability_map
from ...problems import nikolai_model
from ...simulate import simulate
from ...stability import spectrum
from ..spec import ModelSpec
from ._common import TIGHT, Check, K, fmt, save

# The Nikolai problem (4.57)-(4.62), d = A1 = 1, with M, c and A3 taken from the map's axes.
_MAP_MODEL = {
    "inertia": {"A1": 1.0, "A3": "A3"},
    "foundation": {"type": "quadratic", "c": "c", "d": 1.0},
    "loads": [{"type": "follower", "M": "M"}],
}


def _maps(n_grid: int):
    Ms = np.linspace(-0.8, 0.8, 2 * (n_grid // 2) + 1)
    axes1 = {"M": Ms, "c": np.linspace(0.2, 2.0, n_grid), "A3": np.array([0.6])}
    axes2 = {"M": Ms, "c": np.array([1.0]), "A3": np.linspace(0.2, 2.0, n_grid)}
    spec = ModelSpec.from_mapping(
        _MAP_MODEL, axes={n: np.concatenate([axes1[n], axes2[n]]) for n in axes1}
    )

    def model_fn(M, c, A3):
        return spec.build({"M": M, "c": c, "A3": A3})

    def theta_eq_fn(M, c, A3):
        return nikolai_equilibrium(M, 1.0, K)  # (4.62), d = 1

    return [stability_map(model_fn, ax, theta_eq_fn=theta_eq_fn) for ax in (axes1, axes2)]


def _map_checks(maps) -> list[Check]:
    err = 0.0
    for ds in maps:
        pts = np.stack(
            np.meshgrid(*[ds[k].values for k in ("M", "c", "A3")], indexing="ij"), -1
        ).reshape(-1, 3)
        ref = np.asarray(
            jax.jit(jax.vmap(lambda x: jnp.sort(nikolai_spectrum(1.0, x[2], x[1], 1.0, x[0]))))(
                jnp.asarray(pts)
            )
        )
        ours = ds["eigenvalues"].values.reshape(-1, 6)
        err = max(err, float(np.max(np.abs(np.sort_complex(ours) - np.sort_complex(ref)))))
    checks = [
        Check(
            "4.4 Nikolai",
            "autodiff spectrum vs bending/torsion roots of (4.69), all map points",
            "(A1p²+K)²+M²/4 = 0, A3p²+d = 0",
            f"max |Δp| = {err:.2e}",
            err,
            1e-10,
        )
    ]
    ab = maps[0]["spectral_abscissa"]
    nonzero = ab.sel(M=ab.M[np.abs(ab.M) > 1e-12])
    frac = float((nonzero > 0).mean())
    checks.append(
        Check(
            "4.4-4.5 Nikolai",
            "fraction of points with M ≠ 0 and max Re p > 0",
            "1 (unstable for every M ≠ 0)",
            fmt(frac),
            abs(1 - frac),
            0.0,
        )
    )
    # the linear theory (4.73)/(4.74): Aθ̈ + [c(E − k⊗k) + d k⊗k]θ = Mk, as a first-order system
    lin = 0.0
    for c in maps[0]["c"].values:
        A = np.diag([1.0, 1.0, 0.6])
        Kl = c * np.diag([1.0, 1.0, 0.0]) + np.diag([0.0, 0.0, 1.0])
        Jl = np.block([[np.zeros((3, 3)), np.eye(3)], [-np.linalg.solve(A, Kl), np.zeros((3, 3))]])
        lin = max(lin, float(np.max(np.linalg.eigvals(Jl).real)))
    ours = float(nonzero.min())
    checks.append(
        Check(
            "4.4 (4.73)-(4.74)",
            "max Re p of the linear theory (4.73) over the c grid",
            f"0: misses the instability (ours: min over M ≠ 0 of max Re p = {ours:.3g} > 0)",
            f"{lin:.2e}",
            abs(lin),
            1e-12,
        )
    )
    return checks


def _map_figures(maps, out, plt):
    from ...plotting import plot_root_locus, plot_stability_map

    for ds, (x, y, sel, name) in zip(
        maps, [("M", "c", {"A3": 0.6}, "map_M_c.png"), ("M", "A3", {"c": 1.0}, "map_M_A3.png")]
    ):
        ax = plot_stability_map(
            ds, x, y, select=sel, title=f"Nikolai problem: max Re p over ({x}, {y}/d)"
        )
        save(plt, ax.figure, out, name)
    Ms = np.linspace(-0.8, 0.8, 81)
    f = jax.jit(
        jax.vmap(
            lambda M: spectrum(nikolai_model(M, 1.0, 1.0, A3=0.6), nikolai_equilibrium(M, 1.0, K))
        )
    )
    ax = plot_root_locus(Ms, np.asarray(f(jnp.asarray(Ms))), label="follower moment M")
    save(plt, ax.figure, out, "root_locus.png")


def _growth(out, plt) -> Check:
    """A 1e-9 perturbation of the equilibrium grows at max Re p of (4.69)."""
    M, c, d = 0.5, 1.0, 2.0
    rate = float(np.max(np.real(nikolai_spectrum(1.0, 0.6, c, d, M))))
    ts = jnp.linspace(0.0, 100.0, 401)
    traj = simulate(
        nikolai_model(M, c, d, A3=0.6),
        nikolai_equilibrium(M, d, K) + jnp.array([1e-9, 0.0, 0.0]),
        jnp.zeros(3),
        ts,
        **TIGHT,
    )
    dev = np.linalg.norm(np.asarray(traj.theta)[:, :2], axis=1)
    t = np.asarray(ts)
    slope = np.polyfit(t[t > 30], np.log(dev[t > 30]), 1)[0]
    if plt is not None:
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.semilogy(t, dev, label="simulation |bending deviation|")
        ax.semilogy(
            t,
            dev[t > 30][0] * np.exp(rate * (t - t[t > 30][0])),
            "--",
            label="exp(max Re p · t), (4.69)",
        )
        ax.set_xlabel("t")
        ax.legend()
        ax.set_title(f"Nikolai paradox, follower M = {M}, c = {c}, d = {d}")
        save(plt, fig, out, "nikolai_growth.png")
    return Check(
        "4.4 Nikolai",
        "growth rate of a 1e-9 perturbation in a simulation",
        f"max Re p of (4.69) = {rate:.6f}",
        f"{slope:.6f}",
        abs(slope / rate - 1),
        0.02,
    )


def nikolai(n_grid: int, out: str, plt) -> list[Check]:
    maps = _maps(n_grid)
    checks = _map_checks(maps)
    if plt is not None:
        _map_figures(maps, out, plt)
    return checks + [_growth(out, plt)]
