r"""Beyond linear stability: the Hopf point of the Nikolai problem with friction (4.57), (4.84)
against the closed form $M_{cr} = 2b\sqrt{K(M_{cr})/A_1}$, $\omega = \sqrt{K/A_1}$ ((4.69) with
friction: $(A_1p^2 + bp + K)^2 + M^2/4 = 0$), the sign of its first Lyapunov coefficient, its
detection by the continuation of equilibria, and the bifurcation diagram. The full run adds the
Floquet multipliers of a regular precession (4.110)–(4.113) against $e^{\lambda T}$ of the
rotating-frame exponents (4.115)–(4.118), the derivative $dM_{cr}/db$ (implicit function
theorem) against finite differences and the closed form, the family of limit cycles against the
Hopf normal form, and the flutter boundary in $b$ against the closed form and a stability map."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ...analytic import nikolai_bending_stiffness, nikolai_equilibrium
from ...batch import stability_map
from ...bifurcation import (
    continue_equilibria,
    continue_hopf,
    continue_limit_cycles,
    floquet_multipliers,
    hopf_point,
)
from ...foundations import QuadraticFoundation
from ...inertia import transversely_isotropic_inertia
from ...models.rigid_body import RigidBodyOscillator
from ...precession import precession_spectrum, regular_precession
from ...problems import nikolai_model
from ._common import Check, K, fmt, save

A1, C, D = 1.0, 1.0, 2.0
SECTION = "Hopf (4.69), (4.84)"


def _model_fn(M, b):
    """The Nikolai problem with friction; one function for every call, so that each program of
    the bifurcation module compiles once."""
    return nikolai_model(M, C, D, A1=A1, A3=0.6, k=K, friction=b)


def _K(M):
    return nikolai_bending_stiffness(C, D, M)


def _hopf(b):
    return hopf_point(_model_fn, {"b": b}, "M", 2 * b * jnp.sqrt(C / A1))


def _hopf_checks(bs):
    checks = []
    for b in bs:
        h = _hopf(b)
        M, w = float(h.value), float(h.frequency)
        K_cr = float(_K(M))
        checks.append(
            Check(
                SECTION,
                f"critical follower moment (Hopf point), b = {b}",
                f"2b√(K(M)/A1) = {2 * b * np.sqrt(K_cr / A1):.12f}",
                f"{M:.12f}",
                abs(M - 2 * b * np.sqrt(K_cr / A1)),
                1e-12,
            )
        )
        checks.append(
            Check(
                SECTION,
                f"Hopf frequency ω, b = {b}",
                f"√(K/A1) = {np.sqrt(K_cr / A1):.12f}",
                f"{w:.12f}",
                abs(w - np.sqrt(K_cr / A1)),
                1e-12,
            )
        )
    h = _hopf(0.1)
    l1 = float(h.first_lyapunov)
    checks.append(
        Check(
            SECTION,
            "first Lyapunov coefficient ℓ1, b = 0.1 (error: 1 unless ℓ1 < 0)",
            "ℓ1 < 0: supercritical, soft flutter",
            fmt(l1),
            float(not l1 < 0),
            0.0,
        )
    )
    return checks, h


def _gradient_check():
    """dM_cr/db by jax.grad (implicit function theorem) against central differences and the
    implicit derivative of the closed form G(M, b) = M − 2b√(K(M)/A1) = 0."""
    b, eps = 0.1, 1e-6

    def value(b):
        return _hopf(b).value

    g = float(jax.grad(value)(b))
    fd = float((value(b + eps) - value(b - eps)) / (2 * eps))
    M = float(value(b))
    K_cr, dK = float(_K(M)), float(jax.grad(_K)(M))
    closed = 2 * np.sqrt(K_cr / A1) / (1 - b * dK / np.sqrt(A1 * K_cr))
    return [
        Check(
            SECTION,
            "dM_cr/db by jax.grad through hopf_point, b = 0.1, vs central differences (ε = 1e-6)",
            f"{fd:.10f}",
            f"{g:.10f}",
            abs(g - fd),
            1e-7,
        ),
        Check(
            SECTION,
            "dM_cr/db vs the implicit derivative of M = 2b√(K(M)/A1)",
            f"2√(K/A1)/(1 − bK'/√(A1K)) = {closed:.10f}",
            f"{g:.10f}",
            abs(g - closed),
            1e-9,
        ),
    ]


def _match(mu, expected):
    """``expected`` reordered to pair each multiplier with its nearest expected value."""
    left, out = list(expected), []
    for m in mu:
        j = int(np.argmin([abs(m - e) for e in left]))
        out.append(left.pop(j))
    return np.array(out)


def _floquet_checks():
    """Floquet multipliers of a regular precession vs exp(λT), T = 2π/ψ̇ the period in the body
    frame, λ the rotating-frame exponents. The double exponent 0 (the neighbouring precessions
    and the phase: a Jordan block) splits under the solver's error like its square root."""
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(A1, 0.6, K), QuadraticFoundation(C, D, K)
    )
    pr = regular_precession(model, 0.5)
    T = 2 * np.pi / float(pr.rate)
    mu = np.asarray(floquet_multipliers(model, pr.theta0, pr.Omega0, T, rtol=1e-12, atol=1e-12))
    lam = np.asarray(precession_spectrum(model, pr))
    expected = _match(mu, np.exp(lam * T))
    trivial = np.abs(lam[np.argsort(np.abs(lam))[:2]]).max()
    near_one = np.abs(expected - 1) < 1e-3
    nontrivial = float(np.max(np.abs(mu[~near_one] - expected[~near_one])))
    split = float(np.max(np.abs(mu[near_one] - 1)))
    return [
        Check(
            "4.7 (4.115)-(4.118)",
            "Floquet multipliers of the regular precession ϑ = 0.5 (monodromy by forward "
            "mode) vs exp(λT), T = 2π/ψ̇: the four non-trivial ones",
            "exp(λT), λ of the rotating-frame spectrum",
            f"max |Δμ| = {nontrivial:.1e}",
            nontrivial,
            1e-7,
        ),
        Check(
            "4.7 (4.115)-(4.118)",
            f"the double multiplier 1 (λ = 0 twice, |λ| ≤ {trivial:.0e}; a Jordan block "
            "splits like √(solver error))",
            "1 (double)",
            f"max |μ − 1| = {split:.1e}",
            split,
            1e-4,
        ),
    ]


