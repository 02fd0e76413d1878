r"""``rbo-jax reproduce``: reproduce the results of the paper and write ``out/report.md``.

Every check compares a quantity computed by rbo_jax with the paper's value or closed form (or an
independent computation: scipy integration of the reduced equations, the Euler-angle equations of
section 4.6.3) and passes when the error is below a stated tolerance. Figures are written next to
the report. The exit status is non-zero if any check fails.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .analytic import nikolai_spectrum, precession_rate
from .fitting import TrajectoryData, fit
from .foundations import IsotropicFoundation, QuadraticFoundation, TransverselyIsotropicFoundation
from .inertia import transversely_isotropic_inertia
from .kinematics import (
    composition_invariants,
    integrating_tensor,
    integrating_tensor_det,
    integrating_tensor_inv,
    skew,
    turn_tensor,
)
from .loads import FollowerMoment, Friction, SemiTangentialMoment
from .maps import stability_map
from .model import RigidBodyOscillator
from .precession import precession_spectrum, regular_precession
from .simulate import simulate
from .stability import spectrum

__all__ = ["Check", "run_reproduction"]

K = jnp.array([0.0, 0.0, 1.0])
TIGHT = dict(rtol=1e-12, atol=1e-12)


@dataclasses.dataclass
class Check:
    section: str
    quantity: str
    paper: str
    ours: str
    error: float
    tolerance: float

    @property
    def passed(self) -> bool:
        return bool(np.isfinite(self.error) and self.error <= self.tolerance)


def _fmt(x) -> str:
    return f"{x:.6g}" if isinstance(x, (float, np.floating)) else str(x)


# ---------------------------------------------------------------------------------------------
# 4.2 Kinematics
# ---------------------------------------------------------------------------------------------


def _kinematics(n: int) -> list[Check]:
    key = jax.random.PRNGKey(0)
    k1, k2, k3 = jax.random.split(key, 3)

    def sample(key):
        axes = jax.random.normal(key, (n, 3))
        axes = axes / jnp.linalg.norm(axes, axis=1, keepdims=True)
        return axes * jax.random.uniform(jax.random.fold_in(key, 1), (n, 1), maxval=3.0)

    th, ph, ps = sample(k1), sample(k2), sample(k3)
    eye = jnp.eye(3)

    def per_point(th, ph, ps):
        Q = turn_tensor(th)
        Z, Zi = integrating_tensor(th), integrating_tensor_inv(th)
        S = turn_tensor(ph)
        # Poisson (4.9)/(4.10) along θ(t) = th + t·ps: ω = Z⁻¹θ̇, dQ/dt = ω×Q
        Qdot = jax.jvp(turn_tensor, (th,), (ps,))[1]
        omega = Zi @ ps
        Qphps = turn_tensor(ph) @ turn_tensor(ps)
        cos_t, vec = composition_invariants(ph, ps)
        t2 = jnp.clip(0.5 * (jnp.trace(Qphps) - 1.0), -1.0, 1.0)
        vinv = 0.5 * jnp.stack([Qphps[2, 1] - Qphps[1, 2], Qphps[0, 2] - Qphps[2, 0],
                                Qphps[1, 0] - Qphps[0, 1]])
        t = jnp.dot(th, th)
        return jnp.stack([
            jnp.max(jnp.abs(Q @ Q.T - eye)),                      # (4.27)
            jnp.max(jnp.abs(Q @ th - th)),                        # (4.8)
            jnp.max(jnp.abs(Z @ Zi - eye)),                       # (4.11)/(4.20)
            # det Z, rel.; 2(1 − cos θ) written as 4 sin²(θ/2), free of cancellation at small θ
            jnp.abs(integrating_tensor_det(th) * 4 * jnp.sin(0.5 * jnp.sqrt(t)) ** 2 / t - 1),
            jnp.max(jnp.abs(Z.T - Q @ Z)) + jnp.max(jnp.abs(Q @ Z - Z @ Q)),  # (4.13)
            jnp.max(jnp.abs(integrating_tensor(S @ th) - S @ Z @ S.T)),      # (4.12)
            jnp.max(jnp.abs(Qdot - skew(omega) @ Q)),            # (4.9)
            jnp.abs(cos_t - t2) + jnp.max(jnp.abs(vec - vinv)),  # (4.6)-(4.7)
        ])

    errs = np.asarray(jax.jit(jax.vmap(per_point))(th, ph, ps)).max(axis=0)
    names = [
        ("(4.27)", "Q·Qᵀ = E", "0"),
        ("(4.8)", "Q(θ)·θ = θ", "0"),
        ("(4.11), (4.20)", "Z·Z⁻¹ = E", "0"),
        ("after (4.11)", "det Z = θ²/(2(1−cosθ)) (relative)", "closed form"),
        ("(4.13)", "Zᵀ = Q·Z = Z·Q", "0"),
        ("(4.12)", "Z(S·θ) = S·Z·Sᵀ", "0"),
        ("(4.9), (4.19)", "dQ/dt = ω×Q, ω = Z⁻¹·θ̇", "0"),
        ("(4.6), (4.7) ERRATA 1-2", "composition invariants vs Q(φ)·Q(ψ)", "matrix product"),
    ]
    return [
        Check(f"4.2 {eq}", f"{quantity} ({n} random points, max error)", paper, _fmt(float(e)),
              float(e), 1e-12)
        for (eq, quantity, paper), e in zip(names, errs)
    ]


# ---------------------------------------------------------------------------------------------
# 4.4-4.5 Nikolai paradox
# ---------------------------------------------------------------------------------------------


def _nikolai_model(M, c, A3, d=1.0, A1=1.0):
    return RigidBodyOscillator(transversely_isotropic_inertia(A1, A3, K),
                               QuadraticFoundation(c, d, K), FollowerMoment(M, K))


def _nikolai(n_grid: int, out: str, plt) -> list[Check]:
    checks = []
    Ms = np.linspace(-0.8, 0.8, 2 * (n_grid // 2) + 1)
    axes1 = {"M": Ms, "c": np.linspace(0.2, 2.0, n_grid), "A3": np.array([0.6])}
    axes2 = {"M": Ms, "c": np.array([1.0]), "A3": np.linspace(0.2, 2.0, n_grid)}

    def model_fn(M, c, A3):
        return _nikolai_model(M, c, A3)

    def theta_eq_fn(M, c, A3):
        return M * K  # (4.62), d = 1

    maps = [stability_map(model_fn, ax, theta_eq_fn=theta_eq_fn) for ax in (axes1, axes2)]
    err = 0.0
    for ds in maps:
        pts = np.stack(np.meshgrid(*[ds[k].values for k in ("M", "c", "A3")], indexing="ij"),
                       -1).reshape(-1, 3)
        ref = np.asarray(jax.jit(jax.vmap(
            lambda x: jnp.sort(nikolai_spectrum(1.0, x[2], x[1], 1.0, x[0]))))(jnp.asarray(pts)))
        ours = ds["eigenvalues"].values.reshape(-1, 6)
        err = max(err, float(np.max(np.abs(np.sort_complex(ours) - np.sort_complex(ref)))))
    checks.append(Check("4.4 Nikolai",
                        "autodiff spectrum vs bending/torsion roots of (4.69), all map points",
                        "(A1p²+K)²+M²/4 = 0, A3p²+d = 0", f"max |Δp| = {err:.2e}", err, 1e-10))
    ab = maps[0]["spectral_abscissa"]
    nonzero = ab.sel(M=ab.M[np.abs(ab.M) > 1e-12])
    frac = float((nonzero > 0).mean())
    checks.append(Check("4.4-4.5 Nikolai", "fraction of points with M ≠ 0 and max Re p > 0",
                        "1 (unstable for every M ≠ 0)", _fmt(frac), abs(1 - frac), 0.0))
    # the linear theory (4.73)/(4.74): Aθ̈ + [c(E − k⊗k) + d k⊗k]θ = Mk, as a first-order system
    lin = 0.0
    for c in axes1["c"]:
        A = np.diag([1.0, 1.0, 0.6])
        Kl = c * np.diag([1.0, 1.0, 0.0]) + np.diag([0.0, 0.0, 1.0])
        Jl = np.block([[np.zeros((3, 3)), np.eye(3)], [-np.linalg.solve(A, Kl), np.zeros((3, 3))]])
        lin = max(lin, float(np.max(np.linalg.eigvals(Jl).real)))
    ours = float(ab.sel(M=ab.M[np.abs(ab.M) > 1e-12]).min())
    checks.append(Check("4.4 (4.73)-(4.74)", "max Re p of the linear theory (4.73) over the c grid",
                        "0: misses the instability "
                        f"(ours: min over M ≠ 0 of max Re p = {ours:.3g} > 0)",
                        f"{lin:.2e}", abs(lin), 1e-12))

    # root locus against M
    Ms_locus = np.linspace(-0.8, 0.8, 81)
    f = jax.jit(jax.vmap(lambda M: spectrum(_nikolai_model(M, 1.0, 0.6), M * K)))
    eigs = np.asarray(f(jnp.asarray(Ms_locus)))
    if plt is not None:
        from .plotting import plot_root_locus, plot_stability_map

        for ds, (x, y, sel, name) in zip(maps, [("M", "c", {"A3": 0.6}, "map_M_c.png"),
                                               ("M", "A3", {"c": 1.0}, "map_M_A3.png")]):
            ax = plot_stability_map(ds, x, y, select=sel,
                                    title=f"Nikolai problem: max Re p over ({x}, {y}/d)")
            ax.figure.savefig(os.path.join(out, name), dpi=110, bbox_inches="tight")
            plt.close(ax.figure)
        ax = plot_root_locus(Ms_locus, eigs, label="follower moment M")
        ax.figure.savefig(os.path.join(out, "root_locus.png"), dpi=110, bbox_inches="tight")
        plt.close(ax.figure)

    # simulation growth vs Re p
    M, c = 0.5, 1.0
    model = _nikolai_model(M, c, 0.6, d=2.0)
    rate = float(np.max(np.real(nikolai_spectrum(1.0, 0.6, c, 2.0, M))))
    ts = jnp.linspace(0.0, 100.0, 401)
    traj = simulate(model, (M / 2.0) * K + jnp.array([1e-9, 0.0, 0.0]), jnp.zeros(3), ts, **TIGHT)
    dev = np.linalg.norm(np.asarray(traj.theta)[:, :2], axis=1)
    t = np.asarray(ts)
    slope = np.polyfit(t[t > 30], np.log(dev[t > 30]), 1)[0]
    checks.append(Check("4.4 Nikolai", "growth rate of a 1e-9 perturbation in a simulation",
                        f"max Re p of (4.69) = {rate:.6f}", f"{slope:.6f}", abs(slope / rate - 1),
                        0.02))
    if plt is not None:
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.semilogy(t, dev, label="simulation |bending deviation|")
        ax.semilogy(t, dev[t > 30][0] * np.exp(rate * (t - t[t > 30][0])), "--",
                    label="exp(max Re p · t), (4.69)")
        ax.set_xlabel("t")
        ax.legend()
        ax.set_title(f"Nikolai paradox, follower M = {M}, c = {c}, d = 2")
        fig.savefig(os.path.join(out, "nikolai_growth.png"), dpi=110, bbox_inches="tight")
        plt.close(fig)
    return checks


# ---------------------------------------------------------------------------------------------
# 4.5 the balance (4.78); energy
# ---------------------------------------------------------------------------------------------


def _gauss_legendre(t1, n_int, n_nodes=8):
    x, w = np.polynomial.legendre.leggauss(n_nodes)
    edges = np.linspace(0.0, t1, n_int + 1)
    h = np.diff(edges)[:, None]
    return (edges[:-1, None] + 0.5 * h * (x + 1)).ravel(), (0.5 * h * w).ravel()


def _balance_and_energy() -> list[Check]:
    from .foundations import BarrierFoundation

    A1, A3, M, l1, l2 = 1.0, 0.6, 0.35, 1.0, 0.4
    load = SemiTangentialMoment(M, K, l1, l2)
    model = RigidBodyOscillator(transversely_isotropic_inertia(A1, A3, K),
                                BarrierFoundation(1.0, 1.7, 1.8, 1.4, K), load)
    T = 8.0
    nodes, weights = _gauss_legendre(T, 16)
    ts = jnp.asarray(np.concatenate([[0.0], nodes, [T]]))
    traj = simulate(model, jnp.array([0.5, -0.4, 0.3]), jnp.array([0.3, 0.9, 0.6]), ts, **TIGHT)
    cv = jnp.einsum("i,nij,j->n", K, traj.turn_tensor, K)
    G = A1 * (traj.omega - traj.Omega) @ K + (A1 - A3) * (traj.Omega @ K) * (1 - cv)
    rhs = np.asarray(jax.vmap(load.gamma)(traj.theta) * M * (l1 - l2) * (1 - cv))[1:-1]
    lhs, integral = float(G[-1] - G[0]), float(np.sum(weights * rhs))
    checks = [Check("4.5 (4.78)",
                    "Δ[A1(ω−Ω)·k + (A1−A3)(k·Ω)(1−cosϑ)] over t ∈ [0, 8], "
                    "barrier (4.49), l1=1, l2=0.4",
                    f"∫γM(l1−l2)(1−cosϑ)dt = {integral:.10f}", f"{lhs:.10f}",
                    abs(lhs - integral) / abs(integral), 1e-8)]
    free = RigidBodyOscillator(transversely_isotropic_inertia(A1, A3, K),
                               BarrierFoundation(1.0, 2.0, 2.0, 1.5, K))
    ts = jnp.linspace(0.0, 200 * np.pi, 401)
    E = np.asarray(simulate(free, jnp.array([0.8, -0.3, 0.5]), jnp.array([0.2, 1.1, -0.7]), ts,
                            **TIGHT).energy)
    drift = float(np.max(np.abs(E - E[0])) / abs(E[0]))
    checks.append(Check("4.3, (4.124)",
                        "relative energy drift K + U over 100 periods (barrier foundation)",
                        "0 (conserved)", f"{drift:.2e}", drift, 1e-9))
    return checks


# ---------------------------------------------------------------------------------------------
# 4.6 the simplest oscillator; Euler angles (4.88)-(4.92)
# ---------------------------------------------------------------------------------------------


def _simplest(out: str, plt) -> list[Check]:
    from scipy.integrate import solve_ivp

    A, c0, c2, b = 1.3, 1.0, 0.4, 0.08
    F = lambda s: 0.5 * c0 * s + 0.25 * c2 * s**2  # noqa: E731  u(θ²) of (4.83)
    c_of = lambda s: c0 + c2 * s  # noqa: E731  c(θ²) = 2u'
    model = RigidBodyOscillator(A * jnp.eye(3), IsotropicFoundation(F), Friction(b))
    th0, Om0 = jnp.array([0.9, 0.2, -0.4]), jnp.array([0.1, 0.8, 0.5])
    ts = jnp.linspace(0.0, 15.0, 301)
    tr = simulate(model, th0, Om0, ts, **TIGHT)
    t = np.asarray(ts)
    theta, omega, Omega = np.asarray(tr.theta), np.asarray(tr.omega), np.asarray(tr.Omega)
    d0 = omega[0] - Omega[0]
    e = d0 / np.linalg.norm(d0)
    err94 = np.max(np.abs(omega - Omega - d0 * np.exp(-b * t / A)[:, None])) / np.linalg.norm(d0)
    err96 = np.max(np.abs(theta @ e))
    th_dot = np.asarray(jax.vmap(lambda a, o: integrating_tensor(a).T @ o)(tr.theta, tr.Omega))
    n = np.linalg.norm(theta, axis=1)
    psi_dot = np.cross(theta, th_dot) @ e / n**2
    pred = (1 - np.cos(n[0])) / (1 - np.cos(n)) * psi_dot[0] * np.exp(-b * t / A)
    err99 = np.max(np.abs(psi_dot / pred - 1))
    checks = [
        Check("4.6 (4.94)", "ω − Ω − (ω0 − Ω0)e^{−bt/A}, relative", "0", f"{err94:.2e}", err94,
              1e-8),
        Check("4.6 (4.96)", "max |θ(t)·e|", "0", f"{err96:.2e}", err96, 1e-8),
        Check("4.6 (4.99)", "ψ̇ vs (1−cosθ0)/(1−cosθ) ψ̇0 e^{−bt/A}, relative", "0",
              f"{err99:.2e}", err99, 1e-8),
    ]
    # (4.101): reduced nutation equation, integrated independently
    ndot0 = theta[0] @ th_dot[0] / n[0]

    def rhs(tt, y):
        x, v = y
        cen = (A * np.sin(x) / x * ((1 - np.cos(n[0])) / (1 - np.cos(x))) ** 2 * psi_dot[0] ** 2
               * np.exp(-2 * b * tt / A))
        return [v, -(b * v + (c_of(x * x) - cen) * x) / A]

    sol = solve_ivp(rhs, (0, t[-1]), [n[0], ndot0], method="DOP853", t_eval=t, rtol=1e-12,
                    atol=1e-12)
    err101 = float(np.max(np.abs(sol.y[0] - n)))
    checks.append(Check("4.6 (4.101)", "|θ(t)| of the 3-D solution vs the reduced equation (scipy)",
                        "solution of (4.101)", f"max |Δθ| = {err101:.2e}", err101, 1e-8))

    # 4.6.3: Euler angles (4.88)-(4.92) with φ = −ψ (β = 0, ϑ = θ): the system after (4.107)
    #   A(ψ̇(1−cosθ))˙ + bψ̇(1−cosθ) = 0,  A(θ̈ − ψ̇² sinθ) + bθ̇ + c(θ²)θ = 0
    psi = np.arctan2(np.cross(theta[0] / n[0], theta / n[:, None]) @ e,
                     theta @ theta[0] / (n * n[0]))
    psi = np.unwrap(psi)

    def euler(tt, y):
        x, v, ps, h = y  # h = ψ̇(1 − cos θ)
        psid = h / (1 - np.cos(x))
        return [v, (A * psid**2 * np.sin(x) - b * v - c_of(x * x) * x) / A, psid, -b * h / A]

    y0 = [n[0], ndot0, 0.0, psi_dot[0] * (1 - np.cos(n[0]))]
    sol = solve_ivp(euler, (0, t[-1]), y0, method="DOP853", t_eval=t, rtol=1e-12, atol=1e-12)
    err_e = float(max(np.max(np.abs(sol.y[0] - n)), np.max(np.abs(sol.y[2] - psi))))
    checks.append(Check("4.6.3 (4.88)-(4.92)",
                        "Euler-angle equations (special solution φ = −ψ) vs turn-vector solution: "
                        "θ(t), ψ(t)",
                        "same motion", f"max |Δ| = {err_e:.2e}", err_e, 1e-8))
    if plt is not None:
        fig, axs = plt.subplots(1, 2, figsize=(10, 3.8))
        axs[0].plot(t, n, label="|θ| turn-vector solution")
        axs[0].plot(t, sol.y[0], "--", label="θ, Euler angles / (4.101)")
        axs[0].set_xlabel("t")
        axs[0].legend()
        axs[1].plot(t, psi_dot, label="ψ̇ from θ×θ̇ (4.98)")
        axs[1].plot(t, pred, "--", label="(4.99)")
        axs[1].set_xlabel("t")
        axs[1].legend()
        fig.suptitle("Simplest oscillator with friction: nutation and precession")
        fig.savefig(os.path.join(out, "simplest_oscillator.png"), dpi=110, bbox_inches="tight")
        plt.close(fig)
    return checks


# ---------------------------------------------------------------------------------------------
# 4.7 regular precession
# ---------------------------------------------------------------------------------------------


def _precession(out: str, plt) -> list[Check]:
    checks = []
    for A1, A3, vt in [(1.0, 0.6, 0.7), (1.0, 1.0, 1.5)]:
        model = RigidBodyOscillator(transversely_isotropic_inertia(A1, A3, K),
                                    QuadraticFoundation(1.2, 2.0, K))
        pr = regular_precession(model, vt)
        rate = float(pr.rate)
        paper = float(precession_rate(1.2, vt, A1, A3))
        ts = jnp.linspace(0.0, 3 * 2 * np.pi / rate, 61)
        tr = simulate(model, pr.theta0, pr.Omega0, ts, **TIGHT)
        expected = jax.vmap(pr.theta)(ts)
        err = float(jnp.max(jnp.abs(tr.theta - expected)))
        eq = "(4.106)" if A1 == A3 else "(4.113)"
        checks.append(Check(f"4.7 {eq}",
                            f"simulation started on the precession, A1={A1}, A3={A3}, ϑ={vt}: "
                            "θ(t) − ϑQ(ψ̇tk)·p",
                            f"ψ̇ = {paper:.10f}", f"max |Δθ| = {err:.2e}", err, 1e-8))
    # stability in the precessing frame: an unstable case (softening foundation) and its growth
    F = lambda x, t: 0.5 * t - 0.075 * t**2 + 0.5 * x**2  # noqa: E731
    model = RigidBodyOscillator(transversely_isotropic_inertia(1.0, 1.2, K),
                                TransverselyIsotropicFoundation(F, K))
    pr = regular_precession(model, 1.8)
    p = np.asarray(precession_spectrum(model, pr))
    growth = float(np.max(p.real))
    ts = jnp.linspace(0.0, 12.0, 241)
    tr = simulate(model, pr.theta0 + 1e-9 * pr.p, pr.Omega0, ts, **TIGHT)
    x = np.asarray(jax.vmap(lambda t, th: turn_tensor(-pr.rate * t * pr.k) @ th)(ts, tr.theta))
    dev = np.linalg.norm(x - np.asarray(pr.theta0), axis=1)
    tt = np.asarray(ts)
    win = (tt > 3) & (dev < 1e-3)
    slope = float(np.polyfit(tt[win], np.log(dev[win]), 1)[0])
    checks.append(Check("4.7 (4.115)-(4.118)",
                        "growth of a perturbed precession (softening foundation, ϑ = 1.8) "
                        "vs rotating-frame spectrum",
                        f"max Re p = {growth:.6f}", f"{slope:.6f}", abs(slope / growth - 1), 0.03))
    if plt is not None:
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.semilogy(tt, dev, label="simulation: deviation in the precessing frame")
        ax.semilogy(tt[win], dev[win][0] * np.exp(growth * (tt[win] - tt[win][0])), "--",
                    label="exp(max Re p · t)")
        ax.set_xlabel("t")
        ax.legend()
        ax.set_title("Unstable regular precession (4.113): autodiff variational spectrum")
        fig.savefig(os.path.join(out, "precession_growth.png"), dpi=110, bbox_inches="tight")
        plt.close(fig)
    return checks


# ---------------------------------------------------------------------------------------------
# Fitting
# ---------------------------------------------------------------------------------------------


def _fitting() -> list[Check]:
    sigma = 1e-3
    A = transversely_isotropic_inertia(1.0, 0.6, K)
    true = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    th0, Om0 = jnp.array([0.8, -0.3, 0.5]), jnp.array([0.2, 1.1, -0.7])
    ts = jnp.linspace(0.0, 6.0, 60)
    Q = simulate(true, th0, Om0, ts, **TIGHT).turn_tensor
    eta = sigma * jax.random.normal(jax.random.PRNGKey(7), (ts.shape[0], 3))
    Q_obs = jax.vmap(lambda e, q: turn_tensor(e) @ q)(eta, Q)
    res = fit(RigidBodyOscillator(A, QuadraticFoundation(1.3, 1.4, K)),
              TrajectoryData(ts, Q=Q_obs, theta0=th0, Omega0=Om0, sigma_theta=sigma),
              lambda m: (m.foundation.c, m.foundation.d))
    checks = []
    for name, truth, val, se in zip(("c", "d"), (1.0, 2.0), res.params, res.stderr):
        z = abs(float(val) - truth) / float(se)
        checks.append(Check("fitting",
                            f"{name} from noisy attitudes (σ = 1e-3 rad), start 30 % off",
                            f"{truth}", f"{float(val):.5f} ± {float(se):.1e}", z, 3.0))
    return checks


# ---------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------


def run_reproduction(out: str = "out", *, quick: bool = False, figures: bool = True,
                     log: Callable[[str], None] = print) -> list[Check]:
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
        ("kinematics (4.2)", lambda: _kinematics(50 if quick else 1000)),
        ("Nikolai paradox (4.4)-(4.5)", lambda: _nikolai(9 if quick else 61, out, plt)),
        ("balance (4.78) and energy", _balance_and_energy),
        ("simplest oscillator (4.6)", lambda: _simplest(out, plt)),
        ("regular precession (4.7)", lambda: _precession(out, plt)),
        ("fitting", _fitting),
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
        "refer to its section 4 (with the project's ERRATA).",
        "",
        f"{sum(c.passed for c in checks)} of {len(checks)} checks passed in {elapsed:.1f} s"
        + (" (quick mode)" if quick else "") + ".",
        "",
        "| section | quantity | paper | ours | error | tolerance | |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in checks:
        lines.append(f"| {c.section} | {c.quantity} | {c.paper} | {c.ours} | {c.error:.2e} | "
                     f"{c.tolerance:.0e} | {'pass' if c.passed else '**FAIL**'} |")
    if figures:
        lines += ["", "## Figures", ""]
        for name, caption in [
            ("map_M_c.png", "Stability map of the Nikolai problem over (M, c/d), A3/A1 = 0.6"),
            ("map_M_A3.png", "Stability map over (M, A3/A1), c/d = 1"),
            ("root_locus.png", "Root locus against the follower moment M"),
            ("nikolai_growth.png", "Simulated growth vs max Re p of (4.69)"),
            ("simplest_oscillator.png",
             "Simplest oscillator: (4.99), (4.101) and the Euler-angle equations"),
            ("precession_growth.png", "Unstable regular precession vs its rotating-frame spectrum"),
        ]:
            if os.path.exists(os.path.join(out, name)):
                lines += [f"![{caption}]({name})", "", f"*{caption}*", ""]
    with open(os.path.join(out, "report.md"), "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
