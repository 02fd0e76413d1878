r"""Section 4.8 (media of rigid bodies): lattices of rigid body oscillators, :mod:`rbo_jax.lattice`.

The Bloch branches of a chain at rest against their closed forms
$\omega^2 = (c + 4\kappa_b\sin^2\frac q2)/A_1$ (bending, double) and
$(d + 4\kappa_t\sin^2\frac q2)/A_3$ (torsion); the Bloch matrix at $q = 0$ against one body's roots
(4.69); without friction every wave of a loaded chain grows (the Nikolai paradox), with friction a
band of long waves flutters above the body's Hopf load, its growth at $q = 0$ the body's; the
sine-Gordon kink's speed and energy $8\sqrt{c\kappa}/\sqrt{1 - v^2/s^2}$; Kelvin's spinning twist,
an exact solution. Two compiled programs: the spectra (vmapped over wavenumbers and loads) and the
motion (the kink's ring and Kelvin's medium differ only in parameter values: the foundation's
stiffness 0 for Kelvin's).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..._programs import jit
from ...analytic import nikolai_bending_stiffness, nikolai_equilibrium, nikolai_spectrum
from ...foundations import CosineFoundation, QuadraticFoundation
from ...inertia import transversely_isotropic_inertia
from ...lattice import bloch_blocks, chain, dispersion, kink, simulate, twist
from ...models.rigid_body import RigidBodyOscillator
from ...problems import nikolai_model
from ._common import Check, K, fmt, save

SECTION = "4.8 lattice"
A1, A3, C, D, KB, KT = 1.0, 0.6, 1.0, 2.0, 0.7, 0.3
B = 0.1  # friction of the flutter band
N_CHAIN = 16  # a chain's length: its Bloch waves do not depend on it
TOL = dict(rtol=1e-11, atol=1e-12)


def _closed_form(qs):
    """The branches of the chain at rest, (Q, 2): bending (double) and torsion."""
    s = np.sin(np.asarray(qs) / 2) ** 2
    return np.stack([np.sqrt((C + 4 * KB * s) / A1), np.sqrt((D + 4 * KT * s) / A3)], -1)


@functools.partial(jit, small=True)
def _spectra(qs, Ms, b):
    """The six eigenvalues of the Bloch matrix of a chain of Nikolai bodies (4.57) with friction
    ``b`` (4.84), about theta = (M/d) k (4.62): (len(qs), len(Ms), 6). M = b = 0: the bodies
    on the foundation (4.50) alone."""

    def at_load(M):
        body = nikolai_model(M, C, D, A1=A1, A3=A3, k=K, friction=b)
        lat = chain(N_CHAIN, body, QuadraticFoundation(KB, KT, K))
        blocks = bloch_blocks(lat, nikolai_equilibrium(M, D, K))
        return jax.vmap(lambda q: dispersion(lat, q, blocks=blocks))(qs)

    return jax.vmap(at_load, out_axes=1)(Ms)


def _by_frequency(z):
    return (round(z.imag, 8), round(z.real, 8))


def _hopf_load():
    """One body's Hopf load M = 2b sqrt(K(M)/A1) (fixed-point iteration)."""
    M = 2 * B * np.sqrt(C / A1)
    for _ in range(50):
        M = 2 * B * np.sqrt(float(nikolai_bending_stiffness(C, D, M)) / A1)
    return M


def _body_growth(M):
    """The largest real part of the roots of (A1 p² + bp + K)² + M²/4 = 0 and A3 p² + bp + d."""
    Kb = float(nikolai_bending_stiffness(C, D, M))
    roots = np.concatenate(
        [np.roots([A1, B, Kb + 0.5j * M]), np.roots([A1, B, Kb - 0.5j * M]), np.roots([A3, B, D])]
    )
    return roots.real.max()


def _band_violations(growth, Ms, qs, M_H):
    """Points of the (q, M) map against one band 0 <= q < q*(M) above the Hopf load, none below,
    widening with M (loads within 0.01 of M_H are skipped)."""
    bad, edges = 0, []
    for j, M in enumerate(Ms):
        unstable = growth[:, j] > 0
        if M < M_H - 0.01:
            bad += int(unstable.sum())
        elif M > M_H + 0.01:
            n_band = int(np.argmin(unstable)) if not unstable.all() else len(qs)
            bad += int((~unstable[:n_band]).sum() + unstable[n_band:].sum()) + int(n_band == 0)
            edges.append(n_band)
    bad += int(np.sum(np.diff(edges) < 0)) + int(len(edges) < 2 or edges[-1] <= edges[0])
    return bad, [qs[min(e, len(qs) - 1)] for e in edges]


