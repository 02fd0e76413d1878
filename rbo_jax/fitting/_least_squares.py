"""The least-squares solvers of :func:`rbo_jax.fit`: Levenberg–Marquardt and damped
Gauss–Newton on the whitened residuals, with forward-mode Jacobians through the ODE solves."""

from __future__ import annotations

import numpy as np

from ._residuals import flatten, jacobian_matrix, unflatten_like

_PATIENCE = 6


def log(history, loss, bar, verbose):
    """Record the loss of an iteration (progress bar, verbose print)."""
    history.append(float(loss))
    if bar is not None:
        bar.update(1)
        bar.set_postfix(loss=f"{float(loss):.3e}")
    if verbose:
        print(f"iteration {len(history)}: loss = {float(loss):.6e}")


def run_least_squares(evaluate, u, optimizer, tol, max_steps, history, bar=None, verbose=False):
    r"""Levenberg–Marquardt (Madsen, Nielsen & Tingleff 2004, Alg. 3.16, with Marquardt's
    diagonal scaling) or damped Gauss–Newton (step halving), iterated on the host around one
    compiled program ``evaluate(u) -> (residuals, Jacobian as a tree like u)`` (for a fit,
    :func:`residuals_and_jacobian`; also the lattice fits of :mod:`rbo_jax.lattice`).

    Why not ``optimistix.LevenbergMarquardt``: its init, step, termination and our loss and
    covariance evaluations are separate compiled programs, each one containing the ODE solve and
    its forward-mode derivative (~4 compilations of tens of seconds per fit structure); here one
    program serves everything, and the p×p linear algebra runs in NumPy. Returns ``(u, steps,
    converged, message)``.
    """
    x = flatten(u)
    r, J_tree = evaluate(u)
    r = np.asarray(r, dtype=np.float64)
    J = jacobian_matrix(J_tree, r.size)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        raise FloatingPointError(
            "the residuals or their Jacobian are not finite at the starting point: check the "
            "starting parameters and initial states (the simulation may fail there: a singular "
            "point, the foundation's domain, or the step budget solve_max_steps)."
        )
    F = 0.5 * float(r @ r)
    log(history, F, bar, verbose)
    A = J.T @ J
    g = J.T @ r
    gauss_newton = optimizer == "gauss_newton"
    mu = 0.0 if gauss_newton else 1e-3 * float(np.max(np.diag(A)))
    nu = 2.0
    stalled = 0
    for steps in range(1, max_steps + 1):
        if F == 0.0 or not np.any(g):
            return unflatten_like(x, u), steps - 1, True, "converged (zero residual or gradient)"
        D = np.diag(np.maximum(np.diag(A), 1e-30))
        try:
            h = np.linalg.solve(A + mu * D, -g)
        except np.linalg.LinAlgError:
            h = np.linalg.lstsq(A + mu * D, -g, rcond=None)[0]
        if np.linalg.norm(h) <= tol * (np.linalg.norm(x) + tol):
            return unflatten_like(x, u), steps - 1, True, "converged (step below tolerance)"
        factor = 1.0
        accepted = False
        for _ in range(12 if gauss_newton else 1):
            x_new = x + factor * h
            r_new, J_new = evaluate(unflatten_like(x_new, u))
            r_new = np.asarray(r_new, dtype=np.float64)
            F_new = 0.5 * float(r_new @ r_new) if np.all(np.isfinite(r_new)) else np.inf
            predicted = 0.5 * float((factor * h) @ (mu * D @ (factor * h) - g))
            rho = (F - F_new) / predicted if predicted > 0 else -np.inf
            if rho > 0 and np.isfinite(F_new):
                accepted = True
                break
            factor *= 0.5
        if accepted:
            improvement = F - F_new
            x, r, F = x_new, r_new, F_new
            J = jacobian_matrix(J_new, r.size)
            A, g = J.T @ J, J.T @ r
            if not gauss_newton:
                mu *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
                nu = 2.0
            stalled = stalled + 1 if improvement <= tol * F else 0
        else:
            if gauss_newton:
                return unflatten_like(x, u), steps, False, "Gauss-Newton: no descent step found"
            mu *= nu
            nu *= 2.0
            stalled += 1
        log(history, F, bar, verbose)
        if stalled >= _PATIENCE:
            return (
                unflatten_like(x, u),
                steps,
                True,
                (
                    f"converged (no relative decrease of the loss above tol in {_PATIENCE} steps: "
                    "a minimum, possibly local, or the noise floor of the ODE solves)"
                ),
            )
    return (
        unflatten_like(x, u),
        max_steps,
        False,
        f"max_steps = {max_steps} reached before convergence",
    )
