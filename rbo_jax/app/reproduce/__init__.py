r"""``rbo-jax reproduce``: reproduce the results of the paper and write ``out/report.md``.

Every check compares a quantity computed by rbo_jax with the paper's value or closed form (or an
independent computation: scipy integration of the reduced equations, the Euler-angle equations of
section 4.6.3) and passes when the error is below a stated tolerance. Figures are written next to
the report. The exit status is non-zero if any check fails. One module per part of the paper:
``_kinematics`` (4.2), ``_nikolai`` (4.4–4.5), ``_dynamics`` (4.3–4.6), ``_precession`` (4.7),
``_fitting``, ``_bifurcation`` (Hopf points, Floquet multipliers, continuation), ``_flutter``
(Bautin point, folds of cycles, hysteresis; full run only), ``_lattice``
(4.8: chains of bodies, their waves, the sine-Gordon kink and Kelvin's medium), ``_rods`` (rods
of bodies that turn and translate: the elastica, Euler's, Beck's, Pflüger's columns, Ziegler's
pendulum, flutter motion).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

from .._outputs import write_text
from ._bifurcation import bifurcation
from ._common import Check
from ._dynamics import balance_and_energy, simplest
from ._fitting import fitting
from ._flutter import flutter
from ._kinematics import kinematics
from ._lattice import lattice
from ._nikolai import nikolai
from ._precession import precession
from ._rods import rods

__all__ = ["Check", "run_reproduction"]


def run_reproduction(
    out: str = "out",
    *,
    quick: bool = False,
    figures: bool = True,
    log: Callable[[str], None] = print,
) -> list[Check]:
    """Run every reproduction check, write ``out/report.md`` (and PNG figures), return checks."""
    os.makedirs(out, exist_ok=True)
    plt = None
    if figures:
        try:
            import matplotlib.pyplot as plt
        except ImportError:
            log("matplotlib not installed: no figures (pip install 'rbo_jax[plot]').")
    start = time.perf_counter()
    steps = [
        ("kinematics (4.2)", lambda: kinematics(50 if quick else 1000)),
        ("Nikolai paradox (4.4)-(4.5)", lambda: nikolai(9 if quick else 61, out, plt)),
        ("balance (4.78) and energy", balance_and_energy),
        ("simplest oscillator (4.6)", lambda: simplest(out, plt)),
        ("regular precession (4.7)", lambda: precession(out, plt)),
        ("fitting", fitting),
        ("bifurcations: Hopf points, continuation", lambda: bifurcation(out, plt, quick)),
        *(
            []
            if quick
            else [
                (
                    "hard and soft flutter: Bautin point, folds, hysteresis",
                    lambda: flutter(out, plt),
                )
            ]
        ),
        (
            "lattices of bodies (4.8): waves, kink, Kelvin's medium",
            lambda: lattice(out, plt, quick),
        ),
        (
            "rods: elastica, Euler, Beck, Pflüger, Ziegler, flutter motion",
            lambda: rods(out, plt, quick),
        ),
    ]
    checks: list[Check] = []
    for i, (name, fn) in enumerate(steps, 1):
        t0 = time.perf_counter()
        log(f"[{i}/{len(steps)}] {name} ...")
        new = fn()
        checks += new
        bad = sum(not c.passed for c in new)
        log(f"      {len(new)} checks, {bad} failed ({time.perf_counter() - t0:.1f} s)")
    elapsed = time.perf_counter() - start
    _write_report(out, checks, elapsed, quick, plt is not None)
    return checks


def _write_report(out, checks, elapsed, quick, figures):
    lines = [
        "# rbo_jax: reproduction of the paper",
        "",
        "P. A. Zhilin, *Rigid body oscillator: a general model and some results*; equation numbers "
        "refer to its section 4, read as docs/readings.md of the rbo_jax repository says.",
        "",
        f"{sum(c.passed for c in checks)} of {len(checks)} checks passed in {elapsed:.1f} s"
        + (" (quick mode)" if quick else "")
        + ".",
        "",
        "| section | quantity | paper | ours | error | tolerance | |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in checks:
        lines.append(
            f"| {c.section} | {c.quantity} | {c.paper} | {c.ours} | {c.error:.2e} | "
            f"{c.tolerance:.0e} | {'pass' if c.passed else '**FAIL**'} |"
        )
    if figures:
        lines += ["", "## Figures", ""]
        for name, caption in [
            ("map_M_c.png", "Stability map of the Nikolai problem over (M, c/d), A3/A1 = 0.6"),
            ("map_M_A3.png", "Stability map over (M, A3/A1), c/d = 1"),
            ("root_locus.png", "Root locus against the follower moment M"),
            ("nikolai_growth.png", "Simulated growth vs max Re p of (4.69)"),
            (
                "simplest_oscillator.png",
                "Simplest oscillator: (4.99), (4.101) and the Euler-angle equations",
            ),
            ("precession_growth.png", "Unstable regular precession vs its rotating-frame spectrum"),
            (
                "bifurcation_diagram.png",
                "Bifurcation diagram of the Nikolai problem with friction: equilibria, Hopf point "
                "and (full run) the limit cycles",
            ),
            ("hopf_boundary.png", "Flutter boundary by continue_hopf over the stability map"),
            ("flutter_map.png", "Soft and hard flutter over (A3, b) with the Bautin curve"),
            ("hysteresis.png", "Hysteresis of a quasi-static follower moment over the cycles"),
            (
                "lattice_dispersion.png",
                "Chain of bodies: Bloch branches at rest against the closed forms; the flutter "
                "band of Nikolai bodies with friction",
            ),
            (
                "lattice_kink.png",
                "Space-time image of a moving sine-Gordon kink on a ring of bodies, with x0 + vt",
            ),
            ("rods_statics.png", "Rods: the elastica at α = 1, 2, 5, 10 and the closed circle"),
            (
                "rods_stability.png",
                "Rods: Beck's column against Kelvin–Voigt damping (the flutter load halves), "
                "Pflüger's against its tip mass, Ziegler's pendulum against its dampers",
            ),
            (
                "rods_flutter.png",
                "Rods: Beck's column past its flutter load, the tip's growth against the spectrum",
            ),
        ]:
            if os.path.exists(os.path.join(out, name)):
                lines += [f"![{caption}]({name})", "", f"*{caption}*", ""]
    write_text(os.path.join(out, "report.md"), "\n".join(lines) + "\n")  # whole or not at all