def _q0_error(lam_q0, M) -> float:
    """max |Delta lambda| between the Bloch matrix at q = 0 and the roots (4.69) of one body."""
    roots = np.asarray(nikolai_spectrum(A1, A3, C, D, M))
    ours = np.array(sorted(lam_q0, key=_by_frequency))
    return float(np.abs(ours - np.array(sorted(roots, key=_by_frequency))).max())


def _dispersion_checks(n_q: int, n_m: int, out, plt) -> list[Check]:
    qs = np.linspace(0.0, np.pi, n_q)
    Ms = np.linspace(0.0, 0.35, n_m)
    lam = np.asarray(_spectra(qs, Ms, jnp.asarray(0.0)))  # b an array: one program
    w = _closed_form(qs)
    expected = np.sort(np.stack([w[:, 0], w[:, 0], w[:, 1]], 1), 1)
    at_rest = lam[:, 0]
    err = float(np.abs(np.sort(at_rest.imag[:, 3:], 1) - expected).max())
    re = float(np.abs(at_rest.real).max())
    checks = [
        Check(
            SECTION,
            f"chain at rest, (4.50) and a quadratic coupling: Bloch branches at "
            f"{n_q} wavenumbers q ∈ [0, π], and no growth",
            "ω² = (c + 4κ_b sin²(q/2))/A1 (double), (d + 4κ_t sin²(q/2))/A3",
            f"max |Δω| = {err:.1e}, max |Re λ| = {re:.1e}",
            max(err, re),
            1e-12,
        )
    ]
    err = max(_q0_error(lam[0, j], M) for j, M in enumerate(Ms))
    checks.append(
        Check(
            SECTION,
            f"Bloch matrix at q = 0 of a chain of Nikolai bodies, {n_m} "
            "follower moments M ∈ [0, 0.35]",
            "roots of (4.69), one body",
            f"max |Δλ| = {err:.1e}",
            err,
            1e-12,
        )
    )
    growth = lam.real.max(-1)[:, 1:]
    frac = float(np.mean(growth > 0))
    checks.append(
        Check(
            SECTION,
            "no friction, M ≠ 0: fraction of (q, M) points with a growing wave",
            "1 (the Nikolai paradox at every wavenumber)",
            fmt(frac),
            1 - frac,
            0.0,
        )
    )
    lam_b = np.asarray(_spectra(qs, Ms, jnp.asarray(B)))
    growth_b = lam_b.real.max(-1)
    err = float(np.abs(growth_b[0] - [_body_growth(M) for M in Ms]).max())
    checks.append(
        Check(
            SECTION,
            f"friction b = {B}: growth rate at q = 0 (uniform motion)",
            "max Re p, (A1p² + bp + K)² + M²/4 = 0, A3p² + bp + d = 0",
            f"max |Δ| = {err:.1e}",
            err,
            1e-12,
        )
    )
    M_H = _hopf_load()
    bad, edges = _band_violations(growth_b, Ms, qs, M_H)
    checks.append(
        Check(
            SECTION,
            f"friction b = {B}: points off one flutter band 0 ≤ q < q*(M) "
            "above the body's Hopf load, widening with M",
            f"0 (none below M_H = {M_H:.5f})",
            f"{bad}; q* = " + ", ".join(f"{q:.2f}" for q in edges),
            float(bad),
            0.0,
        )
    )
    if plt is not None:
        _dispersion_figure(qs, Ms, at_rest, lam_b, w, out, plt)
    return checks


def _dispersion_figure(qs, Ms, at_rest, lam_b, w, out, plt):
    """The branches at rest with their closed forms, and the flutter band with friction."""
    from ...plotting import plot_dispersion

    fig = plt.figure(figsize=(12, 5), layout="constrained")
    grid = fig.add_gridspec(2, 2, height_ratios=(2, 1))
    ax_w = fig.add_subplot(grid[0, 1])
    plot_dispersion(
        None,
        qs,
        eigenvalues=at_rest,
        ax=fig.add_subplot(grid[:, 0]),
        closed_form={"bending (closed form)": w[:, 0], "torsion (closed form)": w[:, 1]},
        title="chain at rest: Bloch branches and closed forms",
    )
    plot_dispersion(
        None,
        qs,
        eigenvalues=lam_b[:, -1],
        ax=ax_w,
        growth_ax=fig.add_subplot(grid[1, 1], sharex=ax_w),
        title=f"Nikolai bodies, M = {Ms[-1]}, friction b = {B}: flutter band",
    )
    save(plt, fig, out, "lattice_dispersion.png")


