"""The continuum snake against PyElastica (issue 50, C): PyElastica's own
``examples/ContinuumSnakeCase/continuum_snake.py`` and the same snake as an ``rbo_jax.lattice``
rod, side by side in one process, float64, every thread pinned to one core (``--core``).

The case (PyElastica's parameters): a free rod of n = 50 elements, L = 0.35 m, r = 0.011 L,
ρ = 1000 kg/m³, E = 10⁶ Pa, G = E/1.5; gravity −9.80665 m/s² along y; ``MuscleTorques`` with
its optimised spline coefficients (3.4, 3.3, 4.2, 2.6, 3.6, 3.5)·10⁻³ N m, wave length 1 (as a
fraction of L), period 2 s, ramped up over one period, about y; a plane y = −r with kinetic
friction μ = L/(T² g Fr), Fr = 0.1, forward μ, backward 1.5 μ, sideways 2 μ (no static
friction); 11.01 periods.

- PyElastica: ``PositionVerlet`` at its example's dt = 10⁻⁴ s, ``AnalyticalLinearDamper``
  (damping constant 2·10⁻³), ``RodPlaneContactWithAnisotropicFriction`` (k = 1, ν = 10⁻⁶,
  slip velocity 10⁻⁸ m/s), its numba kernels compiled by a short run first.
- rbo_jax: ``circular_rod`` with the same n and material, ``Gravity``, ``MuscleTorques`` (the
  same couples), ``FrictionalPlane`` (a contact spring of 10⁴ N/m² per unit length, critically
  damped, its onset smoothed over 10⁻⁴ m; friction smoothed over a slip velocity of 10⁻³ m/s),
  ``lattice.simulate`` with the default method (the implicit midpoint rule: the rod is stiff)
  at ``--dt`` (10⁻² s by default; at 2·10⁻² s, the samples' spacing and the default step, the
  Newton iterations fail where the friction switches direction within a step, and those steps
  are taken in substeps: it completes, slower), no damping.

Both report the average forward and lateral speed as PyElastica's
``compute_projected_velocity`` defines them (the centre of mass's velocity projected on its mean
direction of travel, averaged from the second period on) from samples every 0.02 s, and the wall
time per simulated second. Without PyElastica (``pip install pyelastica``, the ``bench`` extra)
its row is skipped.

Usage: ``python benchmarks/bench_snake.py [--n 50] [--periods 11] [--dt 0.01] [--core C]
[--json PATH] [--smoke]``
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import jax
import numpy as np
from _common import cpu_name, versions, write_json
from _pinning import pinned, restart_pinned

from rbo_jax import lattice as L

try:
    import elastica as ea
except ImportError:  # PyElastica is optional (the "bench" extra)
    ea = None

B_COEFF = np.array([3.4e-3, 3.3e-3, 4.2e-3, 2.6e-3, 3.6e-3, 3.5e-3])
SNAKE = dict(length=0.35, density=1000.0, E=1e6, period=2.0, wave_length=1.0, froude=0.1)
G_ACC = 9.80665
SAMPLE_DT = 0.02


def _parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=50, help="elements (PyElastica) = segments (rbo_jax)")
    p.add_argument("--periods", type=float, default=11.0, help="simulated periods (plus 0.01)")
    p.add_argument("--dt", type=float, default=0.01, help="rbo_jax's step")
    p.add_argument("--pe-dt", type=float, default=1e-4, help="PyElastica's step")
    p.add_argument("--core", type=int, default=None, help="the core to pin to (default: first)")
    p.add_argument("--json", default=None, help="also write the figures to this file")
    p.add_argument("--smoke", action="store_true", help="a tiny run (tests)")
    args = p.parse_args(argv)
    if args.smoke:
        args.n, args.periods = 10, 3.0
    return args


def _mu():
    s = SNAKE
    return s["length"] / (s["period"] ** 2 * G_ACC * s["froude"])


def forward_speed(ts, com, v, period):
    """PyElastica's ``compute_projected_velocity``: the direction of travel from the centre of
    mass's displacement over each period (the first and the last left out), the velocity
    projected on it and averaged from the second period on; ``(forward, lateral)``: its z and x
    components."""
    per = int(round(period / (ts[1] - ts[0])))
    count = int(ts[-1] / period)
    moves = [
        np.mean(com[(i + 1) * per : (i + 2) * per] - com[i * per : (i + 1) * per], axis=0)
        for i in range(1, count - 1)
    ]
    d = np.mean(moves, axis=0)
    d = d / np.linalg.norm(d)
    projected = (v[2 * per :] @ d)[:, None] * d[None]
    avg = projected.mean(axis=0)
    return float(avg[2]), float(avg[0])


def pe_snake(n, periods, dt, b_coeff=B_COEFF):
    """PyElastica's continuum snake (module docstring): ``(ts, com, v, wall seconds)``."""
    s = SNAKE
    period, length = s["period"], s["length"]
    radius = 0.011 * length

    class Sim(ea.BaseSystemCollection, ea.Forcing, ea.Damping, ea.CallBacks, ea.Contact):
        pass

    sim = Sim()
    final_time = (periods + 0.01) * period
    rod = ea.CosseratRod.straight_rod(
        n,
        np.zeros(3),
        np.array([0.0, 0.0, 1.0]),
        np.array([0.0, 1.0, 0.0]),
        length,
        radius,
        s["density"],
        youngs_modulus=s["E"],
        shear_modulus=s["E"] / 1.5,
    )
    sim.append(rod)
    sim.add_forcing_to(rod).using(ea.GravityForces, acc_gravity=np.array([0.0, -G_ACC, 0.0]))
    sim.add_forcing_to(rod).using(
        ea.MuscleTorques,
        base_length=length,
        b_coeff=b_coeff,
        period=period,
        wave_number=2.0 * np.pi / s["wave_length"],
        phase_shift=0.0,
        rest_lengths=rod.rest_lengths,
        ramp_up_time=period,
        direction=np.array([0.0, 1.0, 0.0]),
        with_spline=True,
    )
    plane = ea.Plane(plane_origin=np.array([0.0, -radius, 0.0]), plane_normal=np.array([0, 1.0, 0]))
    sim.append(plane)
    mu = _mu()
    sim.detect_contact_between(rod, plane).using(
        ea.RodPlaneContactWithAnisotropicFriction,
        k=1.0,
        nu=1e-6,
        slip_velocity_tol=1e-8,
        static_mu_array=np.zeros(3),
        kinetic_mu_array=np.array([mu, 1.5 * mu, 2.0 * mu]),
    )
    sim.dampen(rod).using(ea.AnalyticalLinearDamper, damping_constant=2e-3, time_step=dt)
    every = int(round(SAMPLE_DT / dt))
    rec = {"t": [], "com": [], "v": []}

    class Record(ea.CallBackBaseClass):
        def make_callback(self, system, time, current_step):  # noqa: A002 (PyElastica's names)
            if current_step % every == 0:
                rec["t"].append(time)
                rec["com"].append(system.compute_position_center_of_mass())
                rec["v"].append(system.compute_velocity_center_of_mass())

    sim.collect_diagnostics(rod).using(Record)
    sim.finalize()
    stepper = ea.PositionVerlet()
    t0 = time.perf_counter()
    ea.integrate(stepper, sim, final_time, int(round(final_time / dt)), progress_bar=False)
    wall = time.perf_counter() - t0
    return np.array(rec["t"]), np.array(rec["com"]), np.array(rec["v"]), wall


