r"""Rods (issue 32): chains of rigid body oscillators that turn and translate (:mod:`.lattice`).

Statics against the continuum: Timoshenko's cantilever $\delta = FL/(\kappa GA) + FL^3/(3EI)$,
the elastica's tip deflections at $\alpha = FL^2/EI$ = 1, 2, 5, 10 (0.30172, 0.49346, 0.71379,
0.81061 L), a tip moment $2\pi EI/L$ rolling the rod into a closed circle. Stability: Euler's
buckling $\pi^2EI/(4L^2)$, the cantilever's frequencies 3.51602 and 22.0345
$\sqrt{EI/(\rho AL^4)}$, Beck's flutter load $20.0509\,EI/L^2$, Pflüger's column against its tip
mass, Kelvin–Voigt damping lowering Beck's load to about $10.94\,EI/L^2$, Ziegler's pendulum at
$(7/2 - \sqrt2)\,c/l$ and with dampers $b$ at $41/28 + b^2/2$ (the paradox: $41/28$ as
$b \to 0$). Motion: Beck's column just past its flutter load, its tip's growth and frequency
against the spectrum. References in :mod:`._rod_references`.

EI = GJ = ρA = L = 1 throughout. Five compiled programs, each vmapped over its cases: the
statics (N = 40 bodies past the base, 20 load steps), the critical loads of the columns (N = 20;
a dead and a follower tip force, damping, tip mass, shear stiffness and rotary inertia traced),
their spectra (N = 20), Ziegler's pendulum, and one motion (N = 20, a softer shear and a larger
rotary inertia, so that an explicit method takes steps of reasonable size).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..._programs import jit
from ...lattice import (
    RodState,
    TipForce,
    TipMoment,
    critical_load,
    pendulum,
    rod,
    simulate,
    solve_equilibrium,
    spectrum,
)
from . import _rod_references as ref
from ._common import Check, fmt

SECTION = "rods"
N_STATICS = 40  # bodies of the statics; tip deflections second order in 1/N
N_COLUMN = 20  # bodies of the columns (Beck 20.196 at N = 20, 0.7 % high)
STIFF = 1e6  # shear and stretch stiffness of the columns: unshearable, inextensible to 1e-6
ROTARY = 1e-8  # their rotary inertia per length: Euler-Bernoulli's beam
SOFT = (1e3, 1e-3)  # shear/stretch stiffness and rotary inertia of the rod that moves
ELASTICA = {1.0: 0.30172, 2.0: 0.49346, 5.0: 0.71379, 10.0: 0.81061}  # alpha: delta/L
TIMOSHENKO = (1e-6, 50.0)  # a small tip force, and kGA of a shear-flexible cantilever
PFLUGER_MU = (0.1, 0.5, 1.0, 2.0)  # tip mass / rod mass
KV_ETA = (1e-3, 1e-2, 3e-2)  # Kelvin-Voigt times of Beck's column (bending and twist)
ZIEGLER_B = (1e-2, 3e-2, 0.1, 0.3)  # hinge dampers of Ziegler's pendulum (units of c s)


def _cantilever(n, loads, shear, stretch, rotary, **constants):
    """A clamped rod of ``n`` bodies, EI = GJ = ρA = L = 1, under ``loads``."""
    unit = dict(bending=1.0, torsion=1.0, mass=1.0)
    return rod(
        n, 1.0, shear=shear, stretch=stretch, rotary=rotary, loads=loads, **unit, **constants
    )


def _statics_rod(F, M, kGA):
    """A cantilever under a dead tip force F e1 and a dead tip moment M e2."""
    loads = (TipForce(jnp.stack([F, 0.0, 0.0])), TipMoment(jnp.stack([0.0, M, 0.0])))
    return _cantilever(N_STATICS, loads, kGA, STIFF, ROTARY)


@functools.partial(jit, fast_compile=True)
def _statics(F, M, kGA):
    """Equilibria of :func:`_statics_rod`, vmapped over the cases: (ok, centreline, tip turn)."""

    def one(F, M, kGA):
        sol = solve_equilibrium(_statics_rod(F, M, kGA), steps=20)
        return sol.ok, sol.state.centreline, sol.state.theta[-1]

    return jax.vmap(one)(F, M, kGA)


def column(P, case):
    r"""Cantilever of N_COLUMN bodies under a compressive tip force P: a fraction ``f`` of it a
    follower (Beck), ``1 - f`` dead (Euler). ``case`` = (f, Kelvin–Voigt η in bending and twist,
    tip mass μρAL, shear = stretch stiffness, rotary inertia per length)."""
    f, eta, mu, stiff, rotary = case
    loads = (
        TipForce(jnp.stack([0.0, 0.0, -(1.0 - f) * P])),
        TipForce(jnp.stack([0.0, 0.0, -f * P]), follower=True),
    )
    return _cantilever(
        N_COLUMN, loads, stiff, stiff, rotary, damping=eta, shear_damping=0.0, tip_mass=mu
    )


@functools.partial(jit, fast_compile=True)
def _column_loads(cases, rtol):
    """Critical loads of :func:`column` for the rows of ``cases`` (scan of 16, 24 bisections)."""

    def one(case, rtol):
        return critical_load(lambda P: column(P, case), 30.0, n_scan=16, n_bisect=24, rtol=rtol)

    return jax.vmap(one)(cases, rtol)


_column_spectrum = jit(lambda P, case: spectrum(column(P, case)), fast_compile=True)


@functools.partial(jit, fast_compile=True)
def _ziegler_loads(b, rtol):
    """Critical loads of Ziegler's pendulum (masses 2, 1; links 1; hinge springs 1, dampers b)."""

    def one(b, rtol):
        def pend(P):
            load = TipForce(jnp.stack([0.0, 0.0, -P]), follower=True)
            return pendulum([2.0, 1.0], [1.0, 1.0], [1.0, 1.0], damping=b, loads=load)

        return critical_load(pend, 5.0, n_scan=16, n_bisect=30, rtol=rtol)

    return jax.vmap(one)(b, rtol)


