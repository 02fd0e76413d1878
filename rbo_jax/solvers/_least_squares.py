r"""Nonlinear least squares on the host: Levenberg–Marquardt or damped Gauss–Newton around one
compiled program that returns the residuals and their Jacobian, and the Gauss–Newton covariance
of the fitted parameters at the optimum. Every least-squares fit of the package runs here:
:func:`rbo_jax.fit` and the lattice's and rod's fits (:mod:`rbo_jax.lattice`).

The iteration runs in NumPy (the p×p linear algebra is tiny) around that one program, which
serves the iterations, the trial points and the covariance, rather than optimistix's
``LevenbergMarquardt``, whose init, step and termination are separate compiled programs, each
holding the model's solve and its derivative (see benchmarks/README.md, History).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

_PATIENCE = 6


def record_loss(history, loss, bar, verbose):
    """Record the loss of an iteration (progress bar, verbose print)."""
    history.append(float(loss))
    if bar is not None:
        bar.update(1)
        bar.set_postfix(loss=f"{float(loss):.3e}")
    if verbose:
        print(f"iteration {len(history)}: loss = {float(loss):.6e}")


def run_least_squares(evaluate, u, optimizer, tol, max_steps, history, bar=None, verbose=False):
    r"""Levenberg–Marquardt (Madsen, Nielsen & Tingleff 2004, Alg. 3.16, with Marquardt's
    diagonal scaling; ``optimizer="levenberg_marquardt"``) or damped Gauss–Newton (step halving;
    ``"gauss_newton"``) on $F(u) = \frac12|r(u)|^2$, from ``u`` (a tree of float arrays),
    iterated on the host around one compiled program ``evaluate(u) -> (residuals, Jacobian as a
    tree like u)``. Converged: a zero residual or gradient, a step below ``tol`` relative to
    ``u``, or no relative decrease of $F$ above ``tol`` in six steps; ``history`` receives $F$
    of every iteration. Returns ``(u, steps, converged, message)``.
    """
    x = _flatten(u)
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
    record_loss(history, F, bar, verbose)
    A = J.T @ J
    g = J.T @ r
    gauss_newton = optimizer == "gauss_newton"
    mu = 0.0 if gauss_newton else 1e-3 * float(np.max(np.diag(A)))
    nu = 2.0
    stalled = 0
    for steps in range(1, max_steps + 1):
        if F == 0.0 or not np.any(g):
            steps, converged, message = steps - 1, True, "converged (zero residual or gradient)"
            break
        D = np.diag(np.maximum(np.diag(A), 1e-30))
        try:
            h = np.linalg.solve(A + mu * D, -g)
        except np.linalg.LinAlgError:
            h = np.linalg.lstsq(A + mu * D, -g, rcond=None)[0]
        if np.linalg.norm(h) <= tol * (np.linalg.norm(x) + tol):
            steps, converged, message = steps - 1, True, "converged (step below tolerance)"
            break
        factor = 1.0
        accepted = False
        for _ in range(12 if gauss_newton else 1):
            x_new = x + factor * h
            r_new, J_new = evaluate(_unflatten_like(x_new, u))
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
        elif gauss_newton:
            converged, message = False, "Gauss-Newton: no descent step found"
            break
        else:
            mu *= nu
            nu *= 2.0
            stalled += 1
        record_loss(history, F, bar, verbose)
        if stalled >= _PATIENCE:
            converged, message = (
                True,
                (
                    f"converged (no relative decrease of the loss above tol in {_PATIENCE} steps: "
                    "a minimum, possibly local, or the noise floor of the ODE solves)"
                ),
            )
            break
    else:
        steps, converged = max_steps, False
        message = f"max_steps = {max_steps} reached before convergence"
    return _unflatten_like(x, u), steps, converged, message


def gauss_newton_covariance(r, J_tree, scale, measured=None):
    r"""The Gauss–Newton covariance of the fitted parameters $x$ at a least-squares optimum,
    $\mathrm{Cov} = s^2 (J_x^TJ_x)^{-1}$, the Hessian of $\frac12|r|^2$ approximated by $J^TJ$.

    ``J_tree`` is the Jacobian of the residuals ``r`` with respect to the coordinates $u$ the
    fit iterates on (a tree, as ``evaluate`` returns it); ``scale`` is $du/dx$ per column (flat;
    $1/x$ for $u = \log x$), so that $J_x = J_u\,\mathrm{diag}(du/dx)$: the delta method, which
    carries the covariance of $u$ to $x$. $s^2 = 1$ for residuals whitened by known noise levels
    (``measured=None``), else the residual variance $|r|^2/(m - p)$ over the ``measured``
    residuals $m$ (at least 1 in the denominator). Returns ``(covariance, standard errors (flat),
    note)``; a singular $J^TJ$ (parameters not identifiable from the data) gives infinite
    covariances and a note for the fit's message.
    """
    r = np.asarray(r, dtype=np.float64)
    J = jacobian_matrix(J_tree, r.size) * np.asarray(scale, dtype=np.float64)[None, :]
    n_par = J.shape[1]
    s2 = 1.0 if measured is None else float(r @ r) / max(measured - n_par, 1)
    note = ""
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((n_par, n_par), np.inf)
        note = "; J^T J is singular: the parameters are not identifiable from these data"
    return cov, np.sqrt(np.clip(np.diag(cov), 0.0, np.inf)), note


def value_and_jacfwd(f, u):
    """``(f(u), ∂f/∂u)``, the Jacobian by forward mode (one tangent per scalar of the tree ``u``,
    batched) as a tree like ``u``: what ``evaluate`` returns, given the residual function."""

    def both(v):
        r = f(v)
        return r, r

    J, r = jax.jacfwd(both, has_aux=True)(u)
    return r, J


def jacobian_matrix(J_tree, n_res):
    """The Jacobian tree of ``evaluate`` as an (residuals, scalars of u) matrix, the scalars in
    the order of the tree's leaves."""
    return np.concatenate(
        [
            np.asarray(b, dtype=np.float64).reshape(n_res, -1)
            for b in jax.tree_util.tree_leaves(J_tree)
        ],
        axis=1,
    )