def _waves(n_ring: int, t_end: float, n_samples: int, out, plt) -> list[Check]:
    """The sine-Gordon kink on a ring and Kelvin's spinning twist: one compiled solve."""
    c, kappa = 1.0, 25.0
    s = np.sqrt(kappa / A1)
    v = 0.5 * s
    gamma = 1.0 / np.sqrt(1.0 - (v / s) ** 2)
    ts = np.linspace(0.0, t_end, n_samples)

    def ring(c, A3, kb, kt):
        body = RigidBodyOscillator(transversely_isotropic_inertia(A1, A3, K), CosineFoundation(c))
        return chain(n_ring, body, QuadraticFoundation(kb, kt, K))

    x0 = n_ring / 3
    theta0, Omega0 = kink(n_ring, c, kappa, A1, x0=x0, v=v)
    traj = simulate(ring(c, A1, kappa, kappa), theta0, Omega0, ts, **TOL)
    phi = np.asarray(traj.theta)[..., 2]
    plane = float(np.abs(np.asarray(traj.theta)[..., :2]).max())
    i = np.argmax(phi > np.pi, axis=1)
    rows = np.arange(len(ts))
    centre = i - 1 + (np.pi - phi[rows, i - 1]) / (phi[rows, i] - phi[rows, i - 1])
    speed = float(np.polyfit(ts, centre, 1)[0])
    energy = np.asarray(traj.energy)
    E = 8 * np.sqrt(c * kappa) * gamma
    label = f"sine-Gordon kink, λ = √(κ/c) = 5, v = s/2, ring of {n_ring} bodies, t ≤ {t_end:g}"
    checks = [
        Check(
            SECTION,
            f"{label}: speed of its centre (fitted)",
            f"v = {v:g}",
            f"{speed:.5f}",
            abs(speed / v - 1) if plane == 0.0 else np.inf,
            1e-2,
        ),
        Check(
            SECTION,
            f"{label}: energy",
            f"8√(cκ)/√(1 − v²/s²) = {E:.5f}",
            f"{energy[0]:.5f}",
            abs(energy[0] / E - 1),
            2e-3,
        ),
        Check(
            SECTION,
            f"{label}: energy drift of DOP853 (rtol 1e-11), relative",
            "0",
            f"{np.ptp(energy) / energy[0]:.1e}",
            float(np.ptp(energy) / energy[0]),
            1e-9,
        ),
    ]
    m, spin = 2, 1.7
    theta0, Omega0 = twist(n_ring, m, spin)
    tw = simulate(ring(0.0, A3, 0.9, 0.4), theta0, Omega0, ts, **TOL)
    theta = np.asarray(tw.theta)
    exact = theta0[:, 2][None, :] + spin * ts[:, None]
    err = max(float(np.abs(theta[..., 2] - exact).max()), float(np.abs(theta[..., :2]).max()))
    checks.append(
        Check(
            SECTION,
            f"Kelvin's medium (no foundation): spinning twist, m = {m} "
            f"twists, Ω = {spin}, through |θ| = 2π",
            "θ_n = (2πmn/N + Ωt)k (exact)",
            f"max |Δθ| = {err:.1e}",
            err,
            1e-8,
        )
    )
    if plt is not None:
        from ...plotting import plot_space_time

        ax = plot_space_time(
            traj, "z", title=f"sine-Gordon kink on a ring of {n_ring} bodies, v = s/2"
        )
        ax.plot(x0 + v * ts, ts, "w--", lw=1.2, label=r"$x_0 + vt$")
        ax.legend(loc="upper left", fontsize=8)
        save(plt, ax.figure, out, "lattice_kink.png")
    return checks


def lattice(out: str, plt, quick: bool) -> list[Check]:
    """The quick run checks everything at small sizes; the full run at finer grids and on a
    longer, larger ring. Either compiles the same two programs, most of its time."""
    if quick:
        return _dispersion_checks(13, 8, out, plt) + _waves(96, 6.4, 17, out, plt)
    return _dispersion_checks(61, 36, out, plt) + _waves(160, 12.0, 49, out, plt)