def _cycle_checks(h, cycles):
    """Limit cycles near the Hopf point: amplitude² against the normal form."""
    sigma, omega, l1 = (float(h.transversality), float(h.frequency), float(h.first_lyapunov))
    q = np.asarray(h.eigenvector)[:3]
    phase = np.exp(1j * np.linspace(0.0, 2 * np.pi, 4001))
    a_q = np.max(np.linalg.norm(np.real(phase[:, None] * q[None, :]), axis=1))
    slope = 4 * a_q**2 * (-sigma / (omega * l1))
    dM = cycles["M"].values[1:4] - float(h.value)
    ratio = cycles["amplitude"].values[1:4] ** 2 / dM / slope
    trivial = float(np.nanmax(cycles["trivial_multiplier_error"].values))
    return [
        Check(
            SECTION,
            "limit cycles next to the Hopf point (b = 0.1): amplitude²/(M − M_H)",
            f"normal form 4a²σ/(−ωℓ1), a = max|Re(e^(iφ)q_θ)|: {slope:.4f}",
            " ".join(f"{r * slope:.4f}" for r in ratio),
            float(np.max(np.abs(ratio - 1))),
            1e-2,
        ),
        Check(
            SECTION,
            "limit cycles: trivial Floquet multiplier",
            "1",
            f"max |μ − 1| = {trivial:.1e}",
            trivial,
            1e-7,
        ),
        Check(
            SECTION,
            "limit cycles beyond M_H orbitally stable (fraction)",
            "1 (ℓ1 < 0)",
            fmt(float(cycles["stable"].values[1:].mean())),
            1 - float(cycles["stable"].values[1:].mean()),
            0.0,
        ),
    ]


