"""Rods against PyElastica (issue 32): ``rbo_jax.lattice`` rods and PyElastica's Cosserat rods on
PyElastica's own cases, side by side in one process, float64, every thread pinned to one core
(``--core``; PyElastica is single-threaded).

1. **Statics: PyElastica's Timoshenko beam** (``examples/TimoshenkoBeamCase/timoshenko.py``): a
   cantilever, n = 100 elements, L = 3, r = 0.25, ρ = 5000, E = 10⁶, G = E/100 = 10⁴, the tip
   force (-15, 0, 0) ramped up over ``final_time``/2 (``EndpointForces``), damped by
   ``AnalyticalLinearDamper`` (damping constant 0.1/7/ρ/A, dt = 0.07 L/n), ``PositionVerlet``
   to ``final_time`` = 5000 (2.4 million steps), the base clamped by ``OneEndFixedBC``. Its
   answer is the tip deflection after the run; the reference is the Timoshenko closed form
   δ = F L/(α G A) + F L³/(3 E I) with PyElastica's shear coefficient α (read from the rod:
   ``shear_matrix[0, 0, 0] / (G A)``, 27/28 in PyElastica 1.0). rbo_jax: ``circular_rod`` with the
   same n, material and α, ``TipForce``, ``lattice.equilibrium`` (Newton, block-tridiagonal
   solves). Timed: PyElastica's whole run (``ea.integrate``, its numba kernels compiled by a
   short run first), and the time at which its tip deflection settles (stays within 0.1 % of its
   final value; the callback records every 500 steps); rbo_jax's first call (tracing,
   compilation, run) and its best warm call.
2. **Free vibration**: a slender cantilever (L = 1, r = 0.01, ρ = 1000, E = 10⁷, G = E/3,
   PyElastica's default), at rest and straight, set moving by a small velocity
   v_x(z) = V (φ₁(z) + φ₂(z)/2) (φₖ the Euler-Bernoulli cantilever modes, V = 10⁻³ m/s) with the
   angular velocity Ω_y = ∂v_x/∂z (no shear rate); the tip's x(t) over ``--vib-t`` simulated
   seconds (default: four periods of the first bending mode, 14.3 s, issue 50's case), sampled
   every 5 ms, gives the first two bending frequencies by the matrix pencil method (the two
   largest of 8 damped exponentials). Reference: the Timoshenko beam of the
   same model (shear α G A, rotary inertia ρI), the roots of its frequency equation by the
   transfer matrix (scipy's ``expm``); the Euler-Bernoulli values 3.51602 and 22.0345
   √(EI/(ρAL⁴)) are printed too. PyElastica: ``PositionVerlet`` at dt = 0.5 (L/n)/√(E/ρ)
   (0.7 blew up at n = 50), its stepping loop timed; rbo_jax: ``lattice.simulate`` explicit
   (Dopri8), implicit (Kvaerno5) and ``method="splitting"`` (the Lie-group position Verlet at
   its default step), and ``lattice.spectrum`` (the eigenvalues of the
   linearisation: the frequencies with no simulation at all). Equal accuracy: for each
   PyElastica size, rbo_jax's smallest size whose errors in both frequencies are no larger.
3. **O(n)**: ``lattice.equilibrium`` of the Timoshenko rod at n = 10², 10³, 10⁴ bodies, best warm
   call per size.
4. **Compile time** of one call: the first calls above less their best warm calls.

``--parts pairs`` (with the vibration): PyElastica and the splitting at equal accuracy
(PyElastica n = 50 / splitting n = 5, n = 100 / n = 10) timed in turn, five rounds, so that both
see the same load on a shared machine.

Without PyElastica (``pip install pyelastica``, the ``bench`` extra) its rows are skipped.

Usage: ``python benchmarks/bench_rod.py [--final-time 5000] [--vib-t 14.3] [--pe-n 50,100]
[--explicit-n 5,10,50] [--implicit-n 5,10] [--splitting-n 5,10,20,50] [--spectrum-n 5,10,50,100]
[--scaling-n 100,1000,10000] [--repeat 3] [--core C] [--parts statics,vibration,pairs,scaling]
[--json PATH] [--smoke]``
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import io
import math
import os
import platform
import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _common import cpu_name, versions, write_json
from _pinning import pinned, restart_pinned

import rbo_jax
from rbo_jax import lattice as L

try:
    import elastica as ea
except ImportError:  # PyElastica is optional (the "bench" extra)
    ea = None

PE_ALPHA = 27.0 / 28.0  # PyElastica 1.0's alpha_c (read from its rod when it is installed)

# PyElastica's Timoshenko beam (examples/TimoshenkoBeamCase/timoshenko.py)
TIMO = dict(n=100, length=3.0, radius=0.25, density=5000.0, E=1e6, G=1e6 / 100.0, force=-15.0)
# the vibrating cantilever
VIB = dict(length=1.0, radius=0.01, density=1000.0, E=1e7, G=1e7 / 3.0, V=1e-3)
BETA = (1.8751040687119611, 4.6940911329741745)  # Euler-Bernoulli cantilever, β L
EB = (3.516015, 22.034492)  # β² (ω √(ρA L⁴/(EI)))
SAMPLE_DT = 0.005
# the vibration simulated over this many periods of its first bending mode (issue 50)
VIB_PERIODS = 4


def openblas_threads(n: int | None = None) -> list[tuple[str, int]]:
    """The threads of every OpenBLAS loaded in this process (SciPy's and NumPy's wheels; JAX's
    LAPACK calls on CPU go through SciPy's), set to ``n`` first when given. On a shared 2-core
    machine OpenBLAS's idle threads made ``jnp.linalg.eigvals`` of a 120 x 120 matrix take
    17-640 ms instead of 3.5 ms (README), so the benchmark runs with one (``--blas-threads``)."""
    found = []
    try:
        with open("/proc/self/maps") as f:
            paths = sorted({ln.split()[-1] for ln in f if "openblas" in ln.split()[-1]})
    except OSError:
        return found
    for path in paths:
        lib = ctypes.CDLL(path)
        for suffix in ("", "64_"):
            get = getattr(lib, f"scipy_openblas_get_num_threads{suffix}", None)
            put = getattr(lib, f"scipy_openblas_set_num_threads{suffix}", None)
            if get is None or put is None:
                continue
            if n is not None:
                put(ctypes.c_int(n))
            found.append((os.path.basename(path), int(get())))
            break
    return found


def _parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ints = lambda s: [int(x) for x in s.split(",") if x]  # noqa: E731
    p.add_argument("--final-time", type=float, default=5000.0, help="PyElastica's Timoshenko run")
    p.add_argument(
        "--vib-t",
        type=float,
        default=None,
        help="simulated seconds of the vibration (default: four periods of the first bending "
        "mode, Euler-Bernoulli's, 14.3 s: issue 50's case)",
    )
    p.add_argument("--pe-n", type=ints, default=[50, 100, 200], help="PyElastica's sizes")
    p.add_argument("--explicit-n", type=ints, default=[5, 10, 50])
    p.add_argument("--implicit-n", type=ints, default=[5, 10])
    p.add_argument("--splitting-n", type=ints, default=[5, 10, 20, 50], help="Lie-group Verlet")
    p.add_argument(
        "--midpoint-n", type=ints, default=[50, 100, 200], help="implicit midpoint (same n as PE)"
    )
    p.add_argument(
        "--midpoint-dt",
        type=lambda s: [float(x) for x in s.split(",") if x],
        default=[0.02],
        help="the midpoint rule also at these steps (longer than the samples: interpolated)",
    )
    p.add_argument("--spectrum-n", type=ints, default=[5, 10, 50, 100])
    p.add_argument("--scaling-n", type=ints, default=[100, 1000, 10000])
    p.add_argument("--motion-n", type=ints, default=[100, 1000, 10000], help="midpoint a step")
    p.add_argument("--batch-sizes", type=ints, default=[1, 4, 16], help="vmap over designs")
    p.add_argument("--explicit-rtol", type=float, default=1e-6)
    p.add_argument("--implicit-rtol", type=float, default=1e-4)
    p.add_argument("--repeat", type=int, default=3, help="timed calls per side (best kept)")
    p.add_argument("--statics-n", type=ints, default=[10], help="rbo_jax's smaller Timoshenko rods")
    p.add_argument("--blas-threads", type=int, default=1, help="OpenBLAS threads (0: as is)")
    p.add_argument("--core", type=int, default=None, help="the core to pin to (default: first)")
    p.add_argument(
        "--options-study", action="store_true", help="the rod programs under XLA's options"
    )
    p.add_argument("--json", default=None, help="also write the figures to this file")
    p.add_argument(
        "--parts",
        default="statics,vibration,pairs,scaling,motion,batch",
        help="which parts to run (the profile follows the vibration)",
    )
    p.add_argument("--smoke", action="store_true", help="a tiny run (tests)")
    args = p.parse_args(argv)
    args.motion_work = 200_000  # body-steps a size of the midpoint rule's cost a step
    if args.smoke:
        args.final_time, args.vib_t, args.repeat = 20.0, 0.2, 1
        args.pe_n, args.explicit_n, args.implicit_n = [50], [5], []
        args.splitting_n, args.midpoint_n = [5], [5]
        args.spectrum_n, args.scaling_n, args.statics_n = [10], [100], []
        args.motion_n, args.batch_sizes, args.motion_work = [5, 10], [2], 2_000
    if args.vib_t is None:
        args.vib_t = VIB_PERIODS * 2.0 * math.pi / (EB[0] * vib_units()[2])
    if args.core is None:
        args.core = min(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 0
    return args


def _best(fn, repeat):
    """(best seconds, last result) of ``repeat`` calls of ``fn``."""
    best, out = math.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


# --------------------------------------------------------------------------------------------
# 1. Statics: the Timoshenko beam.
# --------------------------------------------------------------------------------------------


def closed_form(alpha):
    r, E, G, Lr, F = (TIMO[k] for k in ("radius", "E", "G", "length", "force"))
    A, I = math.pi * r**2, math.pi * r**4 / 4.0  # noqa: E741
    return abs(F) * Lr / (alpha * G * A) + abs(F) * Lr**3 / (3.0 * E * I)


def _pe_straight_rod(n, Lr, r, rho, E, G):
    """PyElastica's straight rod along e3 from the origin, normal e2 (both of its cases)."""
    return ea.CosseratRod.straight_rod(
        n,
        np.zeros(3),
        np.array([0.0, 0.0, 1.0]),
        np.array([0.0, 1.0, 0.0]),
        Lr,
        r,
        rho,
        youngs_modulus=E,
        shear_modulus=G,
    )


def pe_timoshenko(final_time, *, record=True):
    """PyElastica's Timoshenko example run to ``final_time``: (seconds of ``ea.integrate``, tip
    x at the end, alpha, [(simulated t, wall s, tip x)] every 500 steps)."""
    n, Lr, r, rho, E, G = (TIMO[k] for k in ("n", "length", "radius", "density", "E", "G"))
    A = math.pi * r**2

    class Sim(ea.BaseSystemCollection, ea.Constraints, ea.Forcing, ea.CallBacks, ea.Damping):
        pass

    sim = Sim()
    rod = _pe_straight_rod(n, Lr, r, rho, E, G)
    sim.append(rod)
    dt = 0.07 * Lr / n
    sim.dampen(rod).using(
        ea.AnalyticalLinearDamper, damping_constant=0.1 / 7 / rho / A, time_step=dt
    )
    sim.constrain(rod).using(
        ea.OneEndFixedBC, constrained_position_idx=(0,), constrained_director_idx=(0,)
    )
    force = np.array([TIMO["force"], 0.0, 0.0])
    sim.add_forcing_to(rod).using(
        ea.EndpointForces, 0.0 * force, force, ramp_up_time=final_time / 2.0
    )
    trace = []
    clock = time.perf_counter

    class TipCallBack(ea.CallBackBaseClass):
        def make_callback(self, system, time, current_step):  # noqa: A002 (PyElastica's names)
            if record and current_step % 500 == 0:
                trace.append((time, clock(), system.position_collection[0, -1]))

    sim.collect_diagnostics(rod).using(TipCallBack)
    sim.finalize()
    steps = int(final_time / dt)
    t0 = clock()
    with contextlib.redirect_stdout(io.StringIO()):  # its "Final time of simulation is"
        ea.integrate(ea.PositionVerlet(), sim, final_time, steps, progress_bar=False)
    seconds = clock() - t0
    trace = np.array(trace)
    if trace.size:
        trace[:, 1] -= t0
    alpha = float(rod.shear_matrix[0, 0, 0] / (G * A))
    return seconds, float(rod.position_collection[0, -1]), alpha, trace, steps


def settled(trace, final_tip, tol=1e-3):
    """(simulated t, wall s) from which the recorded tip stays within ``tol`` of its final
    value, relatively."""
    ok = np.abs(trace[:, 2] / final_tip - 1.0) <= tol
    bad = np.flatnonzero(~ok)
    i = 0 if bad.size == 0 else bad[-1] + 1
    if i >= len(trace):
        return float("nan"), float("nan")
    return float(trace[i, 0]), float(trace[i, 1])


def case_rod(case, n, alpha, **kw):
    """The rbo_jax rod of a PyElastica case (TIMO, VIB): its circular section and moduli."""
    return L.circular_rod(
        n,
        case["length"],
        radius=case["radius"],
        density=case["density"],
        youngs_modulus=case["E"],
        shear_modulus=case["G"],
        shear_coefficient=alpha,
        **kw,
    )


def timoshenko_rod(n, alpha):
    return case_rod(TIMO, n, alpha, loads=L.TipForce([TIMO["force"], 0.0, 0.0]))


def rj_equilibrium(rod):
    state = L.equilibrium(rod)
    return float(jax.block_until_ready(state.r)[-1, 0])


def statics(args, alpha):
    out = {"final_time": args.final_time, "n": TIMO["n"], "alpha": alpha}
    delta = closed_form(alpha)
    out["closed_form"] = delta
    rows = []
    for n in [TIMO["n"]] + [m for m in args.statics_n if m != TIMO["n"]]:
        rod = timoshenko_rod(n, alpha)
        first, tip = _timed(lambda: rj_equilibrium(rod))
        warm, tip = _best(lambda: rj_equilibrium(rod), max(args.repeat, 3))
        it = int(L.solve_equilibrium(rod).iterations)
        r = {
            "n": n,
            "first": first,
            "warm": warm,
            "compile": first - warm,
            "tip": tip,
            "error": -tip / delta - 1.0,
            "newton": it,
        }
        rows.append(r)
        print(
            f"rbo_jax equilibrium, n = {n}: tip deflection {-tip:.6f} (closed form "
            f"{delta:.6f}, error {r['error']:+.2e}), {it} Newton steps; first call "
            f"{first:.2f} s, warm {warm * 1e3:.2f} ms",
            flush=True,
        )
    out["rbo_jax"], out["rbo_jax_other_n"] = rows[0], rows[1:]
    warm, first = rows[0]["warm"], rows[0]["first"]
    if ea is None:
        out["pyelastica"] = None
        print("pyelastica not installed, skipped (pip install pyelastica, or the 'bench' extra)")
        return out
    runs = []
    for k in range(args.repeat):
        seconds, pe_tip, _, trace, steps = pe_timoshenko(args.final_time)
        t_set, wall_set = settled(trace, pe_tip)
        runs.append((seconds, pe_tip, t_set, wall_set, steps))
        print(
            f"PyElastica run {k + 1}: {steps} steps in {seconds:.1f} s "
            f"({seconds / steps * 1e6:.1f} us/step), tip deflection {-pe_tip:.6f} (error "
            f"{-pe_tip / delta - 1:+.2e}), within 0.1 % of its final deflection from t = "
            f"{t_set:.0f} on ({wall_set:.1f} s wall)",
            flush=True,
        )
    best = min(runs, key=lambda x: x[0])
    pe = {
        "seconds": best[0],
        "tip": best[1],
        "error": -best[1] / delta - 1.0,
        "settled_t": best[2],
        "settled_wall": min(r[3] for r in runs),
        "steps": best[4],
        "us_per_step": best[0] / best[4] * 1e6,
    }
    out["pyelastica"] = pe
    out["ratio"] = pe["seconds"] / warm
    out["ratio_settled"] = pe["settled_wall"] / warm
    out["ratio_first"] = pe["seconds"] / first
    print(
        f"PyElastica (best of {args.repeat}) {pe['seconds']:.1f} s / rbo_jax warm "
        f"{warm * 1e3:.1f} ms (same n = {TIMO['n']}) = {out['ratio']:.0f}x; PyElastica to its "
        f"settled deflection {pe['settled_wall']:.1f} s: {out['ratio_settled']:.0f}x; PyElastica "
        f"/ rbo_jax's first call (compile + run) {out['ratio_first']:.1f}x"
    )
    same = [r for r in rows if abs(r["error"]) <= abs(pe["error"])]
    if same:
        r = min(same, key=lambda x: x["n"])
        out["equal_accuracy"] = {"n": r["n"], "ratio": pe["seconds"] / r["warm"]}
        print(
            f"equal accuracy: rbo_jax n = {r['n']} (error {r['error']:+.2e}, PyElastica's "
            f"{pe['error']:+.2e}): {pe['seconds'] / r['warm']:.0f}x"
        )
    return out


# --------------------------------------------------------------------------------------------
# 2. Free vibration.
# --------------------------------------------------------------------------------------------


def vib_units():
    r, rho, E, Lr = (VIB[k] for k in ("radius", "density", "E", "length"))
    A, I = math.pi * r**2, math.pi * r**4 / 4.0  # noqa: E741
    return A, I, math.sqrt(E * I / (rho * A * Lr**4))


def timoshenko_frequencies(alpha):
    """ω₁, ω₂ of the clamped-free Timoshenko beam (shear α G A, rotary inertia ρI): the roots
    of det(Φ₂₂(ω)) = 0, Φ the transfer matrix over L of (w, ψ, M, Q)."""
    from scipy.linalg import expm
    from scipy.optimize import brentq

    r, rho, E, G, Lr = (VIB[k] for k in ("radius", "density", "E", "G", "length"))
    A, I, unit = vib_units()  # noqa: E741
    kGA, EI = alpha * G * A, E * I

    def det(w):
        m = np.array(
            [
                [0.0, 1.0, 0.0, 1.0 / kGA],
                [0.0, 0.0, 1.0 / EI, 0.0],
                [0.0, -rho * I * w**2, 0.0, -1.0],
                [-rho * A * w**2, 0.0, 0.0, 0.0],
            ]
        )
        return np.linalg.det(expm(m * Lr)[2:4, 2:4])

    roots = []
    for eb in EB:
        ws = np.linspace(0.9, 1.01, 111) * eb * unit
        d = [det(w) for w in ws]
        i = next(i for i in range(len(ws) - 1) if np.sign(d[i]) != np.sign(d[i + 1]))
        roots.append(brentq(det, ws[i], ws[i + 1], xtol=1e-14, rtol=1e-15))
    return np.array(roots)


def _eb_mode(z, beta, derivative=False):
    s = (math.cosh(beta) + math.cos(beta)) / (math.sinh(beta) + math.sin(beta))
    bz = beta * z
    if derivative:
        return beta * (np.sinh(bz) + np.sin(bz) - s * (np.cosh(bz) - np.cos(bz)))
    return np.cosh(bz) - np.cos(bz) - s * (np.sinh(bz) - np.sin(bz))


def initial_velocity(z):
    """(v_x, Ω_y) at the heights ``z`` (m)."""
    Lr, V = VIB["length"], VIB["V"]
    x = np.asarray(z) / Lr
    v = V * (_eb_mode(x, BETA[0]) + 0.5 * _eb_mode(x, BETA[1]))
    dv = V * (_eb_mode(x, BETA[0], True) + 0.5 * _eb_mode(x, BETA[1], True)) / Lr
    return v, dv


def matrix_pencil(y, dt, order=8):
    """The complex exponents and amplitudes of ``order`` damped exponentials fitted to ``y``."""
    n = len(y)
    p = n // 3
    H = np.array([y[i : i + p + 1] for i in range(n - p)])
    V = np.linalg.svd(H, full_matrices=False)[2][:order].conj().T
    z = np.linalg.eigvals(np.linalg.pinv(V[:-1]) @ V[1:])
    lam = np.log(z.astype(complex)) / dt
    Z = np.exp(np.outer(np.arange(n) * dt, lam))
    amp = np.linalg.lstsq(Z, y.astype(complex), rcond=None)[0]
    return lam, amp


def two_frequencies(tip, dt=SAMPLE_DT):
    """The two frequencies (rad/s) of the largest amplitudes in the tip's motion."""
    lam, amp = matrix_pencil(np.asarray(tip, float), dt)
    keep = lam.imag > 0
    lam, amp = lam[keep], amp[keep]
    top = np.argsort(-np.abs(amp))[:2]
    return np.sort(lam[top].imag)


def vib_rod(n, alpha):
    return case_rod(VIB, n, alpha)


def _pe_cantilever(n):
    """PyElastica's cantilever released with the initial velocity: ``(sim, rod, dt, every)``,
    ``dt`` its stable step cut to divide the 5 ms sampling into ``every`` steps."""
    Lr, r, rho, E, G = (VIB[k] for k in ("length", "radius", "density", "E", "G"))

    class Sim(ea.BaseSystemCollection, ea.Constraints):
        pass

    sim = Sim()
    rod = _pe_straight_rod(n, Lr, r, rho, E, G)
    sim.append(rod)
    sim.constrain(rod).using(
        ea.OneEndFixedBC, constrained_position_idx=(0,), constrained_director_idx=(0,)
    )
    z = rod.position_collection[2]
    rod.velocity_collection[0, :] = initial_velocity(z)[0]
    # ω in the elements' frames: d1 = the normal (e_y), so Ω_y is the first component
    rod.omega_collection[0, :] = initial_velocity(0.5 * (z[1:] + z[:-1]))[1]
    sim.finalize()
    dt = 0.5 * (Lr / n) / math.sqrt(E / rho)
    every = max(1, math.ceil(SAMPLE_DT / dt))
    return sim, rod, SAMPLE_DT / every, every


def pe_vibration(n, T):
    """PyElastica's cantilever released with the initial velocity: (seconds of the stepping
    loop, tip x every 5 ms, dt, steps)."""
    sim, rod, dt, every = _pe_cantilever(n)
    samples = int(round(T / SAMPLE_DT))
    stepper = ea.PositionVerlet()
    tip = np.empty(samples + 1)
    tip[0] = rod.position_collection[0, -1]
    t = 0.0
    t0 = time.perf_counter()
    for k in range(samples):
        for _ in range(every):
            t = stepper.step(sim, t, dt)
        tip[k + 1] = rod.position_collection[0, -1]
    seconds = time.perf_counter() - t0
    return seconds, tip, dt, samples * every


def pe_energy_drift(n, T):
    """PyElastica's energy drift on the same run (not timed): max |E(t) - E(0)| / E(0) over the
    samples, E its translational, rotational, bending and shear energies with the strains
    computed at the sample's positions."""
    sim, rod, dt, every = _pe_cantilever(n)
    stepper, t, energies = ea.PositionVerlet(), 0.0, []

    def total():
        rod.compute_internal_forces_and_torques(t)  # the strains at the current positions
        return float(
            rod.compute_translational_energy()
            + rod.compute_rotational_energy()
            + rod.compute_bending_energy()
            + rod.compute_shear_energy()
        )

    energies.append(total())
    for _ in range(int(round(T / SAMPLE_DT))):
        for _ in range(every):
            t = stepper.step(sim, t, dt)
        energies.append(total())
    e = np.asarray(energies)
    return float(np.max(np.abs(e - e[0])) / e[0])


def rj_initial_state(rod):
    s = rod.straight()
    v, dv = initial_velocity(np.asarray(s.r)[:, 2])
    vel = np.zeros((rod.n_bodies, 3))
    om = np.zeros((rod.n_bodies, 3))
    vel[1:, 0], om[1:, 1] = v[1:], dv[1:]
    return L.RodState(s.theta, s.r, jnp.asarray(om), jnp.asarray(vel))


def rj_simulate(rod, state0, ts, method, rtol, dt=None, energy=False):
    """(tip x at ts, steps) of ``lattice.simulate``; with ``energy`` also its energy drift,
    max |E(t) - E(0)| / E(0) over the samples (not timed)."""
    if method in ("splitting", "midpoint"):  # fixed steps: each method's default dt
        traj = L.simulate(rod, state0, ts, method=method, dt=dt)
    else:
        traj = L.simulate(rod, state0, ts, method=method, rtol=rtol, atol=rtol * 1e-3)
    tip = np.asarray(jax.block_until_ready(traj.states.r)[:, -1, 0])
    if not energy:
        return tip, int(traj.num_steps)
    e = np.asarray(traj.energy)
    return tip, int(traj.num_steps), float(np.max(np.abs(e - e[0])) / e[0])


def spectrum_frequencies(rod):
    p = np.asarray(jax.block_until_ready(L.spectrum(rod)))
    w = np.sort(p.imag[p.imag > 0])
    return w[[0, 2]]  # every bending frequency twice (the two planes)


def _err_text(err):
    return f"{err[0]:+.2e} {err[1]:+.2e}"


def vibration(args, alpha):
    unit = vib_units()[2]
    ref = timoshenko_frequencies(alpha)
    eb = np.array(EB) * unit
    T = args.vib_t
    ts = np.arange(int(round(T / SAMPLE_DT)) + 1) * SAMPLE_DT
    out = {"T": T, "alpha": alpha, "timoshenko": ref.tolist(), "euler_bernoulli": eb.tolist()}
    print(
        f"reference: Timoshenko ω = {ref[0]:.6f}, {ref[1]:.6f} rad/s (Euler-Bernoulli "
        f"{eb[0]:.6f}, {eb[1]:.6f}: Timoshenko/EB - 1 = {ref[0] / eb[0] - 1:+.2e}, "
        f"{ref[1] / eb[1] - 1:+.2e}); T = {T} s simulated, tip sampled every "
        f"{SAMPLE_DT * 1e3:.0f} ms",
        flush=True,
    )
    rows = []

    def row(code, n, first, best, sim_t, w, steps, note="", drift=None):
        err = (np.asarray(w) / ref - 1.0).tolist()
        r = {
            "code": code,
            "n": n,
            "first": first,
            "seconds": best,
            "per_sim_s": best / sim_t if sim_t else None,
            "omega": list(map(float, w)),
            "error": err,
            "error_eb": float(w[0] / eb[0] - 1.0),
            "energy_drift": drift,
            "steps": steps,
            "note": note,
        }
        rows.append(r)
        per = "-" if r["per_sim_s"] is None else f"{r['per_sim_s']:.3f}"
        first_s = "-" if first is None else f"{first:.1f}"
        drift_s = "-" if drift is None else f"{drift:.1e}"
        print(
            f"{code:<26} {n:>5}  {first_s:>8}  {best:>9.4f}  {per:>9}  {_err_text(err):>19}"
            f"  {r['error_eb']:>+9.2e}  {drift_s:>8}  {steps if steps is not None else '-':>8}"
            f"  {note}",
            flush=True,
        )

    print(
        f"{'code':<26} {'n':>5}  {'first[s]':>8}  {'best[s]':>9}  {'s/sim s':>9}  "
        f"{'error ω1 ω2 vs Timo':>19}  {'ω1 vs EB':>9}  {'drift':>8}  {'steps':>8}"
    )
    if ea is not None:
        pe_vibration(10, 0.01)  # numba's kernels compiled (or loaded from its cache) first
        for n in args.pe_n:
            best, last = math.inf, None
            for _ in range(args.repeat):
                seconds, tip, dt, steps = pe_vibration(n, T)
                best, last = min(best, seconds), (tip, dt, steps)
            tip, dt, steps = last
            bad = not np.all(np.isfinite(tip)) or np.max(np.abs(tip)) > 100 * VIB["V"]
            w = [np.nan, np.nan] if bad else two_frequencies(tip)
            drift = None if bad else pe_energy_drift(n, T)
            row("PyElastica PositionVerlet", n, None, best, T, w, steps, f"dt {dt:.3g}", drift)
    else:
        print("pyelastica not installed, skipped (pip install pyelastica, or the 'bench' extra)")
    name = {"explicit": "Dopri8", "implicit": "Kvaerno5", "splitting": "splitting"}
    runs = [
        ("explicit", args.explicit_n, args.explicit_rtol, None),
        ("implicit", args.implicit_n, args.implicit_rtol, None),
        ("splitting", args.splitting_n, None, None),
        ("midpoint", args.midpoint_n, None, None),
    ] + [("midpoint", args.midpoint_n, None, dt) for dt in args.midpoint_dt]
    for method, ns, rtol, dt in runs:
        for n in ns:
            rod = vib_rod(n, alpha)
            s0 = rj_initial_state(rod)
            run = lambda: rj_simulate(rod, s0, ts, method, rtol, dt)  # noqa: E731
            first, _ = _timed(run)
            best, (tip, steps) = _best(run, args.repeat)
            drift = rj_simulate(rod, s0, ts, method, rtol, dt, energy=True)[2]
            note = f"dt {T / steps:.3g}" if rtol is None else f"rtol {rtol:g}"
            code = "rbo_jax " + name.get(method, method) + ("" if dt is None else f" dt={dt:g}")
            row(code, n, first, best, T, two_frequencies(tip), steps, note, drift)
    for n in args.spectrum_n:
        rod = vib_rod(n, alpha)
        first, _ = _timed(lambda: spectrum_frequencies(rod))
        best, w = _best(lambda: spectrum_frequencies(rod), max(args.repeat, 3))
        row("rbo_jax spectrum", n, first, best, None, w, None, "no simulation")
        rows[-1]["omega_max"] = float(np.max(np.abs(np.asarray(L.spectrum(rod)).imag)))
    out["rows"] = rows
    out["same_n"] = same_n(rows)
    for e in out["same_n"]:
        print(
            f"same n = {e['n']}: {e['code']} {e['ratio']:.2f}x PyElastica per simulated second "
            f"(ω1 vs EB {e['error_eb']:+.2e} against {e['pe_error_eb']:+.2e}; energy drift "
            f"{e['drift'] or float('nan'):.1e} against {e['pe_drift'] or float('nan'):.1e})"
        )
    out["equal_accuracy"] = equal_accuracy(rows)
    for e in out["equal_accuracy"]:
        print(
            f"equal accuracy: PyElastica n = {e['pe_n']} (errors {_err_text(e['pe_error'])}) vs "
            f"{e['code']} n = {e['n']} ({_err_text(e['error'])}): "
            + (
                f"{e['ratio']:.2f}x per simulated second"
                if e["per_sim"]
                else f"{e['ratio']:.1f}x against PyElastica's whole run ({T:g} s simulated)"
            )
        )
    return out


def interleaved(args, alpha, pairs=((50, 5), (100, 10)), rounds=5):
    """PyElastica at n_pe and the splitting at n_rj (the equal-accuracy pairs) timed in turn,
    ``rounds`` times, so that both see the same load: the best of each and the ratio of the
    bests, and the median of the per-round ratios."""
    T = args.vib_t
    ts = np.arange(int(round(T / SAMPLE_DT)) + 1) * SAMPLE_DT
    out = []
    for n_pe, n_rj in pairs:
        rod = vib_rod(n_rj, alpha)
        s0 = rj_initial_state(rod)
        rj_simulate(rod, s0, ts, "splitting", None)  # compiled first
        pe, rj = [], []
        for _ in range(rounds):
            pe.append(pe_vibration(n_pe, T)[0])
            rj.append(_timed(lambda: rj_simulate(rod, s0, ts, "splitting", None))[0])
        ratios = sorted(a / b for a, b in zip(pe, rj))
        e = {"pe_n": n_pe, "n": n_rj, "pe": pe, "rj": rj, "best_ratio": min(pe) / min(rj)}
        e["median_ratio"] = ratios[len(ratios) // 2]
        out.append(e)
        print(
            f"PyElastica n = {n_pe} / splitting n = {n_rj}, in turn x{rounds}: best "
            f"{min(pe):.4f} s / {min(rj):.4f} s = {e['best_ratio']:.2f}x, median of the rounds' "
            f"ratios {e['median_ratio']:.2f}x (ratios {', '.join(f'{r:.2f}' for r in ratios)})",
            flush=True,
        )
    return out


def equal_accuracy(rows):
    """For each PyElastica row and rbo_jax route: rbo_jax's smallest n with both errors no
    larger, and the ratio of PyElastica's seconds per simulated second to rbo_jax's (the
    spectrum: PyElastica's whole run, from which its frequencies came, to the spectrum's
    time)."""
    found = []
    for pe in (r for r in rows if r["code"].startswith("PyElastica")):
        if not np.all(np.isfinite(pe["error"])):
            continue
        for code in ("rbo_jax Dopri8", "rbo_jax Kvaerno5", "rbo_jax splitting", "rbo_jax spectrum"):
            cands = [
                r
                for r in rows
                if r["code"] == code
                and all(abs(a) <= abs(b) for a, b in zip(r["error"], pe["error"]))
            ]
            if not cands:
                continue
            r = min(cands, key=lambda x: x["n"])
            per_sim = r["per_sim_s"] is not None
            # the spectrum: against PyElastica's whole run, which its frequencies came from
            ratio = pe["per_sim_s"] / r["per_sim_s"] if per_sim else pe["seconds"] / r["seconds"]
            found.append(
                {
                    "pe_n": pe["n"],
                    "pe_error": pe["error"],
                    "code": code,
                    "n": r["n"],
                    "error": r["error"],
                    "per_sim": per_sim,
                    "ratio": ratio,
                }
            )
    return found


def same_n(rows):
    """Each rbo_jax row against PyElastica's at the same n: the ratio of seconds per simulated
    second (PyElastica's over ours: above 1, ours is faster), with both sides' errors."""
    pes = {r["n"]: r for r in rows if r["code"].startswith("PyElastica")}
    out = []
    for r in rows:
        pe = pes.get(r["n"])
        if pe is None or r is pe or not r["per_sim_s"] or r["code"].endswith("spectrum"):
            continue
        out.append(
            {
                "n": r["n"],
                "code": r["code"],
                "ratio": pe["per_sim_s"] / r["per_sim_s"],
                "error_eb": r["error_eb"],
                "pe_error_eb": pe["error_eb"],
                "drift": r["energy_drift"],
                "pe_drift": pe["energy_drift"],
            }
        )
    return out


# --------------------------------------------------------------------------------------------
# 3. O(n) and 4. compile time.
# --------------------------------------------------------------------------------------------


def scaling(args, alpha):
    rows = []
    print(f"{'bodies':>8}  {'first[s]':>8}  {'warm[ms]':>9}  {'us/body':>8}  {'Newton':>6}  error")
    for n in args.scaling_n:
        rod = timoshenko_rod(n, alpha)
        first, _ = _timed(lambda: rj_equilibrium(rod))
        warm, tip = _best(lambda: rj_equilibrium(rod), max(args.repeat, 3))
        it = int(L.solve_equilibrium(rod).iterations)
        err = -tip / closed_form(alpha) - 1.0
        rows.append(
            {"n": n, "first": first, "warm": warm, "us_per_body": warm / n * 1e6, "newton": it}
        )
        print(
            f"{n:>8}  {first:>8.2f}  {warm * 1e3:>9.2f}  {warm / n * 1e6:>8.2f}  {it:>6}  "
            f"{err:+.2e}",
            flush=True,
        )
    _print_slope(rows, "warm", "warm time")
    return rows


def _print_slope(rows, key, what):
    """The power of n that ``key`` grows with from the first row to the last, printed."""
    if len(rows) > 1:
        a, b = rows[0], rows[-1]
        if not (a[key] > 0 and b[key] > 0):  # a difference of two timings lost in the noise
            print(f"{what}: not resolved from n = {a['n']} to {b['n']} (a time <= 0)")
            return
        slope = math.log(b[key] / a[key]) / math.log(b["n"] / a["n"])
        print(f"{what} ~ n^{slope:.2f} from n = {a['n']} to {b['n']}")


def motion_scaling(args, alpha):
    """The midpoint rule's cost a step against the number of bodies: the cantilever of the
    vibration (its initial velocity) stepped ``K`` and ``2K`` steps of 1 ms, the difference over
    ``K`` (so the first Jacobian, factoring and the program's start are not counted); ``K`` about
    200,000 body-steps over n (at least 10), so that the difference is well above the noise
    (``--smoke``: 2,000, the code path only)."""
    rows, dt = [], 1e-3
    print(f"{'bodies':>8}  {'first[s]':>8}  {'us/step':>9}  {'ns/step/body':>12}")
    for n in args.motion_n:
        K = max(10, args.motion_work // n)
        rod = vib_rod(n, alpha)
        s0 = rj_initial_state(rod)

        def run(k, rod=rod, s0=s0):
            ts = np.linspace(0.0, k * dt, k + 1)
            traj = L.simulate(rod, s0, ts, method="midpoint", dt=dt)
            return jax.block_until_ready(traj.states.r)

        first, _ = _timed(lambda: run(K))
        run(2 * K)  # compiled for the longer ts too
        short = _best(lambda: run(K), max(args.repeat, 3))[0]
        long_ = _best(lambda: run(2 * K), max(args.repeat, 3))[0]
        per_step = (long_ - short) / K
        rows.append({"n": n, "first": first, "per_step": per_step, "per_body": per_step / n})
        print(f"{n:>8}  {first:>8.2f}  {per_step * 1e6:>9.1f}  {per_step / n * 1e9:>12.1f}")
    _print_slope(rows, "per_step", "time a step")
    return rows


def batch_scaling(args, alpha):
    """``jax.vmap`` of the midpoint rule over designs (the turn stiffnesses scaled in
    [0.9, 1.1]): wall time per rod against the batch size, the cantilever at n = 50 over
    0.5 s (samples every 5 ms)."""
    rows, n = [], 50
    ts = np.arange(101) * SAMPLE_DT
    base = vib_rod(n, alpha)
    s0 = rj_initial_state(base)

    def alone():
        return jax.block_until_ready(L.simulate(base, s0, ts, method="midpoint").states.r)

    alone()
    one = _best(alone, max(args.repeat, 3))[0]
    print(f"one rod outside jax.vmap (an eager call): {one:.4f} s")
    print(f"{'rods':>6}  {'first[s]':>8}  {'wall[s]':>8}  {'per rod[s]':>10}  {'/ alone':>7}")
    for b in args.batch_sizes:
        scale = jnp.linspace(0.9, 1.1, b)

        @jax.jit
        def run(scale):
            def one(c):
                k = jnp.asarray(base.turn_stiffness) * c
                rod = eqx.tree_at(lambda r: r.turn_stiffness, base, k)
                return L.simulate(rod, s0, ts, method="midpoint").states.r[:, -1, 0]

            return jax.vmap(one)(scale)

        first, _ = _timed(lambda: jax.block_until_ready(run(scale)))
        wall = _best(lambda: jax.block_until_ready(run(scale)), max(args.repeat, 3))[0]
        rows.append({"rods": b, "first": first, "wall": wall, "per_rod": wall / b, "alone": one})
        print(f"{b:>6}  {first:>8.2f}  {wall:>8.3f}  {wall / b:>10.4f}  {wall / b / one:>7.2f}")
    return rows


def _rates_cost(rod, state, evaluations=200):
    """Seconds per evaluation of the rod's equations of motion (``_rod_field.rates``), best of
    three runs of a compiled loop of ``evaluations``."""
    import equinox as eqx

    from rbo_jax.models.rod import rates

    @eqx.filter_jit
    def loop(s):
        def body(i, s):
            d = rates(rod, s)
            return jax.tree_util.tree_map(lambda a, b: a + 1e-12 * b, s, d)

        return jax.lax.fori_loop(0, evaluations, body, s)

    jax.block_until_ready(loop(state))
    return _best(lambda: jax.block_until_ready(loop(state)), 3)[0] / evaluations


def _splitting_parts(rod, state, evaluations=2000):
    """Seconds of the two parts of a splitting step, each in a compiled loop of its own (best
    of three): one evaluation of the forces (``_rod_field.forces_at`` at the turn-tensors of
    quaternions, as in the step: ``_rod_field.forces_tangent``) and the free rotations of
    every body (Cayley maps)."""
    import equinox as eqx

    from rbo_jax.lattice import _rod_verlet as V
    from rbo_jax.models.rod import forces_tangent
    from rbo_jax.models.rod._field import matrix_of

    stripped, _ = V._static_zeros(rod)
    w, u = V._quaternion_of_vector(state.theta)
    q0 = (w, u[:, 0], u[:, 1], u[:, 2])
    principal = (*jnp.linalg.eigh(jnp.asarray(rod.inertia)), V._skipped_axes(rod))

    @eqx.filter_jit
    def forces(rod, q, r):
        def body(i, c):
            q, r = c
            M, F = forces_tangent(rod, matrix_of(q[0], jnp.stack(q[1:], -1)), r)
            return tuple(x + 1e-12 * M[:, min(j, 2)] for j, x in enumerate(q)), r + 1e-12 * F

        return jax.lax.fori_loop(0, evaluations, body, (q, r))

    @jax.jit
    def rotations(q, Pi):
        def body(i, c):
            return V._free_rotation(principal, *c, 1e-4)

        return jax.lax.fori_loop(0, evaluations, body, (q, Pi))

    Pi0 = tuple(state.Omega[:, j] + 0.1 for j in range(3))
    out = {}
    for key, fn in (
        ("per_force", lambda: forces(stripped, q0, state.r)),
        ("per_rotation", lambda: rotations(q0, Pi0)),
    ):
        jax.block_until_ready(fn())
        out[key] = _best(lambda fn=fn: jax.block_until_ready(fn()), 3)[0] / evaluations
    return out


def _jacobian_cost(rod, state):
    """Seconds of one dense Jacobian of the equations (``jax.jacfwd``, what diffrax's implicit
    stages build), best of three."""
    import equinox as eqx
    from jax.flatten_util import ravel_pytree

    from rbo_jax.models.rod import rates

    flat, unravel = ravel_pytree(state)

    @eqx.filter_jit
    def jac(x):
        return jax.jacfwd(lambda y: ravel_pytree(rates(rod, unravel(y)))[0])(x)

    jax.block_until_ready(jac(flat))
    return _best(lambda: jax.block_until_ready(jac(flat)), 3)[0]


def profile(args, alpha, vib):
    """Where the time of a simulated second goes (printed; the figures in the JSON)."""
    out = []
    wmax = {r["n"]: r.get("omega_max") for r in vib["rows"] if r["code"] == "rbo_jax spectrum"}
    for r in vib["rows"]:
        if r["steps"] is None or not r["steps"]:
            continue
        n, steps, T = r["n"], r["steps"], vib["T"]
        per_step = r["seconds"] / steps
        e = {"code": r["code"], "n": n, "steps": steps, "dt": T / steps, "per_step": per_step}
        text = (
            f"{r['code']:<26} n = {n:>4}: {steps:>6} steps (mean dt {T / steps:.2e} s), "
            f"{per_step * 1e6:8.1f} us/step"
        )
        if wmax.get(n):
            e["omega_max_dt"] = wmax[n] * T / steps
            text += f", stiffest |ω| {wmax[n]:.3g} rad/s (ω dt = {e['omega_max_dt']:.2f})"
        if r["code"].startswith("rbo_jax"):
            rod = vib_rod(n, alpha)
            s0 = rj_initial_state(rod)
            e["per_eval"] = _rates_cost(rod, s0)
            text += (
                f"; one evaluation of the equations {e['per_eval'] * 1e6:.1f} us "
                f"({per_step / e['per_eval']:.1f} per step)"
            )
            if "splitting" in r["code"]:
                e.update(_splitting_parts(rod, s0))
                text += (
                    f"; in its step: the forces {e['per_force'] * 1e6:.1f} us, the free "
                    f"rotations {e['per_rotation'] * 1e6:.2f} us, the rest "
                    f"{(per_step - e['per_force'] - e['per_rotation']) * 1e6:.1f} us"
                )
            if "Kvaerno5" in r["code"]:
                e["jacobian"] = _jacobian_cost(rod, s0)
                text += (
                    f"; a dense Jacobian ({12 * (n + 1)}²) {e['jacobian'] * 1e3:.2f} ms "
                    f"({per_step / e['jacobian']:.1f} per step)"
                )
        print(text, flush=True)
        out.append(e)
    return out


def options_study(alpha):
    """The rod programs (``equilibrium`` of the Timoshenko rod, n = 100; ``spectrum`` of the
    vibrating rod, n = 50) compiled with rbo_jax's three sets of XLA options: first call and
    best warm call of each (``--options-study``)."""
    import equinox as eqx

    from rbo_jax import _programs
    from rbo_jax.stability._equilibrium import _equilibrium
    from rbo_jax.stability._linearize import _sorted_spectrum

    rows = []
    rod_s = timoshenko_rod(TIMO["n"], alpha)
    st = rod_s.straight()
    rod_v = vib_rod(50, alpha)
    eq_v = L.equilibrium(rod_v)
    for name, opts in (
        ("fast_compile (what rbo_jax uses)", _programs.fast_compile_options()),
        ("small_program", _programs.small_program_options()),
        ("XLA defaults", None),
    ):
        for prog, fn, call in (
            ("equilibrium n=100", _equilibrium, lambda f: f(rod_s, st, 0.0, 1, 1e-10, 64, 1e-6)),
            ("spectrum n=50", _sorted_spectrum, lambda f: f(rod_v, eq_v, 0.0)),
        ):
            # a fresh function: nothing compiled before is reused
            f = eqx.filter_jit(lambda *a, fn=fn: fn(*a), compiler_options=opts)
            first, _ = _timed(lambda: jax.block_until_ready(call(f)))
            warm, _ = _best(lambda: jax.block_until_ready(call(f)), 3)
            rows.append({"options": name, "program": prog, "first": first, "warm": warm})
            print(
                f"{name:<34} {prog:<18} first {first:6.2f} s  warm {warm * 1e3:8.2f} ms",
                flush=True,
            )
    return rows


def machine() -> str:
    cpu = cpu_name()
    pe = getattr(ea, "__version__", None) if ea is not None else None
    if ea is not None and pe is None:
        from importlib.metadata import version

        pe = version("pyelastica")
    return f"{cpu}, {os.cpu_count()} CPUs; {platform.platform()}; {versions()}; pyelastica {pe}"


def main(argv=None):
    args = _parse(argv)
    load0 = os.getloadavg()
    blas_before = openblas_threads()
    blas = openblas_threads(args.blas_threads if args.blas_threads > 0 else None)
    print(f"{time.strftime('%Y-%m-%d %H:%M')}  {machine()}", flush=True)
    print(
        f"load average {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}; every thread pinned to "
        f"core {args.core}; OpenBLAS threads "
        + (", ".join(f"{k} {v}" for k, v in blas) or "(none loaded)")
        + f"; rbo_jax from {os.path.dirname(rbo_jax.__file__)}",
        flush=True,
    )
    out = {"args": dict(vars(args)), "load_start": load0, "openblas": blas}
    with pinned((args.core,)) as ok:
        out["pinned"] = ok
        alpha = PE_ALPHA
        if ea is not None:
            # PyElastica's shear coefficient, and its numba kernels compiled (or loaded) first
            alpha = pe_timoshenko(1.0, record=False)[2]
        parts = args.parts.split(",")
        if "statics" in parts:
            print(f"\n-- statics: PyElastica's Timoshenko beam (shear coefficient α = {alpha:.6f})")
            out["statics"] = statics(args, alpha)
        if "vibration" in parts:
            print("\n-- free vibration of a cantilever: the first two bending frequencies")
            out["vibration"] = vibration(args, alpha)
        if "pairs" in parts and ea is not None:
            print("\n-- PyElastica and the splitting at equal accuracy, timed in turn")
            smoke = {"pairs": ((50, 5),), "rounds": 1} if args.smoke else {}
            out["pairs"] = interleaved(args, alpha, **smoke)
        if "scaling" in parts:
            print("\n-- lattice.equilibrium against the number of bodies (the Timoshenko rod)")
            out["scaling"] = scaling(args, alpha)
        if "motion" in parts:
            print("\n-- the midpoint rule a step against the number of bodies (the cantilever)")
            out["motion"] = motion_scaling(args, alpha)
        if "batch" in parts:
            print("\n-- jax.vmap of the midpoint rule over designs (n = 50)")
            out["batch"] = batch_scaling(args, alpha)
        if "vibration" in parts:
            print("\n-- where a simulated second goes")
            out["profile"] = profile(args, alpha, out["vibration"])
        if args.options_study:
            print("\n-- the rod programs under rbo_jax's XLA options")
            out["options"] = options_study(alpha)
    if blas_before:  # as they were (run.py runs other benchmarks in this process after)
        openblas_threads(blas_before[0][1])
    load1 = os.getloadavg()
    out["load_end"] = load1
    compiles = []
    if "statics" in out:
        compiles += [
            (
                f"equilibrium n = {out['statics']['rbo_jax']['n']}",
                out["statics"]["rbo_jax"]["compile"],
            )
        ]
    compiles += [
        (f"{r['code'].split()[-1]} n = {r['n']}", r["first"] - r["seconds"])
        for r in out.get("vibration", {}).get("rows", [])
        if r["first"] is not None
    ]
    out["compile"] = compiles
    print(
        "\ncompile (first call less the best warm call): "
        + ", ".join(f"{k} {v:.1f} s" for k, v in compiles)
    )
    print(f"load average at the end {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    write_json(args.json, out, indent=2, default=float)
    return out


if __name__ == "__main__":
    restart_pinned(sys.argv[1:])  # one core from the start (the "one core each")
    main()