def snake_rod(n, b_coeff=B_COEFF, wave_length=None, period=None):
    """The continuum snake as an ``rbo_jax.lattice`` rod (module docstring)."""
    s = SNAKE
    length = s["length"]
    radius = 0.011 * length
    period = s["period"] if period is None else period
    wave_length = s["wave_length"] if wave_length is None else wave_length
    mu = _mu()
    k = 1e4
    rho_A = s["density"] * np.pi * radius**2
    loads = (
        L.Gravity((0.0, -G_ACC, 0.0)),
        L.MuscleTorques(
            b_coeff,
            period,
            2 * np.pi / wave_length,
            direction=(0.0, 1.0, 0.0),
            ramp_up_time=s["period"],
        ),
        L.FrictionalPlane(
            mu=(mu, 1.5 * mu, 2.0 * mu),
            stiffness=k,
            damping=2.0 * np.sqrt(k * rho_A),
            origin=(0.0, -radius, 0.0),
            normal=(0.0, 1.0, 0.0),
            radius=radius,
            slip_velocity=1e-3,
        ),
    )
    return L.circular_rod(
        n,
        length,
        radius=radius,
        density=s["density"],
        youngs_modulus=s["E"],
        shear_modulus=s["E"] / 1.5,
        base="free",
        loads=loads,
    )