def _boundary(out, plt):
    """The flutter boundary M_cr(b) by continue_hopf against the closed form and a map."""
    from ...plotting import plot_hopf_boundary

    bs = np.linspace(0.4, 0.02, 39)
    curve = continue_hopf(_model_fn, {}, "M", 0.8, along="b", values=bs)
    M = curve["M"].values
    err = float(np.max(np.abs(M - 2 * bs * np.sqrt(np.asarray(_K(M)) / A1))))
    smap = stability_map(
        _model_fn,
        {"M": np.linspace(0.0, 1.0, 51), "b": bs[::-1]},
        theta_eq_fn=lambda M, b: nikolai_equilibrium(M, D, K),
    )
    a = smap["spectral_abscissa"].transpose("M", "b").values
    Ms = smap["M"].values
    edge = M[::-1]  # the map's b axis is increasing
    step = Ms[1] - Ms[0]
    below, above = Ms[:, None] < edge - step, Ms[:, None] > edge + step
    wrong = int(np.sum(a[below] >= 0) + np.sum(a[above] <= 0))
    if plt is not None:
        ax = plot_hopf_boundary(curve, smap, title="flutter boundary by continue_hopf, c = 1")
        save(plt, ax.figure, out, "hopf_boundary.png")
    return [
        Check(
            SECTION,
            "flutter boundary by continue_hopf, b ∈ [0.02, 0.4] (39 points)",
            "M = 2b√(K(M)/A1)",
            f"max |ΔM| = {err:.1e}",
            err,
            1e-12,
        ),
        Check(
            SECTION,
            "stability map (51 × 39) points more than one M step off the boundary "
            "on the wrong side",
            "0",
            str(wrong),
            float(wrong),
            0.0,
        ),
    ]


def bifurcation(out: str, plt, quick: bool) -> list[Check]:
    """The quick run (one compiled Hopf solver and the equilibrium continuation) checks the
    Hopf points and draws the diagram of the equilibria; the full run adds the Floquet
    multipliers, the derivative, the limit cycles and the flutter boundary (each a program of
    its own to compile)."""
    checks, h = _hopf_checks((0.05, 0.1, 0.2))
    eq = continue_equilibria(_model_fn, {"b": 0.1}, "M", 0.15, 0.25, ds=0.01, ds_max=0.01)
    hopfs = eq["special_value"].values[eq["special_type"].values == "hopf"]
    found = abs(float(hopfs[0]) - float(h.value)) if hopfs.size == 1 else np.inf
    checks.append(
        Check(
            SECTION,
            "Hopf points detected by continue_equilibria, M ∈ [0.15, 0.25]",
            f"one, at hopf_point's M = {float(h.value):.10f}",
            f"{hopfs.size} at {np.round(hopfs, 10)}",
            found,
            1e-10,
        )
    )
    cycles = None
    if not quick:
        checks += _floquet_checks()
        checks += _gradient_check()
        cycles = continue_limit_cycles(_model_fn, {"b": 0.1}, "M", h, amplitude=0.02, max_points=10)
        checks += _cycle_checks(h, cycles)
        checks += _boundary(out, plt)
    if plt is not None:
        from ...plotting import plot_bifurcation_diagram

        ax = plot_bifurcation_diagram(
            eq,
            cycles,
            title="Nikolai problem with friction b = 0.1: "
            "equilibria" + ("" if cycles is None else " and limit cycles"),
        )
        save(plt, ax.figure, out, "bifurcation_diagram.png")
    return checks
