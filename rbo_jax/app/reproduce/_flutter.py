r"""Soft and hard flutter of the damped Nikolai problem (4.57), (4.84): the Bautin point on the
Hopf curve $M_c = 2b\sqrt{K(M_c)/A_1}$ (which does not depend on $A_3$) where the first Lyapunov
coefficient changes sign, its second Lyapunov coefficient against the folds of cycles near it
(normal form $\rho' = \rho(\mu + \ell_1\rho^2 + \ell_2\rho^4)$: $M^* - M_c \to
\omega\ell_1^2/(4\ell_2\sigma)$), the fold of cycles on the hard side, the hysteresis loop of a
quasi-static load against it, and the soft/hard map over $(A_3, b)$."""

from __future__ import annotations

import numpy as np

from ...analytic import nikolai_bending_stiffness, nikolai_equilibrium
from ...bifurcation import (
    bautin_point,
    continue_limit_cycles,
    flutter_map,
    hopf_point,
    hysteresis_loop,
)
from ...problems import nikolai_model
from ._common import Check, K, fmt, save

A1, C, D, B = 1.0, 1.0, 2.0, 0.1
SECTION = "flutter (4.57), (4.84)"


def _model_fn(M, b, c, A3):
    """The damped Nikolai problem; one function for every call (one program of each kind)."""
    return nikolai_model(M, c, D, A1=A1, A3=A3, k=K, friction=b)


def _bautin_checks():
    bp = bautin_point(_model_fn, {"b": B, "c": C}, ("M", "A3"), (0.2, 1.2))
    M_B, A3_B = (float(v) for v in bp.value)
    K_B = float(nikolai_bending_stiffness(C, D, M_B))
    lo, hi = (hopf_point(_model_fn, {"b": B, "c": C, "A3": a}, "M", 0.2) for a in (1.0, 1.6))
    l_lo, l_hi = float(lo.first_lyapunov), float(hi.first_lyapunov)
    line = 1.0 - l_lo * 0.6 / (l_hi - l_lo)  # l1 is linear in A3 (the gyroscopic term only)
    l2 = float(bp.second_lyapunov)
    checks = [
        Check(
            SECTION,
            f"Bautin point (l1 = 0 on the Hopf curve in (M, A3)), b = {B}: M_B",
            f"2b√(K(M)/A1) = {2 * B * np.sqrt(K_B / A1):.12f}",
            f"{M_B:.12f}",
            abs(M_B - 2 * B * np.sqrt(K_B / A1)),
            1e-10,
        ),
        Check(
            SECTION,
            "Bautin point: A3_B vs the root of the line through l1 of two Hopf points "
            f"(A3 = 1.0: {l_lo:.3e}, 1.6: {l_hi:.3e})",
            f"{line:.10f}",
            f"{A3_B:.10f}",
            abs(A3_B - line),
            1e-9,
        ),
    ]
    return checks, bp, l2


def _fold_ratio(bp, l2, dA3):
    """(M* − M_c) / (ω l1²/(4 l2 σ)) at A3 = A3_B + dA3."""
    params = {"b": B, "c": C, "A3": float(bp.value[1]) + dA3}
    h = hopf_point(_model_fn, params, "M", 0.2)
    l1, omega, sigma = float(h.first_lyapunov), float(h.frequency), float(h.transversality)
    cycles = continue_limit_cycles(
        _model_fn, params, "M", h, amplitude=0.01, ds_max=0.05, max_points=40
    )
    folds = cycles["special_value"].values[cycles["special_type"].values == "fold"]
    if folds.size != 1:
        return np.nan
    return (folds[0] - float(h.value)) / (omega * l1**2 / (4 * l2 * sigma))