def _rel(ours, ref_value) -> float:
    return abs(ours / ref_value - 1.0)


def _relative(quantity: str, paper: str, ours, exact, tolerance: float, spec=".6g") -> Check:
    """``ours`` against ``exact`` (relative), shown with the format ``spec``."""
    return Check(SECTION, quantity, paper, format(ours, spec), _rel(ours, exact), tolerance)


def _statics_checks(out, plt) -> list[Check]:
    F_t, kGA_t = TIMOSHENKO
    alphas = list(ELASTICA)
    F = jnp.array([F_t, *alphas, 0.0])
    M = jnp.array([0.0] * (1 + len(alphas)) + [2 * math.pi])
    kGA = jnp.array([kGA_t] + [STIFF] * (len(alphas) + 1))
    ok, lines, tip_turn = (np.asarray(x) for x in _statics(F, M, kGA))
    bad = np.inf if not ok.all() else 0.0
    exact = F_t / kGA_t + F_t / 3.0
    ours = lines[0, -1, 0]
    checks = [
        Check(
            SECTION,
            f"Timoshenko cantilever (κGA = {kGA_t:g}, F = {F_t:g}, N = {N_STATICS}): "
            "tip deflection, relative",
            f"FL/κGA + FL³/3EI = {exact:.6e}",
            f"{ours:.6e}",
            _rel(ours, exact) + bad,
            3e-4,
        )
    ]
    for k, alpha in enumerate(alphas, 1):
        checks.append(
            Check(
                SECTION,
                f"elastica, dead tip force α = FL²/EI = {alpha:g} (N = {N_STATICS}, "
                "20 load steps): tip deflection / L",
                f"{ELASTICA[alpha]}",
                f"{lines[k, -1, 0]:.6f}",
                abs(lines[k, -1, 0] - ELASTICA[alpha]) + bad,
                2e-4,
            )
        )
    nodes = lines[-1, :-1]
    side = 1.0 / N_STATICS
    radius = side / (2 * math.sin(math.pi / N_STATICS))  # the regular N-gon of side L/N
    radii = np.linalg.norm(nodes - nodes.mean(0), axis=1)
    closure = max(np.linalg.norm(lines[-1, -1]), np.linalg.norm(tip_turn[-1]))
    checks += [
        Check(
            SECTION,
            f"tip moment 2πEI/L (N = {N_STATICS}): the tip back at the base with its turn, "
            f"the nodes on a regular {N_STATICS}-gon of side L/N",
            "0; circumradius (L/N)/(2 sin(π/N))",
            f"|r_tip|, |θ_tip| ≤ {closure:.1e}; max |ΔR| = {np.abs(radii - radius).max():.1e}",
            max(closure, np.abs(radii - radius).max()) + bad,
            1e-9,
        ),
        Check(
            SECTION,
            f"tip moment 2πEI/L: circle's radius (N = {N_STATICS}), relative",
            f"L/(2π) = {1 / (2 * math.pi):.6f}",
            f"{radii.mean():.6f}",
            _rel(radii.mean(), 1 / (2 * math.pi)) + bad,
            2e-3,  # the 40-gon's own: (π/N)/sin(π/N) - 1 ≈ π²/(6N²) = 1.03e-3
        ),
    ]
    if plt is not None:
        from ._rods_figures import statics_figure

        statics_figure(plt, out, lines, alphas, ELASTICA)
    return checks