def rj_snake(n, periods, dt):
    """rbo_jax's snake: ``(ts, com, v, first-call seconds, warm seconds, steps)``."""
    rod = snake_rod(n)
    final_time = (periods + 0.01) * SNAKE["period"]
    ts = np.arange(0.0, final_time + 1e-9, SAMPLE_DT)
    state0 = rod.straight()

    def run():
        traj = L.simulate(rod, state0, ts, dt=dt)
        jax.block_until_ready(traj.states)
        return traj

    t0 = time.perf_counter()
    traj = run()
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    traj = run()
    warm = time.perf_counter() - t0
    m = np.asarray(rod.mass)
    com = np.einsum("b,tbi->ti", m, np.asarray(traj.states.r)) / m.sum()
    v = np.einsum("b,tbi->ti", m, np.asarray(traj.states.v)) / m.sum()
    return ts, com, v, first, warm, int(traj.num_steps)


def main(argv=None):
    args = _parse(argv)
    core = args.core if args.core is not None else min(os.sched_getaffinity(0))
    sim_t = (args.periods + 0.01) * SNAKE["period"]
    print(f"# {versions()}; {cpu_name()} ({platform.machine()})")
    print(f"# continuum snake, n = {args.n}, {sim_t:.2f} s simulated, one core each (core {core})")
    rows = []
    with pinned((core,)) as ok:
        if not ok:
            print("# (threads not pinned on this system)")
        ts, com, v, first, warm, steps = rj_snake(args.n, args.periods, args.dt)
        fwd, lat = forward_speed(ts, com, v, SNAKE["period"])
        rows.append(
            dict(
                side="rbo_jax midpoint",
                dt=args.dt,
                steps=steps,
                first=first,
                wall=warm,
                forward=fwd,
                lateral=lat,
                com_z=float(com[-1, 2] - com[0, 2]),
            )
        )
        if ea is not None:
            pe_snake(args.n, 0.05, args.pe_dt)  # numba's kernels compiled first
            ts, com, v, wall = pe_snake(args.n, args.periods, args.pe_dt)
            fwd, lat = forward_speed(ts, com, v, SNAKE["period"])
            rows.append(
                dict(
                    side="PyElastica PositionVerlet",
                    dt=args.pe_dt,
                    steps=int(round(sim_t / args.pe_dt)),
                    first=None,
                    wall=wall,
                    forward=fwd,
                    lateral=lat,
                    com_z=float(com[-1, 2] - com[0, 2]),
                )
            )
        else:
            print("# PyElastica not installed: its row skipped (pip install pyelastica)")
    print(
        f"\n{'side':28s} {'dt [s]':>8s} {'steps':>8s} {'first [s]':>9s} {'wall [s]':>9s} "
        f"{'s/sim s':>8s} {'forward [m/s]':>13s} {'lateral [m/s]':>13s} {'COM dz [m]':>10s}"
    )
    for r in rows:
        first = "-" if r["first"] is None else f"{r['first']:.1f}"
        print(
            f"{r['side']:28s} {r['dt']:8.0e} {r['steps']:8d} {first:>9s} {r['wall']:9.2f} "
            f"{r['wall'] / sim_t:8.3f} {r['forward']:13.5f} {r['lateral']:13.5f} "
            f"{r['com_z']:10.4f}"
        )
    if len(rows) == 2:
        ratio = rows[1]["wall"] / rows[0]["wall"]
        rel = rows[0]["forward"] / rows[1]["forward"] - 1.0
        print(
            f"\nPyElastica / rbo_jax wall time: {ratio:.2f}x; forward speed rbo_jax vs "
            f"PyElastica: {rel:+.2%}"
        )
    result = {"snake": rows, "n": args.n, "simulated_s": sim_t}
    write_json(args.json, result)
    return result


if __name__ == "__main__":
    restart_pinned(sys.argv[1:])  # one core from the start (the "one core each")
    main()