def _l2_check(bp, l2):
    r04, r02 = _fold_ratio(bp, l2, 0.04), _fold_ratio(bp, l2, 0.02)
    extrapolated = 2 * r02 - r04
    return Check(
        SECTION,
        f"second Lyapunov coefficient l2 = {l2:.6e}: folds of cycles at A3_B + 0.04, + 0.02 "
        f"over ω l1²/(4 l2 σ) ({r04:.4f}, {r02:.4f}), extrapolated to l1 → 0",
        "1",
        f"{extrapolated:.4f}",
        abs(extrapolated - 1),
        0.02,
    )


def _hard_side(out, plt):
    """The fold of cycles at A3 = 2 and the hysteresis loop against it."""
    params = {"b": B, "c": C, "A3": 2.0}
    h = hopf_point(_model_fn, params, "M", 0.2)
    cycles = continue_limit_cycles(
        _model_fn, params, "M", h, amplitude=0.02, ds_max=0.3, max_points=28
    )
    folds = cycles["special_value"].values[cycles["special_type"].values == "fold"]
    M_c, fold = float(h.value), float(folds[0]) if folds.size == 1 else np.nan
    up = np.arange(0.165, 0.2301, 0.0025)
    loop = hysteresis_loop(
        _model_fn, params, "M", np.concatenate([up, up[::-1][1:]]),
        nikolai_equilibrium(0.165, D, K), np.zeros(3),
    )  # fmt: skip
    rising, amp, M = loop["direction"].values > 0, loop["amplitude"].values, loop["M"].values
    jump = M[rising][np.argmax(amp[rising] > 0.5)]
    on_cycle = bool(np.all(amp[~rising][M[~rising] > fold] > 1.0))
    rest = bool(np.all(amp[~rising][M[~rising] < fold - 0.008] < 1e-2))
    if plt is not None:
        from ...plotting import plot_hysteresis

        ax = plot_hysteresis(loop, cycles, hopf_value=M_c, title="hard flutter, A3 = 2")
        save(plt, ax.figure, out, "hysteresis.png")
    return [
        Check(
            SECTION,
            f"fold of cycles on the hard side (A3 = 2, l1 = {fmt(float(h.first_lyapunov))}) "
            "below the Hopf point (error: 1 unless M* < M_c)",
            f"M* < M_c = {M_c:.6f}",
            f"M* = {fold:.6f}",
            float(not fold < M_c),
            0.0,
        ),
        Check(
            SECTION,
            "hysteresis under a quasi-static load (fast_simulate): at rest up to M_c, on the "
            "large cycle down to M*, at rest below (error: the number of these that fail)",
            "jump at M > M_c, fall at M < M*",
            f"jump at {jump:.4f}, on the cycle above M*: {on_cycle}, at rest below: {rest}",
            float((not jump > M_c) + (not on_cycle) + (not rest)),
            0.0,
        ),
    ]


def _map(out, plt):
    """Soft/hard over (A3, b): hard exactly above the Bautin curve."""
    fmap = flutter_map(
        _model_fn, {"c": C}, "M", 0.2,
        {"A3": np.linspace(0.5, 2.5, 9), "b": np.linspace(0.05, 0.2, 4)},
    )  # fmt: skip
    above = fmap["A3"].values[:, None] > fmap["bautin_A3"].values[None, :]
    wrong = int(np.sum(fmap["hard"].values != above))
    if plt is not None:
        from ...plotting import plot_flutter_map

        ax = plot_flutter_map(fmap, title="Nikolai problem with friction: soft and hard flutter")
        save(plt, ax.figure, out, "flutter_map.png")
    return Check(
        SECTION,
        "soft/hard flutter map (A3 × b = 9 × 4): points on the wrong side of the Bautin curve",
        "0",
        str(wrong),
        float(wrong),
        0.0,
    )


def flutter(out: str, plt) -> list[Check]:
    """The full run only (four programs of their own to compile)."""
    checks, bp, l2 = _bautin_checks()
    checks.append(_l2_check(bp, l2))
    checks += _hard_side(out, plt)
    checks.append(_map(out, plt))
    return checks