def _cases(quick: bool):
    """The rows of :func:`_column_loads` with their rtol, and the slices of each problem."""
    mus = PFLUGER_MU[2:3] if quick else PFLUGER_MU
    etas = KV_ETA[:1] if quick else KV_ETA
    rows = [(0.0, 0.0, 0.0, STIFF, ROTARY), (1.0, 0.0, 0.0, STIFF, ROTARY)]
    rows += [(1.0, 0.0, mu, STIFF, ROTARY) for mu in mus]
    rows += [(1.0, eta, 0.0, STIFF, ROTARY) for eta in etas]
    rows.append((1.0, 0.0, 0.0, *SOFT))
    rtol = [1e-9] * (2 + len(mus)) + [1e-12] * len(etas) + [1e-9]
    return np.array(rows), np.array(rtol), mus, etas


def _damping_checks(etas, Pc_eta) -> list[Check]:
    """Beck's column with Kelvin-Voigt damping against the Galerkin reference at the same η, the
    reference against Beck's load and the limit η → 0, and the paradox."""
    beck, limit = ref.column_galerkin(0.0), ref.column_galerkin(0.0, 1e-5)
    damped = (
        (
            f"Beck's column, Kelvin–Voigt damping η = {eta:g} in bending (N = {N_COLUMN}): "
            "flutter load, relative",
            f"{exact:.4f} (Galerkin at η)",
            ours,
            exact,
            2e-2,
        )
        for eta, ours, exact in zip(etas, Pc_eta, map(_galerkin_at, etas), strict=True)
    )
    rows = [
        *damped,
        (
            f"the reference: Galerkin ({ref.MODES} modes) of Beck's column",
            f"{ref.BECK} EI/L² (Beck)",
            beck,
            ref.BECK,
            1e-4,
            ".4f",
        ),
        (
            f"the reference: Galerkin ({ref.MODES} modes) at η = 1e-5",
            f"{ref.BECK_KV_LIMIT} EI/L² (η → 0)",
            limit,
            ref.BECK_KV_LIMIT,
            1e-3,
            ".4f",
        ),
        (
            f"the paradox: Beck's column at η = {etas[0]:g} against the limit η → 0, relative",
            f"{ref.BECK_KV_LIMIT} EI/L² (undamped: {ref.BECK})",
            Pc_eta[0],
            ref.BECK_KV_LIMIT,
            2e-2,
        ),
    ]
    return [_relative(*row) for row in rows]


def _galerkin_at(eta):
    return ref.column_galerkin(0.0, eta)


def _column_checks(quick: bool):
    """Euler, Beck, Pflüger, Beck with Kelvin-Voigt damping, the frequencies; returns the checks,
    the results the figures need and the critical load of the rod that moves."""
    rows, rtol, mus, etas = _cases(quick)
    Pc = np.asarray(_column_loads(jnp.asarray(rows), jnp.asarray(rtol)))
    p = np.asarray(_column_spectrum(jnp.asarray(0.0), jnp.asarray(rows[1])))
    w = np.sort(p.imag[p.imag > 1e-6])
    n = f"N = {N_COLUMN}"
    euler = math.pi**2 / 4
    checks = [
        _relative(
            f"Euler buckling, dead compressive tip force ({n}), relative",
            f"π²EI/4L² = {euler:.6f}",
            Pc[0],
            euler,
            2e-3,
        ),
    ]
    for k, exact in ((0, 3.51602), (2, 22.0345)):  # each twice: two planes of bending
        ours = w[k : k + 2]
        checks.append(
            Check(
                SECTION,
                f"cantilever frequency {k // 2 + 1} ({n}, both planes), relative",
                f"{exact} √(EI/ρAL⁴)",
                fmt(ours[0]),
                float(np.abs(ours / exact - 1).max()),
                1e-3,
            )
        )
    beck = (f"Beck's column, follower tip force ({n}): flutter load, relative", f"{ref.BECK} EI/L²")
    checks.append(_relative(*beck, Pc[1], ref.BECK, 1e-2))
    for mu, ours in zip(mus, Pc[2 : 2 + len(mus)], strict=True):
        exact = ref.column_galerkin(mu)
        checks.append(
            _relative(
                f"Pflüger's column, tip mass {mu:g} ρAL ({n}): flutter load, relative",
                f"{exact:.4f} (Galerkin, {ref.MODES} modes)",
                ours,
                exact,
                1e-2,
            )
        )
    checks += _damping_checks(etas, Pc[2 + len(mus) : -1])
    results = dict(Pc=Pc, mus=mus, etas=etas)
    return checks, results, float(Pc[-1]), rows[-1]


