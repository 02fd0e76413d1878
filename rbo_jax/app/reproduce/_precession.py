"""Section 4.7: regular precessions (4.110)–(4.113) simulated against the closed form, and the
growth of a perturbed precession against the rotating-frame spectrum (4.115)–(4.118)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ...analytic import precession_rate
from ...foundations import QuadraticFoundation, TransverselyIsotropicFoundation
from ...inertia import transversely_isotropic_inertia
from ...kinematics import turn_tensor
from ...models.rigid_body import RigidBodyOscillator
from ...precession import precession_spectrum, regular_precession
from ...simulate import simulate
from ._common import TIGHT, Check, K, save


def precession(out: str, plt) -> list[Check]:
    checks = []
    for A1, A3, vt in [(1.0, 0.6, 0.7), (1.0, 1.0, 1.5)]:
        model = RigidBodyOscillator(
            transversely_isotropic_inertia(A1, A3, K), QuadraticFoundation(1.2, 2.0, K)
        )
        pr = regular_precession(model, vt)
        rate = float(pr.rate)
        paper = float(precession_rate(1.2, vt, A1, A3))
        ts = jnp.linspace(0.0, 3 * 2 * np.pi / rate, 61)
        tr = simulate(model, pr.theta0, pr.Omega0, ts, **TIGHT)
        expected = jax.vmap(pr.theta)(ts)
        err = float(jnp.max(jnp.abs(tr.theta - expected)))
        eq = "(4.106)" if A1 == A3 else "(4.113)"
        checks.append(
            Check(
                f"4.7 {eq}",
                f"simulation started on the precession, A1={A1}, A3={A3}, ϑ={vt}: θ(t) − ϑQ(ψ̇tk)·p",
                f"ψ̇ = {paper:.10f}",
                f"max |Δθ| = {err:.2e}",
                err,
                1e-8,
            )
        )
    # stability in the precessing frame: an unstable case (softening foundation) and its growth
    F = lambda x, t: 0.5 * t - 0.075 * t**2 + 0.5 * x**2  # noqa: E731
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(1.0, 1.2, K), TransverselyIsotropicFoundation(F, K)
    )
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
    checks.append(
        Check(
            "4.7 (4.115)-(4.118)",
            "growth of a perturbed precession (softening foundation, ϑ = 1.8) "
            "vs rotating-frame spectrum",
            f"max Re p = {growth:.6f}",
            f"{slope:.6f}",
            abs(slope / growth - 1),
            0.03,
        )
    )
    if plt is not None:
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.semilogy(tt, dev, label="simulation: deviation in the precessing frame")
        ax.semilogy(
            tt[win],
            dev[win][0] * np.exp(growth * (tt[win] - tt[win][0])),
            "--",
            label="exp(max Re p · t)",
        )
        ax.set_xlabel("t")
        ax.legend()
        ax.set_title("Unstable regular precession (4.113): autodiff variational spectrum")
        save(plt, fig, out, "precession_growth.png")
    return checks
