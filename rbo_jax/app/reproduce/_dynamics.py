"""Sections 4.3–4.6: the balance (4.78) of a semi-tangential load, energy conservation, the
integrals of the simplest oscillator (4.94)–(4.101) and the Euler-angle equations of 4.6.3."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ...foundations import BarrierFoundation, IsotropicFoundation
from ...inertia import transversely_isotropic_inertia
from ...kinematics import integrating_tensor
from ...loads import Friction, SemiTangentialMoment
from ...models.rigid_body import RigidBodyOscillator
from ...simulate import simulate
from ._common import TIGHT, Check, K, save


def _gauss_legendre(t1, n_int, n_nodes=8):
    x, w = np.polynomial.legendre.leggauss(n_nodes)
    edges = np.linspace(0.0, t1, n_int + 1)
    h = np.diff(edges)[:, None]
    return (edges[:-1, None] + 0.5 * h * (x + 1)).ravel(), (0.5 * h * w).ravel()


def balance_and_energy() -> list[Check]:
    A1, A3, M, l1, l2 = 1.0, 0.6, 0.35, 1.0, 0.4
    load = SemiTangentialMoment(M, K, l1, l2)
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, K), BarrierFoundation(1.0, 1.7, 1.8, 1.4, K), load
    )
    T = 8.0
    nodes, weights = _gauss_legendre(T, 16)
    ts = jnp.asarray(np.concatenate([[0.0], nodes, [T]]))
    traj = simulate(model, jnp.array([0.5, -0.4, 0.3]), jnp.array([0.3, 0.9, 0.6]), ts, **TIGHT)
    cv = jnp.einsum("i,nij,j->n", K, traj.turn_tensor, K)
    G = A1 * (traj.omega - traj.Omega) @ K + (A1 - A3) * (traj.Omega @ K) * (1 - cv)
    rhs = np.asarray(jax.vmap(load.gamma)(traj.theta) * M * (l1 - l2) * (1 - cv))[1:-1]
    lhs, integral = float(G[-1] - G[0]), float(np.sum(weights * rhs))
    checks = [
        Check(
            "4.5 (4.78)",
            "Δ[A1(ω−Ω)·k + (A1−A3)(k·Ω)(1−cosϑ)] over t ∈ [0, 8], barrier (4.49), l1=1, l2=0.4",
            f"∫γM(l1−l2)(1−cosϑ)dt = {integral:.10f}",
            f"{lhs:.10f}",
            abs(lhs - integral) / abs(integral),
            1e-8,
        )
    ]
    free = RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, K), BarrierFoundation(1.0, 2.0, 2.0, 1.5, K)
    )
    ts = jnp.linspace(0.0, 200 * np.pi, 401)
    E = np.asarray(
        simulate(free, jnp.array([0.8, -0.3, 0.5]), jnp.array([0.2, 1.1, -0.7]), ts, **TIGHT).energy
    )
    drift = float(np.max(np.abs(E - E[0])) / abs(E[0]))
    checks.append(
        Check(
            "4.3, (4.124)",
            "relative energy drift K + U over 100 periods (barrier foundation)",
            "0 (conserved)",
            f"{drift:.2e}",
            drift,
            1e-9,
        )
    )
    return checks


def _simplest_integrals():
    """The simplest oscillator (A = A E, isotropic foundation, friction b): the integrals (4.94),
    (4.96), (4.99) and the reduced equation (4.101). Returns the checks and what the Euler-angle
    comparison needs."""
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
        Check(
            "4.6 (4.94)", "ω − Ω − (ω0 − Ω0)e^{−bt/A}, relative", "0", f"{err94:.2e}", err94, 1e-8
        ),
        Check("4.6 (4.96)", "max |θ(t)·e|", "0", f"{err96:.2e}", err96, 1e-8),
        Check(
            "4.6 (4.99)",
            "ψ̇ vs (1−cosθ0)/(1−cosθ) ψ̇0 e^{−bt/A}, relative",
            "0",
            f"{err99:.2e}",
            err99,
            1e-8,
        ),
    ]
    # (4.101): reduced nutation equation, integrated independently
    ndot0 = theta[0] @ th_dot[0] / n[0]

    def rhs(tt, y):
        x, v = y
        cen = (
            A
            * np.sin(x)
            / x
            * ((1 - np.cos(n[0])) / (1 - np.cos(x))) ** 2
            * psi_dot[0] ** 2
            * np.exp(-2 * b * tt / A)
        )
        return [v, -(b * v + (c_of(x * x) - cen) * x) / A]

    sol = solve_ivp(
        rhs, (0, t[-1]), [n[0], ndot0], method="DOP853", t_eval=t, rtol=1e-12, atol=1e-12
    )
    err101 = float(np.max(np.abs(sol.y[0] - n)))
    checks.append(
        Check(
            "4.6 (4.101)",
            "|θ(t)| of the 3-D solution vs the reduced equation (scipy)",
            "solution of (4.101)",
            f"max |Δθ| = {err101:.2e}",
            err101,
            1e-8,
        )
    )
    return checks, (A, b, c_of, t, theta, n, ndot0, psi_dot, pred, e)


def _euler_angles(state, out, plt) -> Check:
    """4.6.3: the Euler-angle equations (4.88)-(4.92) with φ = −ψ (β = 0, ϑ = θ), the system
    after (4.107): A(ψ̇(1−cosθ))˙ + bψ̇(1−cosθ) = 0, A(θ̈ − ψ̇² sinθ) + bθ̇ + c(θ²)θ = 0."""
    from scipy.integrate import solve_ivp

    A, b, c_of, t, theta, n, ndot0, psi_dot, pred, e = state
    psi = np.arctan2(
        np.cross(theta[0] / n[0], theta / n[:, None]) @ e, theta @ theta[0] / (n * n[0])
    )
    psi = np.unwrap(psi)

    def euler(tt, y):
        x, v, ps, h = y  # h = ψ̇(1 − cos θ)
        psid = h / (1 - np.cos(x))
        return [v, (A * psid**2 * np.sin(x) - b * v - c_of(x * x) * x) / A, psid, -b * h / A]

    y0 = [n[0], ndot0, 0.0, psi_dot[0] * (1 - np.cos(n[0]))]
    sol = solve_ivp(euler, (0, t[-1]), y0, method="DOP853", t_eval=t, rtol=1e-12, atol=1e-12)
    err_e = float(max(np.max(np.abs(sol.y[0] - n)), np.max(np.abs(sol.y[2] - psi))))
    check = Check(
        "4.6.3 (4.88)-(4.92)",
        "Euler-angle equations (special solution φ = −ψ) vs turn-vector solution: θ(t), ψ(t)",
        "same motion",
        f"max |Δ| = {err_e:.2e}",
        err_e,
        1e-8,
    )
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
        save(plt, fig, out, "simplest_oscillator.png")
    return check


def simplest(out: str, plt) -> list[Check]:
    checks, state = _simplest_integrals()
    return checks + [_euler_angles(state, out, plt)]