def _flatten(tree):
    leaves = jax.tree_util.tree_leaves(tree)
    return np.concatenate([np.asarray(x, dtype=np.float64).ravel() for x in leaves])


def _unflatten_like(flat, tree):
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    out, i = [], 0
    for x in leaves:
        n = int(np.size(x))
        out.append(jnp.asarray(flat[i : i + n].reshape(np.shape(x)), dtype=jnp.result_type(float)))
        i += n
    return jax.tree_util.tree_unflatten(treedef, out)


def levenberg_marquardt(evaluate, x, *, max_steps: int = 30, tol: float = 1e-10):
    r"""Levenberg–Marquardt in JAX, the same iteration as :func:`run_least_squares` (Madsen,
    Nielsen & Tingleff 2004, Alg. 3.16, Marquardt's diagonal scaling), run by the package's one
    loop (:func:`rbo_jax.solvers.iterate`) so that it can be jitted and vmapped: the solves of a
    profile likelihood, one lane per profiled value, in one program.

    ``evaluate(x) -> (r, J)``: the residuals and their Jacobian (a matrix) at the flat vector
    ``x``. Converged: a step below ``tol`` relative to ``x``, or a zero gradient. Returns
    ``(x, F, converged, num_steps)``, $F = \frac12|r|^2$ at ``x``.
    """
    from ._iterate import RUNNING, iterate

    r, J = evaluate(x)
    F = 0.5 * jnp.sum(r**2)
    A = J.T @ J
    mu = 1e-3 * jnp.max(jnp.diag(A))
    state = (r, J, F, mu, jnp.asarray(2.0, F.dtype))

    def step(x, state):
        r, J, F, mu, nu = state
        A, g = J.T @ J, J.T @ r
        D = jnp.diag(jnp.maximum(jnp.diag(A), 1e-30))
        h = jnp.linalg.solve(A + mu * D, -g)
        small = jnp.linalg.norm(h) <= tol * (jnp.linalg.norm(x) + tol)
        r_new, J_new = evaluate(x + h)
        F_new = jnp.where(jnp.all(jnp.isfinite(r_new)), 0.5 * jnp.sum(r_new**2), jnp.inf)
        predicted = 0.5 * h @ (mu * D @ h - g)
        rho = jnp.where(predicted > 0, (F - F_new) / predicted, -jnp.inf)
        accept = (rho > 0) & jnp.isfinite(F_new)
        x = jnp.where(accept, x + h, x)
        r, J, F = (jnp.where(accept, a, b) for a, b in ((r_new, r), (J_new, J), (F_new, F)))
        mu = jnp.where(accept, mu * jnp.maximum(1 / 3, 1 - (2 * rho - 1) ** 3), mu * nu)
        nu = jnp.where(accept, 2.0, 2.0 * nu)
        done = small | ~jnp.any(g)
        return x, (r, J, F, mu, nu), jnp.where(done, 0, RUNNING)

    x, state, code, steps = iterate(step, x, state, max_steps=max_steps, exhausted=1)
    return x, state[2], code == 0, steps
