r"""Fitting a rod's constants to its measured eigenvalues: frequencies and decay rates.

A rod's small vibrations about its state at rest (or about its equilibrium under its loads) have
the eigenvalues $p_k = -\zeta_k + i\,\omega_k$ of :func:`rbo_jax.lattice.spectrum`. Given measured
$p_k$ of the lowest modes (a frequency alone when the decay was not measured), the constants
$EI$, $GJ$, the Kelvin–Voigt time $\eta$, ... are fitted by the Levenberg–Marquardt iteration
of :func:`rbo_jax.fit` (:func:`rbo_jax.fitting._least_squares.run_least_squares`) around one
compiled program, the residuals and their forward-mode Jacobian through the eigenvalue problem
(and through the Newton solve of the equilibrium, by the implicit function theorem, when the rod
is loaded). Every parameter is positive and fitted as its logarithm; its standard error is the
Gauss–Newton one, $s^2 (J^TJ)^{-1}$ with $s^2$ the residual variance, carried to the parameter
by the delta method.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..fitting._least_squares import run_least_squares
from ..fitting._residuals import jacobian_matrix
from ._fit import _residuals_and_jacobian, _start
from ._rod import RodState
from ._rod_dynamics import _solve, linearize
from ._rod_statics import solve_equilibrium

__all__ = ["RodFit", "fit_spectrum", "fit_trajectory"]


class RodFit(eqx.Module):
    """The result of :func:`fit_spectrum`: ``params`` and ``stderr`` (name -> value), ``rms``
    (of the residuals at the solution, in the eigenvalues' units), ``num_steps``,
    ``converged``, ``message``."""

    params: dict
    stderr: dict
    rms: float
    num_steps: int
    converged: bool
    message: str = eqx.field(static=True)


def _lowest(p, count):
    """The ``count`` eigenvalues with the smallest positive imaginary parts, ascending."""
    key = jnp.where(p.imag > 1e-9 * jnp.max(jnp.abs(p)), p.imag, jnp.inf)
    return p[jnp.argsort(key)[:count]]


def _spectrum_residuals(rod_fn, at_rest, u, data):
    target, mask = data
    rod = rod_fn(**{k: jnp.exp(v) for k, v in u.items()})
    state = rod.straight() if at_rest else solve_equilibrium(rod).state
    p = _lowest(jnp.linalg.eigvals(linearize(rod, state)), target.shape[0])
    r = jnp.stack([p.real - target[:, 0], p.imag - target[:, 1]], axis=1)
    return jnp.ravel(jnp.where(mask, r, 0.0))


def fit_spectrum(
    rod_fn: Callable,
    params: Mapping[str, float],
    eigenvalues,
    *,
    at_rest: bool = True,
    tol: float = 1e-12,
    max_steps: int = 100,
) -> RodFit:
    r"""Fit ``params`` (name -> starting value > 0) so that the rod ``rod_fn(**params)`` has the
    measured ``eigenvalues``: complex $p_k = -\zeta_k + i\omega_k$ of its lowest modes in order
    of frequency (the modes with $\omega > 0$ of :func:`rbo_jax.lattice.spectrum`; a rod of
    circular section has each bending frequency twice, one per plane: list both). A real part
    that was not measured is NaN (``complex(nan, omega)``): only the frequency is fitted.
    ``at_rest``: linearise about the straight state at rest (a rod without loads), else about
    the equilibrium under the loads (Newton, differentiated implicitly). ``tol``,
    ``max_steps``: as :func:`rbo_jax.fit`. Returns a :class:`RodFit` with standard errors."""
    u0 = _start(params)
    p = np.atleast_1d(np.asarray(eigenvalues, dtype=complex))
    if p.ndim != 1 or p.size == 0:
        raise ValueError(f"fit_spectrum: eigenvalues must be a 1-D array, got shape {p.shape}.")
    if not np.all(np.isfinite(p.imag)) or np.any(p.imag <= 0):
        raise ValueError("fit_spectrum: every eigenvalue needs a measured frequency Im p > 0.")
    target = np.stack([np.nan_to_num(p.real), p.imag], axis=1)
    mask = np.stack([np.isfinite(p.real), np.ones(p.size, bool)], axis=1)
    data = (jnp.asarray(target), jnp.asarray(mask))
    residuals = jax.tree_util.Partial(_spectrum_residuals, rod_fn, bool(at_rest))

    def evaluate(u):
        return _residuals_and_jacobian(residuals, u, data)

    return _fitted(evaluate, u0, tol, max_steps, mask.ravel())


def _fitted(evaluate, u0, tol, max_steps, mask) -> RodFit:
    r"""Levenberg–Marquardt from ``u0`` (logarithms), then the Gauss–Newton standard errors
    $s^2 (J^TJ)^{-1}$, $s^2 = |r|^2/(m - p)$ over the ``mask``ed residuals, carried to every
    parameter by the delta method ($\sigma_p = p\,\sigma_{\log p}$)."""
    u, steps, converged, message = run_least_squares(
        evaluate, u0, "levenberg_marquardt", tol, max_steps, []
    )
    r, J_tree = evaluate(u)
    r = np.asarray(r, dtype=float)
    J = jacobian_matrix(J_tree, r.size)
    dof = max(int(mask.sum()) - len(u), 1)
    s2 = float(r @ r) / dof
    cov = s2 * np.linalg.pinv(J.T @ J)
    values = {k: float(np.exp(v)) for k, v in u.items()}
    names = sorted(u)  # jacobian_matrix flattens the tree in key order
    stderr = {k: values[k] * float(np.sqrt(max(cov[i, i], 0.0))) for i, k in enumerate(names)}
    return RodFit(
        params=values,
        stderr=stderr,
        rms=float(np.sqrt(np.mean(r[mask] ** 2))),
        num_steps=int(steps),
        converged=bool(converged),
        message=message,
    )


def _trajectory_residuals(rod_fn, settings, u, data):
    """The simulated positions of the measured body at ``ts`` minus the measured ones."""
    ts, target, state0 = data
    solver, rtol, atol, max_steps, dt0, body = settings
    rod = rod_fn(**{k: jnp.exp(v) for k, v in u.items()})
    adjoint = diffrax.ForwardMode()  # few parameters: forward mode through the solve
    ys, _, _ = _solve(rod, state0, ts, solver, rtol, atol, max_steps, dt0, adjoint)
    return jnp.ravel(ys.r[:, body, :] - target)


def fit_trajectory(
    rod_fn: Callable,
    params: Mapping[str, float],
    ts,
    positions,
    state0: RodState,
    *,
    body: int = -1,
    solver: diffrax.AbstractSolver | None = None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    tol: float = 1e-12,
    max_fit_steps: int = 100,
) -> RodFit:
    r"""Fit ``params`` (name -> starting value > 0, fitted as logarithms) so that the motion of
    ``rod_fn(**params)`` from ``state0`` (a :class:`RodState`, held fixed: e.g. a measured
    deflected shape at rest) passes through the measured ``positions`` (T, 3) of one body
    (``body``, the tip by default) at the times ``ts`` (T,), ``ts[0]`` the time of ``state0``.

    The residuals are the simulated positions (:func:`rbo_jax.lattice.simulate`'s diffrax solve,
    ``solver`` default ``Dopri8`` with ``rtol``, ``atol``, ``max_steps``) minus the measured
    ones; Levenberg–Marquardt (:func:`rbo_jax.fit`'s) with forward-mode derivatives through the
    solve (``diffrax.ForwardMode``: one tangent per parameter); ``tol``, ``max_fit_steps``: its
    tolerance and iterations. Standard errors: Gauss–Newton, $s^2 (J^TJ)^{-1}$ with the residual
    variance $s^2 = |r|^2/(3T - p)$, by the delta method. Returns a :class:`RodFit` (``rms`` in
    the positions' units)."""
    u0 = _start(params)
    ts = np.asarray(ts, dtype=float)
    target = np.asarray(positions, dtype=float)
    if ts.ndim != 1 or ts.size < 2 or not np.all(np.diff(ts) > 0):
        raise ValueError("fit_trajectory: ts must be a strictly increasing 1-D array of >= 2.")
    if target.shape != (ts.size, 3) or not np.all(np.isfinite(target)):
        raise ValueError(
            f"fit_trajectory: positions must be finite, shape {(ts.size, 3)} (one row per "
            f"time), got {target.shape}."
        )
    if not isinstance(state0, RodState):
        raise TypeError(f"fit_trajectory: state0 must be a RodState, got {type(state0)}.")
    solver = diffrax.Dopri8() if solver is None else solver
    dt0 = float(ts[1] - ts[0]) / 10.0
    settings = (solver, float(rtol), float(atol), int(max_steps), dt0, int(body))
    state0 = jax.tree_util.tree_map(jnp.asarray, state0)
    data = (jnp.asarray(ts), jnp.asarray(target), state0)
    residuals = jax.tree_util.Partial(_trajectory_residuals, rod_fn, settings)

    def evaluate(u):
        return _residuals_and_jacobian(residuals, u, data)

    return _fitted(evaluate, u0, tol, int(max_fit_steps), np.ones(target.size, bool))