def _ziegler_checks(quick: bool):
    bs = np.array((0.0, *(ZIEGLER_B[:1] + ZIEGLER_B[2:3] if quick else ZIEGLER_B)))
    rtol = np.where(bs > 0, 1e-14, 1e-9)  # small damping: slow growth near the boundary
    Pc = np.asarray(_ziegler_loads(jnp.asarray(bs), jnp.asarray(rtol)))
    rows = [
        (
            "Ziegler's pendulum (masses 2m, m; links l; springs c), undamped: "
            "flutter load, relative",
            f"(7/2 − √2) c/l = {ref.ZIEGLER:.7f}",
            Pc[0],
            ref.ZIEGLER,
        ),
        *(
            (
                f"Ziegler's pendulum, equal hinge dampers b = {b:g} c·s: flutter load, relative",
                f"41/28 + b²/2 = {ref.ziegler_damped(b):.7f} c/l",
                ours,
                ref.ziegler_damped(b),
            )
            for b, ours in zip(bs[1:], Pc[1:], strict=True)
        ),
    ]
    return [_relative(*row, 1e-5, ".7f") for row in rows], dict(bs=bs, Pc=Pc)


def _compressed(P, stretch: float) -> RodState:
    """The straight equilibrium under a compressive tip force P: every gap shortened by
    P/EA (K^g = EA/h), at rest."""
    z = np.arange(N_COLUMN + 1) / N_COLUMN * (1.0 - P / stretch)
    r = np.stack([np.zeros_like(z), np.zeros_like(z), z], 1)
    return RodState.at_rest(np.zeros_like(r), r)


def _peaks(ts, x):
    """Times and heights of the local maxima of |x|, refined by a parabola through three
    samples."""
    a = np.abs(x)
    k = np.flatnonzero((a[1:-1] > a[:-2]) & (a[1:-1] >= a[2:])) + 1
    left, mid, right = a[k - 1], a[k], a[k + 1]
    shift = 0.5 * (left - right) / (left - 2 * mid + right)
    dt = ts[1] - ts[0]
    return ts[k] + shift * dt, mid - 0.25 * (left - right) * shift


def _flutter_checks(P_sim, case, quick: bool):
    """Beck's column 5 % past its flutter load, kicked at the tip: the tip's growth rate and
    frequency (the peaks of |x| from 30 times the first one to 1e-2 L) against the unstable
    eigenvalue."""
    P = 1.05 * P_sim
    p = np.asarray(_column_spectrum(jnp.asarray(P), jnp.asarray(case)))
    unstable = p[np.argmax(p.real + 1e-9 * np.abs(p.imag))]  # p = σ + iω, ω > 0
    state0 = _compressed(P, case[3])
    state0 = RodState(state0.theta, state0.r, state0.Omega, state0.v.at[-1, 0].set(1e-4))
    t_end = 4.5 if quick else 8.0
    ts = np.linspace(0.0, t_end, int(t_end * 100) + 1)
    traj = simulate(column(jnp.asarray(P), jnp.asarray(case)), state0, ts, throw=False)
    x = np.asarray(traj.centreline[:, -1, 0])
    tp, hp = _peaks(ts, x)
    window = (hp > 30 * hp[0]) & (hp < 1e-2)  # past the kick's neutral modes, still linear
    sigma = omega = np.nan  # a failed solve or too few peaks: the checks fail
    if bool(traj.ok) and window.sum() >= 3:
        sigma = float(np.polyfit(tp[window], np.log(hp[window]), 1)[0])
        omega = float(np.pi / np.mean(np.diff(tp[window])))  # |x| peaks twice a period
    label = f"Beck's column (N = {N_COLUMN}, κGA = EA = {case[3]:g}, ρI = {case[4]:g}) at 1.05 P_c"
    growth = f"{label}: growth rate of the tip's flutter ({int(window.sum())} peaks)"
    frequency = abs(unstable.imag)
    checks = [
        _relative(
            growth, f"Re p = {unstable.real:.5f} (spectrum)", sigma, unstable.real, 2e-2, ".5f"
        ),
        _relative(
            f"{label}: frequency of the tip's flutter",
            f"Im p = {frequency:.5f} (spectrum)",
            omega,
            frequency,
            1e-2,
            ".5f",
        ),
    ]
    return checks, dict(ts=ts, x=x, p=unstable, P=P, Pc=P_sim, tp=tp[window], hp=hp[window])


def rods(out: str, plt, quick: bool) -> list[Check]:
    """The quick run: fewer tip masses, damping values and dampers, a shorter motion; the same
    sizes (N) and tolerances. Five compiled programs, most of its time."""
    checks = _statics_checks(out, plt)
    column_checks, columns, P_sim, case = _column_checks(quick)
    ziegler_checks, ziegler = _ziegler_checks(quick)
    motion_checks, motion = _flutter_checks(P_sim, case, quick)
    if plt is not None:
        from ._rods_figures import flutter_figure, stability_figure

        stability_figure(plt, out, columns, ziegler)
        flutter_figure(plt, out, motion)
    return checks + column_checks + ziegler_checks + motion_checks
